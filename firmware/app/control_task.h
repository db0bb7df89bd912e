// The control task: kinfly::flight::FlightStack driven by an IMU source, one tick per IMU sample
// (as PX4's rate controller runs on each gyro sample), the odometry's newest pose handed over
// through a LatestValue (never a lock the vision thread could hold; the estimate's poses go back
// to it in a history this thread only tries the lock of), the output to the actuator
// backend: rotor speeds over its own LCM (motors), or body rates and thrust to an autopilot over
// MAVLink (mavlink), which is then the IMU source too. Its own thread: neither the odometry nor
// the keyframe link can hold it up. docs/flight.md, "The control task".
#pragma once

#include <lcm/lcm.h>

#include <cstdint>
#include <memory>
#include <optional>

#include "config.h"
#include "kinfly/actuators/autopilot.h"
#include "kinfly/flight_status_t.hpp"
#include "kinfly/flight/flight_stack.h"
#include "kinfly/fw/latest_value.h"
#include "kinfly/imu_t.hpp"
#include "kinfly/motor_command_t.hpp"
#include "publisher.h"
#include "runtime.h"

namespace kinfly::fw {

// What the control task did, for the summary at exit (read after run() returned).
struct ControlSummary {
  int64_t imu_samples = 0;     // received and taken by the estimator
  int64_t imu_rejected = 0;    // another vehicle's, undecodable, or not after the last in time
  int64_t ticks = 0;           // all ticks ...
  int64_t silent_ticks = 0;    // ... of which without a new IMU sample (the IMU gone quiet)
  int64_t commands_sent = 0;   // motor_command_t published (motors backend)
  int64_t commands_unsent = 0;  // not: the control task's LCM was down
  int64_t poses_fused = 0;
  // Poses (fused or not) fetched after the IMU sample their flight.lockstep_pose_age_s was due
  // at: a simulator waiting for them later than that (kinfly-sim --pose-age-ms larger) or not
  int64_t poses_late = 0;
  int64_t poses_rejected = 0;  // gated, too old, out of order, or before the estimator started
  int64_t pose_resets = 0;     // gated too often in a row: the estimator reset to the pose
  int64_t resets = 0;           // the ground's anchor jumped: the estimator reset
  int64_t resets_rejected = 0;  // ... before the estimator started (the next pose anchors it)
  bool estimator_started = false;
  int64_t baro_fused = 0;     // barometer readings the estimator fused ...
  int64_t baro_rejected = 0;  // ... and gated out
  flight::FlightMode mode = flight::FlightMode::kDisarmed;
  flight::FlightCounters modes;
  std::optional<actuators::AutopilotCounters> autopilot;  // the mavlink backend's
  // [rad] the largest tilt between the estimate and the autopilot's own attitude (mavlink)
  double max_tilt_vs_autopilot_rad = 0.0;
};

class ControlTask {
 public:
  // stack: made from config.flight.stackParams(). poses: written by the odometry thread.
  // commands: written by the link thread (authenticated commands from the ground).
  // mavlink_key: the mavlink backend's signing key, if any. flight_status: read by the link
  // thread, which sends it with the drone's status. pose_history: the estimate's camera poses,
  // for the odometry's motion prior.
  ControlTask(const FirmwareConfig& config, std::unique_ptr<flight::FlightStack> stack,
              std::optional<link::Key> mavlink_key, LatestValue<OdometryPose>* poses,
              LatestValue<CommandMail>* commands, LatestValue<flight_status_t>* flight_status,
              SharedPoseHistory* pose_history, const StopToken* stop);

  // Until a stop is requested. Sets the thread's real-time priority and core first, where the
  // configuration asks and the system allows (a warning where it does not).
  void run();
  const ControlSummary& summary() const { return summary_; }

 private:
  static void onImu(const lcm_recv_buf_t* message, const char* channel, void* self);
  void handleImu(const lcm_recv_buf_t* message);
  // A sample from either source: into the estimator, then one tick.
  void takeImu(const flight::ImuSample& sample);
  // The estimate's camera pose (T_body_cam applied).
  Pose cameraPose(const flight::EstimatorState& state) const;
  // The mavlink backend's loop body: the autopilot's bytes, then what we send it.
  void serveAutopilot();
  void sendToBackend(const flight::TickOutput& out, int64_t utime);
  // The stack's state into flight_status_, at most every kFlightStatusPeriodUs of IMU time.
  void reportStatus(const flight::TickOutput& out, int64_t utime);
  // One tick at `utime` (the IMU's clock): the newest pose, the stack, the backend.
  void tick(int64_t utime);
  void applyScheduling() const;

  const FirmwareConfig& config_;
  std::unique_ptr<flight::FlightStack> stack_;
  const bool mavlink_;  // flight.backend = mavlink
  std::optional<link::Key> mavlink_key_;
  LatestValue<OdometryPose>* poses_;
  LatestValue<CommandMail>* commands_;
  LatestValue<flight_status_t>* flight_status_;
  SharedPoseHistory* pose_history_;
  flight::PredictedTrack predicted_;  // what pose_history_ holds
  const StopToken* stop_;
  const int64_t pose_age_us_;  // flight.lockstep_pose_age_s
  bool pose_held_ = false;     // poses_->front() fetched, not fused yet
  // Made by run() after the thread's priority is set: LCM's receive thread, which empties the
  // IMU's socket, is started from it and inherits the priority.
  std::optional<Publisher> publisher_;
  // The mavlink backend's, made by run(); it opens its port, and again after a failure.
  std::unique_ptr<actuators::Autopilot> autopilot_;
  actuators::AutopilotSetpoint autopilot_setpoint_;
  flight::AnchoredVision anchored_;
  imu_t imu_{};
  motor_command_t command_{};
  ControlSummary summary_;
  // The last command the modes answered, for the flight status.
  int64_t last_command_id_ = -1;
  flight::CommandResult last_command_;
  int64_t last_status_utime_ = -1;
  int64_t last_tick_utime_ = -1;  // [µs] the last tick's: ticks never go back in time
  // The last sample's time, and when (steady clock) it came: the clock the silent ticks run on.
  int64_t last_imu_utime_ = -1;
  Clock::time_point last_imu_arrival_;
};

}  // namespace kinfly::fw
