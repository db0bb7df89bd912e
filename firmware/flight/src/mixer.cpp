#include "kinfly/flight/mixer.h"

#include <algorithm>
#include <cmath>

namespace kinfly::flight {

namespace {

// Which axes of a moment were cut, by the sign the demand had.
void markCut(double demanded, int axis, MixerSaturation* saturation) {
  if (demanded > 0.0) saturation->moment_cut_positive[axis] = true;
  if (demanded < 0.0) saturation->moment_cut_negative[axis] = true;
}

}  // namespace

bool MixerSaturation::any() const {
  return roll_pitch_kept < 1.0 || yaw_kept < 1.0 || thrust_change_n != 0.0;
}

Mixer::Mixer(const Vehicle& vehicle)
    : vehicle_(vehicle),
      speed_sq_min_(std::pow(vehicle.params().rotor_speed_min_rad_s, 2)),
      speed_sq_max_(std::pow(vehicle.params().rotor_speed_max_rad_s, 2)) {}

MixerOutput Mixer::mix(const Wrench& demanded) const {
  const Eigen::Matrix4d& inverse = vehicle_.allocationInverse();
  // Squared speeds per unit of each wrench part: thrust spreads evenly over the rotors, the
  // moments sum to zero over them (true of both layouts), so shifting thrust never moves a moment.
  const Vector4d per_thrust = inverse.col(0);
  const Vector4d roll_pitch = inverse.col(1) * demanded.moment_body_nm.x() +
                              inverse.col(2) * demanded.moment_body_nm.y();
  const Vector4d yaw = inverse.col(3) * demanded.moment_body_nm.z();
  const double range = speed_sq_max_ - speed_sq_min_;
  MixerOutput out;
  MixerSaturation& saturation = out.saturation;

  // Roll and pitch alone wider than the rotors' range: the last resort, cut them to fit.
  const double roll_pitch_spread = roll_pitch.maxCoeff() - roll_pitch.minCoeff();
  if (roll_pitch_spread > range) {
    saturation.roll_pitch_kept = range / roll_pitch_spread;
    markCut(demanded.moment_body_nm.x(), 0, &saturation);
    markCut(demanded.moment_body_nm.y(), 1, &saturation);
  }
  Vector4d speed_sq = per_thrust * demanded.thrust_n + saturation.roll_pitch_kept * roll_pitch;

  // The thrust moves to where roll and pitch fit, before yaw takes any room.
  double shift = 0.0;
  if (speed_sq.maxCoeff() > speed_sq_max_) shift = speed_sq_max_ - speed_sq.maxCoeff();
  if (speed_sq.minCoeff() < speed_sq_min_) shift = speed_sq_min_ - speed_sq.minCoeff();
  speed_sq.array() += shift;
  saturation.thrust_change_n = shift / per_thrust(0);

  // Yaw takes the room left: the largest fraction that keeps every rotor within its limits.
  double yaw_kept = 1.0;
  for (int i = 0; i < 4; ++i) {
    if (yaw(i) > 0.0) yaw_kept = std::min(yaw_kept, (speed_sq_max_ - speed_sq(i)) / yaw(i));
    if (yaw(i) < 0.0) yaw_kept = std::min(yaw_kept, (speed_sq_min_ - speed_sq(i)) / yaw(i));
  }
  saturation.yaw_kept = std::max(yaw_kept, 0.0);
  if (saturation.yaw_kept < 1.0) markCut(demanded.moment_body_nm.z(), 2, &saturation);
  speed_sq += saturation.yaw_kept * yaw;

  // Rounding may leave a rotor a hair outside: the limits are hard.
  speed_sq = speed_sq.cwiseMax(speed_sq_min_).cwiseMin(speed_sq_max_);
  out.rotor_speed_rad_s = speed_sq.cwiseSqrt();
  out.achieved = vehicle_.wrenchFromRotorSpeeds(out.rotor_speed_rad_s);
  return out;
}

}  // namespace kinfly::flight
