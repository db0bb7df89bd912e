// A test plant for the flight stack's closed-loop tests and its benchmark, not part of the
// library. The simulator proper (sim/, kinfly::sim::Multirotor) has a richer model of the same
// body, but it is built natively only (Embree), and these tests also run cross-built under qemu;
// this plant keeps them free of it: a 6-DoF rigid body in the flight stack's world
// (z down, gravity +z), the rotors' thrust and drag quadratic in their speed, each rotor
// following its command with a first-order lag, integrated by RK4 with the command held over the
// step. The wrench comes from the rotor positions and spins by cross products, not from the
// library's allocation matrix, so a wrong matrix shows. Gyro and accelerometer readings
// optionally carry white noise of a given density from a seeded generator. A steady wind pushes
// the body by linear drag on the air speed.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cmath>
#include <cstdint>

#include "gaussian.h"
#include "kinfly/flight/vehicle.h"

namespace kinfly::flight::test {

struct PlantState {
  Eigen::Vector3d p_world_m = Eigen::Vector3d::Zero();
  Eigen::Vector3d v_world_m_s = Eigen::Vector3d::Zero();
  Eigen::Quaterniond q_world_body = Eigen::Quaterniond::Identity();
  Eigen::Vector3d omega_body_rad_s = Eigen::Vector3d::Zero();
  Vector4d rotor_speed_rad_s = Vector4d::Zero();
};

class FlightPlant {
 public:
  // Noise densities: 0 for exact sensors; a MEMS IMU (ICM-42688) has ~5e-5 rad/s/sqrt(Hz) and
  // ~7e-4 m/s^2/sqrt(Hz).
  FlightPlant(const Vehicle& vehicle, double gyro_noise_density_rad_s_rt_hz = 0.0,
              uint32_t seed = 1, double accel_noise_density_m_s2_rt_hz = 0.0)
      : vehicle_(vehicle),
        gyro_noise_density_(gyro_noise_density_rad_s_rt_hz),
        accel_noise_density_(accel_noise_density_m_s2_rt_hz),
        gaussian_(seed) {}

  // At rest in the air at p_world_m, the rotors already at hover speed.
  void startHovering(const Eigen::Vector3d& p_world_m = Eigen::Vector3d::Zero()) {
    state_ = PlantState{};
    state_.p_world_m = p_world_m;
    state_.rotor_speed_rad_s.setConstant(vehicle_.hoverRotorSpeedRadS());
  }
  // A steady wind: the air pushes the body with drag_n_s_m times the air's velocity relative to
  // it, a constant force while the body holds its place.
  void setWind(const Eigen::Vector3d& wind_world_m_s, double drag_n_s_m) {
    wind_world_m_s_ = wind_world_m_s;
    drag_n_s_m_ = drag_n_s_m;
  }
  void setAttitude(const Eigen::Quaterniond& q_world_body) { state_.q_world_body = q_world_body; }
  // Held still (not stepped) by a stand, whatever the rotors and the wind do: the accelerometer
  // then feels the hold, gravity's support alone, as a real one on a held body does.
  void hold(bool held) { held_ = held; }

  void step(const Vector4d& rotor_speed_cmd_rad_s, double dt_s) {
    // Without lag the rotors are where they are told, and derivative() leaves them there.
    if (vehicle_.params().motor_time_constant_s == 0.0) {
      state_.rotor_speed_rad_s = rotor_speed_cmd_rad_s;
    }
    const Derivative k1 = derivative(state_, rotor_speed_cmd_rad_s);
    const Derivative k2 = derivative(advanced(state_, k1, 0.5 * dt_s), rotor_speed_cmd_rad_s);
    const Derivative k3 = derivative(advanced(state_, k2, 0.5 * dt_s), rotor_speed_cmd_rad_s);
    const Derivative k4 = derivative(advanced(state_, k3, dt_s), rotor_speed_cmd_rad_s);
    Derivative sum;
    sum.p = k1.p + 2.0 * k2.p + 2.0 * k3.p + k4.p;
    sum.v = k1.v + 2.0 * k2.v + 2.0 * k3.v + k4.v;
    sum.q = k1.q + 2.0 * k2.q + 2.0 * k3.q + k4.q;
    sum.omega = k1.omega + 2.0 * k2.omega + 2.0 * k3.omega + k4.omega;
    sum.rotor = k1.rotor + 2.0 * k2.rotor + 2.0 * k3.rotor + k4.rotor;
    state_ = advanced(state_, sum, dt_s / 6.0);
    sample_rate_hz_ = 1.0 / dt_s;
    const Eigen::Vector3d v_free_world_m_s = state_.v_world_m_s;
    touchGround();
    // What the floor did to the velocity over the step, as the accelerometer feels it: the
    // landing's jolt, and the floor's push against gravity while resting on it.
    contact_accel_world_m_s2_ = (state_.v_world_m_s - v_free_world_m_s) / dt_s;
  }

  // A floor at world height ground_z_m (z down): the body stops on it, level at its heading, and
  // rests there until the thrust lifts it again. Landing is inelastic and sticky, as on skids.
  void setGround(double ground_z_m) { ground_z_m_ = ground_z_m; }
  // At rest on the floor at p_world_m, the rotors stopped.
  void startOnGround(const Eigen::Vector3d& p_world_m) {
    state_ = PlantState{};
    state_.p_world_m = p_world_m;
    setGround(p_world_m.z());
    on_ground_ = true;
  }
  bool onGround() const { return on_ground_; }

  const PlantState& state() const { return state_; }

