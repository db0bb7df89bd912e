// The inner loop: a PID per body axis from the body-rate error to an angular acceleration, times
// the inertia, plus the gyroscopic moment: the output is the body moment in N m that the mixer
// takes. Gains are in angular acceleration, so they carry over between vehicles of similar
// agility whatever their inertia (docs/flight.md, "Rate controller").
#pragma once

#include <Eigen/Core>

#include "kinfly/core/status.h"
#include "kinfly/flight/mixer.h"
#include "kinfly/flight/vehicle.h"

namespace kinfly::flight {

struct RateSetpoint {
  Eigen::Vector3d omega_body_rad_s = Eigen::Vector3d::Zero();
  // The setpoint's own angular acceleration, fed forward (zero when the caller has none).
  Eigen::Vector3d alpha_body_rad_s2 = Eigen::Vector3d::Zero();
};

class RateController {
 public:
  // Per body axis (roll, pitch, yaw).
  struct Params {
    Eigen::Vector3d p_gain_1_s{120.0, 120.0, 40.0};    // [1/s] [0, 1000] per rate error
    Eigen::Vector3d i_gain_1_s2{150.0, 150.0, 60.0};   // [1/s^2] [0, 1e4] per integrated error
    // [-] [0, 1] per measured rate derivative: damps the overshoot the motor lag gives the high
    // P gain (1 % instead of 11 % on the 5 ms Hummingbird); yaw, slow, needs none.
    Eigen::Vector3d d_gain{0.3, 0.3, 0.0};
    Eigen::Vector3d integrator_limit_rad_s2{30.0, 30.0, 15.0};  // [rad/s^2] [0, 1e3]
    double d_cutoff_hz = 40.0;  // [Hz] (0, 500] low-pass on the derivative: gyro noise and
                                // rotor vibration would otherwise reach the motors amplified
    Status validate() const;
  };

  RateController(const Params& params, const Vehicle& vehicle);

  // Allocation-free. saturation: the mixer's report of the previous tick; an axis it cut in the
  // direction the error pushes keeps its integrator (PX4's anti-windup). dt_s <= 0 moves no
  // state (a repeated sample), so the output stays finite.
  Eigen::Vector3d update(const RateSetpoint& setpoint, const Eigen::Vector3d& omega_body_rad_s,
                         double dt_s, const MixerSaturation& saturation);
  void reset();

  const Eigen::Vector3d& integratorRadS2() const { return integrator_rad_s2_; }

 private:
  Params params_;
  Eigen::Vector3d inertia_kg_m2_;
  Eigen::Vector3d integrator_rad_s2_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d previous_omega_body_rad_s_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d derivative_filtered_rad_s2_ = Eigen::Vector3d::Zero();
  bool has_previous_ = false;
};

}  // namespace kinfly::flight
