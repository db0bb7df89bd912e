// The flight mode manager and its failsafes (docs/flight.md, "Modes and failsafes"): which mode
// the drone is in, which commands it takes, and what the position loop is to do. Pure, like the
// rest of kinfly::flight: no threads, no I/O, no clock; every update brings its time, the
// estimator's health and state, and the sensors' and the ground's last times. Every mode change
// and every failsafe comes back as an event for the caller to log, and is counted.
//
// Frames: `world` gravity-aligned with z down (heights are negative z), body FRD.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <limits>
#include <optional>

#include "kinfly/core/status.h"
#include "kinfly/flight/estimator.h"

namespace kinfly::flight {

enum class FlightMode {
  kDisarmed,
  kArmed,     // on the ground, rotors at idle
  kTakeOff,   // climbing to the take-off target
  kHold,      // holding a point
  kGoTo,      // flying to a point
  kMission,   // following the mission's trajectory
  kLand,      // descending over the point where the landing began
  kDescend,   // failsafe: vision lost or estimator diverged, level attitude and a slow descent,
              // no position
  kMotorsCut,   // failsafe: attitude out of limits or IMU silent, rotors stopped (the simulator)
  kHandedOver,  // failsafe: attitude out of limits or IMU silent, the autopilot flies
};

// What happens when the tilt or the body rate stays beyond its limit, or the IMU falls silent.
enum class AttitudeLimitAction {
  kHandOver,  // the autopilot takes over (the mavlink backend)
  kCutMotors,  // the rotors stop (the motors backend: the simulator)
};

struct FlightModeParams {
  // Arming and every command that flies to a point need the IMU and a fused pose this recent.
  double imu_timeout_s = 0.005;        // [s] (0, imu_lost_s]: five samples at 1 kHz
  double vision_fresh_s = 0.2;         // [s] (0, vision_lost_s] as its vision_timeout_s
  // A lower take-off would end barely above the landed detector's height band.
  double takeoff_height_min_m = 0.5;   // [m] [0.1, 100]
  // Take-off and go-to end in hold once the position is this close to the target.
  double target_reached_m = 0.1;       // [m] (0, 10]
  double land_speed_m_s = 0.5;         // [m/s] (0, 5] down
  // Landed: below this height, slower than this and with less thrust than this share of the
  // weight (the loop pushing against the ground), all for landed_time_s. Arming needs the same
  // stillness and at most max_tilt_rad.
  double landed_height_m = 0.2;        // [m] (0, 5]
  double landed_speed_m_s = 0.2;       // [m/s] (0, 5]
  double landed_thrust_ratio = 0.3;    // [-] (0, 1]
  double landed_time_s = 1.0;          // [s] [0, 10]
  // Ground contact while landing or descending (FlightStack): the accelerometer's lift (low-passed)
  // exceeds the thrust commanded over the mass by this much for ground_contact_s: the floor
  // carries part of the weight. Then the thrust ramps down by this share of the weight per
  // second until the landed detector disarms; it is given back the moment the floor stops
  // carrying (a false contact in the air lets the drone sink, which ends it). This works without
  // vision or a velocity estimate: an IMU-only velocity drifts, and the descent that vision
  // loss or a diverged estimator starts could otherwise never tell it had landed.
  double ground_contact_accel_m_s2 = 1.5;  // [m/s²] (0, 9.81]
  double ground_contact_s = 0.3;           // [s] [0, 10]
  double ground_thrust_ramp_per_s = 0.5;   // [1/s] (0, 10]

