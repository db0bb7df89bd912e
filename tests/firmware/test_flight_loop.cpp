// The inner loops closed around the test plant (flight_plant.h: RK4 at 1 kHz, motor lag, noisy
// gyros): a body-rate step and a 10 degree attitude step with each law converge without steady
// error or large overshoot, and a control tick allocates nothing. Correctness with wide margins;
// the figures themselves are kinfly-flight-bench's.
#include <gtest/gtest.h>

#include "count_allocations.h"
#include "flight_loop.h"

namespace {

using kinfly::flight::AttitudeController;
using kinfly::flight::AttitudeLaw;
using kinfly::flight::Mixer;
using kinfly::flight::MixerOutput;
using kinfly::flight::MixerSaturation;
using kinfly::flight::Vehicle;
using kinfly::flight::VehicleParams;
namespace test = kinfly::flight::test;

constexpr uint32_t kSeed = 3;
// Gyro noise of 1.6e-3 rad/s per sample moves the mean of the last 0.1 s by ~1e-4 of the step.
constexpr double kFinalErrorTolerance = 0.01;
// Twice the targets: these check the loops work, the benchmark reports how well.
constexpr double kRateRiseLimitS = 0.1;
constexpr double kRateOvershootLimit = 0.2;
constexpr double kAttitudeSettleLimitS = 0.5;
constexpr double kAttitudeOvershootLimit = 0.15;

TEST(FlightLoop, RateStepConverges) {
  const Vehicle vehicle{VehicleParams{}};
  const test::StepFigures figures = test::stepFigures(test::flyRateStep(
      vehicle, kinfly::flight::RateController::Params{}, test::kGyroNoiseDensity, kSeed));
  EXPECT_LT(figures.rise_time_s, kRateRiseLimitS);
  EXPECT_LT(figures.overshoot, kRateOvershootLimit);
  EXPECT_LT(std::abs(figures.final_error), kFinalErrorTolerance);
}

class FlightLoopAttitude : public ::testing::TestWithParam<AttitudeLaw> {};

TEST_P(FlightLoopAttitude, TenDegreeStepConverges) {
  const Vehicle vehicle{VehicleParams{}};
  AttitudeController::Params params;
  params.law = GetParam();
  auto controller = AttitudeController::create(params, vehicle);
  ASSERT_TRUE(controller.ok()) << controller.status().message();
  const test::StepFigures figures = test::stepFigures(
      test::flyAttitudeStep(vehicle, *controller, test::kGyroNoiseDensity, kSeed));
  EXPECT_LT(figures.settling_time_s, kAttitudeSettleLimitS);
  EXPECT_LT(figures.overshoot, kAttitudeOvershootLimit);
  EXPECT_LT(std::abs(figures.final_error), kFinalErrorTolerance);
}

TEST_P(FlightLoopAttitude, TiltAndYawTogetherReachTheSetpoint) {
  // Every axis and sign at once: a sign slip in pitch or yaw, which a roll step cannot see,
  // would leave the body away from the setpoint or diverging.
  const Vehicle vehicle{VehicleParams{}};
  AttitudeController::Params params;
  params.law = GetParam();
  auto controller = AttitudeController::create(params, vehicle);
  ASSERT_TRUE(controller.ok()) << controller.status().message();
  const Eigen::Quaterniond q_world_body_sp =
      Eigen::AngleAxisd(0.5, Eigen::Vector3d::UnitZ()) *
      Eigen::AngleAxisd(-0.15, Eigen::Vector3d::UnitY()) *
      Eigen::AngleAxisd(0.1, Eigen::Vector3d::UnitX());
  const std::vector<Eigen::Quaterniond> q_world_body = test::flyAttitude(
      vehicle, *controller, q_world_body_sp, test::kGyroNoiseDensity, kSeed);
  // Yaw is the slowest axis. Through the geometric law the yaw-rate integrator, wound up while
  // the 29 degree yaw lagged its rate setpoint, unwinds over K_p/K_i ~ 0.7 s: 0.25 degrees are
  // left after 1 s (the LQR: 0.02), measured.
  constexpr double kFinalAngleToleranceRad = 0.5 * M_PI / 180.0;
  EXPECT_LT(q_world_body.back().angularDistance(q_world_body_sp), kFinalAngleToleranceRad);
}

INSTANTIATE_TEST_SUITE_P(Laws, FlightLoopAttitude,
                         ::testing::Values(AttitudeLaw::kGeometric, AttitudeLaw::kLqr),
                         [](const auto& law) { return std::string(toString(law.param)); });

TEST(FlightLoop, ControlTickAllocatesNothing) {
  const Vehicle vehicle{VehicleParams{}};
  auto controller = AttitudeController::create(AttitudeController::Params{}, vehicle);
  ASSERT_TRUE(controller.ok());
  const Mixer mixer(vehicle);
  test::FlightPlant plant(vehicle, test::kGyroNoiseDensity, kSeed);
  plant.startHovering();
  const Eigen::Quaterniond q_world_body_sp(Eigen::AngleAxisd(0.2, Eigen::Vector3d::UnitY()));
  MixerSaturation saturation;
  int64_t allocations = 0;
  for (const AttitudeLaw law : {AttitudeLaw::kGeometric, AttitudeLaw::kLqr}) {
    controller->setLaw(law);
    for (int k = 0; k < 500; ++k) {
      const Eigen::Vector3d gyro_body_rad_s = plant.gyroBodyRadS();
      const int64_t before = g_allocations;
      const Eigen::Vector3d moment_body_nm = controller->update(
          plant.state().q_world_body, q_world_body_sp, gyro_body_rad_s, test::kControlDtS,
          saturation);
      const MixerOutput out = mixer.mix({vehicle.weightN(), moment_body_nm});
      allocations += g_allocations - before;
      saturation = out.saturation;
      plant.step(out.rotor_speed_rad_s, test::kControlDtS);
    }
  }
  EXPECT_EQ(allocations, 0);
}

}  // namespace
