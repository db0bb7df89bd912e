// The controllers alone, against what their equations give by hand: the rate PID's parts and
// anti-windup, the attitude error with tilt before yaw, the LQR's discretisation, Riccati
// solution and closed-loop stability.
#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>
#include <cmath>

#include "kinfly/flight/attitude_controller.h"
#include "kinfly/flight/rate_controller.h"
#include "kinfly/flight/riccati.h"

namespace {

using kinfly::flight::AttitudeController;
using kinfly::flight::attitudeErrorBodyRad;
using kinfly::flight::designAttitudeLqr;
using kinfly::flight::GeometricAttitudeParams;
using kinfly::flight::geometricRateSetpointRadS;
using kinfly::flight::LqrAttitudeParams;
using kinfly::flight::MixerSaturation;
using kinfly::flight::RateController;
using kinfly::flight::RateSetpoint;
using kinfly::flight::Vehicle;
using kinfly::flight::VehicleParams;

constexpr double kDtS = 0.001;
// Sums of a few products of gains ~100 and inertias ~4e-3: double precision, with margin.
constexpr double kMomentToleranceNm = 1e-12;
// Quaternion products and atan2 of angles ~0.1 rad.
constexpr double kAngleToleranceRad = 1e-12;

Eigen::Quaterniond rotation(double angle_rad, const Eigen::Vector3d& axis) {
  return Eigen::Quaterniond(Eigen::AngleAxisd(angle_rad, axis.normalized()));
}

class FlightRate : public ::testing::Test {
 protected:
  const Vehicle vehicle_{VehicleParams{}};
  const RateController::Params params_;
  const Eigen::Vector3d inertia_ = vehicle_.inertiaDiagKgM2();
  const MixerSaturation unsaturated_;
};

TEST_F(FlightRate, SetpointStepGivesTheProportionalMomentWithoutDerivativeKick) {
  RateController rate(params_, vehicle_);
  RateSetpoint setpoint;
  EXPECT_LE(rate.update(setpoint, Eigen::Vector3d::Zero(), kDtS, unsaturated_).norm(),
            kMomentToleranceNm);
  setpoint.omega_body_rad_s = Eigen::Vector3d(1.0, -0.5, 0.2);
  const Eigen::Vector3d moment_nm =
      rate.update(setpoint, Eigen::Vector3d::Zero(), kDtS, unsaturated_);
  const Eigen::Vector3d expected_nm =
      inertia_.cwiseProduct(params_.p_gain_1_s.cwiseProduct(setpoint.omega_body_rad_s));
  EXPECT_LE((moment_nm - expected_nm).cwiseAbs().maxCoeff(), kMomentToleranceNm);
}

TEST_F(FlightRate, DerivativeActsOnTheFilteredMeasurementAndFeedForwardOnTheSetpoint) {
  RateController rate(params_, vehicle_);
  // Setpoint and measurement ramp together about x: no error, so only D and the feed-forward
  // act; after ten filter time constants the filtered derivative is the slope.
  constexpr double kSlopeRadS2 = 10.0;
  const double settle_s = 10.0 / (2.0 * M_PI * params_.d_cutoff_hz);
  RateSetpoint setpoint;
  setpoint.alpha_body_rad_s2 = Eigen::Vector3d(0.0, 3.0, 0.0);
  Eigen::Vector3d moment_nm;
  for (double t_s = 0.0; t_s <= settle_s; t_s += kDtS) {
    setpoint.omega_body_rad_s = Eigen::Vector3d(kSlopeRadS2 * t_s, 0.0, 0.0);
    moment_nm = rate.update(setpoint, setpoint.omega_body_rad_s, kDtS, unsaturated_);
  }
  // About a single body axis the gyroscopic moment omega x J omega vanishes.
  constexpr double kFilterResidual = 1e-3;  // e^-10 of the slope, and the ramp's discretisation
  EXPECT_NEAR(moment_nm.x(), -inertia_.x() * params_.d_gain.x() * kSlopeRadS2,
              kFilterResidual * inertia_.x() * params_.d_gain.x() * kSlopeRadS2);
  EXPECT_NEAR(moment_nm.y(), inertia_.y() * 3.0, kMomentToleranceNm);
  EXPECT_LE(rate.integratorRadS2().norm(), kMomentToleranceNm);
}

TEST_F(FlightRate, IntegratorIsClampedAndFrozenOnlyTowardsTheCut) {
  RateController rate(params_, vehicle_);
  RateSetpoint setpoint;
  setpoint.omega_body_rad_s = Eigen::Vector3d(1.0, 1.0, 1.0);
  for (int k = 0; k < 5000; ++k) rate.update(setpoint, Eigen::Vector3d::Zero(), kDtS, unsaturated_);
  EXPECT_EQ(rate.integratorRadS2(), params_.integrator_limit_rad_s2);

  rate.reset();
  MixerSaturation cut;
  cut.moment_cut_positive[0] = true;  // roll was cut while positive
  cut.moment_cut_negative[1] = true;  // pitch was cut while negative
  for (int k = 0; k < 100; ++k) rate.update(setpoint, Eigen::Vector3d::Zero(), kDtS, cut);
  EXPECT_EQ(rate.integratorRadS2().x(), 0.0);  // a positive error would push roll further
  const double expected_rad_s2 = params_.i_gain_1_s2.y() * 1.0 * 100 * kDtS;
  EXPECT_NEAR(rate.integratorRadS2().y(), expected_rad_s2, 1e-9);  // pushing away: unwinds
  setpoint.omega_body_rad_s.x() = -1.0;
  rate.update(setpoint, Eigen::Vector3d::Zero(), kDtS, cut);
  EXPECT_LT(rate.integratorRadS2().x(), 0.0);  // a negative error leaves the cut: it moves
}

TEST_F(FlightRate, RepeatedSampleMovesNoState) {
  RateController rate(params_, vehicle_);
  RateSetpoint setpoint;
  setpoint.omega_body_rad_s.x() = 1.0;
  rate.update(setpoint, Eigen::Vector3d::Zero(), kDtS, unsaturated_);
  const Eigen::Vector3d integrator = rate.integratorRadS2();
  const Eigen::Vector3d moment_nm =
      rate.update(setpoint, Eigen::Vector3d(0.5, 0.0, 0.0), 0.0, unsaturated_);
  EXPECT_TRUE(moment_nm.allFinite());
  EXPECT_EQ(rate.integratorRadS2(), integrator);
}

TEST(FlightRateParams, ValidateNamesTheAxis) {
  RateController::Params params;
  EXPECT_TRUE(params.validate().ok());
  params.p_gain_1_s.z() = -1.0;
  EXPECT_EQ(params.validate().message(), "rate.p_gain_1_s.yaw must be in [0, 1000] (got -1)");
  params = RateController::Params{};
  params.d_cutoff_hz = 0.0;
  EXPECT_EQ(params.validate().message(), "rate.d_cutoff_hz must be in (0, 500] (got 0)");
}

TEST(FlightAttitudeError, SmallTiltIsTheRotationVector) {
  const double angle_rad = 0.1;
  const Eigen::Vector3d error = attitudeErrorBodyRad(
      Eigen::Quaterniond::Identity(), rotation(angle_rad, Eigen::Vector3d::UnitX()), 1.0);
  EXPECT_NEAR(error.x(), 2.0 * std::sin(angle_rad / 2.0), kAngleToleranceRad);
  EXPECT_NEAR(error.tail<2>().norm(), 0.0, kAngleToleranceRad);
}

TEST(FlightAttitudeError, YawIsWeightedAfterTheTilt) {
  // Pure yaw: the weight takes that share of the angle.
  const double yaw_rad = 0.8;
  const Eigen::Vector3d yaw_error = attitudeErrorBodyRad(
      Eigen::Quaterniond::Identity(), rotation(yaw_rad, Eigen::Vector3d::UnitZ()), 0.25);
  EXPECT_NEAR(yaw_error.z(), 2.0 * std::sin(0.25 * yaw_rad / 2.0), kAngleToleranceRad);
  // Tilt and yaw, yaw weighted 0: the correction tilts the body z onto the setpoint's exactly.
  const Eigen::Quaterniond q_world_body = rotation(0.3, Eigen::Vector3d(1.0, 2.0, 0.5));
  const Eigen::Quaterniond q_world_body_sp = rotation(0.4, Eigen::Vector3d(-1.0, 0.5, 2.0));
  const Eigen::Vector3d tilt_error = attitudeErrorBodyRad(q_world_body, q_world_body_sp, 0.0);
  const double half_angle_sin = 0.5 * tilt_error.norm();
  const Eigen::Quaterniond q_correction(std::sqrt(1.0 - half_angle_sin * half_angle_sin),
                                        0.5 * tilt_error.x(), 0.5 * tilt_error.y(),
                                        0.5 * tilt_error.z());
  const Eigen::Vector3d z_world = q_world_body * q_correction * Eigen::Vector3d::UnitZ();
  EXPECT_LE((z_world - q_world_body_sp * Eigen::Vector3d::UnitZ()).norm(), kAngleToleranceRad);
}

TEST(FlightAttitudeError, GeometricRateSetpointIsLimited) {
  const GeometricAttitudeParams params;
  const Eigen::Vector3d rate_sp_rad_s = geometricRateSetpointRadS(
      params, Eigen::Quaterniond::Identity(), rotation(1.5, Eigen::Vector3d::UnitY()));
  EXPECT_EQ(rate_sp_rad_s.y(), params.rate_limit_rad_s.y());
  const Eigen::Vector3d small_rad_s = geometricRateSetpointRadS(
      params, Eigen::Quaterniond::Identity(), rotation(0.01, Eigen::Vector3d::UnitX()));
  EXPECT_NEAR(small_rad_s.x(), params.p_gain_1_s.x() * 2.0 * std::sin(0.005), 1e-12);
}

class FlightLqr : public ::testing::Test {
 protected:
  const Vehicle vehicle_{VehicleParams{}};
  const LqrAttitudeParams params_;
};

TEST_F(FlightLqr, DiscretisationIsTheExactZeroOrderHold) {
  const auto design = designAttitudeLqr(params_, vehicle_);
  ASSERT_TRUE(design.ok()) << design.status().message();
  const double dt = 1.0 / params_.control_rate_hz;
  const double jx = vehicle_.params().inertia_xx_kg_m2;
  // Roll: error' = rate, rate' = u / J, integral' = error, u held over dt.
  constexpr double kEntryTolerance = 1e-18;  // entries down to dt^3 / J ~ 3e-8
  EXPECT_NEAR(design->A(0, 3), dt, kEntryTolerance);
  EXPECT_NEAR(design->A(6, 0), dt, kEntryTolerance);
  EXPECT_NEAR(design->A(6, 3), dt * dt / 2.0, kEntryTolerance);
  EXPECT_NEAR(design->B(0, 0), dt * dt / (2.0 * jx), kEntryTolerance);
  EXPECT_NEAR(design->B(3, 0), dt / jx, 1e-15);
  EXPECT_NEAR(design->B(6, 0), dt * dt * dt / (6.0 * jx), kEntryTolerance);
}

TEST_F(FlightLqr, SolvesTheRiccatiEquationAndStabilises) {
  const auto design = designAttitudeLqr(params_, vehicle_);
  ASSERT_TRUE(design.ok()) << design.status().message();
  const auto& A = design->A;
  const auto& B = design->B;
  const auto& P = design->P;
  const auto& K = design->K;
  const Eigen::Matrix<double, 9, 9> residual =
      A.transpose() * P * A - A.transpose() * P * B * K + design->Q - P;
  constexpr double kRelativeResidual = 1e-9;  // P's entries span ~10 orders of magnitude
  EXPECT_LE(residual.norm(), kRelativeResidual * P.norm());
  EXPECT_LE((P - P.transpose()).norm(), kRelativeResidual * P.norm());
  // Dynamic sizes: Eigen's fixed-size eigen solvers take minutes to compile.
  EXPECT_GT(Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd>(P).eigenvalues().minCoeff(), 0.0);
  // The closed loop's eigenvalues, computed here, all strictly inside the unit circle.
  const Eigen::VectorXcd poles =
      Eigen::EigenSolver<Eigen::MatrixXd>(Eigen::MatrixXd(A - B * K)).eigenvalues();
  EXPECT_LT(poles.cwiseAbs().maxCoeff(), 1.0);
  EXPECT_NEAR(poles.cwiseAbs().maxCoeff(), design->closed_loop_spectral_radius, 1e-12);
}

TEST(FlightRiccati, UnstabilisablePairIsAnError) {
  // An unstable mode the input cannot reach: no stabilising solution exists.
  const Eigen::Matrix2d A = 2.0 * Eigen::Matrix2d::Identity();
  const Eigen::Matrix<double, 2, 1> B(1.0, 0.0);
  const auto solved = kinfly::flight::solveDiscreteRiccati(
      A, B, Eigen::Matrix2d::Identity(), Eigen::Matrix<double, 1, 1>::Identity());
  EXPECT_FALSE(solved.ok());
}

TEST(FlightRiccati, ScalarMatchesTheClosedForm) {
  // x' = a x + b u, cost q x^2 + r u^2: p = q + a^2 p r / (r + b^2 p), a quadratic in p.
  const double a = 1.2, b = 0.5, q = 2.0, r = 0.3;
  const double c2 = b * b, c1 = r - a * a * r - q * b * b, c0 = -q * r;
  const double p = (-c1 + std::sqrt(c1 * c1 - 4.0 * c2 * c0)) / (2.0 * c2);
  const auto solved = kinfly::flight::solveDiscreteRiccati(
      Eigen::Matrix<double, 1, 1>(a), Eigen::Matrix<double, 1, 1>(b),
      Eigen::Matrix<double, 1, 1>(q), Eigen::Matrix<double, 1, 1>(r));
  ASSERT_TRUE(solved.ok()) << solved.status().message();
  constexpr double kClosedFormTolerance = 1e-12;  // one square root apart
  EXPECT_NEAR(solved->P(0, 0), p, kClosedFormTolerance * p);
  EXPECT_NEAR(solved->K(0, 0), a * b * p / (r + b * b * p), kClosedFormTolerance);
}

TEST(FlightAttitudeParams, ValidateNamesTheKey) {
  AttitudeController::Params params;
  EXPECT_TRUE(params.validate().ok());
  params.lqr.integral_weight_1_rad2_s2.x() = 0.0;
  EXPECT_EQ(params.validate().message(),
            "attitude.lqr.integral_weight_1_rad2_s2.roll must be in (0, 1e+10] (got 0)");
}

}  // namespace
