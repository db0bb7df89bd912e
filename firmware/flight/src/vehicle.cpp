#include "kinfly/flight/vehicle.h"

#include <Eigen/LU>
#include <cmath>

#include "kinfly/core/range_check.h"

namespace kinfly::flight {

Status VehicleParams::validate() const {
  Status status = firstError(
      outOfRange("vehicle.mass_kg", mass_kg, 0.0, 50.0, Bound::kOpen),
      outOfRange("vehicle.inertia_xx_kg_m2", inertia_xx_kg_m2, 0.0, 10.0, Bound::kOpen),
      outOfRange("vehicle.inertia_yy_kg_m2", inertia_yy_kg_m2, 0.0, 10.0, Bound::kOpen),
      outOfRange("vehicle.inertia_zz_kg_m2", inertia_zz_kg_m2, 0.0, 10.0, Bound::kOpen),
      outOfRange("vehicle.arm_length_m", arm_length_m, 0.0, 2.0, Bound::kOpen),
      outOfRange("vehicle.thrust_coeff_n_s2_rad2", thrust_coeff_n_s2_rad2, 0.0, 1e-2,
                 Bound::kOpen),
      outOfRange("vehicle.moment_coeff_nm_s2_rad2", moment_coeff_nm_s2_rad2, 0.0, 1e-3,
                 Bound::kOpen),
      outOfRange("vehicle.motor_time_constant_s", motor_time_constant_s, 0.0, 0.5),
      outOfRange("vehicle.rotor_speed_max_rad_s", rotor_speed_max_rad_s, 0.0, 1e4, Bound::kOpen),
      outOfRange("vehicle.rotor_speed_min_rad_s", rotor_speed_min_rad_s, 0.0,
                 std::nextafter(rotor_speed_max_rad_s, 0.0)));
  if (!status.ok()) return status;
  // Hovering at either limit leaves no room to control: demand a margin on both sides.
  const double hover_rad_s = std::sqrt(mass_kg * kGravityMS2 / (4.0 * thrust_coeff_n_s2_rad2));
  if (hover_rad_s <= rotor_speed_min_rad_s || hover_rad_s >= rotor_speed_max_rad_s) {
    return Status::error("vehicle: the hover rotor speed " + std::to_string(hover_rad_s) +
                         " rad/s must lie between rotor_speed_min_rad_s and rotor_speed_max_rad_s");
  }
  return {};
}

Vehicle::Vehicle(const VehicleParams& params) : params_(params) {
  // (x, y) in units of the arm length and the spin, in PX4's rotor order (vehicle.h).
  const double d = params.layout == RotorLayout::kX ? std::sqrt(0.5) : 1.0;
  const double xy_x[4][2] = {{d, d}, {-d, -d}, {d, -d}, {-d, d}};
  const double xy_plus[4][2] = {{0.0, 1.0}, {0.0, -1.0}, {1.0, 0.0}, {-1.0, 0.0}};
  const auto& xy = params.layout == RotorLayout::kX ? xy_x : xy_plus;
  const double spin[4] = {1.0, 1.0, -1.0, -1.0};
  const double k_f = params.thrust_coeff_n_s2_rad2;
  for (int i = 0; i < 4; ++i) {
    rotor_position_body_m_[i] = params.arm_length_m * Eigen::Vector3d(xy[i][0], xy[i][1], 0.0);
    spin_direction_[i] = spin[i];
    // Thrust f = (0, 0, -k_f w^2) at r: moment r x f = k_f w^2 (-y, x, 0).
    allocation_.col(i) << k_f, -k_f * rotor_position_body_m_[i].y(),
        k_f * rotor_position_body_m_[i].x(), spin[i] * params.moment_coeff_nm_s2_rad2;
  }
  allocation_inverse_ = allocation_.inverse();
}

Eigen::Vector3d Vehicle::inertiaDiagKgM2() const {
  return {params_.inertia_xx_kg_m2, params_.inertia_yy_kg_m2, params_.inertia_zz_kg_m2};
}

Wrench Vehicle::wrenchFromRotorSpeeds(const Vector4d& rotor_speed_rad_s) const {
  const Vector4d wrench = allocation_ * rotor_speed_rad_s.cwiseAbs2();
  return {wrench(0), wrench.tail<3>()};
}

double Vehicle::weightN() const { return params_.mass_kg * kGravityMS2; }

double Vehicle::hoverRotorSpeedRadS() const {
  return std::sqrt(weightN() / (4.0 * params_.thrust_coeff_n_s2_rad2));
}

}  // namespace kinfly::flight
