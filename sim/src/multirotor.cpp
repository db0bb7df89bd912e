#include "kinfly/sim/multirotor.h"

#include <algorithm>
#include <cmath>

#include "kinfly/core/range_check.h"

namespace kinfly::sim {

Status MultirotorParams::validate() const {
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
      outOfRange("vehicle.motor_time_constant_s", motor_time_constant_s, 0.0, 0.5, Bound::kOpen),
      outOfRange("vehicle.rotor_speed_max_rad_s", rotor_speed_max_rad_s, 0.0, 1e4, Bound::kOpen),
      outOfRange("vehicle.rotor_speed_min_rad_s", rotor_speed_min_rad_s, 0.0,
                 std::nextafter(rotor_speed_max_rad_s, 0.0)),
      outOfRange("vehicle.rotor_drag_coeff", rotor_drag_coeff, 0.0, 1e-2),
      outOfRange("vehicle.induced_inflow_coeff", induced_inflow_coeff, 0.0, 1e-2),
      outOfRange("vehicle.parasitic_drag_x", parasitic_drag_x, 0.0, 10.0),
      outOfRange("vehicle.parasitic_drag_y", parasitic_drag_y, 0.0, 10.0),
      outOfRange("vehicle.parasitic_drag_z", parasitic_drag_z, 0.0, 10.0),
      outOfRange("vehicle.body_radius_m", body_radius_m, 0.0, 5.0, Bound::kOpen),
      outOfRange("vehicle.gear_height_m", gear_height_m, 0.0, 1.0),
      outOfRange("vehicle.gear_sag_m", gear_sag_m, 0.0, 0.1, Bound::kOpen));
  if (!status.ok()) return status;
  const double hover_rad_s = std::sqrt(mass_kg * kGravityMS2 / (4.0 * thrust_coeff_n_s2_rad2));
  if (hover_rad_s <= rotor_speed_min_rad_s || hover_rad_s >= rotor_speed_max_rad_s) {
    return Status::error("vehicle: the hover rotor speed " + std::to_string(hover_rad_s) +
                         " rad/s must lie between rotor_speed_min_rad_s and rotor_speed_max_rad_s");
  }
  return {};
}

StatusOr<RotorLayout> parseRotorLayout(const std::string& text) {
  if (text == "x") return RotorLayout::kX;
  if (text == "plus") return RotorLayout::kPlus;
  return Status::error("vehicle.layout must be x or plus (got '" + text + "')");
}

Multirotor::Multirotor(const MultirotorParams& params)
    : params_(params),
      inertia_kg_m2_(params.inertia_xx_kg_m2, params.inertia_yy_kg_m2, params.inertia_zz_kg_m2),
      contact_z_m_(std::nan("")) {
  const double d = std::sqrt(0.5);
  const double xy_x[4][2] = {{d, d}, {-d, -d}, {d, -d}, {-d, d}};
  const double xy_plus[4][2] = {{0.0, 1.0}, {0.0, -1.0}, {1.0, 0.0}, {-1.0, 0.0}};
  const auto& xy = params.layout == RotorLayout::kX ? xy_x : xy_plus;
  const double spin[4] = {1.0, 1.0, -1.0, -1.0};
  for (int i = 0; i < 4; ++i) {
    rotor_position_body_m_[i] = params.arm_length_m * Eigen::Vector3d(xy[i][0], xy[i][1], 0.0);
    spin_direction_[i] = spin[i];
  }
}

double Multirotor::hoverRotorSpeedRadS() const {
  return std::sqrt(params_.mass_kg * kGravityMS2 / (4.0 * params_.thrust_coeff_n_s2_rad2));
}

void Multirotor::placeOnFloor(const Eigen::Vector2d& xy_world_m, double yaw_rad,
                              double floor_z_m) {
  state_ = MultirotorState{};
  contact_z_m_ = floor_z_m - params_.gear_height_m;
  state_.p_world_m << xy_world_m, contact_z_m_ + params_.gear_sag_m;
  state_.q_world_body = Eigen::AngleAxisd(yaw_rad, Eigen::Vector3d::UnitZ());
  on_floor_ = true;
  specific_force_body_m_s2_ = Eigen::Vector3d(0.0, 0.0, -kGravityMS2);
}

void Multirotor::placeHovering(const Eigen::Vector3d& p_world_m, double yaw_rad) {
  state_ = MultirotorState{};
  state_.p_world_m = p_world_m;
  state_.q_world_body = Eigen::AngleAxisd(yaw_rad, Eigen::Vector3d::UnitZ());
  state_.rotor_speed_rad_s.setConstant(hoverRotorSpeedRadS());
  on_floor_ = false;
  specific_force_body_m_s2_ = Eigen::Vector3d(0.0, 0.0, -kGravityMS2);
}

