#include "kinfly/flight/attitude_controller.h"

#include <algorithm>
#include <cmath>
#include <string>

#include "axes_in_range.h"
#include "kinfly/core/range_check.h"
#include "kinfly/flight/riccati.h"

namespace kinfly::flight {

namespace {

// Below this the two body z axes point opposite ways and the tilt rotation has no unique axis.
constexpr double kAntiparallelCos = -1.0 + 1e-5;

}  // namespace

Status GeometricAttitudeParams::validate() const {
  return firstError(
      axesInRange("attitude.geometric.p_gain_1_s", p_gain_1_s, kBodyAxes, 0.0, 100.0),
      axesInRange("attitude.geometric.rate_limit_rad_s", rate_limit_rad_s, kBodyAxes, 0.0, 30.0,
                  Bound::kOpen));
}

Status LqrAttitudeParams::validate() const {
  return firstError(
      outOfRange("attitude.lqr.control_rate_hz", control_rate_hz, 50.0, 1e4),
      axesInRange("attitude.lqr.attitude_weight_1_rad2", attitude_weight_1_rad2, kBodyAxes, 0.0,
                  1e10, Bound::kOpen),
      axesInRange("attitude.lqr.rate_weight_s2_rad2", rate_weight_s2_rad2, kBodyAxes, 0.0, 1e10),
      // Unweighted, the integral would be a mode at 1 the gain never moves: no stabilising P.
      axesInRange("attitude.lqr.integral_weight_1_rad2_s2", integral_weight_1_rad2_s2, kBodyAxes,
                  0.0, 1e10, Bound::kOpen),
      outOfRange("attitude.lqr.accel_weight_s4_rad2", accel_weight_s4_rad2, 0.0, 1e6,
                 Bound::kOpen),
      axesInRange("attitude.lqr.integral_limit_rad_s", integral_limit_rad_s, kBodyAxes, 0.0, 10.0),
      outOfRange("attitude.lqr.integral_band_rad", integral_band_rad, 0.0, M_PI));
}

Status AttitudeController::Params::validate() const {
  return firstError(geometric.validate(), lqr.validate(), rate.validate());
}

StatusOr<LqrDesign> designAttitudeLqr(const LqrAttitudeParams& params, const Vehicle& vehicle) {
  const Eigen::Vector3d inertia_kg_m2 = vehicle.inertiaDiagKgM2();
  const double dt_s = 1.0 / params.control_rate_hz;
  // Continuous model about hover, [x; u]' = F [x; u]: error' = rate, rate' = J^-1 u,
  // integral' = error; the input is held over the period (zero-order hold).
  Eigen::Matrix<double, 12, 12> F = Eigen::Matrix<double, 12, 12>::Zero();
  F.block<3, 3>(0, 3).setIdentity();
  F.block<3, 3>(3, 9) = inertia_kg_m2.cwiseInverse().asDiagonal();
  F.block<3, 3>(6, 0).setIdentity();
  // exp(F dt) by its series, which is finite: F is nilpotent (F^4 = 0), so this is exact.
  Eigen::Matrix<double, 12, 12> term = Eigen::Matrix<double, 12, 12>::Identity();
  Eigen::Matrix<double, 12, 12> transition = term;
  for (int k = 1; k <= 4; ++k) {
    term = term * F * (dt_s / k);
    transition += term;
  }
  LqrDesign design;
  design.A = transition.topLeftCorner<9, 9>();
  design.B = transition.topRightCorner<9, 3>();
  design.Q.setZero();
  design.Q.diagonal() << params.attitude_weight_1_rad2, params.rate_weight_s2_rad2,
      params.integral_weight_1_rad2_s2;
  design.R = (params.accel_weight_s4_rad2 * inertia_kg_m2.cwiseAbs2().cwiseInverse()).asDiagonal();

  auto solved = solveDiscreteRiccati(design.A, design.B, design.Q, design.R);
  if (!solved.ok()) return Status::error("attitude.lqr: " + solved.status().message());
  design.P = solved->P;
  design.K = solved->K;
  design.doubling_steps = solved->doubling_steps;
  design.closed_loop_spectral_radius = solved->closed_loop_spectral_radius;
  return design;
}

Eigen::Vector3d attitudeErrorBodyRad(const Eigen::Quaterniond& q_world_body,
                                     const Eigen::Quaterniond& q_world_body_sp,
                                     double yaw_weight) {
  const Eigen::Vector3d z_world = q_world_body * Eigen::Vector3d::UnitZ();
  const Eigen::Vector3d z_sp_world = q_world_body_sp * Eigen::Vector3d::UnitZ();
  Eigen::Quaterniond q_world_reduced = q_world_body_sp;
  if (z_world.dot(z_sp_world) > kAntiparallelCos) {
    // The current attitude tilted the shortest way onto the setpoint's z axis: tilt done, yaw
    // as it is now.
    q_world_reduced = Eigen::Quaterniond::FromTwoVectors(z_world, z_sp_world) * q_world_body;
    // What is left is a yaw about that common z axis; take yaw_weight of it.
    Eigen::Quaterniond q_yaw = q_world_reduced.conjugate() * q_world_body_sp;
    if (q_yaw.w() < 0.0) q_yaw.coeffs() = -q_yaw.coeffs();
    const double half_yaw_rad = std::atan2(q_yaw.z(), q_yaw.w());
    q_world_reduced = q_world_reduced * Eigen::Quaterniond(std::cos(yaw_weight * half_yaw_rad), 0.0,
                                                           0.0, std::sin(yaw_weight * half_yaw_rad));
  }
  Eigen::Quaterniond q_error = q_world_body.conjugate() * q_world_reduced;
  if (q_error.w() < 0.0) q_error.coeffs() = -q_error.coeffs();  // the shorter way round
  // 2 sin(angle / 2) along the axis: the rotation vector to second order, bounded for any error.
  return 2.0 * q_error.vec();
}

Eigen::Vector3d geometricRateSetpointRadS(const GeometricAttitudeParams& params,
                                          const Eigen::Quaterniond& q_world_body,
                                          const Eigen::Quaterniond& q_world_body_sp) {
  // Yaw as much slower than tilt as its gain says: the tilt gain is the reference.
  const double tilt_gain_1_s = 0.5 * (params.p_gain_1_s.x() + params.p_gain_1_s.y());
  const double yaw_weight =
      tilt_gain_1_s > 0.0 ? std::clamp(params.p_gain_1_s.z() / tilt_gain_1_s, 0.0, 1.0) : 1.0;
  const Eigen::Vector3d error_rad =
      attitudeErrorBodyRad(q_world_body, q_world_body_sp, yaw_weight);
  Eigen::Vector3d rate_sp_rad_s = params.p_gain_1_s.cwiseProduct(error_rad);
  // The yaw gain already lives in yaw_weight's reduced error: apply the tilt gain to yaw too.
  rate_sp_rad_s.z() = tilt_gain_1_s * error_rad.z();
  return rate_sp_rad_s.cwiseMax(-params.rate_limit_rad_s).cwiseMin(params.rate_limit_rad_s);
}

AttitudeController::AttitudeController(const Params& params, const Vehicle& vehicle,
                                       const LqrDesign& lqr)
    : params_(params), rate_(params.rate, vehicle), lqr_(lqr) {}

StatusOr<AttitudeController> AttitudeController::create(const Params& params,
                                                        const Vehicle& vehicle) {
  if (Status valid = params.validate(); !valid.ok()) return valid;
  auto lqr = designAttitudeLqr(params.lqr, vehicle);
  if (!lqr.ok()) return lqr.status();
  return AttitudeController(params, vehicle, *lqr);
}

void AttitudeController::reset() {
  rate_.reset();
  integral_rad_s_.setZero();
}

void AttitudeController::setLaw(AttitudeLaw law) {
  if (law != params_.law) reset();  // neither law's memory means anything to the other
  params_.law = law;
}

Eigen::Vector3d AttitudeController::update(const Eigen::Quaterniond& q_world_body,
                                           const Eigen::Quaterniond& q_world_body_sp,
                                           const Eigen::Vector3d& omega_body_rad_s, double dt_s,
                                           const MixerSaturation& saturation) {
  if (params_.law == AttitudeLaw::kGeometric) {
    RateSetpoint rate_sp;
    rate_sp.omega_body_rad_s =
        geometricRateSetpointRadS(params_.geometric, q_world_body, q_world_body_sp);
    return rate_.update(rate_sp, omega_body_rad_s, dt_s, saturation);
  }
  // The LQR's state is the error of the body from the setpoint, the opposite of the correction.
  const Eigen::Vector3d error_rad = -attitudeErrorBodyRad(q_world_body, q_world_body_sp, 1.0);
  Eigen::Matrix<double, 9, 1> state;
  state << error_rad, omega_body_rad_s, integral_rad_s_;
  const Eigen::Vector3d moment_body_nm = -lqr_.K * state;
  // An axis the mixer cut keeps its integral, whichever way: the gain couples no axes.
  for (int axis = 0; axis < 3 && dt_s > 0.0; ++axis) {  // no time, no integral (as the rate PID)
    if (saturation.moment_cut_positive[axis] || saturation.moment_cut_negative[axis]) continue;
    if (std::abs(error_rad(axis)) > params_.lqr.integral_band_rad) continue;
    const double limit = params_.lqr.integral_limit_rad_s(axis);
    integral_rad_s_(axis) =
        std::clamp(integral_rad_s_(axis) + error_rad(axis) * dt_s, -limit, limit);
  }
  return moment_body_nm;
}

const char* toString(AttitudeLaw law) {
  switch (law) {
    case AttitudeLaw::kGeometric: return "geometric";
    case AttitudeLaw::kLqr: return "lqr";
  }
  return "?";
}

}  // namespace kinfly::flight
