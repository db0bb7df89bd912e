// The whole flight stack, one control tick at a time, as kinfly-fw's control task runs it: the
// estimator fed with the IMU samples and the odometry's poses as they come (addImu, addVision,
// applyReset), then on each tick the flight modes on its health and state, the setpoint the mode
// asks for (a straight line for take-off and go-to, the mission's trajectory, a descent for
// landing), the position loop on every decimation-th tick, the attitude and rate loops and the
// mixer. Pure like the rest of kinfly::flight: no threads, no I/O, no clock; nothing in a tick
// allocates (only create and loadMission do). docs/flight.md, "The flight stack".
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cmath>
#include <cstdint>
#include <memory>
#include <optional>

#include "kinfly/core/status.h"
#include "kinfly/flight/attitude_controller.h"
#include "kinfly/flight/estimator.h"
#include "kinfly/flight/flight_modes.h"
#include "kinfly/flight/mixer.h"
#include "kinfly/flight/position_controller.h"
#include "kinfly/flight/trajectory.h"
#include "kinfly/flight/vehicle.h"

namespace kinfly::flight {

struct FlightStackParams {
  // [Hz] [100, 4000] the control tick: the modes, the attitude and rate loops and the mixer; the
  // position loop runs on every round(rate_hz / position.rate_hz)-th tick.
  double rate_hz = 1000.0;
  VehicleParams vehicle;
  EstimatorParams estimator;
  FlightModeParams modes;
  PositionControllerParams position;
  AttitudeController::Params attitude;
  TrajectoryParams trajectory;
  Status validate() const;
};

// One tick's inputs besides the sensors already given.
struct TickInputs {
  int64_t utime = 0;  // [µs] now, on the IMU's clock
  std::optional<FlightCommand> command;
  int64_t last_ground_utime = -1;  // [µs] the last ground status's arrival; -1 before any
  // [m] the ground under the body where a sensor measures it; NaN: the estimate's height above
  // the world's origin, the body where the estimator started (on the ground, before take-off).
  double height_above_ground_m = NAN;
  AutopilotInputs autopilot;  // the mavlink backend's autopilot; unused by default
};

// What the actuators get.
enum class RotorCommand {
  kNone,     // nothing at all: handed over to the autopilot
  kStopped,  // zero speeds: disarmed or cut
  kIdle,     // the mixer's speeds at no thrust: armed on the floor
  kFlying,   // the mixer's speeds
};

struct TickOutput {
  FlightOutput modes;
  PositionSetpoint setpoint;  // what the position loop follows (as of its last update)
  PositionOutput position;    // as of the position loop's last update
  MixerOutput mixer;  // zero speeds unless idle or flying
  RotorCommand rotors = RotorCommand::kNone;
};

class FlightStack {
 public:
  static StatusOr<std::unique_ptr<FlightStack>> create(const FlightStackParams& params);
  FlightStack(const FlightStack&) = delete;
  FlightStack& operator=(const FlightStack&) = delete;

  // Starts the estimator at a known state (a start in flight: the tests' plant), instead of
  // from the first pose after the IMU has been still (Estimator::addVision).
  void initialise(const EstimatorInit& init) { estimator_.initialise(init); }
  // The sensors, in time order per sensor, between ticks (the estimator's calls).
  bool addImu(const ImuSample& sample);
  VisionOutcome addVision(const VisionPose& pose);
  bool applyReset(const OdomReset& reset);

  // The trajectory a mission command flies (it starts with a straight line to the trajectory's
  // first point). Allocates: outside the tick. Refused while a mission is flown.
  Status loadMission(const Trajectory& mission);

  TickOutput tick(const TickInputs& in);

  const Estimator& estimator() const { return estimator_; }
  const FlightModes& modes() const { return modes_; }
  const Vehicle& vehicle() const { return vehicle_; }
  const FlightStackParams& params() const { return params_; }
  int64_t lastImuUtime() const { return last_imu_utime_; }
  int64_t lastVisionUtime() const { return last_vision_utime_; }
  // [µs] when the mission's trajectory proper begins (after the line to its first point).
  int64_t missionStartUtime() const { return mission_start_utime_; }

 private:
  FlightStack(const FlightStackParams& params, AttitudeController attitude);
  // The setpoint for this tick from the mode's, starting a new profile when the mode's changed.
  PositionSetpoint guide(const FlightOutput& out, const EstimatorState& state, int64_t utime);
  // Whether the floor carries the drone while it lands or descends (FlightModeParams'
  // ground_contact_*), from the lift the accelerometer feels against the thrust last commanded.
  void detectGroundContact(int64_t utime, const Eigen::Quaterniond& q_world_body);
  // Learns, in free flight, the lift the commanded thrust really gives (thrust_scale_).
  void learnThrustScale(FlightMode mode, double height_above_ground_m, double dt_s);

  FlightStackParams params_;
  Vehicle vehicle_;  // before the mixer, which keeps a reference
  Estimator estimator_;
  FlightModes modes_;
  PositionController position_;
  AttitudeController attitude_;
  Mixer mixer_;
  int decimation_ = 1;
  int64_t ticks_in_flight_ = 0;  // since the take-off: the position loop's phase
  int64_t last_imu_utime_ = -1;
  int64_t last_vision_utime_ = -1;

  // Ground contact: the specific force along body up, low-passed (the rotors' vibration on a
  // real frame is metres per second squared per sample), and the thrust cap that ramps down
  // while the floor carries the drone.
  double lift_m_s2_ = 0.0;
  // The lift over the commanded thrust over the mass, learnt in free flight and kept for the
  // program's life (the vehicle does not change between flights; a payload is learnt again in
  // seconds of hover): a vehicle lighter or with stronger rotors than the parameters say would
  // otherwise seem carried by the floor in the air (20 % more thrust than believed is 1.6 m/s²
  // of it in a hover).
  double thrust_scale_ = 1.0;
  int64_t pressed_since_utime_ = -1;
  bool ground_contact_ = false;
  double ground_thrust_cap_n_ = 0.0;

  // Guidance: the profile the mode's setpoint started, and when.
  ModeSetpoint mode_setpoint_;
  bool flying_ = false;  // the position loop ran on the last tick
  int64_t profile_start_utime_ = 0;
  StraightLine line_;
  Descent descent_;
  std::optional<Trajectory> mission_;
  Eigen::Vector3d mission_end_world_m_ = Eigen::Vector3d::Zero();
  int64_t mission_start_utime_ = 0;  // after the straight line to its first point
  bool mission_finished_ = false;

  PositionSetpoint setpoint_;
  PositionOutput command_;
  MixerSaturation saturation_;
};

}  // namespace kinfly::flight