Multirotor::Derivative Multirotor::derivative(const MultirotorState& s,
                                              const Vector4d& rotor_speed_cmd_rad_s,
                                              const Eigen::Vector3d& wind_world_m_s) const {
  const Eigen::Quaterniond q = s.q_world_body.normalized();
  // The air's velocity relative to the body, in the body.
  const Eigen::Vector3d v_air_body = q.conjugate() * (s.v_world_m_s - wind_world_m_s);
  Eigen::Vector3d force_body_n = Eigen::Vector3d::Zero();
  Eigen::Vector3d moment_body_nm = Eigen::Vector3d::Zero();
  for (int i = 0; i < 4; ++i) {
    const double speed = s.rotor_speed_rad_s(i);
    const double thrust_n = efficiency_[i] * params_.thrust_coeff_n_s2_rad2 * speed * speed;
    const Eigen::Vector3d& r = rotor_position_body_m_[i];
    // Rotor drag and induced inflow: linear in the air speed at the rotor and in its spin.
    const Eigen::Vector3d v_rotor = v_air_body + s.omega_body_rad_s.cross(r);
    const Eigen::Vector3d drag_n(-params_.rotor_drag_coeff * speed * v_rotor.x(),
                                 -params_.rotor_drag_coeff * speed * v_rotor.y(),
                                 -params_.induced_inflow_coeff * speed * v_rotor.z());
    const Eigen::Vector3d rotor_force_n = Eigen::Vector3d(0.0, 0.0, -thrust_n) + drag_n;
    force_body_n += rotor_force_n;
    moment_body_nm += r.cross(rotor_force_n);
    moment_body_nm.z() +=
        spin_direction_[i] * efficiency_[i] * params_.moment_coeff_nm_s2_rad2 * speed * speed;
  }
  const Eigen::Vector3d parasitic(params_.parasitic_drag_x, params_.parasitic_drag_y,
                                  params_.parasitic_drag_z);
  force_body_n -= v_air_body.norm() * parasitic.cwiseProduct(v_air_body);

  Eigen::Vector3d floor_world_n = Eigen::Vector3d::Zero();
  Eigen::Vector3d floor_moment_body_nm = Eigen::Vector3d::Zero();
  floorWrench(s, &floor_world_n, &floor_moment_body_nm);
  moment_body_nm += floor_moment_body_nm;

  Derivative d;
  d.p = s.v_world_m_s;
  d.v = Eigen::Vector3d(0.0, 0.0, kGravityMS2) + (q * force_body_n + floor_world_n) / params_.mass_kg;
  const Eigen::Quaterniond omega_quat(0.0, s.omega_body_rad_s.x(), s.omega_body_rad_s.y(),
                                      s.omega_body_rad_s.z());
  d.q = 0.5 * (q * omega_quat).coeffs();
  d.omega = (moment_body_nm -
             s.omega_body_rad_s.cross(inertia_kg_m2_.cwiseProduct(s.omega_body_rad_s)))
                .cwiseQuotient(inertia_kg_m2_);
  d.rotor = (rotor_speed_cmd_rad_s - s.rotor_speed_rad_s) / params_.motor_time_constant_s;
  return d;
}

MultirotorState Multirotor::advanced(const MultirotorState& s, const Derivative& d, double dt_s) {
  MultirotorState next = s;
  next.p_world_m += dt_s * d.p;
  next.v_world_m_s += dt_s * d.v;
  next.q_world_body.coeffs() += dt_s * d.q;
  next.q_world_body.normalize();
  next.omega_body_rad_s += dt_s * d.omega;
  next.rotor_speed_rad_s += dt_s * d.rotor;
  return next;
}

