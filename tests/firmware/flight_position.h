// The whole flight stack closed around the test plant (flight_plant.h): the estimator on the
// plant's noisy IMU at 1 kHz and the odometry's noisy 30 Hz poses delivered 30 ms late
// (vision_poses.h), the position loop on its estimate at its own rate, the attitude and rate
// loops, the mixer and the flight modes at 1 kHz (FlightStack, one tick as the control task runs
// it). And the flights issue 15 measures it on, with their figures: hover, a figure eight, a
// steady wind; and a flight's sensors recorded, to fly the stack alone again for its cost. One
// definition, for test_flight_position.cpp and kinfly-flight-bench, so the test and the
// benchmark fly the same thing.
#pragma once

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <deque>
#include <optional>
#include <vector>

#include "flight_loop.h"
#include "kinfly/flight/estimator.h"
#include "kinfly/flight/flight_modes.h"
#include "kinfly/flight/position_controller.h"
#include "kinfly/flight/trajectory.h"
#include "vision_poses.h"

namespace kinfly::flight::test {

constexpr double kAccelNoiseDensity = 7e-4;  // [m/s^2/sqrt(Hz)] an ICM-42688-class accelerometer
constexpr int64_t kFlightStartUs = 1000000;  // a start after 0 keeps every utime positive
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

inline Pose poseOf(const PlantState& state) {
  Pose T_world_body = Pose::Identity();
  T_world_body.linear() = state.q_world_body.toRotationMatrix();
  T_world_body.translation() = state.p_world_m;
  return T_world_body;
}

// The flight stack as the control task runs it, one 1 kHz tick at a time: sense() the tick's IMU
// sample (the estimator's prediction) and the odometry poses that arrived (fused, late), then
// control(): the flight modes, the position loop every decimation-th tick, the attitude and rate
// loops and the mixer. The modes run every tick on the estimator's health and state and are
// commanded up to a mission as the ground would (arm, take off, mission), so that they take
// their flying path; the setpoint is the flight's trajectory, sampled as mission mode follows
// it, so that the flights' figures do not hang on the modes' own targets.
class FlightStack {
 public:
  // flight must outlive the stack.
  FlightStack(const Vehicle& vehicle, const PositionFlight& flight, const EstimatorInit& init)
      : flight_(flight),
        weight_n_(vehicle.weightN()),
        estimator_(EstimatorParams{}),
        position_(flight.position, vehicle),
        // The default parameters always build (test_flight_loop), so the value is there.
        attitude_(*AttitudeController::create(AttitudeController::Params{}, vehicle)),
        mixer_(vehicle),
        modes_(FlightModeParams{}),
        decimation_(static_cast<int>(std::lround(1.0 / (flight.position.rate_hz * kControlDtS)))) {
    estimator_.initialise(init);
  }

  // The IMU sample that closed the last tick and the poses that arrived by then.
  void sense(const ImuSample& imu, const VisionPose* poses, size_t pose_count) {
    estimator_.addImu(imu);
    last_imu_utime_ = imu.utime;
    for (size_t i = 0; i < pose_count; ++i) {
      if (estimator_.addVision(poses[i]) == VisionOutcome::kFused) {
        last_vision_utime_ = poses[i].utime;
      }
    }
  }

  // Tick k's rotor command, from the estimate as sense() left it.
  MixerOutput control(int k) {
    const double t_s = k * kControlDtS;
    const EstimatorState state = estimator_.state();
    FlightInputs inputs;
    inputs.utime = kFlightStartUs + static_cast<int64_t>(k) * kControlUs;
    inputs.estimator = estimator_.health();
    inputs.state = state;
    inputs.last_imu_utime = last_imu_utime_;
    inputs.last_vision_utime = last_vision_utime_;
    inputs.height_above_ground_m = -state.p_world_body_m.z();  // the ground at z = 0
    inputs.thrust_ratio = command_.thrust_n / weight_n_;
    const FlightOutput modes = modes_.update(inputs, nextCommand());
    lost_control_ = lost_control_ || modes.cut_motors || modes.hand_over;
    if (k % decimation_ == 0) {
      command_ = position_.update(flight_.trajectory.sample(t_s), state, decimation_ * kControlDtS);
    }
    const Eigen::Vector3d moment_body_nm = attitude_.update(
        state.q_world_body, command_.q_world_body_sp, state.omega_body_rad_s, kControlDtS,
        saturation_);
    const MixerOutput out = mixer_.mix({command_.thrust_n, moment_body_nm});
    saturation_ = out.saturation;
    return out;
  }

  const Estimator& estimator() const { return estimator_; }
  const FlightModes& modes() const { return modes_; }
  bool lostControl() const { return lost_control_; }

  static constexpr int64_t kControlUs = 1000;  // kControlDtS in µs
  static constexpr double kTakeOffHeightM = 1.0;

 private:
  // The ground's commands up to a mission, one a tick, each repeated until accepted.
  std::optional<FlightCommand> nextCommand() const {
    FlightCommand command;
    switch (modes_.mode()) {
      case FlightMode::kDisarmed: command.kind = CommandKind::kArm; return command;
      case FlightMode::kArmed:
        command.kind = CommandKind::kTakeOff;
        command.height_m = kTakeOffHeightM;
        return command;
      case FlightMode::kTakeOff: command.kind = CommandKind::kMission; return command;
      default: return std::nullopt;
    }
  }

