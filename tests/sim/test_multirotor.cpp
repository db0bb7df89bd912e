// The simulated multirotor against closed-form answers: hover, a free fall through the rotors'
// lag, the moments of a speed difference, the rotors' drag in a wind, the floor.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>

#include "kinfly/sim/multirotor.h"

namespace kinfly::sim {
namespace {

constexpr double kDt = 0.001;  // [s] the simulator's 1 kHz step
// RK4 at 1 kHz against a closed form over a second: far below a millimetre; the bound leaves
// room for rounding only.
constexpr double kIntegrationTolM = 1e-6;

MultirotorParams withoutDrag() {
  MultirotorParams params;
  params.rotor_drag_coeff = 0.0;
  params.induced_inflow_coeff = 0.0;
  params.parasitic_drag_x = params.parasitic_drag_y = params.parasitic_drag_z = 0.0;
  return params;
}

TEST(Multirotor, DefaultsAreValidAndImpossibleVehiclesAreNamed) {
  EXPECT_TRUE(MultirotorParams().validate().ok());
  MultirotorParams heavy;
  heavy.mass_kg = 5.2;  // hovers at 1513 rad/s, beyond the rotors' 1500
  const Status status = heavy.validate();
  ASSERT_FALSE(status.ok());
  EXPECT_NE(status.message().find("hover rotor speed"), std::string::npos) << status.message();
  MultirotorParams bad;
  bad.motor_time_constant_s = 0.0;
  EXPECT_EQ(bad.validate().message(), "vehicle.motor_time_constant_s must be in (0, 0.5] (got 0)");
  EXPECT_FALSE(parseRotorLayout("h").ok());
  EXPECT_EQ(parseRotorLayout("plus").value(), RotorLayout::kPlus);
}

TEST(Multirotor, HoverSpeedHoldsItStill) {
  Multirotor drone(MultirotorParams{});
  drone.placeHovering({1.0, 2.0, -1.5}, 0.3);
  const Vector4d hover = Vector4d::Constant(drone.hoverRotorSpeedRadS());
  for (int i = 0; i < 2000; ++i) drone.step(hover, Eigen::Vector3d::Zero(), kDt);
  EXPECT_LT((drone.state().p_world_m - Eigen::Vector3d(1.0, 2.0, -1.5)).norm(), kIntegrationTolM);
  EXPECT_LT(drone.state().omega_body_rad_s.norm(), 1e-9);
  EXPECT_LT((drone.specificForceBodyMS2() - Eigen::Vector3d(0.0, 0.0, -kGravityMS2)).norm(), 1e-9);
}

TEST(Multirotor, FallsThroughTheRotorsLagAsTheClosedForm) {
  // Rotors told to stop from hover: w = w0 e^(-t/tau), so the thrust fades as e^(-2t/tau) and
  // z(t) = g t^2/2 - g (tau/2) t + g (tau/2)^2 (1 - e^(-2t/tau)).
  const MultirotorParams params = withoutDrag();
  Multirotor drone(params);
  drone.placeHovering(Eigen::Vector3d::Zero(), 0.0);
  const double tau = params.motor_time_constant_s;
  const int steps = 500;
  for (int i = 0; i < steps; ++i) drone.step(Vector4d::Zero(), Eigen::Vector3d::Zero(), kDt);
  const double t = steps * kDt;
  const double half = tau / 2.0;
  const double z = kGravityMS2 * (0.5 * t * t - half * t + half * half * (1.0 - std::exp(-t / half)));
  EXPECT_NEAR(drone.state().p_world_m.z(), z, kIntegrationTolM);
  EXPECT_NEAR(drone.state().rotor_speed_rad_s(0), drone.hoverRotorSpeedRadS() * std::exp(-t / tau),
              1e-6);
  // Falling freely, the accelerometer reads (almost) nothing.
  EXPECT_LT(drone.specificForceBodyMS2().norm(), 1e-3);
}

// The angular acceleration of a body whose rotors have settled at `speeds` (40 lag constants),
// over one short step: the moments divided by the inertia.
Eigen::Vector3d angularAcceleration(const MultirotorParams& params, const Vector4d& speeds) {
  Multirotor drone(params);
  drone.placeHovering(Eigen::Vector3d::Zero(), 0.0);
  for (int i = 0; i < 200; ++i) drone.step(speeds, Eigen::Vector3d::Zero(), kDt);
  const Eigen::Vector3d before = drone.state().omega_body_rad_s;
  const double dt = 1e-5;
  drone.step(speeds, Eigen::Vector3d::Zero(), dt);
  return (drone.state().omega_body_rad_s - before) / dt;
}

TEST(Multirotor, SpeedDifferencesTurnTheBodyAsTheRotorGeometrySays) {
  const MultirotorParams params = withoutDrag();
  const double w = Multirotor(params).hoverRotorSpeedRadS();
  const double dw = 20.0;
  const double d_speed_sq = (w + dw) * (w + dw) - w * w;
  // The right rotors (X: 1 front-right, 4 rear-right) faster lift the right side: a negative
  // roll moment -(y_1 + y_4) k_f d(w^2); front and rear cancel in pitch, CCW 1 and CW 4 in yaw.
  Vector4d right = Vector4d::Constant(w);
  right(0) += dw;
  right(3) += dw;
  const Eigen::Vector3d roll = angularAcceleration(params, right);
  const double y = params.arm_length_m * std::sqrt(0.5);
  const double expected_roll =
      -2.0 * y * params.thrust_coeff_n_s2_rad2 * d_speed_sq / params.inertia_xx_kg_m2;
  EXPECT_NEAR(roll.x(), expected_roll, 1e-3 * std::abs(expected_roll));
  EXPECT_NEAR(roll.y(), 0.0, 1e-6 * std::abs(expected_roll));
  EXPECT_NEAR(roll.z(), 0.0, 1e-6 * std::abs(expected_roll));
  // The CCW rotors (1, 2) faster turn the body about +z by their drag moments.
  Vector4d ccw = Vector4d::Constant(w);
  ccw(0) += dw;
  ccw(1) += dw;
  const Eigen::Vector3d yaw = angularAcceleration(params, ccw);
  const double expected_yaw =
      2.0 * params.moment_coeff_nm_s2_rad2 * d_speed_sq / params.inertia_zz_kg_m2;
  EXPECT_NEAR(yaw.z(), expected_yaw, 1e-3 * expected_yaw);
  EXPECT_NEAR(yaw.x(), 0.0, 1e-6 * expected_yaw);
}

TEST(Multirotor, RotorDragPushesTheHoveringBodyDownwind) {
  // Hovering level in a wind W along x: each rotor drags k_d w W toward +x, the frame c_x W^2.
  const MultirotorParams params;
  Multirotor drone(params);
  drone.placeHovering(Eigen::Vector3d::Zero(), 0.0);
  const double wind = 2.0;
  const double w = drone.hoverRotorSpeedRadS();
  const double dt = 1e-5;
  drone.step(Vector4d::Constant(w), Eigen::Vector3d(wind, 0.0, 0.0), dt);
  const double a_x = drone.state().v_world_m_s.x() / dt;
  const double expected =
      (4.0 * params.rotor_drag_coeff * w * wind + params.parasitic_drag_x * wind * wind) /
      params.mass_kg;
  EXPECT_NEAR(a_x, expected, 1e-3 * expected);
  EXPECT_NEAR(drone.specificForceBodyMS2().x(), expected, 1e-3 * expected);
}

TEST(Multirotor, StandsOnItsGearTakesOffAndLandsOnIt) {
  const MultirotorParams params;
  Multirotor drone(params);
  drone.placeOnFloor({0.5, -0.5}, 0.0, 0.0);
  for (int i = 0; i < 500; ++i) drone.step(Vector4d::Constant(100.0), Eigen::Vector3d::Zero(), kDt);
  EXPECT_TRUE(drone.onFloor());
  // Standing, the gear carries the weight less the idle rotors' thrust: it sags that much less.
  const double idle_thrust_n = 4.0 * params.thrust_coeff_n_s2_rad2 * 100.0 * 100.0;
  const double weight_n = params.mass_kg * kGravityMS2;
  const double sag_m = params.gear_sag_m * (weight_n - idle_thrust_n) / weight_n;
  constexpr double kSettledTolM = 1e-5;  // 2.5 s of a critically damped 7 Hz gear
  EXPECT_NEAR(drone.state().p_world_m.z(), -params.gear_height_m + sag_m, kSettledTolM);
  // Standing still, the accelerometer reads the floor's and the rotors' push: -g along z.
  constexpr double kStillTolMS2 = 1e-3;
  EXPECT_NEAR(drone.specificForceBodyMS2().z(), -kGravityMS2, kStillTolMS2);
  const double climb = 1.2 * drone.hoverRotorSpeedRadS();
  for (int i = 0; i < 1000; ++i) drone.step(Vector4d::Constant(climb), Eigen::Vector3d::Zero(), kDt);
  EXPECT_FALSE(drone.onFloor());
  EXPECT_LT(drone.state().p_world_m.z(), -0.5);
  // Rotors cut: it falls back, and the touchdown speed is what it fell at.
  double touchdown = 0.0;
  double peak_specific_force = 0.0;
  for (int i = 0; i < 3000 && touchdown == 0.0; ++i) {
    touchdown = drone.step(Vector4d::Zero(), Eigen::Vector3d::Zero(), kDt);
  }
  EXPECT_TRUE(drone.onFloor());
  EXPECT_GT(touchdown, 2.0);
  // The gear spreads the impact: at most its damping times the speed, over the mass (a rigid
  // floor would give speed / step: thousands of m/s^2).
  const double damping = 2.0 * std::sqrt(weight_n / params.gear_sag_m * params.mass_kg);
  for (int i = 0; i < 1000; ++i) {
    drone.step(Vector4d::Zero(), Eigen::Vector3d::Zero(), kDt);
    peak_specific_force = std::max(peak_specific_force, drone.specificForceBodyMS2().norm());
  }
  EXPECT_LT(peak_specific_force, 1.2 * damping * touchdown / params.mass_kg);
  EXPECT_LT(drone.state().v_world_m_s.norm(), 1e-3);  // settled
  EXPECT_TRUE(drone.onFloor());
  // Standing is no new touchdown.
  EXPECT_EQ(drone.step(Vector4d::Zero(), Eigen::Vector3d::Zero(), kDt), 0.0);
}

TEST(Multirotor, TheGearLevelsATiltedBody) {
  Multirotor drone(MultirotorParams{});
  drone.placeOnFloor({0.0, 0.0}, 0.3, 0.0);
  // Rotors on one side only tilt it while it stands; cut, the gear brings it back level.
  Vector4d one_side = Vector4d::Zero();
  one_side(0) = one_side(3) = 300.0;
  for (int i = 0; i < 300; ++i) drone.step(one_side, Eigen::Vector3d::Zero(), kDt);
  const auto tilt = [&] {
    return std::acos(std::clamp((drone.state().q_world_body * Eigen::Vector3d::UnitZ()).z(), -1.0, 1.0));
  };
  EXPECT_GT(tilt(), 1e-3);
  for (int i = 0; i < 2000; ++i) drone.step(Vector4d::Zero(), Eigen::Vector3d::Zero(), kDt);
  EXPECT_LT(tilt(), 1e-4);
  EXPECT_TRUE(drone.onFloor());
}

TEST(Multirotor, AWeakRotorLosesItsShareOfThrust) {
  const MultirotorParams params = withoutDrag();
  Multirotor drone(params);
  drone.placeHovering(Eigen::Vector3d::Zero(), 0.0);
  drone.setRotorEfficiency(0, 0.8);
  const double dt = 1e-5;
  drone.step(Vector4d::Constant(drone.hoverRotorSpeedRadS()), Eigen::Vector3d::Zero(), dt);
  // A fifth of one rotor's quarter of the weight is missing: the body sinks at g / 20.
  EXPECT_NEAR(drone.state().v_world_m_s.z() / dt, kGravityMS2 / 20.0, 1e-3);
}

}  // namespace
}  // namespace kinfly::sim
