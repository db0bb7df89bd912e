// kinfly-fw's link to a PX4 or ArduPilot flight controller (the `mavlink` backend, docs/flight.md
// "The mavlink backend"): the companion-computer way. The autopilot's IMU comes in
// (HIGHRES_IMU, else SCALED_IMU) as the control task's clock, its attitude (ATTITUDE_QUATERNION)
// for comparison; out go our heartbeat, body-rate and thrust setpoints (SET_ATTITUDE_TARGET), the
// vision pose (ODOMETRY, with the reset counter) and the offboard handshake: setpoints streamed
// first, then the mode asked for, then arming, each re-asked until the heartbeat shows it.
// MAVLink 2, signed with a key when one is given. MAVLink's types and NED stay in this class:
// kinfly's `world` (gravity-aligned, z down, x the heading at the start) is MAVLink's
// MAV_FRAME_LOCAL_FRD, and the body is FRD on both sides, so nothing is converted but units.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>

#include "kinfly/actuators/mavlink_port.h"
#include "kinfly/core/se3.h"
#include "kinfly/core/status.h"
#include "kinfly/flight/estimator.h"
#include "kinfly/flight/flight_modes.h"
#include "kinfly/link/signing.h"

namespace kinfly::actuators {

struct AutopilotParams {
  int system_id = 1;       // [1, 255] ours: a companion computer shares its vehicle's system id
  int component_id = 191;  // [1, 255] MAV_COMP_ID_ONBOARD_COMPUTER
  double heartbeat_timeout_s = 1.5;  // [s] (0, 10] silent this long: the autopilot is lost
  double setpoint_rate_hz = 200.0;   // [Hz] [100, 1000] at most one setpoint per tick
  double imu_rate_hz = 250.0;        // [Hz] [50, 1000] HIGHRES_IMU asked of the autopilot
  double attitude_rate_hz = 50.0;    // [Hz] [1, 500] ATTITUDE_QUATERNION asked
  double request_interval_s = 0.5;   // [s] [0.05, 10] mode, arm and stream requests re-sent
  // PX4 enters offboard only once setpoints are streaming (COM_OF_LOSS_T).
  double prestream_s = 0.5;          // [s] [0, 10]
  // The autopilot's normalised thrust at hover (PX4's MPC_THR_HOVER): the thrust setpoint is
  // hover_thrust x the stack's thrust over the weight, so that hover matches whatever the
  // vehicle's motors and props.
  double hover_thrust = 0.5;         // [-] [0.05, 0.95]
  Status validate() const;
};

// The autopilot's clock (µs since its boot) on ours (the wall clock the depth sources stamp
// frames with): wall = remote + offset, the offset the smallest delay seen (arrival - remote),
// which may grow only as fast as two crystals drift apart, and is found again when the
// autopilot restarted (its time fell back, or a sample seems seconds late). Mapped times
// always increase.
class ClockMap {
 public:
  // [µs per µs] the largest drift between the clocks followed upwards (two 50 ppm crystals).
  static constexpr double kDrift = 100e-6;
  // [µs] a fall of the autopilot's time beyond this is its restart, not jitter ...
  static constexpr int64_t kRestartUs = 1000000;
  // [µs] ... and so is a sample this much later than the smallest delay says (a burst after a
  // stall of this computer is shorter: the IMU-lost failsafe acts after 0.25 s).
  static constexpr int64_t kLateRestartUs = 3000000;

  // The sample's time on our clock.
  int64_t map(int64_t remote_us, int64_t arrival_utime);
  // Our time on the autopilot's clock (for what we stamp); 0 before the first map().
  int64_t toRemote(int64_t utime) const { return have_offset_ ? utime - offset_us_ : 0; }
  bool ready() const { return have_offset_; }
  int64_t offsetUs() const { return offset_us_; }

