// The whole flight stack closed around the test plant (flight_plant.h): the estimator on the
// plant's noisy IMU at 1 kHz and the odometry's noisy 30 Hz poses delivered 30 ms late
// (vision_poses.h), the position loop on its estimate at its own rate, the attitude and rate
// loops, the mixer and the flight modes at 1 kHz (the library's FlightStack, as the control task
// runs it), commanded through its modes as the ground would. And the flights issue 15 measures it on, with their figures: hover, a figure eight, a
// steady wind; and a flight's sensors recorded, to fly the stack alone again for its cost. One
// definition, for test_flight_position.cpp and kinfly-flight-bench, so the test and the
// benchmark fly the same thing.
#pragma once

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <deque>
#include <memory>
#include <optional>
#include <vector>

#include "flight_loop.h"
#include "kinfly/flight/estimator.h"
#include "kinfly/flight/flight_modes.h"
#include "kinfly/flight/flight_stack.h"
#include "kinfly/flight/position_controller.h"
#include "kinfly/flight/trajectory.h"
#include "vision_poses.h"

namespace kinfly::flight::test {

constexpr double kAccelNoiseDensity = 7e-4;  // [m/s^2/sqrt(Hz)] an ICM-42688-class accelerometer
constexpr int64_t kFlightStartUs = 1000000;  // a start after 0 keeps every utime positive
constexpr int64_t kControlUs = 1000;         // kControlDtS in µs
// The flights' place: 1 m above the world origin (z down).
const Eigen::Vector3d kHoverWorldM(0.0, 0.0, -1.0);
// Issue 15's steady wind, and a linear drag that turns it into a force: 0.15 N s/m at 2 m/s is
// 0.3 N on the 0.5 kg Hummingbird, which must tilt by 3.5 degrees to hold its place.
const Eigen::Vector3d kWindWorldMS(2.0, 0.0, 0.0);
constexpr double kWindDragNSM = 0.15;
// The figure eight: x = (a / 2) sin(theta), y = (b / 2) sin(2 theta), a by b = 2 m by 1 m,
// flown once as a minimum-snap trajectory through its points every 45 degrees, at 1 m/s peak
// speed.
constexpr double kEightLengthM = 2.0;
constexpr double kEightWidthM = 1.0;
constexpr double kEightSpeedMS = 1.0;
constexpr int kEightPoints = 8;
// The steady error is the mean error over a flight's last second.
constexpr double kTailS = 1.0;
// Issue 15's figures, for the tests and the benchmark alike.
constexpr double kHoverRmsTargetM = 0.02;
constexpr double kFigureEightRmsTargetM = 0.03;
constexpr double kWindSteadyErrorTargetM = 0.01;

// The control ticks in a duration, rounded: a truncated 2.001 / 0.001 would lose one.
inline int controlTicks(double duration_s) {
  return static_cast<int>(std::lround(duration_s / kControlDtS));
}

struct PositionFlight {
  Trajectory trajectory = Trajectory::hold(kHoverWorldM, 0.0);
  double duration_s = 5.0;   // beyond the trajectory's end: holding its last point
  double measure_from_s = 0.5;
  Eigen::Vector3d wind_world_m_s = Eigen::Vector3d::Zero();
  PositionControllerParams position;
  uint32_t seed = 1;
};

struct PositionFigures {
  double rms_m = NAN;       // of |p_true - p_setpoint| from measure_from_s on
  double max_m = NAN;       // largest such error
  Eigen::Vector3d tail_mean_m = Eigen::Vector3d::Constant(NAN);  // mean error, last kTailS
  double estimate_rms_m = NAN;  // of |p_estimated - p_true|, for context
  // The flight modes over the flight: a figure flown through a failsafe would not count.
  FlightCounters modes;
  FlightMode final_mode = FlightMode::kDisarmed;
  bool lost_control = false;  // a tick asked to cut the motors or to hand over
};

inline void lostControlIf(const TickOutput& out, PositionFigures* figures) {
  figures->lost_control = figures->lost_control || out.modes.cut_motors || out.modes.hand_over;
}

inline Pose poseOf(const PlantState& state) {
  Pose T_world_body = Pose::Identity();
  T_world_body.linear() = state.q_world_body.toRotationMatrix();
  T_world_body.translation() = state.p_world_m;
  return T_world_body;
}

// The ground's commands up to a mission, as a ground station sends them: one a tick, each
// repeated until accepted (arming waits for the first fused pose).
constexpr double kTakeOffHeightM = 1.0;
inline std::optional<FlightCommand> towardsMission(FlightMode mode) {
  FlightCommand command;
  switch (mode) {
    case FlightMode::kDisarmed: command.kind = CommandKind::kArm; return command;
    case FlightMode::kArmed:
      command.kind = CommandKind::kTakeOff;
      command.height_m = kTakeOffHeightM;
      return command;
    case FlightMode::kTakeOff:
    case FlightMode::kHold: command.kind = CommandKind::kMission; return command;
    default: return std::nullopt;
  }
}

// The library's flight stack (flight_stack.h) for a flight: 1 kHz, the flight's position gains,
// its trajectory loaded as the mission, the estimator started at `init`.
inline StatusOr<std::unique_ptr<FlightStack>> makeStack(const Vehicle& vehicle,
                                                        const PositionFlight& flight,
                                                        const EstimatorInit& init) {
  FlightStackParams params;
  params.rate_hz = 1.0 / kControlDtS;
  params.vehicle = vehicle.params();
  params.position = flight.position;
  auto stack = FlightStack::create(params);
  if (!stack.ok()) return stack;
  (*stack)->initialise(init);
  if (Status loaded = (*stack)->loadMission(flight.trajectory); !loaded.ok()) return loaded;
  return stack;
}

// What a flight's stack was given, tick by tick, to fly the stack again without the plant
// (replayStack): with the same inputs it makes the same calls.
struct SensorLog {
  EstimatorInit init;
  std::vector<TickInputs> ticks;   // tick k's inputs
  std::vector<ImuSample> imu;      // the sample that closed tick k
  std::vector<VisionPose> poses;   // those that arrived in tick k: [poses_end[k-1], poses_end[k])
  std::vector<size_t> poses_end;
  int count() const { return static_cast<int>(ticks.size()); }
};

// The stack's ticks [from, to) on the recorded inputs, alone (to < 0: to the end): what
// kinfly-flight-bench times and callgrind counts (--toggle-collect on this function's name). Not
// inlined, so that it has a name; returns the rotor speeds' sum so that nothing is optimised away.
[[gnu::noinline]] inline double replayStack(FlightStack& stack, const SensorLog& log, int from = 0,
                                            int to = -1) {
  if (to < 0) to = log.count();
  double sink = 0.0;
  size_t first_pose = from > 0 ? log.poses_end[static_cast<size_t>(from - 1)] : 0;
  for (int k = from; k < to; ++k) {
    const auto i = static_cast<size_t>(k);
    sink += stack.tick(log.ticks[i]).mixer.rotor_speed_rad_s.sum();
    stack.addImu(log.imu[i]);
    for (size_t p = first_pose; p < log.poses_end[i]; ++p) stack.addVision(log.poses[p]);
    first_pose = log.poses_end[i];
  }
  return sink;
}

// The plant's sensors as the stack gets them after each tick: its IMU sample, and the odometry's
// poses of the plant's camera at 30 Hz, noisy and delivered 30 ms late (vision_poses.h).
class SensorFeed {
 public:
  SensorFeed(const EstimatorInit& init, uint32_t seed)
      : T_odom_world_(init.T_world_odom.inverse()),
        gaussian_(seed + 1000),  // the odometry's noise, apart from the IMU's
        next_capture_utime_(init.utime + kVisionPeriodUs) {}