void Multirotor::floorWrench(const MultirotorState& s, Eigen::Vector3d* force_world_n,
                             Eigen::Vector3d* moment_body_nm) const {
  const double penetration_m = s.p_world_m.z() - contact_z_m_;  // z down: > 0 when pressed in
  if (std::isnan(contact_z_m_) || penetration_m <= 0.0) return;
  // A critically damped spring that sags gear_sag_m under the weight; it pushes, never pulls.
  const double stiffness_n_m = params_.mass_kg * kGravityMS2 / params_.gear_sag_m;
  const double damping_n_s_m = 2.0 * std::sqrt(stiffness_n_m * params_.mass_kg);
  const double push_n =
      std::max(0.0, stiffness_n_m * penetration_m + damping_n_s_m * s.v_world_m_s.z());
  // Friction along the floor, viscous (no stick-slip: a drone on skids barely slides anyway),
  // as strong as the push: a sliding body stops within centimetres.
  const double friction_n_s_m = damping_n_s_m;
  force_world_n->x() = -friction_n_s_m * s.v_world_m_s.x();
  force_world_n->y() = -friction_n_s_m * s.v_world_m_s.y();
  force_world_n->z() = -push_n;
  // The gear levels a tilted body (a spring on its tilt, critically damped about the smaller
  // inertia) and resists turning on the floor, in proportion to how firmly it stands.
  const double load = std::min(1.0, push_n / (params_.mass_kg * kGravityMS2));
  const double inertia_xy = std::min(params_.inertia_xx_kg_m2, params_.inertia_yy_kg_m2);
  const double tilt_stiffness_nm_rad = stiffness_n_m * params_.arm_length_m * params_.arm_length_m;
  const double tilt_damping_nm_s_rad = 2.0 * std::sqrt(tilt_stiffness_nm_rad * inertia_xy);
  // The rotation about a body axis that takes the body's up onto the world's, as axis * angle
  // (horizontal in the body: both are ups).
  const Eigen::Vector3d up_body(0.0, 0.0, -1.0);
  const Eigen::Vector3d world_up_in_body = s.q_world_body.conjugate() * up_body;
  const Eigen::Vector3d axis = up_body.cross(world_up_in_body);
  const double sin_tilt = axis.norm();
  const Eigen::Vector3d tilt_rad =
      sin_tilt > 1e-12 ? Eigen::Vector3d(axis / sin_tilt *
                                         std::atan2(sin_tilt, up_body.dot(world_up_in_body)))
                       : Eigen::Vector3d::Zero();
  const Eigen::Vector3d level_body_nm =
      tilt_stiffness_nm_rad * tilt_rad - tilt_damping_nm_s_rad * s.omega_body_rad_s;
  *moment_body_nm = load * level_body_nm;
}

double Multirotor::step(const Vector4d& rotor_speed_cmd_rad_s,
                        const Eigen::Vector3d& wind_world_m_s, double dt_s) {
  const Vector4d cmd = rotor_speed_cmd_rad_s.cwiseMax(params_.rotor_speed_min_rad_s)
                           .cwiseMin(params_.rotor_speed_max_rad_s);
  const Eigen::Vector3d v_before_world_m_s = state_.v_world_m_s;
  const Derivative k1 = derivative(state_, cmd, wind_world_m_s);
  const Derivative k2 = derivative(advanced(state_, k1, 0.5 * dt_s), cmd, wind_world_m_s);
  const Derivative k3 = derivative(advanced(state_, k2, 0.5 * dt_s), cmd, wind_world_m_s);
  const Derivative k4 = derivative(advanced(state_, k3, dt_s), cmd, wind_world_m_s);
  Derivative sum;
  sum.p = k1.p + 2.0 * k2.p + 2.0 * k3.p + k4.p;
  sum.v = k1.v + 2.0 * k2.v + 2.0 * k3.v + k4.v;
  sum.q = k1.q + 2.0 * k2.q + 2.0 * k3.q + k4.q;
  sum.omega = k1.omega + 2.0 * k2.omega + 2.0 * k3.omega + k4.omega;
  sum.rotor = k1.rotor + 2.0 * k2.rotor + 2.0 * k3.rotor + k4.rotor;
  state_ = advanced(state_, sum, dt_s / 6.0);
  // The rotors' lag keeps them within their limits, but a step longer than the lag overshoots.
  state_.rotor_speed_rad_s = state_.rotor_speed_rad_s.cwiseMax(0.0).cwiseMin(
      params_.rotor_speed_max_rad_s);
  // The accelerometer reads the step's mean acceleration less gravity: what RK4 integrated.
  const Eigen::Vector3d a_world_m_s2 = (state_.v_world_m_s - v_before_world_m_s) / dt_s;
  specific_force_body_m_s2_ =
      state_.q_world_body.conjugate() * (a_world_m_s2 - Eigen::Vector3d(0.0, 0.0, kGravityMS2));
  const bool was_on_floor = on_floor_;
  on_floor_ = !std::isnan(contact_z_m_) && state_.p_world_m.z() >= contact_z_m_;
  return on_floor_ && !was_on_floor ? v_before_world_m_s.norm() : 0.0;
}

}  // namespace kinfly::sim