  // The gyro's reading of the present state: white noise at the rate of the last step.
  Eigen::Vector3d gyroBodyRadS() {
    if (gyro_noise_density_ == 0.0) return state_.omega_body_rad_s;
    const double sigma = gyro_noise_density_ * std::sqrt(sample_rate_hz_);
    return state_.omega_body_rad_s + sigma * gaussian_();
  }
  // The accelerometer's reading of the present state: the specific force (all but gravity) in
  // the body, white noise at the rate of the last step.
  Eigen::Vector3d accelBodyMS2() {
    // The rotor command moves only the rotors' derivative, not the body's acceleration.
    const Eigen::Vector3d a_world_m_s2 =
        held_ ? Eigen::Vector3d::Zero()
              : Eigen::Vector3d(derivative(state_, state_.rotor_speed_rad_s).v +
                                contact_accel_world_m_s2_);
    const Eigen::Vector3d specific_force_body_m_s2 =
        state_.q_world_body.conjugate() * (a_world_m_s2 - Eigen::Vector3d(0.0, 0.0, kGravityMS2));
    if (accel_noise_density_ == 0.0) return specific_force_body_m_s2;
    const double sigma = accel_noise_density_ * std::sqrt(sample_rate_hz_);
    return specific_force_body_m_s2 + sigma * gaussian_();
  }

 private:
  void touchGround() {
    on_ground_ = false;
    // Lifting off, the step leaves the body above the floor.
    if (std::isnan(ground_z_m_) || state_.p_world_m.z() < ground_z_m_) return;
    const Eigen::Vector3d x_body_world = state_.q_world_body * Eigen::Vector3d::UnitX();
    state_.p_world_m.z() = ground_z_m_;
    state_.v_world_m_s.setZero();
    state_.omega_body_rad_s.setZero();
    state_.q_world_body =
        Eigen::AngleAxisd(std::atan2(x_body_world.y(), x_body_world.x()), Eigen::Vector3d::UnitZ());
    on_ground_ = true;
  }

  // Time derivative of the state; q holds dq/dt as a 4-vector (x, y, z, w).
  struct Derivative {
    Eigen::Vector3d p = Eigen::Vector3d::Zero();
    Eigen::Vector3d v = Eigen::Vector3d::Zero();
    Eigen::Vector4d q = Eigen::Vector4d::Zero();
    Eigen::Vector3d omega = Eigen::Vector3d::Zero();
    Vector4d rotor = Vector4d::Zero();
  };

  Derivative derivative(const PlantState& s, const Vector4d& rotor_speed_cmd_rad_s) const {
    const VehicleParams& params = vehicle_.params();
    double thrust_n = 0.0;
    Eigen::Vector3d moment_body_nm = Eigen::Vector3d::Zero();
    for (int i = 0; i < 4; ++i) {
      const double speed_sq = s.rotor_speed_rad_s(i) * s.rotor_speed_rad_s(i);
      const Eigen::Vector3d force_body_n(0.0, 0.0, -params.thrust_coeff_n_s2_rad2 * speed_sq);
      thrust_n += -force_body_n.z();
      moment_body_nm += vehicle_.rotorPositionBodyM(i).cross(force_body_n);
      moment_body_nm.z() += vehicle_.spinDirection(i) * params.moment_coeff_nm_s2_rad2 * speed_sq;
    }
    const Eigen::Vector3d inertia = vehicle_.inertiaDiagKgM2();
    Derivative d;
    d.p = s.v_world_m_s;
    const Eigen::Vector3d drag_world_n = drag_n_s_m_ * (wind_world_m_s_ - s.v_world_m_s);
    d.v = Eigen::Vector3d(0.0, 0.0, kGravityMS2) + drag_world_n / params.mass_kg +
          s.q_world_body.normalized() * Eigen::Vector3d(0.0, 0.0, -thrust_n / params.mass_kg);
    const Eigen::Quaterniond omega_quat(0.0, s.omega_body_rad_s.x(), s.omega_body_rad_s.y(),
                                        s.omega_body_rad_s.z());
    d.q = 0.5 * (s.q_world_body * omega_quat).coeffs();
    d.omega = (moment_body_nm -
               s.omega_body_rad_s.cross(inertia.cwiseProduct(s.omega_body_rad_s)))
                  .cwiseQuotient(inertia);
    if (params.motor_time_constant_s > 0.0) {
      d.rotor = (rotor_speed_cmd_rad_s - s.rotor_speed_rad_s) / params.motor_time_constant_s;
    }
    return d;
  }

  PlantState advanced(const PlantState& s, const Derivative& d, double dt_s) const {
    PlantState next = s;
    next.p_world_m += dt_s * d.p;
    next.v_world_m_s += dt_s * d.v;
    next.q_world_body.coeffs() += dt_s * d.q;
    next.q_world_body.normalize();
    next.omega_body_rad_s += dt_s * d.omega;
    next.rotor_speed_rad_s += dt_s * d.rotor;
    return next;
  }

  const Vehicle& vehicle_;
  PlantState state_;
  double gyro_noise_density_;
  double accel_noise_density_;
  Eigen::Vector3d wind_world_m_s_ = Eigen::Vector3d::Zero();
  double drag_n_s_m_ = 0.0;
  double sample_rate_hz_ = 1000.0;
  double ground_z_m_ = NAN;  // no floor
  Eigen::Vector3d contact_accel_world_m_s2_ = Eigen::Vector3d::Zero();
  bool held_ = false;
  bool on_ground_ = false;
  Gaussian gaussian_;
};

}  // namespace kinfly::flight::test