  // The tick that ended at utime: its sample and the poses that arrived by then go to the stack
  // and, with a log, into it.
  void feed(FlightPlant& plant, int64_t utime, FlightStack& stack, SensorLog* log) {
    ImuSample imu;
    imu.utime = utime;
    imu.gyro_rad_s = plant.gyroBodyRadS();
    imu.accel_m_s2 = plant.accelBodyMS2();
    if (utime >= next_capture_utime_ && camera_on_) {
      in_flight_.push_back(odometryPose(utime, poseOf(plant.state()), T_odom_world_,
                                        EstimatorParams{}, gaussian_));
      in_flight_.back().pose.weak = weak_;
      next_capture_utime_ += kVisionPeriodUs;
    }
    arrived_.clear();
    while (!in_flight_.empty() && in_flight_.front().arrival_utime <= utime) {
      arrived_.push_back(in_flight_.front().pose);
      in_flight_.pop_front();
    }
    stack.addImu(imu);
    for (const VisionPose& pose : arrived_) stack.addVision(pose);
    if (log != nullptr) {
      log->imu.push_back(imu);
      log->poses.insert(log->poses.end(), arrived_.begin(), arrived_.end());
      log->poses_end.push_back(log->poses.size());
    }
  }
  // The camera covered: no pose is captured from now on (those in flight still arrive).
  void coverCamera() { camera_on_ = false; }
  // A corridor along `axis_odom`: the poses captured from now on name it their weak direction.
  void weakenAlong(const Eigen::Vector3d& axis_odom) {
    weak_.count = 1;
    weak_.d[0] << axis_odom.normalized(), Eigen::Vector3d::Zero();
  }

