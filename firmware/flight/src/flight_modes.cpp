#include "kinfly/flight/flight_modes.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>
#include <string>

#include "axes_in_range.h"
#include "kinfly/core/range_check.h"

namespace kinfly::flight {

namespace {

using Eigen::Vector3d;

constexpr double kUsToS = 1e-6;
constexpr double kGeofenceLimitM = 1e4;

// Heading about world z (down), the ZYX yaw.
double yawRad(const Eigen::Quaterniond& q_world_body) {
  const Eigen::Matrix3d R = q_world_body.toRotationMatrix();
  return std::atan2(R(1, 0), R(0, 0));
}

// The angle between the body's z and the world's: both point down when level. NaN stays NaN, so
// that a check written as !(tilt <= limit) takes a broken attitude as beyond every limit.
double tiltRad(const Eigen::Quaterniond& q_world_body) {
  const double cos_tilt = q_world_body.normalized().toRotationMatrix()(2, 2);
  return std::acos(std::clamp(cos_tilt, -1.0, 1.0));
}

ModeSetpoint setpointAt(SetpointKind kind, const Vector3d& point_world_m, const FlightInputs& in,
                        double descent_speed_m_s = 0.0) {
  return {kind, point_world_m, yawRad(in.state.q_world_body), descent_speed_m_s};
}

// The modes the position loop flies on kinfly's estimate.
bool fliesToPoints(FlightMode mode) {
  return mode == FlightMode::kTakeOff || mode == FlightMode::kHold || mode == FlightMode::kGoTo ||
         mode == FlightMode::kMission;
}

// The modes in which kinfly flies (or idles) the drone: the failsafes watch over these.
bool kinflyFlies(FlightMode mode) {
  return mode != FlightMode::kDisarmed && mode != FlightMode::kMotorsCut &&
         mode != FlightMode::kHandedOver;
}

// Why hold, go-to, mission and land cannot act in this mode; kNone in the air (inFlight).
CommandRefusal notFlying(FlightMode mode) {
  switch (mode) {
    case FlightMode::kDisarmed: return CommandRefusal::kDisarmed;
    case FlightMode::kArmed: return CommandRefusal::kOnGround;
    case FlightMode::kMotorsCut:
    case FlightMode::kHandedOver: return CommandRefusal::kNoControl;
    default: return CommandRefusal::kNone;
  }
}

}  // namespace

Status FlightModeParams::validate() const {
  Status status = firstError(
      outOfRange("modes.imu_lost_s", imu_lost_s, 0, 1, Bound::kOpen),
      // Arming must not pass on an IMU gap the failsafe would act on a tick later.
      outOfRange("modes.imu_timeout_s", imu_timeout_s, 0, imu_lost_s, Bound::kOpen),
      outOfRange("modes.vision_lost_s", vision_lost_s, 0, 10, Bound::kOpen),
      outOfRange("modes.vision_fresh_s", vision_fresh_s, 0, vision_lost_s, Bound::kOpen),
      outOfRange("modes.takeoff_height_min_m", takeoff_height_min_m, 0.1, 100),
      outOfRange("modes.target_reached_m", target_reached_m, 0, 10, Bound::kOpen),
      outOfRange("modes.land_speed_m_s", land_speed_m_s, 0, 5, Bound::kOpen),
      outOfRange("modes.landed_height_m", landed_height_m, 0, 5, Bound::kOpen),
      outOfRange("modes.landed_speed_m_s", landed_speed_m_s, 0, 5, Bound::kOpen),
      outOfRange("modes.landed_thrust_ratio", landed_thrust_ratio, 0, 1, Bound::kOpen),
      outOfRange("modes.landed_time_s", landed_time_s, 0, 10),
      outOfRange("modes.ground_contact_accel_m_s2", ground_contact_accel_m_s2, 0, 9.81,
                 Bound::kOpen),
      outOfRange("modes.ground_contact_s", ground_contact_s, 0, 10),
      outOfRange("modes.ground_thrust_ramp_per_s", ground_thrust_ramp_per_s, 0, 10,
                 Bound::kOpen),
      outOfRange("modes.vision_lost_descent_m_s", vision_lost_descent_m_s, 0, 5, Bound::kOpen),
      outOfRange("modes.vision_max_pos_std_m", vision_max_pos_std_m, 0, 10, Bound::kOpen),
      outOfRange("modes.ground_lost_s", ground_lost_s, 0, 60, Bound::kOpen),
      outOfRange("modes.max_tilt_rad", max_tilt_rad, 0, M_PI, Bound::kOpen),
      outOfRange("modes.max_rate_rad_s", max_rate_rad_s, 0, 100, Bound::kOpen),
      outOfRange("modes.attitude_limit_s", attitude_limit_s, 0, 1));
  for (int i = 0; i < 3 && status.ok(); ++i) {
    const char* axis = kWorldAxes[static_cast<size_t>(i)];
    const std::string min_key = std::string("modes.geofence_min_world_m.") + axis;
    const std::string max_key = std::string("modes.geofence_max_world_m.") + axis;
    status = firstError(
        outOfRange(min_key, geofence_min_world_m[i], -kGeofenceLimitM, kGeofenceLimitM),
        outOfRange(max_key, geofence_max_world_m[i], -kGeofenceLimitM, kGeofenceLimitM));
    // An empty box would refuse every arming.
    if (status.ok() && !(geofence_min_world_m[i] < geofence_max_world_m[i])) {
      status = Status::error(min_key + " must be below " + max_key);
    }
  }
  return status;
}

FlightModes::FlightModes(const FlightModeParams& params) : params_(params) {}

double FlightModes::ageS(const FlightInputs& in, int64_t utime) const {
  // Never heard, or stamped ahead of now (another clock): either way, not fresh.
  if (utime < 0 || utime > in.utime) return std::numeric_limits<double>::infinity();
  return static_cast<double>(in.utime - utime) * kUsToS;
}

double FlightModes::heldS(const FlightInputs& in, int64_t* since_utime) const {
  // Starts now; and a time before its start (a caller's clock that went back) starts it again,
  // where ageS would take it as long ago and let the condition act at once.
  if (*since_utime < 0 || *since_utime > in.utime) *since_utime = in.utime;
  return static_cast<double>(in.utime - *since_utime) * kUsToS;
}

bool FlightModes::insideGeofence(const Vector3d& p_world_m) const {
  if (!params_.geofence_enabled) return true;
  // Written so that a non-finite position is outside.
  return (p_world_m.array() >= params_.geofence_min_world_m.array()).all() &&
         (p_world_m.array() <= params_.geofence_max_world_m.array()).all();
}

CommandRefusal FlightModes::positionChecks(const FlightInputs& in) const {
  if (!in.estimator.initialised || in.estimator.diverged) {
    return CommandRefusal::kEstimatorUnhealthy;
  }
  if (!(ageS(in, in.last_imu_utime) <= params_.imu_timeout_s)) return CommandRefusal::kImuNotAlive;
  if (!(ageS(in, in.last_vision_utime) <= params_.vision_fresh_s)) {
    return CommandRefusal::kVisionNotFused;
  }
  return CommandRefusal::kNone;
}

CommandRefusal FlightModes::armingChecks(const FlightInputs& in) const {
  if (in.autopilot.used && !in.autopilot.alive) return CommandRefusal::kNoAutopilot;
  const CommandRefusal position = positionChecks(in);
  if (position != CommandRefusal::kNone) return position;
  if (!(in.state.v_world_body_m_s.norm() <= params_.landed_speed_m_s) ||
      !(tiltRad(in.state.q_world_body) <= params_.max_tilt_rad)) {
    return CommandRefusal::kNotAtRest;
  }
  if (!insideGeofence(in.state.p_world_body_m)) return CommandRefusal::kOutsideGeofence;
  return CommandRefusal::kNone;
}

void FlightModes::setMode(FlightMode to, EventReason reason, const FlightInputs& in,
                          FlightOutput& out) {
  // Enough room by construction (kMaxEventsPerUpdate); the guard keeps a future event in bounds.
  if (out.event_count < kMaxEventsPerUpdate) {
    out.events[static_cast<size_t>(out.event_count++)] = {in.utime, reason, mode_, to};
  }
  if (to != mode_) ++counters_.mode_changes;
  mode_ = to;
  if (to == FlightMode::kDisarmed) resetMonitors();
}

void FlightModes::resetMonitors() {
  setpoint_ = ModeSetpoint();
  landed_since_utime_ = -1;
  attitude_limit_since_utime_ = -1;
  landed_ = false;
  vision_lost_ = false;
  diverged_ = false;
  attitude_limit_ = false;
  imu_lost_ = false;
  outside_geofence_ = false;
}

void FlightModes::monitorGround(const FlightInputs& in, FlightOutput& out) {
  const bool alive = ageS(in, in.last_ground_utime) <= params_.ground_lost_s;
  if (alive && ground_lost_) setMode(mode_, EventReason::kGroundRegained, in, out);
  if (!alive && ground_heard_ && !ground_lost_) {
    ++counters_.ground_lost;
    setMode(mode_, EventReason::kGroundLost, in, out);
  }
  ground_heard_ = ground_heard_ || alive;
  ground_lost_ = ground_heard_ && !alive;
  out.ground_alive = alive;
}

void FlightModes::watchAutopilot(const FlightInputs& in, FlightOutput& out) {
  const AutopilotInputs& ap = in.autopilot;
  const bool lost = autopilot_heard_ && autopilot_alive_ && !ap.alive;
  const bool took_over = autopilot_in_control_ && ap.alive && !ap.inControl();
  autopilot_heard_ = autopilot_heard_ || ap.alive;
  autopilot_alive_ = ap.alive;
  autopilot_in_control_ = ap.inControl();
  // On the ground kinfly's arming ends with the autopilot's; in the air the autopilot flies on
  // (its own failsafe, or the pilot), and kinfly sends it nothing more.
  const FlightMode after = mode_ == FlightMode::kArmed ? FlightMode::kDisarmed
                                                       : FlightMode::kHandedOver;
  if (lost) {
    ++counters_.autopilot_lost;
    if (kinflyFlies(mode_)) setpoint_ = ModeSetpoint();
    setMode(kinflyFlies(mode_) ? after : mode_, EventReason::kAutopilotLost, in, out);
  } else if (took_over && kinflyFlies(mode_)) {
    ++counters_.autopilot_took_over;
    setpoint_ = ModeSetpoint();
    setMode(after, EventReason::kAutopilotTookOver, in, out);
  }
  if (mode_ == FlightMode::kHandedOver && ap.alive && !ap.armed) {
    setMode(FlightMode::kDisarmed, EventReason::kAutopilotDisarmed, in, out);
  }
}

void FlightModes::detectLanded(const FlightInputs& in) {
  // Without vision the height and the velocity are dead-reckoned from the IMU alone: the descent
  // trusts the thrust and the ground's contact.
  const bool near_ground = mode_ == FlightMode::kDescend ||
                           in.height_above_ground_m <= params_.landed_height_m;
  const bool still =
      in.ground_contact || in.state.v_world_body_m_s.norm() <= params_.landed_speed_m_s;
  const bool resting =
      near_ground && still && in.thrust_ratio <= params_.landed_thrust_ratio;
  if (!resting) {
    landed_since_utime_ = -1;
    landed_ = false;
    return;
  }
  landed_ = heldS(in, &landed_since_utime_) >= params_.landed_time_s;
}

void FlightModes::runFailsafes(const FlightInputs& in, FlightOutput& out) {
  // The attitude and the IMU first: nothing else matters once the loops have lost them.
  const FlightMode lost_control = params_.attitude_limit_action == AttitudeLimitAction::kCutMotors
                                      ? FlightMode::kMotorsCut
                                      : FlightMode::kHandedOver;
  const bool imu_lost = !(ageS(in, in.last_imu_utime) <= params_.imu_lost_s);
  const bool imu_lost_starts = imu_lost && !imu_lost_;
  imu_lost_ = imu_lost;
  if (imu_lost_starts) {
    ++counters_.imu_lost;
    setpoint_ = ModeSetpoint();
    setMode(lost_control, EventReason::kImuLost, in, out);
    return;
  }
  const bool beyond = !(tiltRad(in.state.q_world_body) <= params_.max_tilt_rad) ||
                      !(in.state.omega_body_rad_s.norm() <= params_.max_rate_rad_s);
  if (!beyond) attitude_limit_since_utime_ = -1;
  const bool attitude_limit =
      beyond && heldS(in, &attitude_limit_since_utime_) >= params_.attitude_limit_s;
  const bool attitude_starts = attitude_limit && !attitude_limit_;
  attitude_limit_ = attitude_limit;
  if (attitude_starts) {
    ++counters_.attitude_limit;
    setpoint_ = ModeSetpoint();
    setMode(lost_control, EventReason::kAttitudeLimit, in, out);
    return;
  }

  // Each below acts on the mode the one before left: a diverged estimator and lost vision in one
  // update both end in the descent, and the geofence does not pull a descent back to a hold.
  const Vector3d& p_world_m = in.state.p_world_body_m;
  // A diverged position is no place to land on: level attitude and the slow descent, as with
  // vision lost (PX4 descends too when its local position is invalid).
  if (in.estimator.diverged && !diverged_) {
    ++counters_.estimator_diverged;
    const bool descends = fliesToPoints(mode_) || mode_ == FlightMode::kLand;
    if (descends) {
      setpoint_ = setpointAt(SetpointKind::kDescend, p_world_m, in,
                             params_.vision_lost_descent_m_s);
    }
    setMode(descends ? FlightMode::kDescend : mode_, EventReason::kEstimatorDiverged, in, out);
  }
  diverged_ = in.estimator.diverged;

  const bool vision_lost = !(ageS(in, in.last_vision_utime) <= params_.vision_lost_s);
  if (vision_lost && !vision_lost_) {
    ++counters_.vision_lost;
    const bool descends = fliesToPoints(mode_) || mode_ == FlightMode::kLand;
    if (descends) {
      setpoint_ = setpointAt(SetpointKind::kDescend, p_world_m, in,
                             params_.vision_lost_descent_m_s);
    }
    setMode(descends ? FlightMode::kDescend : mode_, EventReason::kVisionLost, in, out);
  }
  vision_lost_ = vision_lost;

  // Landing and the descent go on outside: down is the way out of trouble.
  const bool outside = !insideGeofence(p_world_m);
  if (outside && !outside_geofence_) {
    ++counters_.geofence;
    const bool holds = fliesToPoints(mode_);
    if (holds) setpoint_ = setpointAt(SetpointKind::kHold, last_inside_world_m_, in);
    setMode(holds ? FlightMode::kHold : mode_, EventReason::kGeofence, in, out);
  }
  outside_geofence_ = outside;
}

void FlightModes::progress(const FlightInputs& in, FlightOutput& out) {
  const Vector3d& p_world_m = in.state.p_world_body_m;
  const bool reached = (p_world_m - setpoint_.point_world_m).norm() <= params_.target_reached_m;
  switch (mode_) {
    case FlightMode::kTakeOff:
    case FlightMode::kGoTo:
      if (reached) {
        const EventReason reason = mode_ == FlightMode::kTakeOff ? EventReason::kTakeOffReached
                                                                 : EventReason::kGoToReached;
        setpoint_.kind = SetpointKind::kHold;
        setMode(FlightMode::kHold, reason, in, out);
      }
      break;
    case FlightMode::kMission:
      if (in.mission_finished) {
        setpoint_ = setpointAt(SetpointKind::kHold, in.mission_end_world_m, in);
        setMode(FlightMode::kHold, EventReason::kMissionFinished, in, out);
      }
      break;
    case FlightMode::kLand:
    case FlightMode::kDescend:
      if (landed_) {
        ++counters_.landed_disarms;
        setMode(FlightMode::kDisarmed, EventReason::kLanded, in, out);
      }
      break;
    default:
      break;
  }
}

CommandResult FlightModes::handle(const FlightCommand& command, const FlightInputs& in,
                                  FlightOutput& out) {
  const Vector3d& p_world_m = in.state.p_world_body_m;
  const CommandRefusal not_flying = notFlying(mode_);
  CommandResult result{command.kind, CommandRefusal::kNone};
  CommandRefusal& refusal = result.refusal;
  switch (command.kind) {
    case CommandKind::kArm:
      refusal = mode_ != FlightMode::kDisarmed ? CommandRefusal::kAlreadyArmed : armingChecks(in);
      if (refusal == CommandRefusal::kNone) {
        setpoint_ = ModeSetpoint();
        setMode(FlightMode::kArmed, EventReason::kCommand, in, out);
      }
      break;

    case CommandKind::kDisarm:
      // In the air only a cut or a landed drone may be disarmed: anything else would drop it.
      if (mode_ != FlightMode::kDisarmed && mode_ != FlightMode::kArmed &&
          mode_ != FlightMode::kMotorsCut && !landed_) {
        refusal = CommandRefusal::kAirborne;
      } else if (mode_ != FlightMode::kDisarmed) {
        setMode(FlightMode::kDisarmed, EventReason::kCommand, in, out);
      }
      break;

    case CommandKind::kTakeOff: {
      if (mode_ != FlightMode::kArmed) {
        refusal = not_flying == CommandRefusal::kNone ? CommandRefusal::kAirborne : not_flying;
      } else if (!std::isfinite(command.height_m) ||
                 command.height_m < params_.takeoff_height_min_m) {
        refusal = CommandRefusal::kInvalidTarget;
      } else {
        refusal = positionChecks(in);
      }
      if (refusal == CommandRefusal::kNone && in.autopilot.used && !in.autopilot.inControl()) {
        refusal = CommandRefusal::kAutopilotNotReady;
      }
      // Straight up from here; the ground is height_above_ground_m below the body.
      const double ground_z_m = p_world_m.z() + in.height_above_ground_m;
      const Vector3d target_world_m(p_world_m.x(), p_world_m.y(), ground_z_m - command.height_m);
      if (refusal == CommandRefusal::kNone && !insideGeofence(target_world_m)) {
        refusal = CommandRefusal::kOutsideGeofence;
      }
      if (refusal == CommandRefusal::kNone) {
        setpoint_ = setpointAt(SetpointKind::kTakeOff, target_world_m, in);
        setMode(FlightMode::kTakeOff, EventReason::kCommand, in, out);
      }
      break;
    }

    case CommandKind::kHold:
    case CommandKind::kGoTo:
    case CommandKind::kMission: {
      refusal = not_flying != CommandRefusal::kNone ? not_flying : positionChecks(in);
      const bool go_to = command.kind == CommandKind::kGoTo;
      if (refusal == CommandRefusal::kNone && go_to) {
        if (!command.target_world_m.allFinite() || std::isinf(command.yaw_rad)) {
          refusal = CommandRefusal::kInvalidTarget;
        } else if (!insideGeofence(command.target_world_m)) {
          refusal = CommandRefusal::kOutsideGeofence;
        }
      }
      // Outside the fence a mission could only lead further out; go-to a point inside, hold (at
      // the last point inside) and land are the ways back.
      if (refusal == CommandRefusal::kNone && command.kind == CommandKind::kMission &&
          !insideGeofence(p_world_m)) {
        refusal = CommandRefusal::kOutsideGeofence;
      }
      if (refusal == CommandRefusal::kNone && command.kind == CommandKind::kMission &&
          !in.mission_loaded) {
        refusal = CommandRefusal::kNoMission;
      }
      if (refusal != CommandRefusal::kNone) break;
      // A mission already under way goes on: restarting it is the trajectory's business.
      if (command.kind == CommandKind::kMission && mode_ == FlightMode::kMission) break;
      const SetpointKind kind = go_to ? SetpointKind::kGoTo
                                : command.kind == CommandKind::kHold ? SetpointKind::kHold
                                                                     : SetpointKind::kMission;
      const FlightMode to = go_to ? FlightMode::kGoTo
                            : command.kind == CommandKind::kHold ? FlightMode::kHold
                                                                 : FlightMode::kMission;
      const Vector3d& hold_world_m =
          insideGeofence(p_world_m) ? p_world_m : last_inside_world_m_;
      setpoint_ = setpointAt(kind, go_to ? command.target_world_m : hold_world_m, in);
      if (go_to && !std::isnan(command.yaw_rad)) setpoint_.yaw_rad = command.yaw_rad;
      // A new hold point or go-to target in the same mode is no mode change.
      if (to != mode_) setMode(to, EventReason::kCommand, in, out);
      break;
    }

    case CommandKind::kLand: {
      refusal = not_flying;
      if (refusal != CommandRefusal::kNone) break;
      // Landing is never refused in the air: without a position it is the descent.
      const bool has_position = positionChecks(in) == CommandRefusal::kNone;
      const FlightMode to = has_position ? FlightMode::kLand : FlightMode::kDescend;
      if (to == mode_) break;
      setpoint_ = has_position
                      ? setpointAt(SetpointKind::kLand, p_world_m, in, params_.land_speed_m_s)
                      : setpointAt(SetpointKind::kDescend, p_world_m, in,
                                   params_.vision_lost_descent_m_s);
      setMode(to, EventReason::kCommand, in, out);
      break;
    }
  }
  ++(result.accepted() ? counters_.commands_accepted : counters_.commands_refused);
  return result;
}

FlightOutput FlightModes::update(const FlightInputs& in,
                                 const std::optional<FlightCommand>& command) {
  FlightOutput out;
  monitorGround(in, out);
  if (in.autopilot.used) watchAutopilot(in, out);
  if (mode_ != FlightMode::kDisarmed) detectLanded(in);
  if (kinflyFlies(mode_)) runFailsafes(in, out);
  // After the geofence check, so that a breach holds at the point before it.
  if (insideGeofence(in.state.p_world_body_m)) last_inside_world_m_ = in.state.p_world_body_m;
  progress(in, out);
  if (command) out.command = handle(*command, in, out);

  out.mode = mode_;
  out.setpoint = setpoint_;
  out.cut_motors = mode_ == FlightMode::kMotorsCut;
  out.hand_over = mode_ == FlightMode::kHandedOver;
  out.landed = landed_;
  return out;
}

bool inFlight(FlightMode mode) { return notFlying(mode) == CommandRefusal::kNone; }

const char* toString(FlightMode mode) {
  switch (mode) {
    case FlightMode::kDisarmed: return "disarmed";
    case FlightMode::kArmed: return "armed";
    case FlightMode::kTakeOff: return "take-off";
    case FlightMode::kHold: return "hold";
    case FlightMode::kGoTo: return "go-to";
    case FlightMode::kMission: return "mission";
    case FlightMode::kLand: return "land";
    case FlightMode::kDescend: return "descend";
    case FlightMode::kMotorsCut: return "motors cut";
    case FlightMode::kHandedOver: return "handed over";
  }
  return "?";
}

const char* toString(CommandKind kind) {
  switch (kind) {
    case CommandKind::kArm: return "arm";
    case CommandKind::kDisarm: return "disarm";
    case CommandKind::kTakeOff: return "take-off";
    case CommandKind::kHold: return "hold";
    case CommandKind::kGoTo: return "go-to";
    case CommandKind::kMission: return "mission";
    case CommandKind::kLand: return "land";
  }
  return "?";
}

const char* toString(CommandRefusal refusal) {
  switch (refusal) {
    case CommandRefusal::kNone: return "accepted";
    case CommandRefusal::kEstimatorUnhealthy: return "estimator not initialised or diverged";
    case CommandRefusal::kImuNotAlive: return "IMU not alive";
    case CommandRefusal::kVisionNotFused: return "vision not fused recently";
    case CommandRefusal::kNotAtRest: return "not at rest: moving or tilted";
    case CommandRefusal::kOutsideGeofence: return "outside the geofence";
    case CommandRefusal::kInvalidTarget: return "invalid target";
    case CommandRefusal::kDisarmed: return "disarmed";
    case CommandRefusal::kAlreadyArmed: return "already armed";
    case CommandRefusal::kOnGround: return "on the ground: take off first";
    case CommandRefusal::kAirborne: return "flying: land first";
    case CommandRefusal::kNoControl: return "motors cut or the autopilot has control";
    case CommandRefusal::kNoMission: return "no mission loaded";
    case CommandRefusal::kNoAutopilot: return "the autopilot is not heard";
    case CommandRefusal::kAutopilotNotReady:
      return "the autopilot is not armed in offboard (yet)";
  }
  return "?";
}

const char* toString(SetpointKind kind) {
  switch (kind) {
    case SetpointKind::kIdle: return "idle";
    case SetpointKind::kTakeOff: return "take-off";
    case SetpointKind::kHold: return "hold";
    case SetpointKind::kGoTo: return "go-to";
    case SetpointKind::kMission: return "mission";
    case SetpointKind::kLand: return "land";
    case SetpointKind::kDescend: return "descend";
  }
  return "?";
}

const char* toString(EventReason reason) {
  switch (reason) {
    case EventReason::kCommand: return "command";
    case EventReason::kTakeOffReached: return "take-off height reached";
    case EventReason::kGoToReached: return "go-to target reached";
    case EventReason::kMissionFinished: return "mission finished";
    case EventReason::kLanded: return "landed";
    case EventReason::kVisionLost: return "failsafe: vision lost";
    case EventReason::kEstimatorDiverged: return "failsafe: estimator diverged";
    case EventReason::kGroundLost: return "failsafe: ground station lost";
    case EventReason::kAttitudeLimit: return "failsafe: tilt or rate beyond limits";
    case EventReason::kImuLost: return "failsafe: IMU silent";
    case EventReason::kGeofence: return "failsafe: geofence";
    case EventReason::kAutopilotLost: return "failsafe: autopilot lost";
    case EventReason::kGroundRegained: return "ground station back";
    case EventReason::kAutopilotTookOver: return "the autopilot took over";
    case EventReason::kAutopilotDisarmed: return "the autopilot disarmed";
  }
  return "?";
}

bool isFailsafe(EventReason reason) {
  return reason == EventReason::kVisionLost || reason == EventReason::kEstimatorDiverged ||
         reason == EventReason::kGroundLost || reason == EventReason::kAttitudeLimit ||
         reason == EventReason::kImuLost || reason == EventReason::kGeofence ||
         reason == EventReason::kAutopilotLost;
}

}  // namespace kinfly::flight
