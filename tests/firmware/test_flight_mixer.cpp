// The vehicle model and the mixer: the allocation matrix against one worked by hand, and the
// desaturation order (yaw gives way first, then the collective thrust, roll and pitch last).
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "kinfly/flight/mixer.h"
#include "kinfly/flight/vehicle.h"

namespace {

using kinfly::flight::Mixer;
using kinfly::flight::MixerOutput;
using kinfly::flight::RotorLayout;
using kinfly::flight::Vector4d;
using kinfly::flight::Vehicle;
using kinfly::flight::VehicleParams;
using kinfly::flight::Wrench;

// The allocation is a few products of the parameters: exact up to the last bits.
constexpr double kMatrixTolerance = 1e-15;
// The round trip goes through a 4x4 inverse and square roots of squared speeds ~2e5 (rad/s)^2.
constexpr double kRoundTripToleranceN = 1e-10;
// A product with its inverse: the matrix's rows differ by four orders of magnitude (k_m vs k_f).
constexpr double kInverseTolerance = 1e-12;
// [rad/s] a square root of ~2e5, and ratios of moments of ~1 N m, to double precision.
constexpr double kScalarTolerance = 1e-9;

TEST(FlightVehicle, AllocationMatchesHandWorkedX) {
  const VehicleParams params;  // Hummingbird: arm 0.17 m, X
  const Vehicle vehicle(params);
  const double kf = params.thrust_coeff_n_s2_rad2;
  const double km = params.moment_coeff_nm_s2_rad2;
  const double arm = params.arm_length_m / std::sqrt(2.0);  // each rotor's |x| and |y|
  // Columns: 1 front-right CCW, 2 rear-left CCW, 3 front-left CW, 4 rear-right CW. A rotor on
  // the right (+y) rolls the body left (negative roll); one in front pitches it up.
  Eigen::Matrix4d expected;
  expected << kf, kf, kf, kf,
      -kf * arm, kf * arm, kf * arm, -kf * arm,
      kf * arm, -kf * arm, kf * arm, -kf * arm,
      km, km, -km, -km;
  EXPECT_LE((vehicle.allocation() - expected).cwiseAbs().maxCoeff(), kMatrixTolerance);
  EXPECT_LE((vehicle.allocation() * vehicle.allocationInverse() - Eigen::Matrix4d::Identity())
                .cwiseAbs()
                .maxCoeff(),
            kInverseTolerance);
  // Hover: four rotors carry m g, so w^2 = m g / (4 k_f).
  EXPECT_NEAR(vehicle.hoverRotorSpeedRadS(), std::sqrt(0.5 * 9.81 / (4.0 * 5.57e-6)),
              kScalarTolerance);
}

TEST(FlightVehicle, AllocationMatchesHandWorkedPlus) {
  VehicleParams params;
  params.layout = RotorLayout::kPlus;
  const Vehicle vehicle(params);
  const double kf = params.thrust_coeff_n_s2_rad2;
  const double km = params.moment_coeff_nm_s2_rad2;
  const double arm = params.arm_length_m;
  // Columns: 1 right CCW, 2 left CCW, 3 front CW, 4 rear CW.
  Eigen::Matrix4d expected;
  expected << kf, kf, kf, kf,
      -kf * arm, kf * arm, 0.0, 0.0,
      0.0, 0.0, kf * arm, -kf * arm,
      km, km, -km, -km;
  EXPECT_LE((vehicle.allocation() - expected).cwiseAbs().maxCoeff(), kMatrixTolerance);
}

TEST(FlightVehicle, ValidateNamesTheKey) {
  VehicleParams params;
  EXPECT_TRUE(params.validate().ok());
  params.mass_kg = 0.0;
  EXPECT_EQ(params.validate().message(), "vehicle.mass_kg must be in (0, 50] (got 0)");
  params = VehicleParams{};
  params.rotor_speed_max_rad_s = 400.0;  // below the Hummingbird's 469 rad/s hover
  EXPECT_FALSE(params.validate().ok());
}

class FlightMixer : public ::testing::Test {
 protected:
  const VehicleParams params_;
  const Vehicle vehicle_{params_};
  const Mixer mixer_{vehicle_};
};

TEST_F(FlightMixer, UnsaturatedRoundTripIsExact) {
  const Wrench demanded{vehicle_.weightN(), Eigen::Vector3d(0.02, -0.03, 0.01)};
  const MixerOutput out = mixer_.mix(demanded);
  EXPECT_FALSE(out.saturation.any());
  EXPECT_NEAR(out.achieved.thrust_n, demanded.thrust_n, kRoundTripToleranceN);
  EXPECT_LE((out.achieved.moment_body_nm - demanded.moment_body_nm).cwiseAbs().maxCoeff(),
            kRoundTripToleranceN);
}

TEST_F(FlightMixer, YawGivesWayFirst) {
  // At hover the CW rotors can slow by only their hover w^2 before stopping: a yaw of 0.3 N m
  // needs more than the 4 k_m w_hover^2 = 0.12 N m there is.
  const Wrench demanded{vehicle_.weightN(), Eigen::Vector3d(0.05, 0.0, 0.3)};
  const MixerOutput out = mixer_.mix(demanded);
  EXPECT_LT(out.saturation.yaw_kept, 1.0);
  EXPECT_GT(out.saturation.yaw_kept, 0.0);
  EXPECT_TRUE(out.saturation.moment_cut_positive[2]);
  EXPECT_EQ(out.saturation.thrust_change_n, 0.0);
  EXPECT_EQ(out.saturation.roll_pitch_kept, 1.0);
  EXPECT_NEAR(out.achieved.thrust_n, demanded.thrust_n, kRoundTripToleranceN);
  EXPECT_NEAR(out.achieved.moment_body_nm.x(), 0.05, kRoundTripToleranceN);
  EXPECT_NEAR(out.achieved.moment_body_nm.z(), 0.3 * out.saturation.yaw_kept,
              kRoundTripToleranceN);
}

TEST_F(FlightMixer, ThrustGivesWayBeforeRollAndPitch) {
  // Near full thrust (4 k_f w_max^2 = 50 N) a roll of 0.5 N m fits only with less thrust.
  const Wrench demanded{48.0, Eigen::Vector3d(0.5, -0.2, 0.05)};
  const MixerOutput out = mixer_.mix(demanded);
  EXPECT_LT(out.saturation.thrust_change_n, 0.0);
  EXPECT_EQ(out.saturation.roll_pitch_kept, 1.0);
  EXPECT_NEAR(out.achieved.moment_body_nm.x(), 0.5, kRoundTripToleranceN);
  EXPECT_NEAR(out.achieved.moment_body_nm.y(), -0.2, kRoundTripToleranceN);
  EXPECT_NEAR(out.achieved.thrust_n, 48.0 + out.saturation.thrust_change_n, kRoundTripToleranceN);
  // The rotors that the yaw would speed up are at their limit: yaw gave way entirely.
  EXPECT_LT(out.saturation.yaw_kept, 1.0);
  EXPECT_EQ(out.rotor_speed_rad_s.maxCoeff(), params_.rotor_speed_max_rad_s);
}

TEST_F(FlightMixer, RollAndPitchCutLastKeepingTheirDirection) {
  // 5 N m of roll is beyond what the rotors give at any thrust (k_f w_max^2 * 4 * arm / sqrt 2).
  const Wrench demanded{vehicle_.weightN(), Eigen::Vector3d(5.0, 2.5, 0.1)};
  const MixerOutput out = mixer_.mix(demanded);
  EXPECT_LT(out.saturation.roll_pitch_kept, 1.0);
  EXPECT_TRUE(out.saturation.moment_cut_positive[0]);
  EXPECT_TRUE(out.saturation.moment_cut_positive[1]);
  EXPECT_NEAR(out.achieved.moment_body_nm.x() / out.achieved.moment_body_nm.y(), 2.0,
              kScalarTolerance);
  EXPECT_EQ(out.saturation.yaw_kept, 0.0);  // the full range went to roll and pitch
}

TEST_F(FlightMixer, OutputsAlwaysWithinLimitsAndNeverBeyondTheDemand) {
  VehicleParams idle_params;
  idle_params.rotor_speed_min_rad_s = 150.0;  // an ESC that keeps the rotors turning
  const Vehicle idle_vehicle(idle_params);
  std::mt19937 rng(42);
  std::uniform_real_distribution<double> thrust_n(-10.0, 70.0);
  std::uniform_real_distribution<double> moment_nm(-2.0, 2.0);
  // The achieved moment may exceed the demand only by rounding of w^2 ~ 2e6 (rad/s)^2.
  constexpr double kMomentRoundingNm = 1e-9;
  for (const Vehicle* vehicle : {&vehicle_, &idle_vehicle}) {
    const Mixer mixer(*vehicle);
    for (int trial = 0; trial < 5000; ++trial) {
      const Wrench demanded{thrust_n(rng),
                            Eigen::Vector3d(moment_nm(rng), moment_nm(rng), 0.2 * moment_nm(rng))};
      const MixerOutput out = mixer.mix(demanded);
      EXPECT_GE(out.rotor_speed_rad_s.minCoeff(), vehicle->params().rotor_speed_min_rad_s);
      EXPECT_LE(out.rotor_speed_rad_s.maxCoeff(), vehicle->params().rotor_speed_max_rad_s);
      for (int axis = 0; axis < 3; ++axis) {
        const double demand = demanded.moment_body_nm(axis);
        const double achieved = out.achieved.moment_body_nm(axis);
        EXPECT_LE(std::abs(achieved), std::abs(demand) + kMomentRoundingNm);
        EXPECT_GE(achieved * demand, -kMomentRoundingNm);  // never the opposite way
      }
    }
  }
}

}  // namespace
