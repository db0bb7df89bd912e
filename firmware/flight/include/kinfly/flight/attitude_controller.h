// The attitude loop: from the wanted attitude q_world_body_sp to the body moment for the mixer,
// by one of two laws chosen in the parameters (docs/flight.md, "Attitude controller"):
//   geometric  PX4's quaternion P law (Brescianini, Hehn, D'Andrea 2013): the attitude error as
//              a rate setpoint, tilt before yaw, through the rate PID;
//   lqr        a discrete LQR on the attitude dynamics linearised about hover (error, body rate,
//              integral of the error), its gain solved at start from the vehicle model.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "kinfly/core/status.h"
#include "kinfly/flight/mixer.h"
#include "kinfly/flight/rate_controller.h"
#include "kinfly/flight/vehicle.h"

namespace kinfly::flight {

enum class AttitudeLaw { kGeometric, kLqr };

struct GeometricAttitudeParams {
  Eigen::Vector3d p_gain_1_s{25.0, 25.0, 8.0};       // [1/s] [0, 100] rate per attitude error
  Eigen::Vector3d rate_limit_rad_s{6.0, 6.0, 3.0};   // [rad/s] (0, 30] of the rate setpoint
  Status validate() const;
};

// Per axis (roll, pitch, yaw). R = accel_weight * diag(1/J^2): the input is weighed as the
// angular acceleration it gives, so the weights carry over between vehicles.
struct LqrAttitudeParams {
  double control_rate_hz = 1000.0;                                  // [Hz] [50, 1e4]
  Eigen::Vector3d attitude_weight_1_rad2{1.5e6, 1.5e6, 1.0e5};      // [1/rad^2] (0, 1e10]
  Eigen::Vector3d rate_weight_s2_rad2{1.0e3, 1.0e3, 3.0e2};         // [s^2/rad^2] [0, 1e10]
  Eigen::Vector3d integral_weight_1_rad2_s2{1.0e8, 1.0e8, 3.0e6};   // [1/(rad s)^2] (0, 1e10]
  double accel_weight_s4_rad2 = 1.0;                                // [s^4/rad^2] (0, 1e6]
  Eigen::Vector3d integral_limit_rad_s{0.05, 0.05, 0.05};           // [rad s] [0, 10]
  // [rad] [0, pi] the integral runs only while the error is this small: it is there for a
  // constant disturbance (an offset centre of mass), which leaves a small error; integrating a
  // setpoint step's transient would wind it up and leave a slow tail after every step.
  double integral_band_rad = 0.02;
  Status validate() const;
};

using LqrStateMatrix = Eigen::Matrix<double, 9, 9>;
using LqrInputMatrix = Eigen::Matrix<double, 9, 3>;
using LqrGainMatrix = Eigen::Matrix<double, 3, 9>;

// x_{k+1} = A x_k + B u_k with x = (attitude error [rad], body rate [rad/s], integral of the
// attitude error [rad s]) and u = body moment [N m], held over one control period; P solves the
// discrete algebraic Riccati equation and u = -K x.
struct LqrDesign {
  LqrStateMatrix A;
  LqrInputMatrix B;
  LqrStateMatrix Q;
  Eigen::Matrix3d R;
  LqrStateMatrix P;
  LqrGainMatrix K;
  int doubling_steps = 0;
  double closed_loop_spectral_radius = 0.0;  // of A - B K: below 1 is stable
};

// Fails when the Riccati equation has no stabilising solution (riccati.h).
StatusOr<LqrDesign> designAttitudeLqr(const LqrAttitudeParams& params, const Vehicle& vehicle);

// The attitude error as a rotation vector in the body frame, from q_world_body towards
// q_world_body_sp, with the yaw part scaled by yaw_weight in [0, 1] after the tilt is fully
// corrected (PX4's reduced attitude: a large yaw error never delays levelling).
Eigen::Vector3d attitudeErrorBodyRad(const Eigen::Quaterniond& q_world_body,
                                     const Eigen::Quaterniond& q_world_body_sp,
                                     double yaw_weight);

// The geometric law alone: const, no state (PX4's AttitudeControl::update).
Eigen::Vector3d geometricRateSetpointRadS(const GeometricAttitudeParams& params,
                                          const Eigen::Quaterniond& q_world_body,
                                          const Eigen::Quaterniond& q_world_body_sp);

class AttitudeController {
 public:
  struct Params {
    AttitudeLaw law = AttitudeLaw::kGeometric;
    GeometricAttitudeParams geometric;
    LqrAttitudeParams lqr;
    RateController::Params rate;  // the geometric law's inner loop
    Status validate() const;
  };

  // Checks params and solves the LQR gain (whatever the law, so that switching laws in flight
  // needs no solve). The vehicle must be valid.
  static StatusOr<AttitudeController> create(const Params& params, const Vehicle& vehicle);

  // Allocation-free. dt_s: since the previous update; saturation: the mixer's previous report.
  Eigen::Vector3d update(const Eigen::Quaterniond& q_world_body,
                         const Eigen::Quaterniond& q_world_body_sp,
                         const Eigen::Vector3d& omega_body_rad_s, double dt_s,
                         const MixerSaturation& saturation);
  void reset();
  void setLaw(AttitudeLaw law);

  AttitudeLaw law() const { return params_.law; }
  const LqrDesign& lqr() const { return lqr_; }

 private:
  AttitudeController(const Params& params, const Vehicle& vehicle, const LqrDesign& lqr);

  Params params_;
  RateController rate_;
  LqrDesign lqr_;
  Eigen::Vector3d integral_rad_s_ = Eigen::Vector3d::Zero();
};

const char* toString(AttitudeLaw law);

}  // namespace kinfly::flight
