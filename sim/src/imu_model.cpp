#include "kinfly/sim/imu_model.h"

#include <cmath>

#include "kinfly/core/range_check.h"

namespace kinfly::sim {

Status ImuParams::validate() const {
  return firstError(
      outOfRange("imu.rate_hz", rate_hz, 50.0, 8000.0),
      outOfRange("imu.gyro_noise_density_rad_s_rt_hz", gyro_noise_density_rad_s_rt_hz, 0.0, 0.1),
      outOfRange("imu.gyro_random_walk_rad_s2_rt_hz", gyro_random_walk_rad_s2_rt_hz, 0.0, 0.1),
      outOfRange("imu.accel_noise_density_m_s2_rt_hz", accel_noise_density_m_s2_rt_hz, 0.0, 1.0),
      outOfRange("imu.accel_random_walk_m_s3_rt_hz", accel_random_walk_m_s3_rt_hz, 0.0, 1.0),
      outOfRange("imu.gyro_start_bias_sigma_rad_s", gyro_start_bias_sigma_rad_s, 0.0, 1.0),
      outOfRange("imu.accel_start_bias_sigma_m_s2", accel_start_bias_sigma_m_s2, 0.0, 5.0));
}

ImuModel::ImuModel(const ImuParams& params) : params_(params), random_(params.seed) {
  gyro_bias_rad_s_ = params.gyro_start_bias_sigma_rad_s * random_.vector3();
  accel_bias_m_s2_ = params.accel_start_bias_sigma_m_s2 * random_.vector3();
}

ImuReading ImuModel::sample(const Eigen::Vector3d& omega_body_rad_s,
                            const Eigen::Vector3d& specific_force_body_m_s2) {
  const double sqrt_rate = std::sqrt(params_.rate_hz);
  ImuReading reading;
  reading.angular_velocity_rad_s =
      omega_body_rad_s + gyro_bias_rad_s_ +
      params_.gyro_noise_density_rad_s_rt_hz * sqrt_rate * random_.vector3();
  reading.specific_force_m_s2 =
      specific_force_body_m_s2 + accel_bias_m_s2_ +
      params_.accel_noise_density_m_s2_rt_hz * sqrt_rate * random_.vector3();
  gyro_bias_rad_s_ += params_.gyro_random_walk_rad_s2_rt_hz / sqrt_rate * random_.vector3();
  accel_bias_m_s2_ += params_.accel_random_walk_m_s3_rt_hz / sqrt_rate * random_.vector3();
  return reading;
}

void ImuModel::stepBias(const Eigen::Vector3d& gyro_rad_s, const Eigen::Vector3d& accel_m_s2) {
  gyro_bias_rad_s_ += gyro_rad_s;
  accel_bias_m_s2_ += accel_m_s2;
}

}  // namespace kinfly::sim
