// The flight mode manager on scripted inputs: the arming checks, each command accepted or
// refused with its reason, the modes' own ends (take-off and go-to reached, mission finished,
// landed), each failsafe on its own, the counters, and an update that allocates nothing. The
// "estimator" here is its health and state written by hand, tick by tick at 1 kHz.
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <vector>

#include "count_allocations.h"  // g_allocations: for the steady-state test
#include "kinfly/flight/flight_modes.h"

namespace kinfly::flight {
namespace {

using Eigen::Vector3d;

constexpr int64_t kTickUs = 1000;  // the control task's 1 kHz
constexpr double kTickS = 1e-3;
constexpr int64_t kStartUs = 1000000;  // every utime positive, and older times representable
constexpr double kPi = 3.14159265358979323846;
// A take-off height well above the minimum and inside the default fence.
constexpr double kTakeOffHeightM = 2.0;
// Positions are set exactly in these tests: a target is reached within rounding.
constexpr double kExactM = 1e-12;

int ticks(double seconds) { return static_cast<int>(std::lround(seconds / kTickS)); }

// The control task's side: the inputs it gathers every tick, and what came back.
class Flight {
 public:
  explicit Flight(const FlightModeParams& params = FlightModeParams()) : modes_(params) {
    in_.utime = kStartUs;
    in_.estimator.initialised = true;
  }

  // One tick: time moves on and every source that is `fresh` reports now.
  FlightOutput tick(const std::optional<FlightCommand>& command = std::nullopt) {
    in_.utime += kTickUs;
    if (imu_fresh) in_.last_imu_utime = in_.utime;
    if (vision_fresh) in_.last_vision_utime = in_.utime;
    if (ground_fresh) in_.last_ground_utime = in_.utime;
    last_ = modes_.update(in_, command);
    for (int i = 0; i < last_.event_count; ++i) events.push_back(last_.events[i]);
    return last_;
  }
  FlightOutput run(double seconds) {
    for (int i = 0; i < ticks(seconds); ++i) tick();
    return last_;
  }
  CommandResult command(const FlightCommand& command) { return *tick(command).command; }
  CommandResult command(CommandKind kind) { return command(FlightCommand{kind}); }

  // Armed, flown up to the take-off height and holding there.
  void takeOffAndHold() {
    ASSERT_TRUE(command(CommandKind::kArm).accepted());
    ASSERT_TRUE(command(FlightCommand{CommandKind::kTakeOff, kTakeOffHeightM}).accepted());
    in_.state.p_world_body_m = last_.setpoint.point_world_m;
    in_.height_above_ground_m = kTakeOffHeightM;
    in_.thrust_ratio = 1.0;
    ASSERT_EQ(tick().mode, FlightMode::kHold);
  }

  FlightInputs& in() { return in_; }
  EstimatorState& state() { return in_.state; }
  const FlightModes& modes() const { return modes_; }
  int count(EventReason reason) const {
    int n = 0;
    for (const FlightEvent& event : events) n += event.reason == reason ? 1 : 0;
    return n;
  }

  bool imu_fresh = true;
  bool vision_fresh = true;
  bool ground_fresh = true;
  std::vector<FlightEvent> events;