  // Failsafes (each acts once when its condition starts; docs/flight.md's table).
  // No pose fused for this long: level attitude and a slow descent until landed.
  double vision_lost_s = 1.0;            // [s] (0, 10]
  double vision_lost_descent_m_s = 0.3;  // [m/s] (0, 5] down
  // A fused pose counts as vision only while the estimate's position stays known this well (its
  // largest 1σ after the pose, FlightStack::addVision): poses weak along a direction (a corridor)
  // say nothing there, and the drone would drift along it on the IMU alone. Without such poses
  // for vision_lost_s, the vision-lost failsafe acts.
  double vision_max_pos_std_m = 0.3;     // [m] (0, 10]
  // No ground status for this long: only flagged, the onboard odometry flies on.
  double ground_lost_s = 2.0;            // [s] (0, 60]
  // Tilt or body-rate magnitude beyond these for attitude_limit_s: the loops have lost the
  // attitude. The time keeps one wild sample (a knock on landing) from cutting the rotors.
  double max_tilt_rad = 1.0472;          // [rad] (0, π] 60°, PX4's FD_FAIL_R and _P
  double max_rate_rad_s = 10.0;          // [rad/s] (0, 100] beyond the rate loop's 6 rad/s limit
  double attitude_limit_s = 0.1;         // [s] [0, 1]
  AttitudeLimitAction attitude_limit_action = AttitudeLimitAction::kHandOver;
  // No IMU sample for this long in flight: the rate loop flies blind, and the estimate drifts
  // with no prediction. Acts as attitude_limit_action does. Twenty missed samples at 1 kHz: more
  // than a scheduling hiccup of a kernel that is not real-time.
  double imu_lost_s = 0.02;              // [s] (0, 1]
  // The box the drone stays in (world, z down: min.z() is the highest point allowed). A breach
  // holds at the last point inside; arming outside it and targets outside it are refused.
  bool geofence_enabled = true;
  Eigen::Vector3d geofence_min_world_m{-50.0, -50.0, -30.0};  // [m] [-1e4, 1e4], < max
  Eigen::Vector3d geofence_max_world_m{50.0, 50.0, 1.0};      // [m] [-1e4, 1e4]

