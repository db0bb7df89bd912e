// The position loop and the trajectories: the law's pieces against hand-worked values (feed-
// forward, yaw, tilt and thrust limits, the integral's anti-windup), the minimum-snap solve
// against its closed form and its constraints, the simple trajectories, and the whole stack
// closed around the test plant with the estimator on noisy, late poses (flight_position.h):
// issue 15's hover, figure-eight and wind figures, and the stack from the floor and back. The
// whole stack's tick allocates nothing.
#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <memory>
#include <optional>
#include <vector>

#include "count_allocations.h"
#include "flight_position.h"

namespace kinfly::flight {
namespace {

using Eigen::Quaterniond;
using Eigen::Vector3d;

constexpr uint32_t kSeed = 5;
// Exact arithmetic but for rounding.
constexpr double kTight = 1e-9;

EstimatorState stateAt(const Vector3d& p_world_m) {
  EstimatorState state;
  state.p_world_body_m = p_world_m;
  return state;
}

// ---- Position controller -----------------------------------------------------------------------

TEST(PositionControllerParams, DefaultsAreValidAndARangeIsNamed) {
  EXPECT_TRUE(PositionControllerParams().validate().ok());
  PositionControllerParams params;
  params.rate_hz = 50.0;
  EXPECT_EQ(params.validate().message(), "position.rate_hz must be in [100, 1000] (got 50)");
  params = PositionControllerParams();
  params.p_gain_1_s2.y() = -1.0;
  EXPECT_EQ(params.validate().message(), "position.p_gain_1_s2.y must be in [0, 100] (got -1)");
}

TEST(PositionController, OnTheSetpointHoldsTheWeightLevelAtTheYaw) {
  const Vehicle vehicle{VehicleParams{}};
  PositionController controller(PositionControllerParams{}, vehicle);
  PositionSetpoint setpoint;
  setpoint.yaw_rad = 0.7;
  const PositionOutput out = controller.update(setpoint, stateAt(Vector3d::Zero()), 0.01);
  EXPECT_NEAR(out.thrust_n, vehicle.weightN(), kTight);
  EXPECT_LT(out.q_world_body_sp.angularDistance(
                Quaterniond(Eigen::AngleAxisd(0.7, Vector3d::UnitZ()))),
            kTight);
  EXPECT_FALSE(out.tilt_limited || out.thrust_limited);
}

TEST(PositionController, FeedsTheAccelerationForwardThroughTheThrustDirection) {
  // Forward at 2 m/s^2 and up at 1 m/s^2: the thrust must give (2, 0, -1 - g) m/s^2, so z_body
  // points against it (nose down in FRD) and, level now, the collective is its part along -z.
  const Vehicle vehicle{VehicleParams{}};
  PositionController controller(PositionControllerParams{}, vehicle);
  PositionSetpoint setpoint;
  setpoint.a_world_m_s2 = Vector3d(2.0, 0.0, -1.0);
  const PositionOutput out = controller.update(setpoint, stateAt(Vector3d::Zero()), 0.01);
  const Vector3d thrust_m_s2(2.0, 0.0, -1.0 - kGravityMS2);
  const Vector3d z_body_sp_world = out.q_world_body_sp * Vector3d::UnitZ();
  EXPECT_LT((z_body_sp_world + thrust_m_s2.normalized()).norm(), kTight);
  EXPECT_NEAR((out.q_world_body_sp * Vector3d::UnitX()).y(), 0.0, kTight);  // yaw 0 kept
  EXPECT_NEAR(out.thrust_n, vehicle.params().mass_kg * (1.0 + kGravityMS2), kTight);
}

TEST(PositionController, FeedsTheFeltForceForwardAfterItsFilter) {
  // Level, on the setpoint, the accelerometer feeling 0.5 m/s^2 of push along body x (a wind)
  // and a body z that is the thrust's and not fed forward: the thrust leans against the push by
  // its filter's step response, 1 - (tau / (tau + dt))^n after n samples, and the integral,
  // with no position error, stays zero.
  const Vehicle vehicle{VehicleParams{}};
  const PositionControllerParams params;
  PositionController controller(params, vehicle);
  const Vector3d push(0.5, 0.0, -kGravityMS2 - 3.0);
  constexpr double kImuDt = 0.001;
  constexpr int kSamples = 100;
  for (int i = 0; i < kSamples; ++i) controller.feel(push, Quaterniond::Identity(), kImuDt);
  const PositionOutput out = controller.update(PositionSetpoint{}, stateAt(Vector3d::Zero()), 0.01);
  const double felt = 0.5 * (1.0 - std::pow(params.disturbance_filter_s /
                                                (params.disturbance_filter_s + kImuDt), kSamples));
  EXPECT_LT((controller.disturbanceMS2() - Vector3d(felt, 0.0, 0.0)).norm(), kTight);
  const Vector3d thrust_m_s2(-felt, 0.0, -kGravityMS2);
  EXPECT_LT((out.q_world_body_sp * Vector3d::UnitZ() + thrust_m_s2.normalized()).norm(), kTight);
  EXPECT_EQ(controller.integralMS2(), Vector3d::Zero());
  // A take-off starts it afresh; it is felt in world, turned with the body (yawed a quarter
  // turn: body x is world y); a gain of 0 feeds none.
  controller.reset();
  EXPECT_EQ(controller.disturbanceMS2(), Vector3d::Zero());
  const Quaterniond yawed(Eigen::AngleAxisd(M_PI / 2.0, Vector3d::UnitZ()));
  for (int i = 0; i < kSamples; ++i) controller.feel(push, yawed, kImuDt);
  EXPECT_LT((controller.disturbanceMS2() - Vector3d(0.0, felt, 0.0)).norm(), kTight);
  PositionControllerParams off = params;
  off.disturbance_gain = 0.0;
  PositionController unfed(off, vehicle);
  for (int i = 0; i < kSamples; ++i) unfed.feel(push, Quaterniond::Identity(), kImuDt);
  const PositionOutput level = unfed.update(PositionSetpoint{}, stateAt(Vector3d::Zero()), 0.01);
  EXPECT_LT((level.q_world_body_sp * Vector3d::UnitZ() - Vector3d::UnitZ()).norm(), kTight);
}

TEST(PositionController, TheRotorsVibrationStaysOutOfTheFeltForce) {
  // 2 m/s^2 of vibration along body x at 200.5 Hz on a 0.5 m/s^2 push, sampled at 1 kHz: felt
  // at every sample the filter leaves the push; taken every tenth sample (the loop's 100 Hz) the
  // vibration folds down to 0.5 Hz and would tilt the vehicle by metres per second squared.
  const Vehicle vehicle{VehicleParams{}};
  PositionController every(PositionControllerParams{}, vehicle), tenth(PositionControllerParams{}, vehicle);
  constexpr double kImuDt = 0.001, kVibrationHz = 200.5, kVibrationMS2 = 2.0, kPushMS2 = 0.5;
  constexpr double kWithinMS2 = 0.05;  // the filter's leftover at 200 Hz is ~0.016
  double worst = 0.0, worst_tenth = 0.0;
  for (int i = 0; i < 4000; ++i) {
    const double t = i * kImuDt;
    const Vector3d f(kPushMS2 + kVibrationMS2 * std::sin(2.0 * M_PI * kVibrationHz * t), 0.0, -kGravityMS2);
    every.feel(f, Quaterniond::Identity(), kImuDt);
    if (i % 10 == 0) tenth.feel(f, Quaterniond::Identity(), 10 * kImuDt);
    if (t > 1.0) {
      worst = std::max(worst, std::abs(every.disturbanceMS2().x() - kPushMS2));
      worst_tenth = std::max(worst_tenth, std::abs(tenth.disturbanceMS2().x() - kPushMS2));
    }
  }
  EXPECT_LT(worst, kWithinMS2);
  EXPECT_GT(worst_tenth, 1.0);
}

TEST(PositionController, CutsTheTiltAndKeepsTheHeight) {
  const Vehicle vehicle{VehicleParams{}};
  const PositionControllerParams params;
  PositionController controller(params, vehicle);
  // 10 m behind the setpoint: far more than the tilt limit allows.
  const PositionOutput out =
      controller.update(PositionSetpoint{}, stateAt(Vector3d(-10.0, 0.0, 0.0)), 0.01);
  EXPECT_TRUE(out.tilt_limited);
  const Vector3d z_body_sp_world = out.q_world_body_sp * Vector3d::UnitZ();
  EXPECT_NEAR(std::acos(z_body_sp_world.z()), params.tilt_max_rad, kTight);
  EXPECT_GT(-z_body_sp_world.x(), 0.0);  // thrust forward, towards the setpoint
  // Level now, so the collective is the vertical part only: the weight, height held.
  EXPECT_NEAR(out.thrust_n, vehicle.weightN(), kTight);
}

TEST(PositionController, ClampsTheThrustToItsRange) {
  const Vehicle vehicle{VehicleParams{}};
  const PositionControllerParams params;
  PositionController controller(params, vehicle);
  // 10 m above the setpoint (z down): the law asks to fall faster than gravity.
  const PositionOutput down =
      controller.update(PositionSetpoint{}, stateAt(Vector3d(0.0, 0.0, -10.0)), 0.01);
  EXPECT_TRUE(down.thrust_limited);
  EXPECT_NEAR(down.thrust_n, vehicle.params().mass_kg * params.thrust_min_m_s2, kTight);
  EXPECT_LT(down.q_world_body_sp.angularDistance(Quaterniond::Identity()), kTight);
  // 10 m below it: more than the maximum.
  const PositionOutput up =
      controller.update(PositionSetpoint{}, stateAt(Vector3d(0.0, 0.0, 10.0)), 0.01);
  EXPECT_TRUE(up.thrust_limited);
  EXPECT_NEAR(up.thrust_n, vehicle.params().mass_kg * params.thrust_max_m_s2, kTight);
}

TEST(PositionController, HeightComesFirstWhenTheThrustRunsOut) {
  const Vehicle vehicle{VehicleParams{}};
  const PositionControllerParams params;
  PositionController controller(params, vehicle);
  const double mass_kg = vehicle.params().mass_kg;
  // 10 m below and 10 m behind: the climb alone asks for more than the maximum, so nothing is
  // left to go sideways with and the body stays level.
  const PositionOutput all_up =
      controller.update(PositionSetpoint{}, stateAt(Vector3d(-10.0, 0.0, 10.0)), 0.01);
  EXPECT_TRUE(all_up.thrust_limited);
  EXPECT_NEAR(all_up.thrust_n, mass_kg * params.thrust_max_m_s2, kTight);
  EXPECT_LT(all_up.q_world_body_sp.angularDistance(Quaterniond::Identity()), kTight);
  // 0.5 m below and 10 m behind: the climb takes what it needs and the rest goes sideways,
  // within the maximum thrust.
  PositionController partial(params, vehicle);
  const PositionOutput some_up =
      partial.update(PositionSetpoint{}, stateAt(Vector3d(-10.0, 0.0, 0.5)), 0.01);
  const double up_m_s2 = kGravityMS2 + params.p_gain_1_s2.z() * 0.5;
  ASSERT_LT(up_m_s2, params.thrust_max_m_s2);
  const Vector3d thrust_dir_world = -(some_up.q_world_body_sp * Vector3d::UnitZ());
  const double tilt_rad = std::acos(thrust_dir_world.z() * -1.0);
  const double tilt_expected_rad = std::min(
      params.tilt_max_rad,
      std::atan(std::sqrt(params.thrust_max_m_s2 * params.thrust_max_m_s2 - up_m_s2 * up_m_s2) /
                up_m_s2));
  EXPECT_NEAR(tilt_rad, tilt_expected_rad, kTight);
  EXPECT_GT(thrust_dir_world.x(), 0.0);  // towards the setpoint
}

TEST(PositionController, IntegralIsClampedAndHeldWhileLimited) {
  const Vehicle vehicle{VehicleParams{}};
  const PositionControllerParams params;
  PositionController controller(params, vehicle);
  // A small steady error: the integral grows by K_i e dt, up to its limit.
  for (int k = 0; k < 2000; ++k) {
    (void)controller.update(PositionSetpoint{}, stateAt(Vector3d(0.0, 0.1, 0.0)), 0.01);
  }
  EXPECT_NEAR(controller.integralMS2().y(), params.integral_limit_m_s2.y(), kTight);
  EXPECT_EQ(controller.integralMS2().x(), 0.0);
  // Tilt-limited, it does not grow, but it still unwinds.
  controller.reset();
  for (int k = 0; k < 100; ++k) {
    (void)controller.update(PositionSetpoint{}, stateAt(Vector3d(-10.0, 0.0, 0.0)), 0.01);
  }
  EXPECT_EQ(controller.integralMS2().x(), 0.0);
  (void)controller.update(PositionSetpoint{}, stateAt(Vector3d(0.0, 0.0, 0.0)), 0.01);
  const PositionOutput limited =
      controller.update(PositionSetpoint{}, stateAt(Vector3d(0.0, 10.0, 0.0)), 0.01);
  ASSERT_TRUE(limited.tilt_limited);
  EXPECT_EQ(controller.integralMS2().y(), 0.0);
}

// ---- Trajectories ------------------------------------------------------------------------------

TEST(Trajectory, RefusesBadInputsAndNamesThem) {
  const TrajectoryParams params;
  const Vector3d a(0, 0, -1), b(1, 0, -1);
  EXPECT_EQ(Trajectory::minimumSnap({a}, params, 0.0).status().message(),
            "trajectory: needs at least 2 waypoints (got 1)");
  EXPECT_EQ(Trajectory::minimumSnap({a, Vector3d(NAN, 0, 0), b}, params, 0.0).status().message(),
            "trajectory: waypoint 1 is not finite");
  EXPECT_EQ(Trajectory::minimumSnapWithTimes({a, b, a}, {1.0, 0.0}, 0.0).status().message(),
            "trajectory: segment_times_s[1] must be in (0, 1e+06] (got 0)");
  EXPECT_EQ(Trajectory::minimumSnapWithTimes({a, b, a}, {1.0}, 0.0).status().message(),
            "trajectory: 1 segment times for 2 segments");
  TrajectoryParams slow;
  slow.max_speed_m_s = 0.0;
  EXPECT_EQ(Trajectory::minimumSnap({a, b}, slow, 0.0).status().message(),
            "trajectory.max_speed_m_s must be in (0, 20] (got 0)");
  TrajectoryParams gentle;
  gentle.max_accel_m_s2 = 25.0;
  EXPECT_EQ(gentle.validate().message(), "trajectory.max_accel_m_s2 must be in (0, 20] (got 25)");
  TrajectoryParams smooth;
  smooth.max_jerk_m_s3 = 0.0;
  EXPECT_EQ(smooth.validate().message(), "trajectory.max_jerk_m_s3 must be in (0, 200] (got 0)");
}

TEST(Trajectory, OneSegmentIsTheClosedFormRestToRestMinimumSnap) {
  // From rest to rest in T, the minimum-snap polynomial is p0 + d (35 s^4 - 84 s^5 + 70 s^6 -
  // 20 s^7), s = t / T (the degree-7 smoothstep).
  const Vector3d p0(1.0, -2.0, -1.0), d(0.5, 1.0, -0.3);
  const double duration_s = 2.0;
  auto trajectory = Trajectory::minimumSnapWithTimes({p0, p0 + d}, {duration_s}, 0.3);
  ASSERT_TRUE(trajectory.ok()) << trajectory.status().message();
  for (double t_s = 0.0; t_s <= duration_s; t_s += 0.05) {
    const double s = t_s / duration_s;
    const double shape = s * s * s * s * (35.0 - 84.0 * s + 70.0 * s * s - 20.0 * s * s * s);
    const double shape_rate =
        s * s * s * (140.0 - 420.0 * s + 420.0 * s * s - 140.0 * s * s * s) / duration_s;
    const PositionSetpoint sp = trajectory->sample(t_s);
    EXPECT_LT((sp.p_world_m - (p0 + shape * d)).norm(), 1e-9) << t_s;
    EXPECT_LT((sp.v_world_m_s - shape_rate * d).norm(), 1e-9) << t_s;
    EXPECT_EQ(sp.yaw_rad, 0.3);
  }
}

TEST(Trajectory, ThroughWaypointsMeetsThemSmoothlyAndStopsAtTheEnds) {
  const std::vector<Vector3d> waypoints = test::figureEightWaypoints();
  const std::vector<double> times_s = {1.0, 0.7, 1.3, 0.9, 1.1, 0.8, 1.2, 1.0};
  auto trajectory = Trajectory::minimumSnapWithTimes(waypoints, times_s, 0.0);
  ASSERT_TRUE(trajectory.ok()) << trajectory.status().message();
  ASSERT_EQ(trajectory->segmentCount(), 8);
  for (int i = 1; i < trajectory->segmentCount(); ++i) {
    const double knot_s = trajectory->segmentStartS(i);
    const PositionSetpoint before = trajectory->sample(knot_s - 1e-9);
    const PositionSetpoint at = trajectory->sample(knot_s);
    EXPECT_LT((at.p_world_m - waypoints[i]).norm(), 1e-9) << i;
    // Continuous in position, velocity, acceleration and jerk (to what 1 ns moves them).
    EXPECT_LT((before.p_world_m - at.p_world_m).norm(), 1e-7) << i;
    EXPECT_LT((before.v_world_m_s - at.v_world_m_s).norm(), 1e-7) << i;
    EXPECT_LT((before.a_world_m_s2 - at.a_world_m_s2).norm(), 1e-6) << i;
    EXPECT_LT((before.j_world_m_s3 - at.j_world_m_s3).norm(), 1e-5) << i;
  }
  for (const double t_s : {0.0, trajectory->durationS() - 1e-12}) {
    const PositionSetpoint end = trajectory->sample(t_s);
    EXPECT_LT(end.v_world_m_s.norm() + end.a_world_m_s2.norm() + end.j_world_m_s3.norm(), 1e-6);
  }
  EXPECT_LT((trajectory->sample(1e3).p_world_m - waypoints.back()).norm(), kTight);
  EXPECT_LT((trajectory->sample(-1.0).p_world_m - waypoints.front()).norm(), kTight);
}

// The optimality condition of the minimum-snap spline (the Euler-Lagrange conditions at the
// knots, de Boor's natural conditions for the interpolating spline that minimises the integral
// of the squared 4th derivative): with only position fixed at the inner waypoints and
// continuity imposed up to snap, the optimum is also continuous in the 5th and 6th derivatives.
// The solve never imposes those, so a wrong cost (its weights, its time scaling) would leave
// them broken while every imposed constraint held.
TEST(Trajectory, TheSolutionMeetsTheMinimumSnapOptimalityConditions) {
  const std::vector<Vector3d> waypoints = test::figureEightWaypoints();
  const std::vector<double> times_s = {1.0, 0.7, 1.3, 0.9, 1.1, 0.8, 1.2, 1.0};
  auto trajectory = Trajectory::minimumSnapWithTimes(waypoints, times_s, 0.0);
  ASSERT_TRUE(trajectory.ok()) << trajectory.status().message();
  // Relative to the derivative's size along the trajectory: the KKT solve's rounding.
  constexpr double kRelative = 1e-6;
  for (int order = 5; order <= 6; ++order) {
    double largest = 0.0;
    for (double t_s = 0.0; t_s < trajectory->durationS(); t_s += 0.01)
      largest = std::max(largest, trajectory->derivative(t_s, order).norm());
    ASSERT_GT(largest, 0.0);
    for (int i = 1; i < trajectory->segmentCount(); ++i) {
      const double knot_s = trajectory->segmentStartS(i);
      const Vector3d jump = trajectory->derivative(knot_s, order) -
                            trajectory->derivative(std::nextafter(knot_s, 0.0), order);
      EXPECT_LT(jump.norm(), kRelative * largest) << "derivative " << order << " at knot " << i;
    }
  }
  // The 7th is the spline's free one: it jumps (else the waypoints would lie on one polynomial).
  double jumps = 0.0;
  for (int i = 1; i < trajectory->segmentCount(); ++i) {
    const double knot_s = trajectory->segmentStartS(i);
    jumps += (trajectory->derivative(knot_s, 7) -
              trajectory->derivative(std::nextafter(knot_s, 0.0), 7))
                 .norm();
  }
  EXPECT_GT(jumps, 1.0);
}

TEST(Trajectory, AllocatedTimesReachTheMaxSpeed) {
  TrajectoryParams params;
  params.max_speed_m_s = 1.5;
  auto trajectory = Trajectory::minimumSnap(test::figureEightWaypoints(), params, 0.0);
  ASSERT_TRUE(trajectory.ok());
  double peak_m_s = 0.0;
  for (double t_s = 0.0; t_s < trajectory->durationS(); t_s += 1e-3) {
    peak_m_s = std::max(peak_m_s, trajectory->sample(t_s).v_world_m_s.norm());
  }
  // Scaled to the peak its 64 samples per segment saw; between them it is hardly higher.
  EXPECT_NEAR(peak_m_s, params.max_speed_m_s, 0.01 * params.max_speed_m_s);
}

TEST(Trajectory, AllocatedTimesKeepTheMaxAcceleration) {
  TrajectoryParams params;
  params.max_speed_m_s = 5.0;  // fast enough that the acceleration is the tighter limit
  params.max_accel_m_s2 = 2.0;
  auto trajectory = Trajectory::minimumSnap(test::figureEightWaypoints(), params, 0.0);
  ASSERT_TRUE(trajectory.ok());
  double peak_m_s = 0.0, peak_m_s2 = 0.0;
  for (double t_s = 0.0; t_s < trajectory->durationS(); t_s += 1e-3) {
    const PositionSetpoint sp = trajectory->sample(t_s);
    peak_m_s = std::max(peak_m_s, sp.v_world_m_s.norm());
    peak_m_s2 = std::max(peak_m_s2, sp.a_world_m_s2.norm());
  }
  EXPECT_NEAR(peak_m_s2, params.max_accel_m_s2, 0.01 * params.max_accel_m_s2);
  EXPECT_LT(peak_m_s, params.max_speed_m_s);
}

TEST(Trajectory, AllocatedTimesKeepTheMaxJerk) {
  TrajectoryParams params;
  params.max_speed_m_s = 5.0;  // speed and acceleration loose: the jerk is the tighter limit
  params.max_accel_m_s2 = 20.0;
  params.max_jerk_m_s3 = 10.0;
  auto trajectory = Trajectory::minimumSnap(test::figureEightWaypoints(), params, 0.0);
  ASSERT_TRUE(trajectory.ok());
  double peak_m_s3 = 0.0;
  for (double t_s = 0.0; t_s < trajectory->durationS(); t_s += 1e-3)
    peak_m_s3 = std::max(peak_m_s3, trajectory->sample(t_s).j_world_m_s3.norm());
  EXPECT_NEAR(peak_m_s3, params.max_jerk_m_s3, 0.01 * params.max_jerk_m_s3);
}

TEST(Trajectory, StraightLineFromRestToRestWithinItsLimits) {
  TrajectoryParams params;
  const Vector3d from(0, 0, -1), to(3, -4, -2);
  const StraightLine line(from, to, params, 0.4, 0.4);
  EXPECT_LT((line.sample(0.0).p_world_m - from).norm(), kTight);
  EXPECT_LT((line.sample(line.durationS()).p_world_m - to).norm(), kTight);
  EXPECT_EQ(line.sample(-1.0).p_world_m, from);
  EXPECT_EQ(line.sample(NAN).p_world_m, to);
  // At 1 m/s and 5 m/s^2 over 5.1 m the speed binds: the peak speed is 35/16 of the mean.
  EXPECT_NEAR(line.durationS(), 35.0 / 16.0 * (to - from).norm() / params.max_speed_m_s, 1e-9);
  double peak_m_s = 0.0, peak_m_s2 = 0.0;
  for (double t_s = 0.0; t_s <= line.durationS(); t_s += 1e-4) {
    const PositionSetpoint sp = line.sample(t_s);
    peak_m_s = std::max(peak_m_s, sp.v_world_m_s.norm());
    peak_m_s2 = std::max(peak_m_s2, sp.a_world_m_s2.norm());
    // Along the line, never off it.
    EXPECT_LT((sp.p_world_m - from).cross(to - from).norm(), 1e-9);
  }
  EXPECT_NEAR(peak_m_s, params.max_speed_m_s, 1e-6);
  EXPECT_LE(peak_m_s2, params.max_accel_m_s2);
  // The same polynomial as the two-point minimum snap solved in general (the KKT system).
  auto solved = Trajectory::minimumSnapWithTimes({from, to}, {line.durationS()}, 0.4);
  ASSERT_TRUE(solved.ok());
  for (const double t_s : {0.1, 0.37, 0.5 * line.durationS(), line.durationS() - 0.2}) {
    const PositionSetpoint a = line.sample(t_s), b = solved->sample(t_s);
    EXPECT_LT((a.p_world_m - b.p_world_m).norm(), 1e-9) << t_s;
    EXPECT_LT((a.v_world_m_s - b.v_world_m_s).norm(), 1e-8) << t_s;
    EXPECT_LT((a.a_world_m_s2 - b.a_world_m_s2).norm(), 1e-7) << t_s;
    EXPECT_LT((a.j_world_m_s3 - b.j_world_m_s3).norm(), 1e-6) << t_s;
    EXPECT_EQ(a.yaw_rad, 0.4);
  }
  // A short hop: the jerk binds, and its peak is the limit, at mid-way.
  const StraightLine hop(from, from + Vector3d(0.05, 0, 0), params, 0.0, 0.0);
  EXPECT_NEAR(hop.durationS(), std::cbrt(52.5 * 0.05 / params.max_jerk_m_s3), 1e-9);
  EXPECT_NEAR(hop.sample(0.5 * hop.durationS()).j_world_m_s3.norm(), params.max_jerk_m_s3, 1e-9);
  // With room for jerk, the acceleration binds.
  TrajectoryParams jerky = params;
  jerky.max_jerk_m_s3 = 200.0;
  const StraightLine quick(from, from + Vector3d(0.05, 0, 0), jerky, 0.0, 0.0);
  EXPECT_NEAR(quick.durationS(), std::sqrt(7.513188404399289 * 0.05 / jerky.max_accel_m_s2), 1e-9);
  // No distance, no time.
  EXPECT_EQ(StraightLine(to, to, params, 0.0, 0.0).durationS(), 0.0);
  const PositionSetpoint held = Trajectory::hold(to, 1.0).sample(5.0);
  EXPECT_EQ(held.p_world_m, to);
  EXPECT_EQ(held.v_world_m_s, Vector3d::Zero());
  EXPECT_EQ(held.yaw_rad, 1.0);
}

TEST(Trajectory, StraightLineTurnsTheShorterWayWithinTheYawRate) {
  const TrajectoryParams params;
  const Vector3d at(1.0, -2.0, -1.0);
  // A turn in place from 170° to -100°: the shorter way is +90° across ±180°, and it alone sets
  // the time.
  const double from_yaw = 170.0 * M_PI / 180.0, to_yaw = -100.0 * M_PI / 180.0;
  const StraightLine turn(at, at, params, from_yaw, to_yaw);
  EXPECT_NEAR(turn.durationS(), 35.0 / 16.0 * (M_PI / 2.0) / params.max_yaw_rate_rad_s, 1e-9);
  EXPECT_EQ(turn.sample(-1.0).yaw_rad, from_yaw);
  EXPECT_NEAR(turn.sample(0.5 * turn.durationS()).yaw_rad, from_yaw + M_PI / 4.0, 1e-9);
  EXPECT_NEAR(std::remainder(turn.sample(turn.durationS()).yaw_rad - to_yaw, 2.0 * M_PI), 0.0,
              1e-12);
  double peak_rate = 0.0, last = turn.sample(0.0).yaw_rad;
  const double dt_s = 1e-4;
  constexpr double kRoundingRad = 1e-12;  // σ's rounding where it flattens at the ends
  for (double t_s = dt_s; t_s <= turn.durationS(); t_s += dt_s) {
    const PositionSetpoint sp = turn.sample(t_s);
    EXPECT_GE(sp.yaw_rad, last - kRoundingRad);  // one way round, never back
    peak_rate = std::max(peak_rate, (sp.yaw_rad - last) / dt_s);
    last = sp.yaw_rad;
    EXPECT_EQ(sp.p_world_m, at);
    EXPECT_EQ(sp.v_world_m_s, Vector3d::Zero());
  }
  EXPECT_NEAR(peak_rate, params.max_yaw_rate_rad_s, 1e-3);
  // Along a long line the distance sets the time, and the heading turns along the same profile.
  const Vector3d to = at + Vector3d(6.0, 0.0, 0.0);
  const StraightLine leg(at, to, params, 0.0, 0.3);
  EXPECT_NEAR(leg.durationS(), 35.0 / 16.0 * 6.0 / params.max_speed_m_s, 1e-9);
  for (const double t_s : {0.5, 3.0, 9.0}) {
    const PositionSetpoint sp = leg.sample(t_s);
    EXPECT_NEAR(sp.yaw_rad / 0.3, (sp.p_world_m - at).norm() / 6.0, 1e-9) << t_s;
  }
}

TEST(Trajectory, DescentReachesItsSpeedAndGoesOn) {
  const TrajectoryParams params;
  const Vector3d from(0.5, 0.2, -3.0);
  const double speed_m_s = 0.5;
  const Descent descent(from, speed_m_s, params, 0.0);
  const double ramp_s = speed_m_s / params.max_accel_m_s2;
  EXPECT_EQ(descent.sample(0.0).p_world_m, from);
  EXPECT_NEAR(descent.sample(0.5 * ramp_s).a_world_m_s2.z(), params.max_accel_m_s2, kTight);
  for (const double t_s : {ramp_s, 10.0, 100.0}) {  // it does not stop: the ground ends it
    const PositionSetpoint sp = descent.sample(t_s);
    EXPECT_NEAR(sp.v_world_m_s.z(), speed_m_s, kTight);
    EXPECT_NEAR(sp.p_world_m.z(), from.z() + speed_m_s * (t_s - 0.5 * ramp_s), 1e-9);
    EXPECT_EQ(sp.p_world_m.head<2>(), from.head<2>());
    EXPECT_EQ(sp.v_world_m_s.head<2>(), Eigen::Vector2d::Zero());
  }
}

// ---- Closed loop -------------------------------------------------------------------------------

void print(const char* name, const test::PositionFigures& f) {
  std::printf("[position] %s: RMS %.2f mm, max %.2f mm, last-second mean |e| %.2f mm "
              "(estimate RMS %.2f mm)\n",
              name, f.rms_m * 1e3, f.max_m * 1e3, f.tail_mean_m.norm() * 1e3,
              f.estimate_rms_m * 1e3);
}

// A figure counts only when flown in mission mode throughout, with no failsafe on the way.
void expectNoFailsafe(const test::PositionFigures& f) {
  EXPECT_FALSE(f.lost_control);
  // Flying the mission at the end, or holding its last point after it.
  EXPECT_TRUE(f.final_mode == FlightMode::kMission || f.final_mode == FlightMode::kHold)
      << toString(f.final_mode);
  EXPECT_EQ(f.modes.vision_lost, 0);
  EXPECT_EQ(f.modes.estimator_diverged, 0);
  EXPECT_EQ(f.modes.attitude_limit, 0);
  EXPECT_EQ(f.modes.imu_lost, 0);
  EXPECT_EQ(f.modes.geofence, 0);
}

TEST(FlightPosition, HoversWithinTheIssueFigure) {
  const Vehicle vehicle{VehicleParams{}};
  const test::PositionFigures figures = test::flyPosition(vehicle, test::hoverFlight(kSeed));
  print("hover", figures);
  expectNoFailsafe(figures);
  EXPECT_LE(figures.rms_m, test::kHoverRmsTargetM);
}

TEST(FlightPosition, FliesTheFigureEightWithinTheIssueFigure) {
  const Vehicle vehicle{VehicleParams{}};
  auto flight = test::figureEightFlight(kSeed);
  ASSERT_TRUE(flight.ok()) << flight.status().message();
  const test::PositionFigures figures = test::flyPosition(vehicle, *flight);
  print("figure eight", figures);
  expectNoFailsafe(figures);
  EXPECT_LE(figures.rms_m, test::kFigureEightRmsTargetM);
}

TEST(FlightPosition, SteadyWindLeavesNoSteadyError) {
  const Vehicle vehicle{VehicleParams{}};
  test::PositionFlight flight = test::windFlight(kSeed);
  const test::PositionFigures figures = test::flyPosition(vehicle, flight);
  print("2 m/s wind", figures);
  expectNoFailsafe(figures);
  EXPECT_LT(figures.tail_mean_m.norm(), test::kWindSteadyErrorTargetM);
  // Without the integral and the force fed forward the same wind leaves F / (m K_p) = 3.75 cm;
  // either removes it.
  const test::PositionFlight with_both = flight;
  flight.position.i_gain_1_s3.setZero();
  const test::PositionFigures fed_forward = test::flyPosition(vehicle, flight);
  print("2 m/s wind, no integral", fed_forward);
  expectNoFailsafe(fed_forward);
  EXPECT_LT(fed_forward.tail_mean_m.norm(), test::kWindSteadyErrorTargetM);
  flight.position.disturbance_gain = 0.0;
  const test::PositionFigures proportional = test::flyPosition(vehicle, flight);
  print("2 m/s wind, no integral, nothing fed forward", proportional);
  expectNoFailsafe(proportional);
  EXPECT_GT(proportional.tail_mean_m.norm(), 3.0 * test::kWindSteadyErrorTargetM);
  flight = with_both;
  flight.position.disturbance_gain = 0.0;
  const test::PositionFigures integral = test::flyPosition(vehicle, flight);
  print("2 m/s wind, nothing fed forward", integral);
  expectNoFailsafe(integral);
  EXPECT_LT(integral.tail_mean_m.norm(), test::kWindSteadyErrorTargetM);
}

TEST(FlightStackParams, DefaultsBuildAndARangeIsNamed) {
  FlightStackParams params;
  EXPECT_TRUE(FlightStack::create(params).ok());
  params.rate_hz = 50.0;
  EXPECT_EQ(FlightStack::create(params).status().message(),
            "flight.rate_hz must be in [100, 4000] (got 50)");
  params.rate_hz = 200.0;
  params.position.rate_hz = 250.0;
  EXPECT_EQ(FlightStack::create(params).status().message(),
            "position.rate_hz (250.000000) must not exceed flight.rate_hz (200.000000)");
  params = FlightStackParams();
  params.trajectory.max_accel_m_s2 = 0.0;
  EXPECT_EQ(FlightStack::create(params).status().message(),
            "trajectory.max_accel_m_s2 must be in (0, 20] (got 0)");
}

TEST(FlightStack, AMissionIsNotReplacedWhileFlown) {
  const Vehicle vehicle{VehicleParams{}};
  test::PositionFlight flight = test::hoverFlight(kSeed);
  auto figure_eight = test::figureEightFlight(kSeed);
  ASSERT_TRUE(figure_eight.ok());
  flight.trajectory = figure_eight->trajectory;
  flight.duration_s = 2.0;  // well inside the mission
  test::SensorLog log;
  const test::PositionFigures figures = test::flyPosition(vehicle, flight, &log);
  ASSERT_EQ(figures.final_mode, FlightMode::kMission);
  auto made = test::makeStack(vehicle, flight, log.init);
  ASSERT_TRUE(made.ok());
  test::replayStack(**made, log);
  ASSERT_EQ((*made)->modes().mode(), FlightMode::kMission);
  EXPECT_EQ((*made)->loadMission(Trajectory::hold(test::kHoverWorldM, 0.0)).message(),
            "flight: a mission is being flown; hold or land before loading another");
}

// From the floor and back, by the modes alone, as the ground commands it: arm, take off to 1 m,
// hold, land; the descent goes on until the landed detector sees the thrust fall against the
// floor, and disarms.
TEST(FlightStack, TakesOffFromTheFloorLandsAndDisarms) {
  const Vehicle vehicle{VehicleParams{}};
  test::FlightPlant plant(vehicle, test::kGyroNoiseDensity, kSeed, test::kAccelNoiseDensity);
  plant.startOnGround(Vector3d(0.3, -0.2, 0.0));
  const EstimatorInit init = test::initAt(plant.state());
  FlightStackParams params;
  params.vehicle = vehicle.params();
  auto made = FlightStack::create(params);
  ASSERT_TRUE(made.ok()) << made.status().message();
  FlightStack& stack = **made;
  stack.initialise(init);
  test::SensorFeed sensors(init, kSeed);

  constexpr double kHoldS = 2.0;
  constexpr double kMaxFlightS = 15.0;  // take-off ~2 s, hold, 1 m at 0.5 m/s, landed 1 s
  int64_t utime = test::kFlightStartUs, hold_since_utime = -1, land_utime = -1;
  double highest_m = 0.0;
  bool left_ground = false;
  while (utime < test::kFlightStartUs + static_cast<int64_t>(kMaxFlightS * 1e6)) {
    TickInputs in;
    in.utime = utime;
    const FlightMode mode = stack.modes().mode();
    if (mode == FlightMode::kDisarmed && land_utime < 0) {
      in.command = FlightCommand{CommandKind::kArm};
    } else if (mode == FlightMode::kArmed) {
      in.command = FlightCommand{CommandKind::kTakeOff, test::kTakeOffHeightM};
    } else if (mode == FlightMode::kHold) {
      if (hold_since_utime < 0) hold_since_utime = utime;
      if (utime - hold_since_utime >= static_cast<int64_t>(kHoldS * 1e6)) {
        in.command = FlightCommand{CommandKind::kLand};
      }
    }
    const TickOutput out = stack.tick(in);
    if (out.modes.command && out.modes.command->accepted() &&
        out.modes.command->kind == CommandKind::kLand) {
      land_utime = utime;
    }
    if (land_utime >= 0 && out.modes.mode == FlightMode::kDisarmed) break;
    ASSERT_NE(out.rotors, RotorCommand::kNone);
    plant.step(out.mixer.rotor_speed_rad_s, test::kControlDtS);
    left_ground = left_ground || !plant.onGround();
    highest_m = std::max(highest_m, -plant.state().p_world_m.z());
    utime += test::kControlUs;
    sensors.feed(plant, utime, stack, nullptr);
  }
  const FlightCounters& counters = stack.modes().counters();
  std::printf("[flight] floor to 1 m and back: highest %.3f m, landed %.2f s after the land "
              "command, %.3f m from the take-off point\n",
              highest_m, 1e-6 * static_cast<double>(utime - land_utime),
              (plant.state().p_world_m - Vector3d(0.3, -0.2, 0.0)).norm());
  EXPECT_TRUE(left_ground);
  ASSERT_GE(land_utime, 0) << "never held long enough to land";
  EXPECT_EQ(stack.modes().mode(), FlightMode::kDisarmed);
  EXPECT_EQ(counters.landed_disarms, 1);
  EXPECT_EQ(counters.vision_lost + counters.estimator_diverged + counters.attitude_limit +
                counters.imu_lost + counters.geofence,
            0);
  EXPECT_TRUE(plant.onGround());
  EXPECT_NEAR(highest_m, test::kTakeOffHeightM, 0.1);
  // Down at the land speed, then the landed detector's time; a second's slack.
  const double landing_s = 1e-6 * static_cast<double>(utime - land_utime);
  EXPECT_LT(landing_s, test::kTakeOffHeightM / params.modes.land_speed_m_s +
                           params.modes.landed_time_s + 1.0);
  // It came down where it went up: hold and land keep x and y.
  EXPECT_LT((plant.state().p_world_m.head<2>() - Eigen::Vector2d(0.3, -0.2)).norm(), 0.1);
}

// Flies the stack from the floor: each tick, `command` may give the ground's command for the
// mode the stack is in and see the output; stops when it returns false or after max_s.
template <class Script>
void flyFromTheFloor(FlightStack& stack, test::FlightPlant& plant, test::SensorFeed& sensors,
                     double max_s, Script&& script) {
  int64_t utime = test::kFlightStartUs;
  while (utime < test::kFlightStartUs + static_cast<int64_t>(max_s * 1e6)) {
    TickInputs in;
    in.utime = utime;
    in.command = script.command(utime, stack.modes().mode());
    const TickOutput out = stack.tick(in);
    if (!script.seen(utime, out)) return;
    plant.step(out.mixer.rotor_speed_rad_s, test::kControlDtS);
    utime += test::kControlUs;
    sensors.feed(plant, utime, stack, nullptr);
  }
}

// How long the flights below hold after the take-off before the go-to, and before the camera is
// covered: the thrust scale's time constant (2 s), so that the hover has taught it.
constexpr int64_t kHoldBeforeUs = 1'000'000;
constexpr int64_t kHoldBeforeCoverUs = 2'000'000;

// From the floor to the take-off's hold, as the ground commands it.
std::optional<FlightCommand> armAndTakeOff(FlightMode mode) {
  if (mode == FlightMode::kDisarmed) return FlightCommand{CommandKind::kArm};
  if (mode == FlightMode::kArmed) {
    return FlightCommand{CommandKind::kTakeOff, test::kTakeOffHeightM};
  }
  return std::nullopt;
}

struct FloorFlight {
  Vehicle vehicle;  // before the plant, which keeps a reference
  test::FlightPlant plant;
  EstimatorInit init;
  std::unique_ptr<FlightStack> stack;
  test::SensorFeed sensors;

