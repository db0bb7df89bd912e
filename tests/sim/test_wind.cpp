// The wind: the mean and its steps exactly, gusts by their 1 - cos profile, and the Dryden
// turbulence's intensities and scale lengths as MIL-F-8785C gives them, its variance by
// simulation.
#include <gtest/gtest.h>

#include <cmath>

#include "kinfly/sim/wind.h"

namespace kinfly::sim {
namespace {

constexpr double kFt = 0.3048;  // [m]

TEST(Wind, MeanAndStepsAreExactWithoutTurbulence) {
  WindParams params;
  params.mean_world_m_s = {2.0, -1.0, 0.0};
  Wind wind(params);
  EXPECT_EQ(wind.step(0.001, 0.001, 1.0, Eigen::Vector3d::Zero()), params.mean_world_m_s);
  wind.setMean({0.0, 3.0, 0.0});
  EXPECT_EQ(wind.step(0.002, 0.001, 1.0, Eigen::Vector3d::Zero()), Eigen::Vector3d(0.0, 3.0, 0.0));
}

TEST(Wind, AGustRisesAndFallsAsOneMinusCosine) {
  Wind wind(WindParams{});
  wind.addGust({10.0, 0.5, {1.0, 0.0, 0.0}});
  const auto at = [&](double t) { return wind.step(t, 0.001, 1.0, Eigen::Vector3d::Zero()).x(); };
  EXPECT_EQ(at(9.9), 0.0);
  EXPECT_NEAR(at(10.25), 0.5, 1e-12);  // half way up
  EXPECT_NEAR(at(10.5), 1.0, 1e-12);   // the peak at its duration
  EXPECT_NEAR(at(10.75), 0.5, 1e-12);
  EXPECT_EQ(at(11.1), 0.0);
}

TEST(Wind, IntensitiesAndScaleLengthsFollowMilF8785C) {
  WindParams params;
  params.turbulence_w20_m_s = 10.0;
  const Wind wind(params);
  // At 100 ft: sigma_w = 0.1 W20 = 1 m/s; sigma_u = sigma_w / (0.177 + 0.0823)^0.4;
  // L_w = 100 ft, L_u = 100 / (0.2593)^1.2 ft.
  const double h_m = 100.0 * kFt;
  EXPECT_NEAR(wind.sigmaMS(h_m).z(), 1.0, 1e-12);
  EXPECT_NEAR(wind.sigmaMS(h_m).x(), 1.0 / std::pow(0.2593, 0.4), 1e-9);
  EXPECT_NEAR(wind.scaleLengthM(h_m).z(), 100.0 * kFt, 1e-9);
  EXPECT_NEAR(wind.scaleLengthM(h_m).x(), 100.0 / std::pow(0.2593, 1.2) * kFt, 1e-9);
  // Below 10 ft the model is held at 10 ft.
  EXPECT_EQ(wind.scaleLengthM(0.5), wind.scaleLengthM(10.0 * kFt));
}

// Runs the turbulence for `seconds` at a fixed height and air speed; the sample standard
// deviation of each component in the mean wind's frame.
Eigen::Vector3d turbulenceSigma(uint64_t seed, double seconds) {
  WindParams params;
  params.turbulence_w20_m_s = 10.0;
  params.mean_world_m_s = {5.0, 0.0, 0.0};  // V = 5 m/s past a drone at rest
  params.seed = seed;
  Wind wind(params);
  const double dt = 0.01;
  const int steps = static_cast<int>(seconds / dt);
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  Eigen::Vector3d sum_sq = Eigen::Vector3d::Zero();
  for (int i = 0; i < steps; ++i) {
    wind.step(i * dt, dt, 30.0, Eigen::Vector3d::Zero());
    const Eigen::Vector3d uvw = wind.turbulenceMeanFrameMS();
    sum += uvw;
    sum_sq += uvw.cwiseAbs2();
  }
  const Eigen::Vector3d mean = sum / steps;
  return (sum_sq / steps - mean.cwiseAbs2()).cwiseSqrt();
}

TEST(Wind, TurbulenceHasTheModelsVariance) {
  // 30 m (98 ft): L_u = 98 / 0.258^1.2 ft = 153 m, so at 5 m/s u decorrelates in ~30 s; 40 000 s
  // is ~1300 of its correlation times: the sample sigma's standard error is ~3 %. Bound 10 %.
  constexpr double kSigmaTol = 0.10;
  WindParams params;
  params.turbulence_w20_m_s = 10.0;
  const Eigen::Vector3d expected = Wind(params).sigmaMS(30.0);
  const Eigen::Vector3d measured = turbulenceSigma(7, 40000.0);
  for (int axis = 0; axis < 3; ++axis) {
    EXPECT_NEAR(measured[axis] / expected[axis], 1.0, kSigmaTol) << "axis " << axis;
  }
}

TEST(Wind, TheSeedFixesTheTurbulence) {
  EXPECT_EQ(turbulenceSigma(3, 50.0), turbulenceSigma(3, 50.0));
  EXPECT_NE(turbulenceSigma(3, 50.0), turbulenceSigma(4, 50.0));
}

TEST(Wind, BadSettingsAreNamed) {
  WindParams params;
  params.turbulence_w20_m_s = -1.0;
  EXPECT_EQ(params.validate().message(), "wind.turbulence_w20_m_s must be in [0, 30] (got -1)");
  params = WindParams{};
  params.mean_world_m_s = {40.0, 0.0, 0.0};
  EXPECT_FALSE(params.validate().ok());
}

}  // namespace
}  // namespace kinfly::sim