 private:
  Pose T_odom_world_;
  bool camera_on_ = true;
  WeakDirections weak_;
  Gaussian gaussian_;
  int64_t next_capture_utime_;
  std::deque<Delivery> in_flight_;
  std::vector<VisionPose> arrived_;
};

// The estimator's start for a body at rest at the plant's state; `odom` is the first camera.
inline EstimatorInit initAt(const PlantState& state) {
  EstimatorInit init;
  init.utime = kFlightStartUs;
  init.p_world_body_m = state.p_world_m;
  init.T_world_odom = poseOf(state) * EstimatorParams{}.T_body_cam;
  return init;
}

// The longest the ground's commands may take to bring the stack to its mission: arming waits
// for the first pose (~63 ms), the line to the mission's start is short.
constexpr double kMaxPreRollS = 1.0;

// Flies the flight; with a log, records what the stack was given. The plant is held still where
// the flight starts (not stepped, its sensors read at rest there) while the ground's commands
// bring the stack to its mission, then released: the figures are of the mission's trajectory,
// flown from its start, by the stack through its modes as in flight.
inline PositionFigures flyPosition(const Vehicle& vehicle, const PositionFlight& flight,
                                   SensorLog* log = nullptr) {
  FlightPlant plant(vehicle, kGyroNoiseDensity, flight.seed, kAccelNoiseDensity);
  plant.startHovering(flight.trajectory.sample(0.0).p_world_m);
  plant.setWind(flight.wind_world_m_s, kWindDragNSM);
  plant.hold(true);

  // The estimator starts where the body is, as after a take-off.
  const EstimatorInit init = initAt(plant.state());
  PositionFigures figures;
  auto made = makeStack(vehicle, flight, init);
  if (!made.ok()) return figures;  // NaN figures: every test on them fails
  FlightStack& stack = **made;
  SensorFeed sensors(init, flight.seed);

  const int ticks = controlTicks(flight.duration_s);
  const int tail_ticks = controlTicks(kTailS);
  const int max_ticks = ticks + controlTicks(kMaxPreRollS);
  if (log != nullptr) {
    *log = SensorLog{};
    log->init = init;
    log->ticks.reserve(static_cast<size_t>(max_ticks));
    log->imu.reserve(static_cast<size_t>(max_ticks));
    log->poses_end.reserve(static_cast<size_t>(max_ticks));
  }
  double sum_sq_m2 = 0.0, estimate_sum_sq_m2 = 0.0;
  int measured = 0;
  figures.max_m = 0.0;
  figures.tail_mean_m.setZero();
  int64_t utime = kFlightStartUs;
  int flown = -1;  // ticks since the plant's release; -1 while held
  for (int k = 0; k < max_ticks && flown < ticks; ++k) {
    TickInputs in;
    in.utime = utime;
    if (flown < 0) in.command = towardsMission(stack.modes().mode());
    const TickOutput out = stack.tick(in);
    if (log != nullptr) log->ticks.push_back(in);
    lostControlIf(out, &figures);
    if (flown < 0 && out.modes.mode == FlightMode::kMission &&
        utime >= stack.missionStartUtime()) {
      flown = 0;
      plant.hold(false);
    }
    if (flown >= 0) plant.step(out.mixer.rotor_speed_rad_s, kControlDtS);

    utime += kControlUs;
    sensors.feed(plant, utime, stack, log);
    if (flown < 0) continue;
    ++flown;

    const double t_after_s = static_cast<double>(utime - stack.missionStartUtime()) * 1e-6;
    if (t_after_s < flight.measure_from_s) continue;
    const Eigen::Vector3d error_m =
        plant.state().p_world_m - flight.trajectory.sample(t_after_s).p_world_m;
    sum_sq_m2 += error_m.squaredNorm();
    estimate_sum_sq_m2 +=
        (stack.estimator().state().p_world_body_m - plant.state().p_world_m).squaredNorm();
    ++measured;
    figures.max_m = std::max(figures.max_m, error_m.norm());
    if (flown > ticks - tail_ticks) figures.tail_mean_m += error_m / tail_ticks;
  }
  if (flown < ticks) return PositionFigures{};  // never reached its mission: NaN figures
  figures.rms_m = std::sqrt(sum_sq_m2 / measured);
  figures.estimate_rms_m = std::sqrt(estimate_sum_sq_m2 / measured);
  figures.modes = stack.modes().counters();
  figures.final_mode = stack.modes().mode();
  return figures;
}

// ---- Issue 15's flights ---------------------------------------------------------------------

// Holding a point for 5 s.
inline PositionFlight hoverFlight(uint32_t seed) {
  PositionFlight flight;
  flight.seed = seed;
  return flight;
}

// The figure-eight's waypoints, from its centre round both loops and back.
inline std::vector<Eigen::Vector3d> figureEightWaypoints() {
  std::vector<Eigen::Vector3d> waypoints;
  for (int i = 0; i <= kEightPoints; ++i) {
    const double theta = 2.0 * M_PI * i / kEightPoints;
    waypoints.push_back(kHoverWorldM + Eigen::Vector3d(0.5 * kEightLengthM * std::sin(theta),
                                                       0.5 * kEightWidthM * std::sin(2.0 * theta),
                                                       0.0));
  }
  return waypoints;
}

// Once round the figure eight from rest to rest, then a second's hold.
inline StatusOr<PositionFlight> figureEightFlight(uint32_t seed) {
  TrajectoryParams params;
  params.max_speed_m_s = kEightSpeedMS;
  auto trajectory = Trajectory::minimumSnap(figureEightWaypoints(), params, 0.0);
  if (!trajectory.ok()) return trajectory.status();
  PositionFlight flight;
  flight.trajectory = *trajectory;
  flight.duration_s = flight.trajectory.durationS() + 1.0;
  flight.seed = seed;
  return flight;
}

// Holding a point in the steady wind from the start: long enough for the integral alone to take
// the whole force over (its slowest pole is ~1/s at the default gains), as the test flies it
// without the force fed forward too.
inline PositionFlight windFlight(uint32_t seed) {
  PositionFlight flight;
  flight.duration_s = 8.0;
  flight.wind_world_m_s = kWindWorldMS;
  flight.seed = seed;
  return flight;
}

}  // namespace kinfly::flight::test
