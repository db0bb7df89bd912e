#include "kinfly/flight/rate_controller.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <string>

#include "axes_in_range.h"
#include "kinfly/core/range_check.h"

namespace kinfly::flight {

Status RateController::Params::validate() const {
  return firstError(
      axesInRange("rate.p_gain_1_s", p_gain_1_s, kBodyAxes, 0.0, 1000.0),
      axesInRange("rate.i_gain_1_s2", i_gain_1_s2, kBodyAxes, 0.0, 1e4),
      axesInRange("rate.d_gain", d_gain, kBodyAxes, 0.0, 1.0),
      axesInRange("rate.integrator_limit_rad_s2", integrator_limit_rad_s2, kBodyAxes, 0.0, 1e3),
      outOfRange("rate.d_cutoff_hz", d_cutoff_hz, 0.0, 500.0, Bound::kOpen));
}

RateController::RateController(const Params& params, const Vehicle& vehicle)
    : params_(params), inertia_kg_m2_(vehicle.inertiaDiagKgM2()) {}

void RateController::reset() {
  integrator_rad_s2_.setZero();
  derivative_filtered_rad_s2_.setZero();
  has_previous_ = false;
}

Eigen::Vector3d RateController::update(const RateSetpoint& setpoint,
                                       const Eigen::Vector3d& omega_body_rad_s, double dt_s,
                                       const MixerSaturation& saturation) {
  // A repeated or out-of-order sample (dt_s <= 0) still gets its moment, but moves no state
  // in time: the derivative and the integrator wait for a real step.
  const bool time_moved = dt_s > 0.0;
  // On the measurement, not the error: a setpoint step would otherwise kick the motors.
  if (has_previous_ && time_moved) {
    const double tau_s = 1.0 / (2.0 * M_PI * params_.d_cutoff_hz);
    const double blend = dt_s / (dt_s + tau_s);
    const Eigen::Vector3d raw_rad_s2 = (omega_body_rad_s - previous_omega_body_rad_s_) / dt_s;
    derivative_filtered_rad_s2_ += blend * (raw_rad_s2 - derivative_filtered_rad_s2_);
  }
  previous_omega_body_rad_s_ = omega_body_rad_s;
  has_previous_ = true;

  const Eigen::Vector3d error_rad_s = setpoint.omega_body_rad_s - omega_body_rad_s;
  const Eigen::Vector3d alpha_rad_s2 =
      params_.p_gain_1_s.cwiseProduct(error_rad_s) + integrator_rad_s2_ -
      params_.d_gain.cwiseProduct(derivative_filtered_rad_s2_) + setpoint.alpha_body_rad_s2;

  // The integrator moves after the output (it acts from the next tick, as PX4's), unless the
  // rotors already cut this axis in the direction the error pushes.
  for (int axis = 0; axis < 3 && time_moved; ++axis) {
    const bool pushes_cut = (error_rad_s(axis) > 0.0 && saturation.moment_cut_positive[axis]) ||
                            (error_rad_s(axis) < 0.0 && saturation.moment_cut_negative[axis]);
    if (pushes_cut) continue;
    const double limit = params_.integrator_limit_rad_s2(axis);
    integrator_rad_s2_(axis) = std::clamp(
        integrator_rad_s2_(axis) + params_.i_gain_1_s2(axis) * error_rad_s(axis) * dt_s, -limit,
        limit);
  }
  // Euler's equation: J alpha = M - omega x J omega.
  const Eigen::Vector3d momentum = inertia_kg_m2_.cwiseProduct(omega_body_rad_s);
  return inertia_kg_m2_.cwiseProduct(alpha_rad_s2) + omega_body_rad_s.cross(momentum);
}

}  // namespace kinfly::flight