 private:
  FlightModes modes_;
  FlightInputs in_;
  FlightOutput last_;
};

// ---- Parameters --------------------------------------------------------------------------------

TEST(FlightModeParams, DefaultsAreValidAndARangeIsNamed) {
  EXPECT_TRUE(FlightModeParams().validate().ok());
  FlightModeParams params;
  params.vision_fresh_s = 2.0;  // beyond vision_lost_s: arming could start a failsafe at once
  EXPECT_EQ(params.validate().message(), "modes.vision_fresh_s must be in (0, 1] (got 2)");
  params = FlightModeParams();
  params.imu_timeout_s = 2.0 * params.imu_lost_s;  // arming on a gap the failsafe acts on
  EXPECT_EQ(params.validate().message(), "modes.imu_timeout_s must be in (0, 0.02] (got 0.04)");
  params = FlightModeParams();
  params.geofence_min_world_m.z() = params.geofence_max_world_m.z();
  EXPECT_EQ(params.validate().message(),
            "modes.geofence_min_world_m.z must be below modes.geofence_max_world_m.z");
}

// ---- Arming --------------------------------------------------------------------------------------

TEST(FlightModes, ArmingChecksRefuseWithTheFirstReason) {
  Flight flight;
  flight.in().estimator.initialised = false;
  EXPECT_EQ(flight.command(CommandKind::kArm).refusal, CommandRefusal::kEstimatorUnhealthy);
  flight.in().estimator.initialised = true;
  flight.in().estimator.diverged = true;
  EXPECT_EQ(flight.command(CommandKind::kArm).refusal, CommandRefusal::kEstimatorUnhealthy);
  flight.in().estimator.diverged = false;

  flight.imu_fresh = false;
  flight.run(0.05);  // beyond imu_timeout_s (0.005 s)
  EXPECT_EQ(flight.command(CommandKind::kArm).refusal, CommandRefusal::kImuNotAlive);
  flight.imu_fresh = true;

  flight.vision_fresh = false;
  flight.run(0.3);  // beyond vision_fresh_s (0.2 s)
  EXPECT_EQ(flight.command(CommandKind::kArm).refusal, CommandRefusal::kVisionNotFused);
  flight.vision_fresh = true;

  flight.state().v_world_body_m_s = Vector3d(0.5, 0.0, 0.0);  // carried, or still rolling
  EXPECT_EQ(flight.command(CommandKind::kArm).refusal, CommandRefusal::kNotAtRest);
  flight.state().v_world_body_m_s.setZero();
  flight.state().q_world_body = Eigen::AngleAxisd(kPi / 2.0, Vector3d::UnitX());  // on its side
  EXPECT_EQ(flight.command(CommandKind::kArm).refusal, CommandRefusal::kNotAtRest);
  flight.state().q_world_body.setIdentity();

  flight.state().p_world_body_m = Vector3d(60.0, 0.0, 0.0);  // the default fence is ±50 m
  EXPECT_EQ(flight.command(CommandKind::kArm).refusal, CommandRefusal::kOutsideGeofence);
  flight.state().p_world_body_m.setZero();

  EXPECT_EQ(flight.modes().mode(), FlightMode::kDisarmed);
  EXPECT_TRUE(flight.events.empty());
  const CommandResult armed = flight.command(CommandKind::kArm);
  EXPECT_TRUE(armed.accepted());
  EXPECT_EQ(flight.modes().mode(), FlightMode::kArmed);
  ASSERT_EQ(flight.events.size(), 1u);
  EXPECT_EQ(flight.events[0].reason, EventReason::kCommand);
  EXPECT_EQ(flight.events[0].from, FlightMode::kDisarmed);
  EXPECT_EQ(flight.events[0].to, FlightMode::kArmed);
  EXPECT_EQ(flight.modes().counters().commands_refused, 7);
  EXPECT_EQ(flight.modes().counters().commands_accepted, 1);
  EXPECT_EQ(flight.modes().counters().mode_changes, 1);
  EXPECT_EQ(flight.command(CommandKind::kArm).refusal, CommandRefusal::kAlreadyArmed);
}

// ---- Commands ----------------------------------------------------------------------------------

TEST(FlightModes, CommandsNeedTheRightMode) {
  Flight flight;
  // Disarmed: nothing flies.
  EXPECT_EQ(flight.command(FlightCommand{CommandKind::kTakeOff, kTakeOffHeightM}).refusal,
            CommandRefusal::kDisarmed);
  for (const CommandKind kind : {CommandKind::kHold, CommandKind::kGoTo, CommandKind::kMission,
                                 CommandKind::kLand}) {
    EXPECT_EQ(flight.command(kind).refusal, CommandRefusal::kDisarmed) << toString(kind);
  }
  EXPECT_TRUE(flight.command(CommandKind::kDisarm).accepted());  // already: nothing to do

  // On the ground: only a take-off (or a disarm) makes sense.
  ASSERT_TRUE(flight.command(CommandKind::kArm).accepted());
  for (const CommandKind kind : {CommandKind::kHold, CommandKind::kGoTo, CommandKind::kMission,
                                 CommandKind::kLand}) {
    EXPECT_EQ(flight.command(kind).refusal, CommandRefusal::kOnGround) << toString(kind);
  }
  EXPECT_EQ(flight.command(FlightCommand{CommandKind::kTakeOff, 0.1}).refusal,
            CommandRefusal::kInvalidTarget);  // below takeoff_height_min_m
  EXPECT_EQ(flight.command(FlightCommand{CommandKind::kTakeOff, NAN}).refusal,
            CommandRefusal::kInvalidTarget);
  // The fence's top is 30 m up.
  EXPECT_EQ(flight.command(FlightCommand{CommandKind::kTakeOff, 40.0}).refusal,
            CommandRefusal::kOutsideGeofence);
  EXPECT_TRUE(flight.command(CommandKind::kDisarm).accepted());
  EXPECT_EQ(flight.modes().mode(), FlightMode::kDisarmed);

  // In the air: no second take-off, no disarm, targets inside the fence only.
  flight.takeOffAndHold();
  EXPECT_EQ(flight.command(FlightCommand{CommandKind::kTakeOff, kTakeOffHeightM}).refusal,
            CommandRefusal::kAirborne);
  EXPECT_EQ(flight.command(CommandKind::kDisarm).refusal, CommandRefusal::kAirborne);
  EXPECT_EQ(flight.command(FlightCommand{CommandKind::kGoTo, 0.0, Vector3d(0.0, 60.0, -2.0)})
                .refusal,
            CommandRefusal::kOutsideGeofence);
  EXPECT_EQ(flight.command(FlightCommand{CommandKind::kGoTo, 0.0, Vector3d(NAN, 0.0, -2.0)})
                .refusal,
            CommandRefusal::kInvalidTarget);
  EXPECT_EQ(flight.command(FlightCommand{CommandKind::kGoTo, 0.0, Vector3d(1.0, 0.0, -2.0),
                                         INFINITY})
                .refusal,
            CommandRefusal::kInvalidTarget);
  EXPECT_EQ(flight.modes().mode(), FlightMode::kHold);
}

TEST(FlightModes, AGoToTurnsToItsHeadingAndKeepsItInTheHold) {
  Flight flight;
  flight.state().q_world_body = Eigen::AngleAxisd(0.5, Vector3d::UnitZ());
  flight.takeOffAndHold();
  // Without a heading the body's is kept.
  const Vector3d first(2.0, 0.0, -kTakeOffHeightM);
  ASSERT_TRUE(flight.command(FlightCommand{CommandKind::kGoTo, 0.0, first}).accepted());
  EXPECT_NEAR(flight.tick().setpoint.yaw_rad, 0.5, kExactM);
  // With one, the setpoint has it from the start, and the hold it ends in keeps it.
  const Vector3d target(2.0, 3.0, -kTakeOffHeightM);
  ASSERT_TRUE(
      flight.command(FlightCommand{CommandKind::kGoTo, 0.0, target, M_PI / 2.0}).accepted());
  FlightOutput out = flight.tick();
  EXPECT_EQ(out.setpoint.kind, SetpointKind::kGoTo);
  EXPECT_NEAR(out.setpoint.yaw_rad, M_PI / 2.0, kExactM);
  flight.state().p_world_body_m = target;
  out = flight.tick();
  EXPECT_EQ(out.mode, FlightMode::kHold);
  EXPECT_NEAR(out.setpoint.yaw_rad, M_PI / 2.0, kExactM);
}

TEST(FlightModes, TakeOffClimbsStraightUpAndHoldsAtTheHeight) {
  Flight flight;
  // The body 0.1 m above the ground at (1, 2): the target is kTakeOffHeightM above the ground.
  flight.state().p_world_body_m = Vector3d(1.0, 2.0, -0.1);
  flight.in().height_above_ground_m = 0.1;
  flight.state().q_world_body = Eigen::AngleAxisd(0.5, Vector3d::UnitZ());
  ASSERT_TRUE(flight.command(CommandKind::kArm).accepted());
  EXPECT_EQ(flight.tick().setpoint.kind, SetpointKind::kIdle);
  ASSERT_TRUE(flight.command(FlightCommand{CommandKind::kTakeOff, kTakeOffHeightM}).accepted());
  FlightOutput out = flight.tick();
  EXPECT_EQ(out.mode, FlightMode::kTakeOff);
  EXPECT_EQ(out.setpoint.kind, SetpointKind::kTakeOff);
  EXPECT_NEAR((out.setpoint.point_world_m - Vector3d(1.0, 2.0, -kTakeOffHeightM)).norm(), 0.0,
              kExactM);
  EXPECT_NEAR(out.setpoint.yaw_rad, 0.5, kExactM);

  // Short of target_reached_m (0.1 m): still climbing.
  flight.state().p_world_body_m = Vector3d(1.0, 2.0, -kTakeOffHeightM + 0.2);
  EXPECT_EQ(flight.tick().mode, FlightMode::kTakeOff);
  flight.state().p_world_body_m = Vector3d(1.0, 2.0, -kTakeOffHeightM + 0.05);
  out = flight.tick();
  EXPECT_EQ(out.mode, FlightMode::kHold);
  EXPECT_EQ(out.setpoint.kind, SetpointKind::kHold);
  EXPECT_NEAR((out.setpoint.point_world_m - Vector3d(1.0, 2.0, -kTakeOffHeightM)).norm(), 0.0,
              kExactM);
  EXPECT_EQ(flight.events.back().reason, EventReason::kTakeOffReached);
}

TEST(FlightModes, GoToEndsInHoldAtTheTargetAndAMissionInHoldWhereItFinished) {
  Flight flight;
  flight.takeOffAndHold();
  const Vector3d target(5.0, -3.0, -4.0);
  ASSERT_TRUE(flight.command(FlightCommand{CommandKind::kGoTo, 0.0, target}).accepted());
  FlightOutput out = flight.tick();
  EXPECT_EQ(out.mode, FlightMode::kGoTo);
  EXPECT_EQ(out.setpoint.kind, SetpointKind::kGoTo);
  EXPECT_NEAR((out.setpoint.point_world_m - target).norm(), 0.0, kExactM);
  flight.state().p_world_body_m = target;
  out = flight.tick();
  EXPECT_EQ(out.mode, FlightMode::kHold);
  EXPECT_NEAR((out.setpoint.point_world_m - target).norm(), 0.0, kExactM);
  EXPECT_EQ(flight.events.back().reason, EventReason::kGoToReached);

  EXPECT_EQ(flight.command(CommandKind::kMission).refusal, CommandRefusal::kNoMission);
  flight.in().mission_loaded = true;
  ASSERT_TRUE(flight.command(CommandKind::kMission).accepted());
  EXPECT_EQ(flight.tick().setpoint.kind, SetpointKind::kMission);
  const Vector3d mission_end(2.0, 2.0, -3.0);
  flight.state().p_world_body_m = mission_end;
  EXPECT_EQ(flight.tick().mode, FlightMode::kMission);
  flight.in().mission_finished = true;
  flight.in().mission_end_world_m = mission_end;
  out = flight.tick();
  EXPECT_EQ(out.mode, FlightMode::kHold);
  EXPECT_NEAR((out.setpoint.point_world_m - mission_end).norm(), 0.0, kExactM);
  EXPECT_EQ(flight.events.back().reason, EventReason::kMissionFinished);
}

// ---- Landing -----------------------------------------------------------------------------------

TEST(FlightModes, LandedInLandModeDisarms) {
  const FlightModeParams params;
  Flight flight(params);
  flight.takeOffAndHold();
  const Vector3d above(0.0, 0.0, -kTakeOffHeightM);
  ASSERT_TRUE(flight.command(CommandKind::kLand).accepted());
  FlightOutput out = flight.tick();
  EXPECT_EQ(out.mode, FlightMode::kLand);
  EXPECT_EQ(out.setpoint.kind, SetpointKind::kLand);
  EXPECT_DOUBLE_EQ(out.setpoint.descent_speed_m_s, params.land_speed_m_s);
  EXPECT_NEAR((out.setpoint.point_world_m - above).norm(), 0.0, kExactM);

  // Descending at the land speed is not landed, however low the thrust.
  flight.state().p_world_body_m.z() = -0.05;
  flight.in().height_above_ground_m = 0.05;
  flight.state().v_world_body_m_s = Vector3d(0.0, 0.0, params.land_speed_m_s);
  flight.in().thrust_ratio = 0.1;
  EXPECT_FALSE(flight.run(2.0 * params.landed_time_s).landed);
  // On the ground, still, and the loop pushing down: landed after landed_time_s, then disarmed.
  flight.state().v_world_body_m_s.setZero();
  out = flight.run(params.landed_time_s - 0.01);
  EXPECT_EQ(out.mode, FlightMode::kLand);
  out = flight.run(0.02);
  EXPECT_EQ(out.mode, FlightMode::kDisarmed);
  EXPECT_EQ(out.setpoint.kind, SetpointKind::kIdle);
  EXPECT_EQ(flight.events.back().reason, EventReason::kLanded);
  EXPECT_EQ(flight.events.back().from, FlightMode::kLand);
  EXPECT_EQ(flight.modes().counters().landed_disarms, 1);
}

// A caller's clock that steps back to before a timer began (a late sample after ticks carried on
// by another clock) must restart the modes' own timers, not make them look long expired: landed
// must still take landed_time_s, and the tilt its attitude_limit_s.
TEST(FlightModes, AClockThatStepsBackNeverFiresATimer) {
  const FlightModeParams params;
  Flight flight(params);
  flight.takeOffAndHold();
  ASSERT_TRUE(flight.command(CommandKind::kLand).accepted());
  flight.state().p_world_body_m.z() = -0.05;
  flight.in().height_above_ground_m = 0.05;
  flight.in().thrust_ratio = 0.1;
  flight.run(0.01);                   // resting for 10 ms ...
  flight.in().utime -= 30 * kTickUs;  // ... when the clock steps back to before that began
  EXPECT_FALSE(flight.tick().landed);
  EXPECT_EQ(flight.run(params.landed_time_s - 0.01).mode, FlightMode::kLand);
  EXPECT_EQ(flight.run(0.02).mode, FlightMode::kDisarmed);

  Flight tilted(params);
  tilted.takeOffAndHold();
  tilted.state().q_world_body = Eigen::AngleAxisd(kPi / 2.0, Vector3d::UnitX());
  tilted.run(0.005);
  tilted.in().utime -= 30 * kTickUs;
  EXPECT_EQ(tilted.tick().mode, FlightMode::kHold);
  EXPECT_EQ(tilted.run(params.attitude_limit_s - 0.002).mode, FlightMode::kHold);
  EXPECT_EQ(tilted.run(0.005).mode, FlightMode::kHandedOver);
}

// ---- Failsafes, one by one ---------------------------------------------------------------------

TEST(FlightModes, VisionLostDescendsOnAttitudeAloneUntilLanded) {
  const FlightModeParams params;
  Flight flight(params);
  flight.takeOffAndHold();
  flight.vision_fresh = false;
  FlightOutput out = flight.run(params.vision_lost_s - 0.01);
  EXPECT_EQ(out.mode, FlightMode::kHold);
  // Meanwhile the pose is too old for new targets, and landing falls back on the descent.
  EXPECT_EQ(flight.command(CommandKind::kHold).refusal, CommandRefusal::kVisionNotFused);
  out = flight.run(0.02);
  EXPECT_EQ(out.mode, FlightMode::kDescend);
  EXPECT_EQ(out.setpoint.kind, SetpointKind::kDescend);
  EXPECT_DOUBLE_EQ(out.setpoint.descent_speed_m_s, params.vision_lost_descent_m_s);
  EXPECT_EQ(flight.count(EventReason::kVisionLost), 1);
  EXPECT_EQ(flight.modes().counters().vision_lost, 1);
  EXPECT_TRUE(flight.command(CommandKind::kLand).accepted());
  EXPECT_EQ(flight.modes().mode(), FlightMode::kDescend);

  // Touched down: the dead-reckoned height is not trusted, the stillness and thrust are.
  flight.in().height_above_ground_m = 1.5;
  flight.in().thrust_ratio = 0.1;
  out = flight.run(params.landed_time_s + 0.01);
  EXPECT_EQ(out.mode, FlightMode::kDisarmed);
  EXPECT_EQ(flight.events.back().reason, EventReason::kLanded);
  EXPECT_EQ(flight.modes().counters().vision_lost, 1);  // acted once
}

TEST(FlightModes, EstimatorDivergedDescendsWithoutItsPosition) {
  const FlightModeParams params;
  Flight flight(params);
  flight.takeOffAndHold();
  flight.in().estimator.diverged = true;
  FlightOutput out = flight.tick();
  EXPECT_EQ(out.mode, FlightMode::kDescend);
  EXPECT_EQ(out.setpoint.kind, SetpointKind::kDescend);
  EXPECT_DOUBLE_EQ(out.setpoint.descent_speed_m_s, params.vision_lost_descent_m_s);
  EXPECT_EQ(flight.events.back().reason, EventReason::kEstimatorDiverged);
  EXPECT_EQ(flight.events.back().from, FlightMode::kHold);
  EXPECT_EQ(flight.command(CommandKind::kHold).refusal, CommandRefusal::kEstimatorUnhealthy);
  flight.run(1.0);  // the estimator's flag is sticky: the failsafe acted once
  EXPECT_EQ(flight.modes().counters().estimator_diverged, 1);
  EXPECT_EQ(flight.modes().mode(), FlightMode::kDescend);
}

TEST(FlightModes, DivergedAndVisionLostTogetherEndInTheDescent) {
  const FlightModeParams params;
  Flight flight(params);
  flight.takeOffAndHold();
  flight.vision_fresh = false;
  flight.run(params.vision_lost_s);  // the pose exactly vision_lost_s old: not yet lost
  EXPECT_EQ(flight.modes().mode(), FlightMode::kHold);
  flight.in().estimator.diverged = true;
  flight.tick();
  EXPECT_EQ(flight.modes().mode(), FlightMode::kDescend);
  ASSERT_GE(flight.events.size(), 2u);
  const FlightEvent& diverged = flight.events[flight.events.size() - 2];
  const FlightEvent& lost = flight.events.back();
  EXPECT_EQ(diverged.reason, EventReason::kEstimatorDiverged);
  EXPECT_EQ(diverged.to, FlightMode::kDescend);
  EXPECT_EQ(lost.reason, EventReason::kVisionLost);  // logged and counted, no further change
  EXPECT_EQ(lost.from, FlightMode::kDescend);
  EXPECT_EQ(lost.to, FlightMode::kDescend);
  EXPECT_EQ(diverged.utime, lost.utime);
}

TEST(FlightModes, GroundLostIsFlaggedAndCountedWithoutAModeChange) {
  const FlightModeParams params;
  Flight flight(params);
  // A drone that never heard a ground station flies on it without a word.
  flight.ground_fresh = false;
  flight.takeOffAndHold();
  EXPECT_EQ(flight.count(EventReason::kGroundLost), 0);

  flight.ground_fresh = true;
  EXPECT_TRUE(flight.tick().ground_alive);
  flight.ground_fresh = false;
  FlightOutput out = flight.run(params.ground_lost_s + 0.01);
  EXPECT_FALSE(out.ground_alive);
  EXPECT_EQ(out.mode, FlightMode::kHold);
  ASSERT_EQ(flight.count(EventReason::kGroundLost), 1);
  EXPECT_EQ(flight.events.back().from, FlightMode::kHold);
  EXPECT_EQ(flight.events.back().to, FlightMode::kHold);
  EXPECT_TRUE(isFailsafe(flight.events.back().reason));
  flight.run(1.0);
  EXPECT_EQ(flight.modes().counters().ground_lost, 1);

  flight.ground_fresh = true;
  EXPECT_TRUE(flight.tick().ground_alive);
  EXPECT_EQ(flight.events.back().reason, EventReason::kGroundRegained);
  EXPECT_FALSE(isFailsafe(EventReason::kGroundRegained));
  EXPECT_EQ(flight.modes().mode(), FlightMode::kHold);
}

TEST(FlightModes, TiltBeyondTheLimitCutsTheMotorsWhereSoSet) {
  FlightModeParams params;
  params.attitude_limit_action = AttitudeLimitAction::kCutMotors;
  Flight flight(params);
  flight.takeOffAndHold();
  const Eigen::Quaterniond tilted(Eigen::AngleAxisd(params.max_tilt_rad + 0.1,
                                                    Vector3d::UnitY()));
  // A knock shorter than attitude_limit_s passes.
  flight.state().q_world_body = tilted;
  flight.run(params.attitude_limit_s - 0.01);
  flight.state().q_world_body.setIdentity();
  EXPECT_EQ(flight.tick().mode, FlightMode::kHold);

  flight.state().q_world_body = tilted;
  FlightOutput out = flight.run(params.attitude_limit_s + 0.01);
  EXPECT_EQ(out.mode, FlightMode::kMotorsCut);
  EXPECT_TRUE(out.cut_motors);
  EXPECT_FALSE(out.hand_over);
  EXPECT_EQ(out.setpoint.kind, SetpointKind::kIdle);
  EXPECT_EQ(flight.events.back().reason, EventReason::kAttitudeLimit);
  EXPECT_EQ(flight.modes().counters().attitude_limit, 1);
  EXPECT_EQ(flight.command(CommandKind::kLand).refusal, CommandRefusal::kNoControl);
  // Cut in the air, the drone falls: disarming it is always allowed.
  EXPECT_TRUE(flight.command(CommandKind::kDisarm).accepted());
  EXPECT_FALSE(flight.tick().cut_motors);
}

TEST(FlightModes, BodyRateBeyondTheLimitHandsOverToTheAutopilot) {
  const FlightModeParams params;  // hand-over is the default
  Flight flight(params);
  flight.takeOffAndHold();
  flight.state().omega_body_rad_s = Vector3d(0.0, 0.0, params.max_rate_rad_s + 1.0);
  FlightOutput out = flight.run(params.attitude_limit_s + 0.01);
  EXPECT_EQ(out.mode, FlightMode::kHandedOver);
  EXPECT_TRUE(out.hand_over);
  EXPECT_FALSE(out.cut_motors);
  EXPECT_EQ(flight.modes().counters().attitude_limit, 1);
  EXPECT_EQ(flight.command(CommandKind::kHold).refusal, CommandRefusal::kNoControl);
  // The autopilot has it: disarming waits for the landing.
  EXPECT_EQ(flight.command(CommandKind::kDisarm).refusal, CommandRefusal::kAirborne);
}

TEST(FlightModes, ImuSilentInFlightActsAsTheAttitudeLimitDoes) {
  FlightModeParams params;
  params.attitude_limit_action = AttitudeLimitAction::kCutMotors;
  Flight flight(params);
  flight.takeOffAndHold();
  flight.imu_fresh = false;
  // A gap shorter than imu_lost_s passes: one late sample is no failure.
  FlightOutput out = flight.run(params.imu_lost_s - 2 * kTickS);
  EXPECT_EQ(out.mode, FlightMode::kHold);
  out = flight.run(3 * kTickS);
  EXPECT_EQ(out.mode, FlightMode::kMotorsCut);
  EXPECT_TRUE(out.cut_motors);
  EXPECT_EQ(flight.count(EventReason::kImuLost), 1);
  EXPECT_TRUE(isFailsafe(EventReason::kImuLost));
  EXPECT_EQ(flight.modes().counters().imu_lost, 1);
  EXPECT_EQ(flight.modes().counters().attitude_limit, 0);
  // It acts once, not on every silent tick.
  flight.run(0.1);
  EXPECT_EQ(flight.modes().counters().imu_lost, 1);
}

TEST(FlightModes, GeofenceBreachHoldsAtTheLastPointInside) {
  const FlightModeParams params;
  Flight flight(params);
  flight.takeOffAndHold();
  ASSERT_TRUE(flight.command(FlightCommand{CommandKind::kGoTo, 0.0,
                                           Vector3d(49.0, 0.0, -kTakeOffHeightM)})
                  .accepted());
  // The drone overshoots the target (wind) and leaves the box, 0.4 m per tick.
  const double x_max_m = params.geofence_max_world_m.x();
  double last_inside_x_m = 0.0;
  for (double x_m = 48.0; x_m < x_max_m + 1.0; x_m += 0.4) {
    flight.state().p_world_body_m.x() = x_m;
    if (x_m <= x_max_m) last_inside_x_m = x_m;
    flight.tick();
  }
  FlightOutput out = flight.tick();
  EXPECT_EQ(out.mode, FlightMode::kHold);
  EXPECT_NEAR(out.setpoint.point_world_m.x(), last_inside_x_m, kExactM);
  EXPECT_EQ(flight.count(EventReason::kGeofence), 1);
  // Outside for a while: one breach, one count.
  flight.run(0.5);
  EXPECT_EQ(flight.modes().counters().geofence, 1);
  // Still outside: a mission would lead further out, a hold stays at the last point inside.
  EXPECT_EQ(flight.command(CommandKind::kMission).refusal, CommandRefusal::kOutsideGeofence);
  ASSERT_TRUE(flight.command(CommandKind::kHold).accepted());
  EXPECT_NEAR(flight.tick().setpoint.point_world_m.x(), last_inside_x_m, kExactM);
  // Back inside and out again: a second breach.
  flight.state().p_world_body_m.x() = x_max_m - 1.0;
  flight.tick();
  flight.state().p_world_body_m.x() = x_max_m + 0.5;
  flight.tick();
  EXPECT_EQ(flight.modes().counters().geofence, 2);
  EXPECT_NEAR(flight.tick().setpoint.point_world_m.x(), x_max_m - 1.0, kExactM);
}

// ---- Counters and the steady state -------------------------------------------------------------

TEST(FlightModes, CountsEveryModeChangeAndCommand) {
  Flight flight;
  flight.takeOffAndHold();  // arm, take-off, take-off reached
  ASSERT_TRUE(flight.command(CommandKind::kLand).accepted());
  EXPECT_EQ(flight.command(CommandKind::kDisarm).refusal, CommandRefusal::kAirborne);
  ASSERT_TRUE(flight.command(CommandKind::kHold).accepted());
  ASSERT_TRUE(flight.command(CommandKind::kHold).accepted());  // a new point, the same mode
  const FlightCounters& counters = flight.modes().counters();
  EXPECT_EQ(counters.mode_changes, 5);  // armed, take-off, hold, land, hold
  EXPECT_EQ(counters.commands_accepted, 5);
  EXPECT_EQ(counters.commands_refused, 1);
  int changes = 0;
  for (const FlightEvent& event : flight.events) changes += event.from != event.to ? 1 : 0;
  EXPECT_EQ(changes, counters.mode_changes);
}

// ---- The autopilot (mavlink backend) ---------------------------------------------------------

// Arming needs the autopilot heard; take-off needs it armed in offboard (the backend asks for
// both once kinfly is armed).
TEST(FlightModes, ArmingNeedsTheAutopilotAndTakeOffItsControl) {
  Flight flight;
  AutopilotInputs& ap = flight.in().autopilot;
  ap.used = true;
  flight.run(0.1);
  EXPECT_EQ(flight.command(CommandKind::kArm).refusal, CommandRefusal::kNoAutopilot);
  ap.alive = true;
  ASSERT_TRUE(flight.command(CommandKind::kArm).accepted());
  const FlightCommand take_off{CommandKind::kTakeOff, kTakeOffHeightM};
  EXPECT_EQ(flight.command(take_off).refusal, CommandRefusal::kAutopilotNotReady);
  ap.armed = true;
  EXPECT_EQ(flight.command(take_off).refusal, CommandRefusal::kAutopilotNotReady);
  ap.offboard = true;
  EXPECT_TRUE(flight.command(take_off).accepted());
  EXPECT_EQ(flight.modes().mode(), FlightMode::kTakeOff);
}

// The autopilot's heartbeat stops in flight: a failsafe, handed over (it flies on by its own
// failsafe); on the ground, kinfly disarms.
TEST(FlightModes, AutopilotLostHandsOverInTheAirAndDisarmsOnTheGround) {
  Flight flight;
  AutopilotInputs& ap = flight.in().autopilot;
  ap = {true, true, true, true};
  flight.takeOffAndHold();
  ap.alive = false;
  EXPECT_EQ(flight.tick().mode, FlightMode::kHandedOver);
  EXPECT_EQ(flight.count(EventReason::kAutopilotLost), 1);
  EXPECT_TRUE(isFailsafe(EventReason::kAutopilotLost));
  flight.run(0.5);  // acts once
  EXPECT_EQ(flight.modes().counters().autopilot_lost, 1);
  EXPECT_EQ(flight.command(CommandKind::kHold).refusal, CommandRefusal::kNoControl);
  // Back, and disarmed by its own landing: so is kinfly.
  ap = {true, true, false, false};
  EXPECT_EQ(flight.tick().mode, FlightMode::kDisarmed);
  EXPECT_EQ(flight.count(EventReason::kAutopilotDisarmed), 1);

  Flight ground;
  AutopilotInputs& gap = ground.in().autopilot;
  gap = {true, true, false, false};
  ground.run(0.1);
  ASSERT_TRUE(ground.command(CommandKind::kArm).accepted());
  gap.alive = false;
  EXPECT_EQ(ground.tick().mode, FlightMode::kDisarmed);
  EXPECT_EQ(ground.modes().counters().autopilot_lost, 1);
}

// A pilot's mode switch (or the autopilot's own failsafe) takes the drone out of offboard: not a
// failsafe of kinfly's, but kinfly stops flying it.
TEST(FlightModes, LeavingOffboardHandsOver) {
  Flight flight;
  AutopilotInputs& ap = flight.in().autopilot;
  ap = {true, true, true, true};
  flight.takeOffAndHold();
  ap.offboard = false;
  const FlightOutput out = flight.tick();
  EXPECT_EQ(out.mode, FlightMode::kHandedOver);
  EXPECT_TRUE(out.hand_over);
  EXPECT_EQ(flight.count(EventReason::kAutopilotTookOver), 1);
  EXPECT_FALSE(isFailsafe(EventReason::kAutopilotTookOver));
  EXPECT_EQ(flight.modes().counters().autopilot_took_over, 1);
  EXPECT_EQ(flight.modes().counters().autopilot_lost, 0);
}

// The motors backend has no autopilot: nothing about it is checked or changes a mode.
TEST(FlightModes, WithoutAnAutopilotItsInputsAreIgnored) {
  Flight flight;
  AutopilotInputs& ap = flight.in().autopilot;
  ap = {false, true, true, true};  // in control, but not used: the motors backend
  flight.takeOffAndHold();
  ap.alive = false;  // would be lost ...
  flight.run(0.5);
  ap = {false, true, true, false};  // ... or taken over, were it used
  flight.run(0.5);
  EXPECT_EQ(flight.modes().mode(), FlightMode::kHold);
  EXPECT_EQ(flight.modes().counters().autopilot_lost, 0);
  EXPECT_EQ(flight.modes().counters().autopilot_took_over, 0);
}

TEST(FlightModes, UpdateAllocatesNothing) {
  FlightModeParams params;
  params.attitude_limit_action = AttitudeLimitAction::kCutMotors;
  Flight flight(params);
  flight.events.reserve(64);
  const int64_t before = g_allocations.load();
  flight.takeOffAndHold();
  flight.command(FlightCommand{CommandKind::kGoTo, 0.0, Vector3d(3.0, 0.0, -3.0)});
  flight.in().mission_loaded = true;
  flight.command(CommandKind::kMission);
  flight.vision_fresh = false;
  flight.ground_fresh = false;
  flight.run(3.0);
  flight.state().q_world_body = Eigen::AngleAxisd(kPi / 2.0, Vector3d::UnitX());
  flight.run(0.5);
  flight.command(CommandKind::kDisarm);
  EXPECT_EQ(g_allocations.load(), before);
  EXPECT_EQ(flight.modes().mode(), FlightMode::kDisarmed);
  // The sequence went through the failsafes it meant to.
  const FlightCounters& counters = flight.modes().counters();
  EXPECT_EQ(counters.vision_lost, 1);
  EXPECT_EQ(counters.ground_lost, 1);
  EXPECT_EQ(counters.attitude_limit, 1);
}

TEST(FlightModes, EveryEnumHasAName) {
  for (int i = 0; i <= static_cast<int>(FlightMode::kHandedOver); ++i) {
    EXPECT_STRNE(toString(static_cast<FlightMode>(i)), "?");
  }
  for (int i = 0; i <= static_cast<int>(CommandRefusal::kAutopilotNotReady); ++i) {
    EXPECT_STRNE(toString(static_cast<CommandRefusal>(i)), "?");
  }
  for (int i = 0; i <= static_cast<int>(EventReason::kAutopilotDisarmed); ++i) {
    EXPECT_STRNE(toString(static_cast<EventReason>(i)), "?");
  }
  for (int i = 0; i <= static_cast<int>(SetpointKind::kDescend); ++i) {
    EXPECT_STRNE(toString(static_cast<SetpointKind>(i)), "?");
  }
  for (int i = 0; i <= static_cast<int>(CommandKind::kLand); ++i) {
    EXPECT_STRNE(toString(static_cast<CommandKind>(i)), "?");
  }
}

}  // namespace
}  // namespace kinfly::flight