 private:
  bool have_offset_ = false;
  int64_t offset_us_ = 0;
  int64_t last_arrival_utime_ = 0;
  int64_t last_utime_ = -1;
};

// What kinfly wants of the autopilot this tick, from the flight stack's output.
enum class AutopilotWant {
  kNothing,  // kinfly disarmed or handed over: no setpoints (the autopilot flies on its own)
  kIdle,     // kinfly armed on the ground: zero setpoints streamed, offboard and arming asked
  kFly,      // the stack's setpoints
  kDisarm,   // kinfly disarmed (landed): disarm the autopilot kinfly had flown
};

struct AutopilotSetpoint {
  AutopilotWant want = AutopilotWant::kNothing;
  Eigen::Quaterniond q_world_body_sp = Eigen::Quaterniond::Identity();  // sent, for logs
  Eigen::Vector3d rate_body_rad_s = Eigen::Vector3d::Zero();  // body FRD
  double thrust_ratio = 0.0;  // [-] collective thrust over the weight
};

struct AutopilotCounters {
  int64_t heartbeats = 0;       // the autopilot's
  int64_t imu_samples = 0;      // HIGHRES_IMU or SCALED_IMU handed to the control task
  int64_t imu_rejected = 0;     // not all fields, not finite, or not after the last in time
  int64_t attitudes = 0;        // ATTITUDE_QUATERNION
  int64_t bad_signature = 0;    // unsigned or wrongly signed while a key is set: dropped
  int64_t bad_crc = 0;
  int64_t other_source = 0;     // from a system or component that is not the autopilot
  int64_t setpoints_sent = 0;
  int64_t odometry_sent = 0;
  int64_t mode_requests = 0;    // DO_SET_MODE (offboard)
  int64_t arm_requests = 0;
  int64_t disarm_requests = 0;
  int64_t commands_accepted = 0;  // COMMAND_ACK to us: accepted
  int64_t commands_refused = 0;   // ... anything else (denied, failed, unsupported)
  int64_t send_failures = 0;      // the port refused a frame
  int64_t lost = 0;               // heard, then silent for heartbeat_timeout_s
  int64_t port_errors = 0;        // reads that failed (a serial port unplugged): reopened
};

// One per process: the generated C code keeps the link's parser, sequence and signing state in
// its channel 0, a static.
class Autopilot {
 public:
  // key: MAVLink 2 signing (the same key file rules as the uplink's); none: unsigned, with a
  // warning at start (an autopilot set to require signing then ignores us). Fails only on bad
  // parameters or a malformed URL: a port that cannot be opened yet is opened by receive().
  static StatusOr<std::unique_ptr<Autopilot>> open(const AutopilotParams& params,
                                                   const std::string& url, int baud,
                                                   const std::optional<link::Key>& key);
  ~Autopilot();
  Autopilot(const Autopilot&) = delete;
  Autopilot& operator=(const Autopilot&) = delete;

  // Reads what the port has, waiting up to timeout_ms for the first bytes. IMU samples, on the
  // wall clock of the depth sources (the autopilot's clock mapped by its smallest delay), are
  // returned through imu() until the next receive(). now_s: the steady clock.
  int receive(int timeout_ms, double now_s);
  const flight::ImuSample& imu(int i) const { return imu_[static_cast<size_t>(i)]; }

  // Our heartbeat (1 Hz), the stream requests, the setpoint (at most setpoint_rate_hz) and the
  // handshake its `want` needs.
  void send(const AutopilotSetpoint& setpoint, double now_s);
  // The body's pose from the odometry, in world (MAV_FRAME_LOCAL_FRD), at its capture time
  // (wall clock, mapped to the autopilot's), with its variances and the ground's reset counter.
  void sendVision(int64_t capture_utime, const Pose& T_world_body, double position_var_m2,
                  double attitude_var_rad2, int32_t reset_counter);

  // For the flight modes.
  flight::AutopilotInputs state(double now_s) const;
  // The autopilot's own attitude estimate (body FRD to its local NED), if heard.
  const std::optional<Eigen::Quaterniond>& attitude() const { return attitude_; }
  const AutopilotCounters& counters() const { return counters_; }

 private:
  struct Mavlink;  // the generated headers' state, kept out of this header
  Autopilot(const AutopilotParams& params, const std::string& url, int baud);
  // Opens the port (at the start, or again after it failed), at most every second; false while
  // it cannot.
  bool reopen(double now_s);
  void handle(double now_s, int64_t arrival_utime);
  // baro_alt_m: the sample's pressure altitude, NaN without a new one.
  void addImu(uint64_t remote_us, const Eigen::Vector3d& gyro_rad_s,
              const Eigen::Vector3d& accel_m_s2, double baro_alt_m, int64_t arrival_utime);
  bool sendMessage();
  void sendCommand(uint16_t command, float p1, float p2, float p3, float p4 = 0.0f);
  bool alive(double now_s) const;

  AutopilotParams params_;
  std::string url_;
  int baud_;
  std::unique_ptr<MavlinkPort> port_;  // null after a failure, until reopen()
  double next_reopen_s_ = 0.0;
  bool reopen_failing_ = false;  // the last attempt failed: logged once
  std::unique_ptr<Mavlink> mavlink_;
  AutopilotCounters counters_;

  // The autopilot: the first component whose heartbeat names an autopilot.
  bool heard_ = false;
  bool was_alive_ = false;
  int target_system_ = 0, target_component_ = 0;
  int autopilot_type_ = 0;  // MAV_AUTOPILOT_*
  double last_heartbeat_s_ = -1.0;
  bool armed_ = false, offboard_ = false;

  ClockMap clock_;
  bool highres_seen_ = false;
  std::array<flight::ImuSample, 64> imu_{};
  int imu_count_ = 0;
  std::optional<Eigen::Quaterniond> attitude_;

  // What we sent, when (steady clock).
  double last_heartbeat_sent_s_ = -1e9;
  double last_setpoint_s_ = -1e9;
  double streaming_since_s_ = -1.0;  // -1: not streaming setpoints
  double last_mode_request_s_ = -1e9;
  double last_arm_request_s_ = -1e9;
  double last_disarm_request_s_ = -1e9;
  double last_imu_s_ = -1e9;  // the autopilot's last IMU sample (steady clock)
  // The autopilot has been armed in offboard under kinfly's setpoints since kinfly armed.
  bool flown_ = false;
  double last_stream_request_s_ = -1e9;
};

}  // namespace kinfly::actuators
