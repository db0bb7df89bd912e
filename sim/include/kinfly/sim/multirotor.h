// The simulated quadrotor: a 6-DoF rigid body in the simulator's world (gravity-aligned, z down,
// as the flight stack's), body FRD, integrated by RK4 with the rotor commands held over a step
// (docs/sim.md, "Dynamics"). Its model is its own, deliberately not the flight library's: the
// wrench comes from each rotor's position and spin by cross products, each rotor's speed follows
// its command with a first-order lag and its limits, each rotor drags linearly in the air speed
// at the rotor and in its spin (RotorPy's rotor drag and induced inflow), the frame drags
// quadratically, and a floor carries it on a landing gear that gives like one: a critically
// damped spring under the centre of mass, friction along the floor, and a spring-damper that
// levels the body while it stands (so a landing's impact reaches the accelerometer as real ones
// do, over tens of milliseconds, not as one step's jolt). The simulator's parameters may differ from
// what the controller believes; that difference is the point of a simulated flight.
//
// Rotors are numbered as PX4's quad X / quad + (and motor_command_t):
//   X: 1 front-right CCW, 2 rear-left CCW, 3 front-left CW, 4 rear-right CW
//   +: 1 right CCW,       2 left CCW,      3 front CW,      4 rear CW
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <string>

#include "kinfly/core/status.h"

namespace kinfly::sim {

using Vector4d = Eigen::Matrix<double, 4, 1>;

constexpr double kGravityMS2 = 9.81;  // [m/s^2] along +z of the world (z down)

enum class RotorLayout { kX, kPlus };

// The defaults are RotorPy's AscTec Hummingbird (rotorpy/vehicles/hummingbird_params.py), the
// vehicle kinfly-fw's flight stack assumes by default too.
struct MultirotorParams {
  double mass_kg = 0.500;                    // [kg] (0, 50]
  double inertia_xx_kg_m2 = 3.65e-3;         // [kg m^2] (0, 10]
  double inertia_yy_kg_m2 = 3.68e-3;         // [kg m^2] (0, 10]
  double inertia_zz_kg_m2 = 7.03e-3;         // [kg m^2] (0, 10]
  double arm_length_m = 0.17;                // [m] (0, 2] centre of mass to each rotor axis
  RotorLayout layout = RotorLayout::kX;
  double thrust_coeff_n_s2_rad2 = 5.57e-6;   // [N/(rad/s)^2] (0, 1e-2] k_f: thrust = k_f w^2
  double moment_coeff_nm_s2_rad2 = 1.36e-7;  // [N m/(rad/s)^2] (0, 1e-3] k_m: drag moment
  double motor_time_constant_s = 0.005;      // [s] (0, 0.5] first-order rotor speed lag
  double rotor_speed_min_rad_s = 0.0;        // [rad/s] [0, max) what an ESC can hold
  double rotor_speed_max_rad_s = 1500.0;     // [rad/s] (min, 1e4]
  // [N/(m/s)/(rad/s)] [0, 1e-2] k_d: each rotor's in-plane drag, -k_d w v_air,xy at the rotor
  double rotor_drag_coeff = 1.19e-4;
  // [N/(m/s)/(rad/s)] [0, 1e-2] k_z: each rotor's induced inflow, -k_z w v_air,z at the rotor
  double induced_inflow_coeff = 2.32e-4;
  // [N/(m/s)^2] [0, 10] the frame's parasitic drag per body axis, -c |v_air| v_air
  double parasitic_drag_x = 0.5e-2;
  double parasitic_drag_y = 0.5e-2;
  double parasitic_drag_z = 1e-2;
  double body_radius_m = 0.27;               // [m] (0, 5] arm + rotor: the sphere that collides
  double gear_height_m = 0.10;               // [m] [0, 1] the centre of mass above the floor where
                                             // the unloaded gear touches it
  double gear_sag_m = 0.005;                 // [m] (0, 0.1] how far the gear gives under the weight