  Status validate() const;
};

enum class CommandKind { kArm, kDisarm, kTakeOff, kHold, kGoTo, kMission, kLand };

struct FlightCommand {
  CommandKind kind = CommandKind::kHold;
  double height_m = 0.0;                                      // take-off: above the ground
  Eigen::Vector3d target_world_m = Eigen::Vector3d::Zero();  // go-to
  // go-to: the heading to turn to on the way (ModeSetpoint::yaw_rad's convention); NaN keeps
  // the body's
  double yaw_rad = std::numeric_limits<double>::quiet_NaN();
};

// Why a command was refused; the first check that failed.
enum class CommandRefusal {
  kNone,                 // accepted
  kEstimatorUnhealthy,   // not initialised, or diverged
  kImuNotAlive,          // no sample within imu_timeout_s
  kVisionNotFused,       // no pose fused within vision_fresh_s
  kNotAtRest,            // arming: moving or tilted
  kOutsideGeofence,      // arming outside the box, or a target outside it
  kInvalidTarget,        // not finite (a go-to's yaw: infinite), or a take-off lower than
                         // takeoff_height_min_m
  kDisarmed,             // flying commands need arming first
  kAlreadyArmed,
  kOnGround,             // hold, go-to, mission and land need a take-off first
  kAirborne,             // take-off while flying, disarm before landed
  kNoControl,            // the rotors are cut or the autopilot has control
  kNoMission,            // a mission command with no mission loaded
  kNoAutopilot,          // arming: the autopilot (mavlink backend) is not heard
  kAutopilotNotReady,    // take-off: the autopilot is not armed in the mode that takes
                         // kinfly's setpoints (yet: the backend asks it on arming)
};

struct CommandResult {
  CommandKind kind = CommandKind::kHold;
  CommandRefusal refusal = CommandRefusal::kNone;
  bool accepted() const { return refusal == CommandRefusal::kNone; }
};

// What the position loop is to do.
enum class SetpointKind {
  kIdle,        // nothing: rotors off or at idle (cut_motors / hand_over say more)
  kTakeOff,     // climb to point
  kHold,        // hold point
  kGoTo,        // fly to point
  kMission,     // follow the mission's trajectory
  kLand,        // hold point's x and y, descend at descent_speed_m_s
  kDescend,     // level attitude at yaw_rad, descend at descent_speed_m_s; no position
};

struct ModeSetpoint {
  SetpointKind kind = SetpointKind::kIdle;
  Eigen::Vector3d point_world_m = Eigen::Vector3d::Zero();  // take-off, hold, go-to, land
  double yaw_rad = 0.0;            // the heading to keep: the body's when the mode began
  double descent_speed_m_s = 0.0;  // [m/s] land and descend, down
};

enum class EventReason {
  kCommand,           // an accepted command changed the mode
  kTakeOffReached,
  kGoToReached,
  kMissionFinished,
  kLanded,            // landed in land or descend: disarmed
  // Failsafes.
  kVisionLost,
  kEstimatorDiverged,
  kGroundLost,        // no mode change
  kAttitudeLimit,     // tilt or rate
  kImuLost,
  kGeofence,
  kAutopilotLost,     // the autopilot's heartbeat stopped (mavlink backend)
  kGroundRegained,    // not a failsafe: the end of kGroundLost
  // Not failsafes: the autopilot left kinfly's control (a pilot's mode switch, its own
  // failsafe or disarm), or disarmed after kinfly handed over.
  kAutopilotTookOver,
  kAutopilotDisarmed,
};

// A mode change, or a failsafe (from == to when it changed no mode).
struct FlightEvent {
  int64_t utime = 0;  // [µs] of the update
  EventReason reason = EventReason::kCommand;
  FlightMode from = FlightMode::kDisarmed;
  FlightMode to = FlightMode::kDisarmed;
};

// Counted since construction, for the drone's status.
struct FlightCounters {
  int64_t mode_changes = 0;
  int64_t commands_accepted = 0;
  int64_t commands_refused = 0;
  int64_t landed_disarms = 0;
  int64_t vision_lost = 0;
  int64_t estimator_diverged = 0;
  int64_t ground_lost = 0;
  int64_t attitude_limit = 0;
  int64_t imu_lost = 0;
  int64_t geofence = 0;
  int64_t autopilot_lost = 0;
  int64_t autopilot_took_over = 0;
};

// The autopilot under the mavlink backend, as the control task's link to it sees it.
struct AutopilotInputs {
  bool used = false;      // an autopilot flies kinfly's setpoints (else the rest is ignored)
  bool alive = false;     // its heartbeat heard within the backend's timeout
  bool armed = false;     // its heartbeat says armed
  bool offboard = false;  // in the mode that takes kinfly's setpoints (PX4 offboard, ArduPilot
                          // guided without GPS)
  bool inControl() const { return alive && armed && offboard; }
};

// One update's inputs, all from the control task's tick.
struct FlightInputs {
  int64_t utime = 0;                // [µs] now
  EstimatorHealth estimator;        // Estimator::health()
  EstimatorState state;             // Estimator::state(): position, velocity, attitude, rates
  int64_t last_imu_utime = -1;      // [µs] the last IMU sample's; -1 before any
  int64_t last_vision_utime = -1;   // [µs] capture of the last fused pose; -1 before any
  int64_t last_ground_utime = -1;   // [µs] the last ground status's arrival; -1 before any
  // A mission is loaded; its trajectory has ended (cleared by the caller when one starts), and
  // where: a finished mission holds its last point.
  bool mission_loaded = false;
  bool mission_finished = false;
  Eigen::Vector3d mission_end_world_m = Eigen::Vector3d::Zero();
  // Landed detection: above the ground under the body (a rangefinder, the depth image, or the
  // start's height), and the collective thrust last commanded over the weight: 0 while kinfly
  // commands none (handed over, motors cut), or a drone the autopilot landed could never disarm.
  double height_above_ground_m = 0.0;  // [m]
  double thrust_ratio = 0.0;           // [-]
  // The floor carries the drone (ground_contact_accel_m_s2): stands in for a small velocity,
  // which without vision is not known.
  bool ground_contact = false;
  AutopilotInputs autopilot;
};

// At most one event per failsafe (5), the ground link, the autopilot, the command and the mode's
// own end.
constexpr int kMaxEventsPerUpdate = 9;

struct FlightOutput {
  FlightMode mode = FlightMode::kDisarmed;
  ModeSetpoint setpoint;
  bool cut_motors = false;  // stop the rotors now
  bool hand_over = false;   // the autopilot flies; send it no setpoints
  bool ground_alive = false;  // a ground status within ground_lost_s
  bool landed = false;        // armed and the landed detector holds
  std::optional<CommandResult> command;  // of the command given to this update
  std::array<FlightEvent, kMaxEventsPerUpdate> events{};
  int event_count = 0;
};

class FlightModes {
 public:
  // params must validate.
  explicit FlightModes(const FlightModeParams& params);

