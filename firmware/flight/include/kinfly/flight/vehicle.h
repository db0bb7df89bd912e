// The quadrotor as the controllers see it: mass, inertia, rotor geometry and the quadratic rotor
// model (thrust = k_f w^2, drag moment = k_m w^2), and the allocation matrix that maps the four
// squared rotor speeds to the collective thrust and the body moments (docs/flight.md, "Vehicle").
//
// Frames: body FRD; thrust acts along -z_body. Rotors are numbered as PX4's quad X / quad +:
//   X: 1 front-right CCW, 2 rear-left CCW, 3 front-left CW, 4 rear-right CW
//   +: 1 right CCW,       2 left CCW,      3 front CW,      4 rear CW
// (spin seen from above). A CCW rotor's drag turns the body clockwise from above: +z_body moment.
#pragma once

#include <Eigen/Core>

#include "kinfly/core/status.h"

namespace kinfly::flight {

enum class RotorLayout { kX, kPlus };

// The defaults are RotorPy's AscTec Hummingbird (spencerfolk/rotorpy,
// rotorpy/vehicles/hummingbird_params.py), so that the benchmark against RotorPy flies the same
// vehicle. RotorPy numbers its rotors FLU-wise (r1 front-left, r2 front-right, r3 rear-right, r4
// rear-left): kinfly's 1, 2, 3, 4 are its r2, r4, r1, r3, with the same yaw moments (its
// rotor_directions +1 turns the body about z up: kinfly's CW rotors).
struct VehicleParams {
  double mass_kg = 0.500;                     // [kg] (0, 50]
  double inertia_xx_kg_m2 = 3.65e-3;          // [kg m^2] (0, 10] about x_body
  double inertia_yy_kg_m2 = 3.68e-3;          // [kg m^2] (0, 10] about y_body
  double inertia_zz_kg_m2 = 7.03e-3;          // [kg m^2] (0, 10] about z_body
  double arm_length_m = 0.17;                 // [m] (0, 2] centre of mass to each rotor axis
  RotorLayout layout = RotorLayout::kX;
  double thrust_coeff_n_s2_rad2 = 5.57e-6;    // [N/(rad/s)^2] (0, 1e-2] k_f
  double moment_coeff_nm_s2_rad2 = 1.36e-7;   // [N m/(rad/s)^2] (0, 1e-3] k_m
  double motor_time_constant_s = 0.005;       // [s] [0, 0.5] first-order rotor speed lag
  double rotor_speed_min_rad_s = 0.0;         // [rad/s] [0, max) the idle speed the ESC keeps
  double rotor_speed_max_rad_s = 1500.0;      // [rad/s] (min, 1e4]
  Status validate() const;  // also that the vehicle can hover within the rotor speed limits
};

using Vector4d = Eigen::Matrix<double, 4, 1>;

// The collective thrust along -z_body and the moments about the body axes.
struct Wrench {
  double thrust_n = 0.0;
  Eigen::Vector3d moment_body_nm = Eigen::Vector3d::Zero();
};

// The rotor geometry and the allocation of a validated VehicleParams; built once, used per tick.
class Vehicle {
 public:
  explicit Vehicle(const VehicleParams& params);

  const VehicleParams& params() const { return params_; }
  Eigen::Vector3d inertiaDiagKgM2() const;
  // Rotor i's centre in the body frame (z = 0: the rotor plane holds the centre of mass).
  Eigen::Vector3d rotorPositionBodyM(int i) const { return rotor_position_body_m_[i]; }
  // +1 for CCW rotors (their drag gives +z_body moment), -1 for CW.
  double spinDirection(int i) const { return spin_direction_[i]; }

  // [thrust_n; moment_body_nm] = allocation() * (rotor speed)^2.
  const Eigen::Matrix4d& allocation() const { return allocation_; }
  const Eigen::Matrix4d& allocationInverse() const { return allocation_inverse_; }

  Wrench wrenchFromRotorSpeeds(const Vector4d& rotor_speed_rad_s) const;
  // [rad/s] the speed of each rotor when all four carry the weight.
  double hoverRotorSpeedRadS() const;
  double weightN() const;

 private:
  VehicleParams params_;
  Eigen::Vector3d rotor_position_body_m_[4];
  double spin_direction_[4];
  Eigen::Matrix4d allocation_;
  Eigen::Matrix4d allocation_inverse_;
};

constexpr double kGravityMS2 = 9.81;  // [m/s^2] the flight stack's g; world z is down

}  // namespace kinfly::flight
