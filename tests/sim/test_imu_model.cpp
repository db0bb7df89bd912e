// The simulated IMU: white noise of the stated density, biases that start where the seed puts
// them and walk at the stated rate, and bias steps. The barometer beside it: its noise, its
// drift's walk and its site altitude.
#include <gtest/gtest.h>

#include <cmath>

#include "kinfly/sim/barometer.h"
#include "kinfly/sim/imu_model.h"

namespace kinfly::sim {
namespace {

// 200 000 samples: a sample sigma's standard error is 1/sqrt(2N) = 0.16 %; bound 2 %.
constexpr int kSamples = 200000;
constexpr double kSigmaTol = 0.02;

TEST(ImuModel, WhiteNoiseHasTheDensitysSigma) {
  ImuParams params;
  params.gyro_random_walk_rad_s2_rt_hz = 0.0;
  params.accel_random_walk_m_s3_rt_hz = 0.0;
  params.gyro_start_bias_sigma_rad_s = 0.0;
  params.accel_start_bias_sigma_m_s2 = 0.0;
  ImuModel imu(params);
  const Eigen::Vector3d omega(0.1, -0.2, 0.3);
  const Eigen::Vector3d force(0.0, 0.0, -9.81);
  double gyro_sq = 0.0;
  double accel_sq = 0.0;
  for (int i = 0; i < kSamples; ++i) {
    const ImuReading reading = imu.sample(omega, force);
    gyro_sq += (reading.angular_velocity_rad_s - omega).x() * (reading.angular_velocity_rad_s - omega).x();
    accel_sq += (reading.specific_force_m_s2 - force).z() * (reading.specific_force_m_s2 - force).z();
  }
  const double sqrt_rate = std::sqrt(params.rate_hz);
  EXPECT_NEAR(std::sqrt(gyro_sq / kSamples) / (params.gyro_noise_density_rad_s_rt_hz * sqrt_rate),
              1.0, kSigmaTol);
  EXPECT_NEAR(std::sqrt(accel_sq / kSamples) / (params.accel_noise_density_m_s2_rt_hz * sqrt_rate),
              1.0, kSigmaTol);
}

TEST(ImuModel, BiasesWalkAtTheStatedRate) {
  // After T seconds a bias random walk of density q has spread q^2 T; over many seeded IMUs the
  // spread of their biases shows it. 2000 IMUs: the sigma's standard error is 1.6 %; bound 6 %.
  constexpr int kImus = 2000;
  constexpr double kWalkTol = 0.06;
  const double seconds = 10.0;
  double gyro_sq = 0.0;
  double accel_sq = 0.0;
  ImuParams params;
  params.rate_hz = 100.0;
  params.gyro_start_bias_sigma_rad_s = 0.0;
  params.accel_start_bias_sigma_m_s2 = 0.0;
  for (int k = 0; k < kImus; ++k) {
    params.seed = static_cast<uint64_t>(k) + 1;
    ImuModel imu(params);
    for (int i = 0; i < static_cast<int>(seconds * params.rate_hz); ++i) {
      imu.sample(Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero());
    }
    gyro_sq += imu.gyroBiasRadS().squaredNorm() / 3.0;
    accel_sq += imu.accelBiasMS2().squaredNorm() / 3.0;
  }
  EXPECT_NEAR(std::sqrt(gyro_sq / kImus) / (params.gyro_random_walk_rad_s2_rt_hz * std::sqrt(seconds)),
              1.0, kWalkTol);
  EXPECT_NEAR(std::sqrt(accel_sq / kImus) / (params.accel_random_walk_m_s3_rt_hz * std::sqrt(seconds)),
              1.0, kWalkTol);
}

TEST(ImuModel, StartBiasesComeFromTheSeedAndStepsAdd) {
  ImuParams params;
  params.seed = 11;
  ImuModel a(params);
  ImuModel b(params);
  EXPECT_EQ(a.gyroBiasRadS(), b.gyroBiasRadS());
  EXPECT_GT(a.gyroBiasRadS().norm(), 0.0);
  params.seed = 12;
  EXPECT_NE(ImuModel(params).gyroBiasRadS(), a.gyroBiasRadS());
  const Eigen::Vector3d before = a.accelBiasMS2();
  a.stepBias(Eigen::Vector3d::Zero(), {0.5, 0.0, 0.0});
  EXPECT_EQ(a.accelBiasMS2(), before + Eigen::Vector3d(0.5, 0.0, 0.0));
}

TEST(ImuModel, BadSettingsAreNamed) {
  ImuParams params;
  params.rate_hz = 10.0;
  EXPECT_EQ(params.validate().message(), "imu.rate_hz must be in [50, 8000] (got 10)");
}

TEST(Barometer, ReadsTheHeightFromTheSiteWithTheStatedNoise) {
  BarometerParams params;
  params.drift_m_rt_s = 0.0;
  Barometer baro(params);
  constexpr double kHeightM = 1.25;
  double sum_m = 0.0, sq_m2 = 0.0;
  for (int i = 0; i < kSamples; ++i) {
    const double error_m = baro.read(kHeightM) - (params.site_altitude_m + kHeightM);
    sum_m += error_m;
    sq_m2 += error_m * error_m;
  }
  // The mean's standard error is sigma / sqrt(N): 0.2 mm; bound 1 mm.
  constexpr double kMeanTolM = 1e-3;
  EXPECT_NEAR(sum_m / kSamples, 0.0, kMeanTolM);
  EXPECT_NEAR(std::sqrt(sq_m2 / kSamples) / params.noise_m, 1.0, kSigmaTol);
}

TEST(Barometer, DriftWalksAtTheStatedRate) {
  // As the IMU's biases: 2000 seeded barometers, a minute each; bound 6 %.
  constexpr int kBarometers = 2000;
  constexpr double kWalkTol = 0.06;
  constexpr double kSeconds = 60.0;
  BarometerParams params;
  params.noise_m = 0.0;
  double drift_sq_m2 = 0.0;
  for (int k = 0; k < kBarometers; ++k) {
    params.seed = static_cast<uint64_t>(k) + 1;
    Barometer baro(params);
    for (int i = 0; i < static_cast<int>(kSeconds * params.rate_hz); ++i) baro.read(0.0);
    drift_sq_m2 += baro.driftM() * baro.driftM();
  }
  EXPECT_NEAR(std::sqrt(drift_sq_m2 / kBarometers) / (params.drift_m_rt_s * std::sqrt(kSeconds)),
              1.0, kWalkTol);
  params.rate_hz = 1001.0;
  EXPECT_EQ(params.validate().message(), "baro.rate_hz must be in [0, 1000] (got 1001)");
}

}  // namespace
}  // namespace kinfly::sim
