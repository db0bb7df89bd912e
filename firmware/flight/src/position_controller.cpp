#include "kinfly/flight/position_controller.h"

#include <algorithm>
#include <cmath>
#include <string>

#include "axes_in_range.h"
#include "kinfly/core/range_check.h"

namespace kinfly::flight {

Status PositionControllerParams::validate() const {
  return firstError(
      outOfRange("position.rate_hz", rate_hz, 100.0, 1000.0),
      axesInRange("position.p_gain_1_s2", p_gain_1_s2, kWorldAxes, 0.0, 100.0),
      axesInRange("position.v_gain_1_s", v_gain_1_s, kWorldAxes, 0.0, 50.0),
      axesInRange("position.i_gain_1_s3", i_gain_1_s3, kWorldAxes, 0.0, 200.0),
      axesInRange("position.integral_limit_m_s2", integral_limit_m_s2, kWorldAxes, 0.0, 10.0),
      outOfRange("position.disturbance_gain", disturbance_gain, 0.0, 1.0),
      outOfRange("position.disturbance_filter_s", disturbance_filter_s, 0.01, 1.0),
      outOfRange("position.tilt_max_rad", tilt_max_rad, 0.0, 1.4, Bound::kOpen),
      // Below g, so that the vehicle can always be told to descend; above g at the top, so that
      // it can always climb.
      outOfRange("position.thrust_min_m_s2", thrust_min_m_s2, 0.5, kGravityMS2 - 1e-9),
      outOfRange("position.thrust_max_m_s2", thrust_max_m_s2, kGravityMS2, 100.0,
                 Bound::kOpen));
}

PositionController::PositionController(const PositionControllerParams& params,
                                       const Vehicle& vehicle)
    : params_(params), mass_kg_(vehicle.params().mass_kg) {}

void PositionController::feel(const Eigen::Vector3d& f_body_m_s2,
                              const Eigen::Quaterniond& q_world_body, double dt_s) {
  if (!(dt_s > 0.0)) return;
  const Eigen::Vector3d felt_m_s2 = q_world_body * Eigen::Vector3d(f_body_m_s2.x(), f_body_m_s2.y(), 0.0);
  disturbance_m_s2_ += dt_s / (params_.disturbance_filter_s + dt_s) * (felt_m_s2 - disturbance_m_s2_);
}

void PositionController::reset() {
  integral_m_s2_.setZero();
  disturbance_m_s2_.setZero();
}

PositionOutput PositionController::update(const PositionSetpoint& setpoint,
                                          const EstimatorState& state, double dt_s) {
  const Eigen::Vector3d error_p_m = state.p_world_body_m - setpoint.p_world_m;
  const Eigen::Vector3d error_v_m_s = state.v_world_body_m_s - setpoint.v_world_m_s;
  // Lee et al. (2010) divided by the mass: the acceleration the thrust must give
  // on top of gravity's, a = a_d - K_p e_p - K_v e_v - I; the thrust is then m (a - g - k_d d),
  // d the external force per mass felt, so that a is what the vehicle does.
  const Eigen::Vector3d accel_cmd_m_s2 = setpoint.a_world_m_s2 -
                                         params_.p_gain_1_s2.cwiseProduct(error_p_m) -
                                         params_.v_gain_1_s.cwiseProduct(error_v_m_s) -
                                         integral_m_s2_;
  Eigen::Vector3d thrust_accel_m_s2 = accel_cmd_m_s2 - Eigen::Vector3d(0.0, 0.0, kGravityMS2) -
                                      params_.disturbance_gain * disturbance_m_s2_;

  PositionOutput out;
  // The vertical part first, as PX4 does: thrust must point up (-z) by at least the minimum,
  // whatever the loop asks, or the tilt below would have no meaning, and height has the thrust
  // it needs up to the maximum before any goes sideways.
  const double up_m_s2 = -thrust_accel_m_s2.z();
  if (up_m_s2 < params_.thrust_min_m_s2 || up_m_s2 > params_.thrust_max_m_s2) {
    thrust_accel_m_s2.z() = -std::clamp(up_m_s2, params_.thrust_min_m_s2, params_.thrust_max_m_s2);
    out.thrust_limited = true;
  }
  // Then the horizontal part, cut to the tilt limit and to what the maximum thrust leaves, with
  // the vertical part kept.
  const double vertical_m_s2 = -thrust_accel_m_s2.z();
  const double horizontal_max_m_s2 = std::min(
      vertical_m_s2 * std::tan(params_.tilt_max_rad),
      std::sqrt(std::max(0.0, params_.thrust_max_m_s2 * params_.thrust_max_m_s2 -
                                  vertical_m_s2 * vertical_m_s2)));
  const double horizontal_m_s2 = thrust_accel_m_s2.head<2>().norm();
  if (horizontal_m_s2 > horizontal_max_m_s2) {
    thrust_accel_m_s2.head<2>() *= horizontal_max_m_s2 / horizontal_m_s2;
    out.tilt_limited = true;
  }

  // Lee et al.'s desired body axes: z_body opposite the thrust, x_body as near the yaw setpoint
  // as a body with that z can be (the tilt limit keeps z away from the horizontal x_c).
  const Eigen::Vector3d b3 = -thrust_accel_m_s2.normalized();
  const Eigen::Vector3d b1_c(std::cos(setpoint.yaw_rad), std::sin(setpoint.yaw_rad), 0.0);
  const Eigen::Vector3d b2 = b3.cross(b1_c).normalized();
  Eigen::Matrix3d R_world_body_sp;
  R_world_body_sp << b2.cross(b3), b2, b3;
  out.q_world_body_sp = Eigen::Quaterniond(R_world_body_sp);

  // Lee et al.'s f = -m (a - g) . R e3: only the part along the present thrust axis, so a body
  // still turning towards the setpoint does not push the wrong way with the full force.
  const Eigen::Vector3d thrust_axis_world = -(state.q_world_body * Eigen::Vector3d::UnitZ());
  double thrust_m_s2 = thrust_accel_m_s2.dot(thrust_axis_world);
  if (thrust_m_s2 < params_.thrust_min_m_s2 || thrust_m_s2 > params_.thrust_max_m_s2) {
    thrust_m_s2 = std::clamp(thrust_m_s2, params_.thrust_min_m_s2, params_.thrust_max_m_s2);
    out.thrust_limited = true;
  }
  out.thrust_n = mass_kg_ * thrust_m_s2;

  // The integral after the output (it acts from the next update), held while this output is
  // limited unless it unwinds: a limited loop cannot use more of it.
  const bool limited = out.tilt_limited || out.thrust_limited;
  for (int axis = 0; axis < 3 && dt_s > 0.0; ++axis) {
    const double limit = params_.integral_limit_m_s2(axis);
    const double grown = std::clamp(
        integral_m_s2_(axis) + params_.i_gain_1_s3(axis) * error_p_m(axis) * dt_s, -limit, limit);
    if (!limited || std::abs(grown) < std::abs(integral_m_s2_(axis))) {
      integral_m_s2_(axis) = grown;
    }
  }
  return out;
}

}  // namespace kinfly::flight