  const PositionFlight& flight_;
  double weight_n_;
  Estimator estimator_;
  PositionController position_;
  AttitudeController attitude_;
  Mixer mixer_;
  FlightModes modes_;
  int decimation_;
  MixerSaturation saturation_;
  PositionOutput command_;
  int64_t last_imu_utime_ = -1;
  int64_t last_vision_utime_ = -1;
  bool lost_control_ = false;
};

// What a flight's stack sensed, tick by tick, to fly the stack again without the plant
// (replayStack): with the same inputs it makes the same calls.
struct SensorLog {
  EstimatorInit init;
  std::vector<ImuSample> imu;      // tick k's closing sample
  std::vector<VisionPose> poses;   // those that arrived in tick k: [poses_end[k-1], poses_end[k])
  std::vector<size_t> poses_end;
  int ticks() const { return static_cast<int>(imu.size()); }
};

// The stack's ticks [from, to) on the recorded sensors, alone (to < 0: to the end): what
// kinfly-flight-bench times and callgrind counts (--toggle-collect on this function's name). Not
// inlined, so that it has a name; returns the rotor speeds' sum so that nothing is optimised away.
[[gnu::noinline]] inline double replayStack(FlightStack& stack, const SensorLog& log, int from = 0,
                                            int to = -1) {
  if (to < 0) to = log.ticks();
  double sink = 0.0;
  size_t first_pose = from > 0 ? log.poses_end[static_cast<size_t>(from - 1)] : 0;
  for (int k = from; k < to; ++k) {
    sink += stack.control(k).rotor_speed_rad_s.sum();
    const size_t end = log.poses_end[static_cast<size_t>(k)];
    stack.sense(log.imu[static_cast<size_t>(k)], log.poses.data() + first_pose, end - first_pose);
    first_pose = end;
  }
  return sink;
}

// Flies the flight; with a log, records what the stack sensed.
inline PositionFigures flyPosition(const Vehicle& vehicle, const PositionFlight& flight,
                                   SensorLog* log = nullptr) {
  FlightPlant plant(vehicle, kGyroNoiseDensity, flight.seed, kAccelNoiseDensity);
  plant.startHovering(flight.trajectory.sample(0.0).p_world_m);
  plant.setWind(flight.wind_world_m_s, kWindDragNSM);

  // The estimator starts where the body is, as after a take-off; `odom` is the first camera.
  const EstimatorParams estimator_params;
  EstimatorInit init;
  init.utime = kFlightStartUs;
  init.p_world_body_m = plant.state().p_world_m;
  init.T_world_odom = poseOf(plant.state()) * estimator_params.T_body_cam;
  FlightStack stack(vehicle, flight, init);
  const Pose T_odom_world = init.T_world_odom.inverse();
  Gaussian gaussian(flight.seed + 1000);  // the odometry's noise, apart from the IMU's
  std::deque<Delivery> in_flight;
  std::vector<VisionPose> arrived;

  const int ticks = controlTicks(flight.duration_s);
  const int tail_ticks = controlTicks(kTailS);
  if (log != nullptr) {
    *log = SensorLog{};
    log->init = init;
    log->imu.reserve(static_cast<size_t>(ticks));
    log->poses_end.reserve(static_cast<size_t>(ticks));
  }
  double sum_sq_m2 = 0.0, estimate_sum_sq_m2 = 0.0;
  int measured = 0;
  PositionFigures figures;
  figures.max_m = 0.0;
  figures.tail_mean_m.setZero();
  int64_t utime = kFlightStartUs;
  int64_t next_capture_utime = kFlightStartUs + kVisionPeriodUs;
  for (int k = 0; k < ticks; ++k) {
    const double t_s = k * kControlDtS;
    const MixerOutput out = stack.control(k);
    plant.step(out.rotor_speed_rad_s, kControlDtS);

    utime += FlightStack::kControlUs;
    ImuSample imu;
    imu.utime = utime;
    imu.gyro_rad_s = plant.gyroBodyRadS();
    imu.accel_m_s2 = plant.accelBodyMS2();
    if (utime >= next_capture_utime) {
      in_flight.push_back(odometryPose(utime, poseOf(plant.state()), T_odom_world,
                                       estimator_params, gaussian));
      next_capture_utime += kVisionPeriodUs;
    }
    arrived.clear();
    while (!in_flight.empty() && in_flight.front().arrival_utime <= utime) {
      arrived.push_back(in_flight.front().pose);
      in_flight.pop_front();
    }
    stack.sense(imu, arrived.data(), arrived.size());
    if (log != nullptr) {
      log->imu.push_back(imu);
      log->poses.insert(log->poses.end(), arrived.begin(), arrived.end());
      log->poses_end.push_back(log->poses.size());
    }

    const double t_after_s = t_s + kControlDtS;
    if (t_after_s < flight.measure_from_s) continue;
    const Eigen::Vector3d error_m =
        plant.state().p_world_m - flight.trajectory.sample(t_after_s).p_world_m;
    sum_sq_m2 += error_m.squaredNorm();
    estimate_sum_sq_m2 +=
        (stack.estimator().state().p_world_body_m - plant.state().p_world_m).squaredNorm();
    ++measured;
    figures.max_m = std::max(figures.max_m, error_m.norm());
    if (k >= ticks - tail_ticks) figures.tail_mean_m += error_m / tail_ticks;
  }
  figures.rms_m = std::sqrt(sum_sq_m2 / measured);
  figures.estimate_rms_m = std::sqrt(estimate_sum_sq_m2 / measured);
  figures.modes = stack.modes().counters();
  figures.final_mode = stack.modes().mode();
  figures.lost_control = stack.lostControl();
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

// Holding a point in the steady wind from the start: long enough for the integral to take the
// whole force over (its slowest pole is ~1/s at the default gains).
inline PositionFlight windFlight(uint32_t seed) {
  PositionFlight flight;
  flight.duration_s = 8.0;
  flight.wind_world_m_s = kWindWorldMS;
  flight.seed = seed;
  return flight;
}

}  // namespace kinfly::flight::test