  // Names the first wrong field (vehicle.<name>) and its range; also that the vehicle can hover
  // within its rotor speeds.
  Status validate() const;
};

struct MultirotorState {
  Eigen::Vector3d p_world_m = Eigen::Vector3d::Zero();
  Eigen::Vector3d v_world_m_s = Eigen::Vector3d::Zero();
  Eigen::Quaterniond q_world_body = Eigen::Quaterniond::Identity();
  Eigen::Vector3d omega_body_rad_s = Eigen::Vector3d::Zero();
  Vector4d rotor_speed_rad_s = Vector4d::Zero();
};

class Multirotor {
 public:
  // params must be valid (validate()).
  explicit Multirotor(const MultirotorParams& params);

  const MultirotorParams& params() const { return params_; }
  Eigen::Vector3d rotorPositionBodyM(int i) const { return rotor_position_body_m_[i]; }
  // +1 for CCW rotors (their drag turns the body about +z_body), -1 for CW.
  double spinDirection(int i) const { return spin_direction_[i]; }
  double hoverRotorSpeedRadS() const;

  // Standing on a floor at world height floor_z_m (z down) on its gear, settled under its
  // weight, level, heading yaw_rad, rotors stopped.
  void placeOnFloor(const Eigen::Vector2d& xy_world_m, double yaw_rad, double floor_z_m);
  // At rest in the air, the rotors at hover speed (no floor unless one was placed before).
  void placeHovering(const Eigen::Vector3d& p_world_m, double yaw_rad);

  // Rotor i gives only this fraction of its thrust and drag moment from now on: a damaged
  // propeller or a weak motor. [0, 1].
  void setRotorEfficiency(int i, double fraction) { efficiency_[i] = fraction; }

  // One RK4 step of dt_s: the commands (clamped to the rotor speed limits) held, the air moving
  // at wind_world_m_s. Returns the speed [m/s] at which the gear touched the floor in this step,
  // 0 when it did not (a landing, or a crash: the caller judges).
  double step(const Vector4d& rotor_speed_cmd_rad_s, const Eigen::Vector3d& wind_world_m_s,
              double dt_s);

  const MultirotorState& state() const { return state_; }
  // The gear touches the floor.
  bool onFloor() const { return on_floor_; }
  // What an accelerometer at the centre of mass reads after the last step: the specific force
  // (everything but gravity) in the body frame, the floor's push included.
  const Eigen::Vector3d& specificForceBodyMS2() const { return specific_force_body_m_s2_; }

 private:
  struct Derivative {
    Eigen::Vector3d p = Eigen::Vector3d::Zero();
    Eigen::Vector3d v = Eigen::Vector3d::Zero();
    Eigen::Vector4d q = Eigen::Vector4d::Zero();  // dq/dt as (x, y, z, w)
    Eigen::Vector3d omega = Eigen::Vector3d::Zero();
    Vector4d rotor = Vector4d::Zero();
  };
  Derivative derivative(const MultirotorState& s, const Vector4d& rotor_speed_cmd_rad_s,
                        const Eigen::Vector3d& wind_world_m_s) const;
  static MultirotorState advanced(const MultirotorState& s, const Derivative& d, double dt_s);
  // The floor's force and moment on the body through the gear (zero when it does not touch).
  void floorWrench(const MultirotorState& s, Eigen::Vector3d* force_world_n,
                   Eigen::Vector3d* moment_body_nm) const;

  MultirotorParams params_;
  std::array<Eigen::Vector3d, 4> rotor_position_body_m_;
  std::array<double, 4> spin_direction_{};
  std::array<double, 4> efficiency_{1.0, 1.0, 1.0, 1.0};
  Eigen::Vector3d inertia_kg_m2_;
  MultirotorState state_;
  double contact_z_m_;  // the centre of mass's height where the gear touches; NaN: no floor
  bool on_floor_ = false;
  Eigen::Vector3d specific_force_body_m_s2_ = Eigen::Vector3d(0.0, 0.0, -kGravityMS2);
};

// "x" or "plus" to a layout; an error names the text.
StatusOr<RotorLayout> parseRotorLayout(const std::string& text);

}  // namespace kinfly::sim
