// The simulated IMU (docs/sim.md, "IMU"): each reading is the true rate or specific force plus a
// bias and white noise; each bias starts at a seeded draw and walks randomly. In discrete time at
// rate f: noise sigma = density sqrt(f), bias step sigma = random_walk / sqrt(f).
//
// Noise densities and random walks default to the ADIS16448 as EuRoC publishes it (the EuRoC MAV
// dataset's mav0/imu0/sensor.yaml, "VI-Sensor IMU (ADIS16448)": gyroscope_noise_density 1.6968e-04,
// gyroscope_random_walk 1.9393e-05, accelerometer_noise_density 2.0e-3,
// accelerometer_random_walk 3.0e-3). The start biases' spreads are kinfly's choice (EuRoC gives
// none): large enough that the estimator has to find them. The rate
// defaults to the flight stack's 1 kHz rate loop, above the ADIS16448's own 819.2 Hz: what the
// controller is tuned for matters more here than the part's exact clock.
#pragma once

#include <Eigen/Core>
#include <cstdint>

#include "kinfly/core/status.h"
#include "kinfly/sim/random.h"

namespace kinfly::sim {

struct ImuParams {
  double rate_hz = 1000.0;                            // [Hz] [50, 8000]
  double gyro_noise_density_rad_s_rt_hz = 1.6968e-4;  // [rad/s/sqrt(Hz)] [0, 0.1]
  double gyro_random_walk_rad_s2_rt_hz = 1.9393e-5;   // [rad/s^2/sqrt(Hz)] [0, 0.1]
  double accel_noise_density_m_s2_rt_hz = 2.0e-3;     // [m/s^2/sqrt(Hz)] [0, 1]
  double accel_random_walk_m_s3_rt_hz = 3.0e-3;       // [m/s^3/sqrt(Hz)] [0, 1]
  double gyro_start_bias_sigma_rad_s = 0.005;         // [rad/s] [0, 1] per axis
  double accel_start_bias_sigma_m_s2 = 0.05;          // [m/s^2] [0, 5] per axis
  uint64_t seed = 2;
  Status validate() const;
};

struct ImuReading {
  Eigen::Vector3d angular_velocity_rad_s;  // body FRD
  Eigen::Vector3d specific_force_m_s2;     // body FRD, gravity included (at rest: (0, 0, -g))
};

class ImuModel {
 public:
  explicit ImuModel(const ImuParams& params);

  // One sample of the true rate and specific force; the biases walk by one sample period.
  ImuReading sample(const Eigen::Vector3d& omega_body_rad_s,
                    const Eigen::Vector3d& specific_force_body_m_s2);

  // A bias step (a scripted fault): added to the present biases.
  void stepBias(const Eigen::Vector3d& gyro_rad_s, const Eigen::Vector3d& accel_m_s2);

  const Eigen::Vector3d& gyroBiasRadS() const { return gyro_bias_rad_s_; }
  const Eigen::Vector3d& accelBiasMS2() const { return accel_bias_m_s2_; }
  const ImuParams& params() const { return params_; }

 private:
  ImuParams params_;
  NormalRandom random_;
  Eigen::Vector3d gyro_bias_rad_s_;
  Eigen::Vector3d accel_bias_m_s2_;
};

}  // namespace kinfly::sim
