// The position loop: from a position, velocity and acceleration setpoint with a yaw to the
// collective thrust and the attitude setpoint q_world_body_sp that the AttitudeController takes,
// by the geometric tracking law on SE(3) of Lee, Leok and McClamroch (CDC 2010), with an integral
// of the position error so that a constant external force (a steady wind) leaves no steady error
// (docs/flight.md, "Position controller").
//
// Frames: world gravity-aligned with z down (g_world = (0, 0, +g)); body FRD; the thrust acts
// along -z_body. Gains are accelerations per error (times the mass they are the force), so they
// carry over between vehicles of similar agility whatever their mass.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "kinfly/core/status.h"
#include "kinfly/flight/estimator.h"
#include "kinfly/flight/vehicle.h"

namespace kinfly::flight {

// What the trajectories give the position loop, all in world.
struct PositionSetpoint {
  Eigen::Vector3d p_world_m = Eigen::Vector3d::Zero();
  Eigen::Vector3d v_world_m_s = Eigen::Vector3d::Zero();
  Eigen::Vector3d a_world_m_s2 = Eigen::Vector3d::Zero();  // fed forward
  // Not used by this law (the attitude loop takes no rate feed-forward yet); a trajectory's
  // smoothness is judged by it.
  Eigen::Vector3d j_world_m_s3 = Eigen::Vector3d::Zero();
  double yaw_rad = 0.0;  // heading of x_body about world z (from world x towards world y)
};

// Per world axis (x, y, z).
struct PositionControllerParams {
  // [Hz] [100, 1000] how often the control task runs this loop; the attitude and rate loops run
  // at 1 kHz below it. At 100 Hz the loop's hold (5 ms on average) is small beside its own
  // time constant (~0.3 s): 250 Hz flies the test flights no better.
  double rate_hz = 100.0;
  Eigen::Vector3d p_gain_1_s2{16.0, 16.0, 20.0};   // [1/s^2] [0, 100] per position error
  Eigen::Vector3d v_gain_1_s{7.0, 7.0, 8.0};       // [1/s] [0, 50] per velocity error
  Eigen::Vector3d i_gain_1_s3{10.0, 10.0, 12.0};   // [1/s^3] [0, 200] per integrated error
  // [m/s^2] [0, 10] the integral's share of the commanded acceleration: it holds a steady force
  // (a 2 m/s wind on a small quadrotor needs ~1 m/s^2); beyond that it could only wind up.
  Eigen::Vector3d integral_limit_m_s2{3.0, 3.0, 3.0};
  // [0, 1] how much of the external force the accelerometer feels is fed forward (0: none, the
  // integral alone takes it up). The rotors' thrust acts along body z only, so the specific
  // force's body x and y are what else pushes the vehicle: its drag, the wind's.
  double disturbance_gain = 1.0;
  // [s] [0.01, 1] time constant of the low-pass on that force (at the IMU's rate, feel()): the
  // accelerometer's noise and the frame's vibration stay out of the tilt.
  double disturbance_filter_s = 0.1;
  // [rad] (0, 1.4] largest tilt of the thrust from the vertical; the horizontal demand gives
  // way first, so height is held when the tilt is cut.
  double tilt_max_rad = 0.6;
  // [m/s^2] [0.5, g) collective thrust per mass at least: the rotors keep turning, so roll and
  // pitch keep their authority even when the loop asks to fall.
  double thrust_min_m_s2 = 2.0;
  double thrust_max_m_s2 = 20.0;  // [m/s^2] (g, 100] at most, about 2 g by default
  Status validate() const;
};

struct PositionOutput {
  double thrust_n = 0.0;  // collective, along -z_body
  Eigen::Quaterniond q_world_body_sp = Eigen::Quaterniond::Identity();
  bool tilt_limited = false;    // the horizontal demand was cut to tilt_max_rad
  bool thrust_limited = false;  // the thrust was clamped to its range
};

class PositionController {
 public:
  // params must validate.
  PositionController(const PositionControllerParams& params, const Vehicle& vehicle);

  // Allocation-free. dt_s: since the previous update (about 1 / rate_hz); dt_s <= 0 moves no
  // integral. The integral acts from the next update and stops growing while the output is
  // limited (it still unwinds).
  PositionOutput update(const PositionSetpoint& setpoint, const EstimatorState& state,
                        double dt_s);
  // One accelerometer sample less its bias (body) at the attitude it was taken at, DT_S after the
  // last: its body x and y, turned into world, move the external force's low-pass. At the IMU's
  // rate, not the loop's: the rotors' vibration, sampled at 100 Hz, would fold down into slow
  // tilts that the filter lets through.
  void feel(const Eigen::Vector3d& f_body_m_s2, const Eigen::Quaterniond& q_world_body,
            double dt_s);
  void reset();

  // [m/s^2] the integral's part of the commanded acceleration (subtracted from it).
  const Eigen::Vector3d& integralMS2() const { return integral_m_s2_; }
  // [m/s^2] world, the external force per mass felt (low-passed; subtracted, times the gain).
  const Eigen::Vector3d& disturbanceMS2() const { return disturbance_m_s2_; }

 private:
  PositionControllerParams params_;
  double mass_kg_;
  Eigen::Vector3d integral_m_s2_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d disturbance_m_s2_ = Eigen::Vector3d::Zero();
};

}  // namespace kinfly::flight