  // Allocation-free. In this order: the ground link; landed detection and the failsafes; the
  // mode's own end (target reached, mission finished, landed); last the command, checked against
  // the mode all these left.
  FlightOutput update(const FlightInputs& inputs,
                      const std::optional<FlightCommand>& command = std::nullopt);

  FlightMode mode() const { return mode_; }
  const FlightCounters& counters() const { return counters_; }

 private:
  // Logs the event (a failsafe that changes no mode passes to == mode_) and counts the change.
  void setMode(FlightMode to, EventReason reason, const FlightInputs& in, FlightOutput& out);
  void monitorGround(const FlightInputs& in, FlightOutput& out);
  // The mavlink backend's autopilot: lost, or out of kinfly's control.
  void watchAutopilot(const FlightInputs& in, FlightOutput& out);
  void detectLanded(const FlightInputs& in);
  void runFailsafes(const FlightInputs& in, FlightOutput& out);
  CommandResult handle(const FlightCommand& command, const FlightInputs& in, FlightOutput& out);
  void progress(const FlightInputs& in, FlightOutput& out);
  void resetMonitors();

  // The first failed check for flying to a point, kNone when all pass.
  CommandRefusal positionChecks(const FlightInputs& in) const;
  CommandRefusal armingChecks(const FlightInputs& in) const;
  bool insideGeofence(const Eigen::Vector3d& p_world_m) const;
  double ageS(const FlightInputs& in, int64_t utime) const;
  // [s] a condition of the modes' own has held, since *since_utime (set to now when unset).
  double heldS(const FlightInputs& in, int64_t* since_utime) const;

  FlightModeParams params_;
  FlightMode mode_ = FlightMode::kDisarmed;
  ModeSetpoint setpoint_;
  FlightCounters counters_;
  // The ground link: lost only once it was heard (a drone may fly with no ground station).
  bool ground_heard_ = false;
  bool ground_lost_ = false;
  // The autopilot as of the last update: heard once, alive, flying kinfly's setpoints.
  bool autopilot_heard_ = false;
  bool autopilot_alive_ = false;
  bool autopilot_in_control_ = false;
  // Since when the landed and attitude-limit conditions hold; -1 while they do not.
  int64_t landed_since_utime_ = -1;
  int64_t attitude_limit_since_utime_ = -1;
  bool landed_ = false;
  // Failsafe conditions as of the last update: each failsafe acts when its condition starts.
  bool vision_lost_ = false;
  bool diverged_ = false;
  bool attitude_limit_ = false;
  bool imu_lost_ = false;
  bool outside_geofence_ = false;
  Eigen::Vector3d last_inside_world_m_ = Eigen::Vector3d::Zero();
};

// In the air under kinfly's control (take-off, hold, go-to, mission, land, descend): the modes
// whose setpoints the position loop flies.
bool inFlight(FlightMode mode);

const char* toString(FlightMode mode);
const char* toString(CommandKind kind);
const char* toString(CommandRefusal refusal);
const char* toString(SetpointKind kind);
const char* toString(EventReason reason);
bool isFailsafe(EventReason reason);

}  // namespace kinfly::flight
