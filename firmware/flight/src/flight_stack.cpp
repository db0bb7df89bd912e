#include "kinfly/flight/flight_stack.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <utility>

#include "kinfly/core/range_check.h"

namespace kinfly::flight {
namespace {

constexpr double kUsPerS = 1e6;

// Whether `next` goes on flying the profile made for `current`: the same setpoint, or the hold at
// the point a take-off or go-to was flying to, which its line already ends at, at rest. The modes
// call a point reached within target_reached_m, still moving: a new line from there would
// restart from rest, a step in the velocity setpoint that the sim found kicking the drone into
// 15° per frame swings, more than the odometry can track.
bool continuesProfile(const ModeSetpoint& next, const ModeSetpoint& current) {
  const bool same_target = next.point_world_m == current.point_world_m &&
                           next.yaw_rad == current.yaw_rad &&
                           next.descent_speed_m_s == current.descent_speed_m_s;
  const bool arrives = next.kind == SetpointKind::kHold &&
                       (current.kind == SetpointKind::kGoTo ||
                        current.kind == SetpointKind::kTakeOff);
  return same_target && (next.kind == current.kind || arrives);
}

// The lift's low-pass: long against a frame's vibration, short against the second the landed
// detector waits.
constexpr double kLiftTimeConstantS = 0.1;
// The thrust scale's: long against manoeuvres (drag, the rotors' lag), a few seconds of hover
// after take-off are enough.
constexpr double kThrustScaleTimeConstantS = 2.0;
// Below this share of the weight the ratio says little (and a take-off's first ticks are there).
constexpr double kMinLearningThrustRatio = 0.5;
// What a sane vehicle's parameters can be off by: beyond, they are wrong, not the thrust.
constexpr double kThrustScaleMin = 0.7, kThrustScaleMax = 1.4;
// [m/s²] how far from gravity's share the lift of a body held still may be: the accelerometer's
// noise after the low-pass and the floor's give, with room; a body sinking with its thrust cut
// by a tenth of the weight is beyond it.
constexpr double kStillLiftToleranceMS2 = 0.8;

}  // namespace

Status FlightStackParams::validate() const {
  if (Status valid = firstError(outOfRange("flight.rate_hz", rate_hz, 100.0, 4000.0),
                                vehicle.validate(), estimator.validate(), modes.validate(),
                                position.validate(), attitude.validate(), trajectory.validate());
      !valid.ok()) {
    return valid;
  }
  if (position.rate_hz > rate_hz) {
    return Status::error("position.rate_hz (" + std::to_string(position.rate_hz) +
                         ") must not exceed flight.rate_hz (" + std::to_string(rate_hz) + ")");
  }
  return {};
}

StatusOr<std::unique_ptr<FlightStack>> FlightStack::create(const FlightStackParams& params) {
  if (Status valid = params.validate(); !valid.ok()) return valid;
  const Vehicle vehicle(params.vehicle);
  auto attitude = AttitudeController::create(params.attitude, vehicle);
  if (!attitude.ok()) return attitude.status();
  return std::unique_ptr<FlightStack>(new FlightStack(params, *std::move(attitude)));
}

FlightStack::FlightStack(const FlightStackParams& params, AttitudeController attitude)
    : params_(params),
      vehicle_(params.vehicle),
      estimator_(params.estimator),
      modes_(params.modes),
      position_(params.position, vehicle_),
      attitude_(std::move(attitude)),
      mixer_(vehicle_),
      decimation_(static_cast<int>(std::lround(params.rate_hz / params.position.rate_hz))) {}

bool FlightStack::addImu(const ImuSample& sample) {
  const int64_t previous_utime = last_imu_utime_;
  if (!estimator_.addImu(sample)) return false;
  last_imu_utime_ = sample.utime;
  // A first-order low-pass; the first sample (and one after a long gap) starts it.
  const double lift_m_s2 = -sample.accel_m_s2.z();
  const double dt_s = static_cast<double>(sample.utime - previous_utime) / kUsPerS;
  const double weight =
      previous_utime < 0 || !(dt_s > 0.0) ? 1.0 : std::min(1.0, dt_s / kLiftTimeConstantS);
  lift_m_s2_ += weight * (lift_m_s2 - lift_m_s2_);
  // In flight, not landing: there the floor may already push and rub, and what the wind did is
  // held, not relearnt.
  const FlightMode mode = modes_.mode();
  if (flying_ && previous_utime >= 0 && mode != FlightMode::kLand && mode != FlightMode::kDescend) {
    const EstimatorState state = estimator_.state();
    position_.feel(state.f_body_m_s2, state.q_world_body, dt_s);
  }
  return true;
}

void FlightStack::detectGroundContact(int64_t utime, const Eigen::Quaterniond& q_world_body) {
  const FlightModeParams& p = params_.modes;
  const FlightMode mode = modes_.mode();
  const bool landing = flying_ && (mode == FlightMode::kLand || mode == FlightMode::kDescend);
  const double carried_m_s2 =
      lift_m_s2_ - thrust_scale_ * command_.thrust_n / params_.vehicle.mass_kg;
  // Held still: the lift is gravity's share along body up. A body in the air whose thrust is cut
  // is not (it sinks faster and faster), so a false contact (an excess that does not shrink with
  // the thrust: an accelerometer offset, ground effect) ends as soon as the drone starts to sink.
  const double gravity_up_m_s2 =
      (q_world_body.conjugate() * Eigen::Vector3d(0.0, 0.0, kGravityMS2)).z();
  const bool still = std::abs(lift_m_s2_ - gravity_up_m_s2) <= kStillLiftToleranceMS2;
  if (!landing || !still || !(carried_m_s2 >= p.ground_contact_accel_m_s2)) {
    pressed_since_utime_ = -1;
    ground_contact_ = false;
    return;
  }
  if (pressed_since_utime_ < 0) pressed_since_utime_ = utime;
  const bool held = static_cast<double>(utime - pressed_since_utime_) / kUsPerS >=
                    p.ground_contact_s;
  // The ramp starts from the thrust the contact was found at.
  if (held && !ground_contact_) ground_thrust_cap_n_ = command_.thrust_n;
  ground_contact_ = held;
}

void FlightStack::learnThrustScale(FlightMode mode, double height_above_ground_m, double dt_s) {
  // Not while the loops are limited: the thrust given is then not the thrust commanded.
  const bool free_flight = flying_ && mode != FlightMode::kLand && mode != FlightMode::kDescend &&
                           height_above_ground_m > params_.modes.landed_height_m &&
                           command_.thrust_n > kMinLearningThrustRatio * vehicle_.weightN() &&
                           !command_.thrust_limited && !saturation_.any();
  if (!free_flight) return;
  const double scale = std::clamp(lift_m_s2_ * params_.vehicle.mass_kg / command_.thrust_n,
                                  kThrustScaleMin, kThrustScaleMax);
  thrust_scale_ += std::min(1.0, dt_s / kThrustScaleTimeConstantS) * (scale - thrust_scale_);
}

VisionOutcome FlightStack::addVision(const VisionPose& pose) {
  const VisionOutcome outcome = estimator_.addVision(pose);
  // A reset to the pose used it as much as a fusion did; either counts while the position is
  // known (FlightModeParams::vision_max_pos_std_m).
  if (outcome != VisionOutcome::kFused && outcome != VisionOutcome::kResetToPose) return outcome;
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> position(
      estimator_.covariance().topLeftCorner<3, 3>(), Eigen::EigenvaluesOnly);
  if (position.eigenvalues()(2) <= params_.modes.vision_max_pos_std_m *
                                       params_.modes.vision_max_pos_std_m) {
    last_vision_utime_ = pose.utime;
  }
  return outcome;
}

bool FlightStack::applyReset(const OdomReset& reset) { return estimator_.applyReset(reset); }

Status FlightStack::loadMission(const Trajectory& mission) {
  if (modes_.mode() == FlightMode::kMission) {
    return Status::error("flight: a mission is being flown; hold or land before loading another");
  }
  mission_ = mission;
  mission_end_world_m_ = mission.sample(mission.durationS()).p_world_m;
  return {};
}

TickOutput FlightStack::tick(const TickInputs& in) {
  const EstimatorState state = estimator_.state();
  FlightInputs inputs;
  inputs.utime = in.utime;
  inputs.estimator = estimator_.health();
  inputs.state = state;
  inputs.last_imu_utime = last_imu_utime_;
  inputs.last_vision_utime = last_vision_utime_;
  inputs.last_ground_utime = in.last_ground_utime;
  inputs.height_above_ground_m =
      std::isnan(in.height_above_ground_m) ? -state.p_world_body_m.z() : in.height_above_ground_m;
  inputs.thrust_ratio = flying_ ? command_.thrust_n / vehicle_.weightN() : 0.0;
  const double dt_s = 1.0 / params_.rate_hz;
  learnThrustScale(modes_.mode(), inputs.height_above_ground_m, dt_s);
  detectGroundContact(in.utime, state.q_world_body);
  inputs.ground_contact = ground_contact_;
  inputs.mission_loaded = mission_.has_value();
  inputs.mission_finished = mission_finished_;
  inputs.mission_end_world_m = mission_end_world_m_;
  inputs.autopilot = in.autopilot;

  TickOutput out;
  out.modes = modes_.update(inputs, in.command);
  const FlightMode mode = out.modes.mode;
  if (inFlight(mode)) {
    if (!flying_) {  // a take-off: nothing of the last flight's integral carries over
      position_.reset();
      attitude_.reset();
      // The position loop's phase counts from the take-off, not from the ticks before it (on
      // the ground, a simulator's start or the wall clock's ticks before the first IMU sample):
      // a flight then runs the same for the same samples.
      ticks_in_flight_ = 0;
    }
    setpoint_ = guide(out.modes, state, in.utime);
    if (ticks_in_flight_ % decimation_ == 0) {
      command_ = position_.update(setpoint_, state, decimation_ * dt_s);
    }
    if (ground_contact_ && (mode == FlightMode::kLand || mode == FlightMode::kDescend)) {
      const double ramp_n_s = params_.modes.ground_thrust_ramp_per_s * vehicle_.weightN();
      ground_thrust_cap_n_ = std::max(0.0, ground_thrust_cap_n_ - ramp_n_s * dt_s);
      if (command_.thrust_n > ground_thrust_cap_n_) {
        command_.thrust_n = ground_thrust_cap_n_;
        command_.thrust_limited = true;
      }
    }
    ++ticks_in_flight_;
    flying_ = true;
  } else {
    flying_ = false;
    mode_setpoint_ = ModeSetpoint();
    setpoint_ = PositionSetpoint();
    setpoint_.p_world_m = state.p_world_body_m;
    command_ = PositionOutput();
    command_.q_world_body_sp = state.q_world_body;
  }

  switch (mode) {
    case FlightMode::kHandedOver: out.rotors = RotorCommand::kNone; break;
    case FlightMode::kDisarmed:
    case FlightMode::kMotorsCut: out.rotors = RotorCommand::kStopped; break;
    case FlightMode::kArmed:
      out.rotors = RotorCommand::kIdle;
      out.mixer = mixer_.mix({});
      break;
    default: {
      // Pressed against the floor (landing with the thrust at its minimum): the floor holds the
      // attitude, so the attitude and rate loops' integrals would only wind up and tip the
      // drone over. The rotors go level at the minimum thrust until the landed detector
      // disarms, as PX4 does on ground contact.
      const bool ground_contact = (mode == FlightMode::kLand || mode == FlightMode::kDescend) &&
                                  command_.thrust_limited && command_.thrust_n < vehicle_.weightN();
      if (ground_contact) attitude_.reset();
      const Eigen::Vector3d moment_body_nm =
          ground_contact ? Eigen::Vector3d::Zero()
                         : attitude_.update(state.q_world_body, command_.q_world_body_sp,
                                            state.omega_body_rad_s, dt_s, saturation_);
      out.mixer = mixer_.mix({command_.thrust_n, moment_body_nm});
      saturation_ = out.mixer.saturation;
      out.rotors = RotorCommand::kFlying;
    }
  }
  out.setpoint = setpoint_;
  out.position = command_;
  return out;
}

PositionSetpoint FlightStack::guide(const FlightOutput& out, const EstimatorState& state,
                                    int64_t utime) {
  const ModeSetpoint& sp = out.setpoint;
  // A profile starts from where the last one left the setpoint, so the setpoint never jumps; on
  // a take-off from where the body is.
  const Eigen::Vector3d from_world_m = flying_ ? setpoint_.p_world_m : state.p_world_body_m;
  // The heading turns from where the setpoint's is (a turn still under way goes on from there);
  // a take-off keeps the body's.
  const double from_yaw_rad = flying_ ? setpoint_.yaw_rad : sp.yaw_rad;
  if (!flying_ || !continuesProfile(sp, mode_setpoint_)) {
    mode_setpoint_ = sp;
    profile_start_utime_ = utime;
    switch (sp.kind) {
      case SetpointKind::kTakeOff:
      case SetpointKind::kHold:
      case SetpointKind::kGoTo:
        line_ = StraightLine(from_world_m, sp.point_world_m, params_.trajectory, from_yaw_rad,
                             sp.yaw_rad);
        break;
      case SetpointKind::kMission:
        // Flown only when loaded (the modes refuse a mission without one).
        line_ = StraightLine(from_world_m, mission_->sample(0.0).p_world_m, params_.trajectory,
                             from_yaw_rad, sp.yaw_rad);
        mission_start_utime_ = utime + std::llround(line_.durationS() * kUsPerS);
        mission_finished_ = false;
        break;
      case SetpointKind::kLand:
      case SetpointKind::kDescend:
        descent_ = Descent(Eigen::Vector3d(sp.point_world_m.x(), sp.point_world_m.y(),
                                           from_world_m.z()),
                           sp.descent_speed_m_s, params_.trajectory, sp.yaw_rad);
        break;
      case SetpointKind::kIdle: break;
    }
  }
  const double t_s = static_cast<double>(utime - profile_start_utime_) / kUsPerS;
  switch (sp.kind) {
    case SetpointKind::kMission: {
      if (utime < mission_start_utime_) return line_.sample(t_s);
      const double mission_t_s = static_cast<double>(utime - mission_start_utime_) / kUsPerS;
      mission_finished_ = mission_t_s >= mission_->durationS();
      // At the heading the mission began with, whatever the trajectory was made with.
      PositionSetpoint along = mission_->sample(mission_t_s);
      along.yaw_rad = sp.yaw_rad;
      return along;
    }
    case SetpointKind::kLand: return descent_.sample(t_s);
    case SetpointKind::kDescend: {
      // No position to hold: level (no horizontal correction beyond the integral's steady
      // force), down at the descent's speed.
      PositionSetpoint down = descent_.sample(t_s);
      down.p_world_m = state.p_world_body_m;
      down.v_world_m_s.x() = state.v_world_body_m_s.x();
      down.v_world_m_s.y() = state.v_world_body_m_s.y();
      return down;
    }
    default: return line_.sample(t_s);
  }
}

}  // namespace kinfly::flight