  // The plant may be another vehicle than the one the stack believes in.
  explicit FloorFlight(const FlightStackParams& params)
      : FloorFlight(params, params.vehicle) {}
  FloorFlight(const FlightStackParams& params, const VehicleParams& real)
      : vehicle(real),
        plant(vehicle, test::kGyroNoiseDensity, kSeed, test::kAccelNoiseDensity),
        init(start(plant)),
        stack(std::move(*FlightStack::create(params))),
        sensors(init, kSeed) {
    stack->initialise(init);
  }
  static EstimatorInit start(test::FlightPlant& plant) {
    plant.startOnGround(Vector3d::Zero());
    return test::initAt(plant.state());
  }
};

// A go-to ends in hold when the estimate is within target_reached_m of the target, still moving:
// the hold goes on along the go-to's line, which ends at rest at the target. A new line from
// there would start from rest: a step in the velocity setpoint, which in the simulator kicked
// the drone into swings of 15° per frame that the odometry could not follow.
TEST(FlightStack, AReachedGoToHoldsAlongItsLineWithoutAStep) {
  FloorFlight flight{FlightStackParams{}};
  const Vector3d target_world_m(1.0, -0.6, -test::kTakeOffHeightM);
  struct Script {
    bool went = false, flew = false, reached = false;
    int64_t hold_since_utime = -1;
    Vector3d last_v_sp = Vector3d::Zero();
    double step_at_reach_m_s = -1.0;
    Vector3d target;
    std::optional<FlightCommand> command(int64_t utime, FlightMode mode) {
      if (mode == FlightMode::kHold && !went) {
        if (hold_since_utime < 0) hold_since_utime = utime;
        if (utime - hold_since_utime >= kHoldBeforeUs) {
          went = true;
          FlightCommand go{CommandKind::kGoTo};
          go.target_world_m = target;
          return go;
        }
      }
      return armAndTakeOff(mode);
    }
    bool seen(int64_t, const TickOutput& out) {
      const Vector3d v_sp = out.setpoint.v_world_m_s;
      flew = flew || out.modes.mode == FlightMode::kGoTo;
      if (went && !reached && out.modes.mode == FlightMode::kHold) {
        reached = true;
        step_at_reach_m_s = (v_sp - last_v_sp).norm();
      }
      last_v_sp = v_sp;
      return !reached;
    }
  } script;
  script.target = target_world_m;
  constexpr double kMaxFlightS = 20.0;  // take-off 2 s, the hold, 1.2 m at 1 m/s: 5 s
  flyFromTheFloor(*flight.stack, flight.plant, flight.sensors, kMaxFlightS, script);
  ASSERT_TRUE(script.flew) << "the go-to was never flown";
  ASSERT_TRUE(script.reached) << "the go-to never reached its target";
  std::printf("[flight] go-to reached: velocity setpoint step %.4f m/s at the switch to hold\n",
              script.step_at_reach_m_s);
  // One tick's change along a line flown at max_accel_m_s2: what a continuous setpoint moves by.
  const double one_tick_m_s = FlightStackParams{}.trajectory.max_accel_m_s2 * test::kControlDtS;
  EXPECT_LE(script.step_at_reach_m_s, one_tick_m_s);
}

// A go-to to the hold point with a heading is a turn in place: the body turns the shorter way
// at about max_yaw_rate_rad_s and stays where it was.
TEST(FlightStack, AGoToWithAHeadingTurnsInPlaceAtTheYawRate) {
  FloorFlight flight{FlightStackParams{}};
  constexpr double kHeadingRad = -M_PI / 2.0;  // from facing world x to facing -y
  struct Script {
    const test::FlightPlant* plant;
    bool went = false;
    int64_t hold_since_utime = -1, went_utime = -1;
    Vector3d hold_world_m = Vector3d::Zero();
    double last_yaw = 0.0, peak_rate = 0.0, drift_m = 0.0, yaw_at_end = NAN;
    static double yawOf(const Eigen::Quaterniond& q) {
      const Eigen::Matrix3d R = q.toRotationMatrix();
      return std::atan2(R(1, 0), R(0, 0));
    }
    std::optional<FlightCommand> command(int64_t utime, FlightMode mode) {
      if (mode == FlightMode::kHold && !went) {
        if (hold_since_utime < 0) hold_since_utime = utime;
        if (utime - hold_since_utime >= kHoldBeforeUs) {
          went = true;
          went_utime = utime;
          hold_world_m = plant->state().p_world_m;
          last_yaw = yawOf(plant->state().q_world_body);
          return FlightCommand{CommandKind::kGoTo, 0.0, hold_world_m, kHeadingRad};
        }
      }
      return armAndTakeOff(mode);
    }
    bool seen(int64_t utime, const TickOutput&) {
      if (!went) return true;
      const double yaw = yawOf(plant->state().q_world_body);
      peak_rate = std::max(peak_rate, std::abs(std::remainder(yaw - last_yaw, 2.0 * M_PI)) /
                                          test::kControlDtS);
      last_yaw = yaw;
      drift_m = std::max(drift_m, (plant->state().p_world_m - hold_world_m).norm());
      yaw_at_end = yaw;
      return utime - went_utime < 6'000'000;  // the turn's 4.4 s and some
    }
  } script;
  script.plant = &flight.plant;
  flyFromTheFloor(*flight.stack, flight.plant, flight.sensors, 20.0, script);
  ASSERT_TRUE(script.went) << "the turn was never commanded";
  std::printf("[flight] turn in place: peak yaw rate %.3f rad/s, drift %.3f m, heading error "
              "%.4f rad\n",
              script.peak_rate, script.drift_m, script.yaw_at_end - kHeadingRad);
  constexpr double kHeadingTolRad = 0.02, kTurnDriftTolM = 0.05, kRateOvershoot = 1.3;
  EXPECT_NEAR(std::remainder(script.yaw_at_end - kHeadingRad, 2.0 * M_PI), 0.0, kHeadingTolRad);
  EXPECT_LT(script.drift_m, kTurnDriftTolM);
  EXPECT_LT(script.peak_rate, kRateOvershoot * FlightStackParams{}.trajectory.max_yaw_rate_rad_s);
}

// Vision lost in the air: the descent on the IMU alone cannot see its speed (the velocity drifts
// without poses), so the floor is found by the lift the accelerometer feels beyond the thrust;
// the thrust then ramps down and the landed detector disarms. Also with rotors 20 % stronger or
// 15 % weaker than the parameters say: the lift the thrust gives is learnt in the hold, or the
// stronger drone would seem carried by a floor in the air, its thrust cut and its attitude loop
// held, and sink.
class FlightStackThrustError : public ::testing::TestWithParam<double> {};

TEST_P(FlightStackThrustError, ADescentWithoutVisionFindsTheFloorAndDisarms) {
  FlightStackParams params;
  VehicleParams real = params.vehicle;
  real.thrust_coeff_n_s2_rad2 *= GetParam();
  FloorFlight flight{params, real};
  struct Script {
    test::SensorFeed* sensors;
    test::FlightPlant* plant;
    double fastest_down_m_s = 0.0;  // after the cover, in the air
    int64_t hold_since_utime = -1, covered_utime = -1, disarmed_utime = -1;
    std::optional<FlightCommand> command(int64_t utime, FlightMode mode) {
      if (mode == FlightMode::kHold && covered_utime < 0) {
        if (hold_since_utime < 0) hold_since_utime = utime;
        if (utime - hold_since_utime >= kHoldBeforeCoverUs) {
          sensors->coverCamera();
          covered_utime = utime;
        }
      }
      // Landed after the cover, the flight is over: seen() stops it before a new arming.
      return armAndTakeOff(mode);
    }
    bool seen(int64_t utime, const TickOutput& out) {
      if (covered_utime >= 0 && !plant->onGround()) {
        fastest_down_m_s = std::max(fastest_down_m_s, plant->state().v_world_m_s.z());
      }
      if (covered_utime >= 0 && out.modes.mode == FlightMode::kDisarmed) {
        disarmed_utime = utime;
        return false;
      }
      return true;
    }
  } script{&flight.sensors, &flight.plant};
  // After the cover: vision_lost_s to call vision lost, 1 m down at the descent's speed, the
  // contact held, the ramp from the weight down to the landed ratio and the landed time, with a
  // slack for the loop to settle on the descent's speed and on the floor.
  const FlightModeParams& m = params.modes;
  const double ramp_s = (1.0 - m.landed_thrust_ratio) / m.ground_thrust_ramp_per_s;
  constexpr double kSlackS = 5.0;
  const double bound_s = m.vision_lost_s + test::kTakeOffHeightM / m.vision_lost_descent_m_s +
                         m.ground_contact_s + ramp_s + m.landed_time_s + kSlackS;
  constexpr double kUpToTheCoverS = 6.0;  // take-off about 2 s, the hold
  flyFromTheFloor(*flight.stack, flight.plant, flight.sensors, kUpToTheCoverS + bound_s, script);
  const FlightCounters& counters = flight.stack->modes().counters();
  ASSERT_GE(script.covered_utime, 0) << "never held long enough to cover the camera";
  ASSERT_GE(script.disarmed_utime, 0) << "still " << toString(flight.stack->modes().mode())
                                      << " " << bound_s << " s after the camera was covered";
  const double landing_s = 1e-6 * static_cast<double>(script.disarmed_utime - script.covered_utime);
  std::printf("[flight] camera covered at 1 m, thrust x%.2f of the believed: disarmed on the "
              "floor %.2f s later, down at %.2f m/s at most\n",
              GetParam(), landing_s, script.fastest_down_m_s);
  EXPECT_EQ(counters.vision_lost, 1);
  EXPECT_EQ(counters.landed_disarms, 1);
  EXPECT_TRUE(flight.plant.onGround());
  EXPECT_LT(landing_s, bound_s);
  // The descent's own speed, and what the loop's overshoot on the IMU alone adds.
  constexpr double kDescentOvershootMS = 0.2;
  EXPECT_LE(script.fastest_down_m_s, m.vision_lost_descent_m_s + kDescentOvershootMS);
}

INSTANTIATE_TEST_SUITE_P(Thrust, FlightStackThrustError, ::testing::Values(1.0, 1.2, 0.85));

// Into a corridor: the poses go on, fused, but say nothing along it, and the estimate's position
// there comes from the IMU alone. Once its 1σ passes vision_max_pos_std_m the poses stop
// counting as vision, and after vision_lost_s the vision-lost failsafe descends to the floor:
// holding a position nothing measures would drift (in the simulated corridor, into its end wall).
TEST(FlightStack, PosesThatLeaveThePositionUnknownAreVisionLost) {
  FlightStackParams params;
  FloorFlight flight{params};
  struct Script {
    test::SensorFeed* sensors;
    FlightStack* stack;
    int64_t hold_since_utime = -1, weak_utime = -1, descend_utime = -1, disarmed_utime = -1;
    double std_at_descend_m = 0.0;
    std::optional<FlightCommand> command(int64_t utime, FlightMode mode) {
      if (mode == FlightMode::kHold && weak_utime < 0) {
        if (hold_since_utime < 0) hold_since_utime = utime;
        if (utime - hold_since_utime >= kHoldBeforeCoverUs) {
          sensors->weakenAlong(Vector3d::UnitZ());  // odom's z: the camera's first view, ahead
          weak_utime = utime;
        }
      }
      return armAndTakeOff(mode);
    }
    bool seen(int64_t utime, const TickOutput& out) {
      if (weak_utime >= 0 && descend_utime < 0 && out.modes.mode == FlightMode::kDescend) {
        descend_utime = utime;
        const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> position(
            stack->estimator().covariance().topLeftCorner<3, 3>(), Eigen::EigenvaluesOnly);
        std_at_descend_m = std::sqrt(position.eigenvalues()(2));
      }
      if (weak_utime >= 0 && out.modes.mode == FlightMode::kDisarmed) {
        disarmed_utime = utime;
        return false;
      }
      return true;
    }
  } script{&flight.sensors, flight.stack.get()};
  constexpr double kMaxFlightS = 40.0;
  flyFromTheFloor(*flight.stack, flight.plant, flight.sensors, kMaxFlightS, script);
  ASSERT_GE(script.weak_utime, 0) << "never held long enough to enter the corridor";
  ASSERT_GE(script.descend_utime, 0) << "never descended";
  ASSERT_GE(script.disarmed_utime, 0) << "never disarmed";
  const double to_descend_s = 1e-6 * static_cast<double>(script.descend_utime - script.weak_utime);
  std::printf("[flight] poses weak along the view from the hold on: vision lost %.2f s later "
              "(position 1σ %.2f m), disarmed on the floor %.2f s after that\n",
              to_descend_s, script.std_at_descend_m,
              1e-6 * static_cast<double>(script.disarmed_utime - script.descend_utime));
  const FlightCounters& counters = flight.stack->modes().counters();
  EXPECT_EQ(counters.vision_lost, 1);
  EXPECT_EQ(counters.landed_disarms, 1);
  EXPECT_TRUE(flight.plant.onGround());
  // Not at once: vision held the position until the IMU's uncertainty along the corridor grew.
  EXPECT_GT(to_descend_s, params.modes.vision_lost_s);
  EXPECT_GT(script.std_at_descend_m, params.modes.vision_max_pos_std_m);
}

// The whole stack's tick as the control task runs it (FlightStack: estimator predict and late
// poses fused, flight modes, the position loop on the mission's trajectory, attitude, rate,
// mixer) allocates nothing once flying: the figure eight's sensors replayed into a fresh stack,
// counted after its first second (the take-off commands, the first poses fused).
TEST(FlightPosition, StackTickAllocatesNothingInSteadyState) {
  const Vehicle vehicle{VehicleParams{}};
  auto flight = test::figureEightFlight(kSeed);
  ASSERT_TRUE(flight.ok());
  test::SensorLog log;
  test::flyPosition(vehicle, *flight, &log);
  const int warm_up_ticks = static_cast<int>(1.0 / test::kControlDtS);
  ASSERT_GT(log.count(), 2 * warm_up_ticks);
  auto made = test::makeStack(vehicle, *flight, log.init);
  ASSERT_TRUE(made.ok()) << made.status().message();
  FlightStack& stack = **made;
  double sink = test::replayStack(stack, log, 0, warm_up_ticks);
  const int64_t before = g_allocations;
  sink += test::replayStack(stack, log, warm_up_ticks);
  const int64_t allocations = g_allocations - before;
  EXPECT_EQ(allocations, 0);
  EXPECT_GT(sink, 0.0);
  // Through the mission's end to the hold at its last point.
  EXPECT_EQ(stack.modes().mode(), FlightMode::kHold);
  EXPECT_GT(stack.estimator().health().vision_fused_count, 0);
}

}  // namespace
}  // namespace kinfly::flight
