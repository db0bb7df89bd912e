#include "control_task.h"

#include <pthread.h>
#include <sched.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <string>
#include <thread>
#include <utility>

#include "kinfly/link/conversions.h"
#include "kinfly/link/decode.h"
#include "kinfly/link/multicast.h"

namespace kinfly::fw {
namespace {

constexpr int kHandleTimeoutMs = 1;
// [bytes] The kernel receive buffer the control task's LCM asks for (within net.core.rmem_max):
// at about 1 KB of kernel memory a datagram, a second of 1 kHz IMU with the looped-back rotor
// commands beside it. LCM's own receive thread, not ours, empties the socket, and on a busy
// machine it waits its turn; the system default (~200 KB) overflowed beside two busy loops.
constexpr int kControlRecvBufBytes = 2 << 20;
// Messages LCM queues for the IMU subscription before it drops the newest: a second of samples.
// LCM's default, 30, dropped whatever came while the control thread waited 30 ms for a core.
constexpr int kImuQueueMessages = 1000;
// [µs of the IMU's clock] between flight status reports: 50 Hz, so the link's 10 Hz sends one
// at most 20 ms old.
constexpr int64_t kFlightStatusPeriodUs = 20000;
// [ms] between ticks before the first IMU sample.
constexpr int kIdleTickMs = 10;

// flight.lcm_url, else the link's; a udpm URL that does not say recv_buf_size asks for
// kControlRecvBufBytes.
std::string controlUrl(const FirmwareConfig& config) {
  const std::string url = link::resolvedLcmUrl(
      config.flight.lcm_url.empty() ? config.link.effectiveLcmUrl() : config.flight.lcm_url);
  if (url.rfind("udpm://", 0) != 0 || url.find("recv_buf_size=") != std::string::npos) return url;
  return url + (url.find('?') == std::string::npos ? "?" : "&") +
         "recv_buf_size=" + std::to_string(kControlRecvBufBytes);
}

double steadySeconds() {
  return std::chrono::duration<double>(Clock::now().time_since_epoch()).count();
}

actuators::AutopilotWant autopilotWant(flight::RotorCommand rotors) {
  switch (rotors) {
    case flight::RotorCommand::kStopped: return actuators::AutopilotWant::kDisarm;
    case flight::RotorCommand::kIdle: return actuators::AutopilotWant::kIdle;
    case flight::RotorCommand::kFlying: return actuators::AutopilotWant::kFly;
    default: return actuators::AutopilotWant::kNothing;
  }
}

// [rad] between two attitudes' tilts: the angle between the world's down seen from each body.
// Their headings need not agree (the autopilot's NED against kinfly's world).
double tiltBetweenRad(const Eigen::Quaterniond& q_a, const Eigen::Quaterniond& q_b) {
  const Eigen::Vector3d down_a = q_a.conjugate() * Eigen::Vector3d::UnitZ();
  const Eigen::Vector3d down_b = q_b.conjugate() * Eigen::Vector3d::UnitZ();
  return std::atan2(down_a.cross(down_b).norm(), down_a.dot(down_b));
}

int8_t rotorState(flight::RotorCommand rotors) {
  switch (rotors) {
    case flight::RotorCommand::kIdle: return motor_command_t::IDLE;
    case flight::RotorCommand::kFlying: return motor_command_t::FLYING;
    default: return motor_command_t::STOPPED;
  }
}

}  // namespace

ControlTask::ControlTask(const FirmwareConfig& config, std::unique_ptr<flight::FlightStack> stack,
                         std::optional<link::Key> mavlink_key, LatestValue<OdometryPose>* poses,
                         LatestValue<CommandMail>* commands,
                         LatestValue<flight_status_t>* flight_status,
                         SharedPoseHistory* pose_history, const StopToken* stop)
    : config_(config),
      stack_(std::move(stack)),
      mavlink_(config.flight.backend == "mavlink"),
      mavlink_key_(std::move(mavlink_key)),
      poses_(poses),
      commands_(commands),
      flight_status_(flight_status),
      pose_history_(pose_history),
      stop_(stop),
      pose_age_us_(std::llround(config.flight.lockstep_pose_age_s * 1e6)) {
  command_.vehicle_id = config.vehicle.id;
}

void ControlTask::applyScheduling() const {
  const FlightConfig& f = config_.flight;
  if (f.rt_priority > 0) {
    sched_param param{};
    param.sched_priority = f.rt_priority;
    if (const int err = pthread_setschedparam(pthread_self(), SCHED_FIFO, &param); err != 0) {
      spdlog::warn("control: SCHED_FIFO priority {} not allowed ({}): the control task runs at "
                   "the default policy (the kinfly-fw unit grants it with LimitRTPRIO, "
                   "docs/flight.md)",
                   f.rt_priority, std::strerror(err));
    } else {
      spdlog::info("control: SCHED_FIFO priority {}", f.rt_priority);
    }
  }
  if (f.cpu >= 0) {
    cpu_set_t set;
    CPU_ZERO(&set);
    CPU_SET(f.cpu, &set);
    if (const int err = pthread_setaffinity_np(pthread_self(), sizeof(set), &set); err != 0) {
      spdlog::warn("control: cannot pin the control task to core {} ({}): it runs on any",
                   f.cpu, std::strerror(err));
    } else {
      spdlog::info("control: pinned to core {}", f.cpu);
    }
  }
}

void ControlTask::run() {
  applyScheduling();
  if (!mavlink_) {
    publisher_.emplace("control", controlUrl(config_), config_.vehicle.id, [this](lcm::LCM& lcm) {
      lcm_subscription_t* imu =
          lcm_subscribe(lcm.getUnderlyingLCM(),
                        link::channelName(link::Channel::kImu, config_.vehicle.id).c_str(),
                        &ControlTask::onImu, this);
      lcm_subscription_set_queue_capacity(imu, kImuQueueMessages);
    });
  }
  spdlog::info("control: {} backend, IMU from {} at {:.0f} Hz, position loop at {:.0f} Hz",
               config_.flight.backend, config_.flight.imu, stack_->params().rate_hz,
               stack_->params().position.rate_hz);
  const double silent_after_s = 2.0 / stack_->params().rate_hz;
  if (mavlink_) {
    auto opened = actuators::Autopilot::open(config_.flight.autopilotParams(),
                                             config_.flight.mavlink_url,
                                             config_.flight.mavlink_baud, mavlink_key_);
    if (!opened.ok()) {  // the configuration's check let it through: a bug, said so
      spdlog::error("control: {}: the control task stops", opened.status().message());
      return;
    }
    autopilot_ = *std::move(opened);
    spdlog::info("control: autopilot link on {}", config_.flight.mavlink_url);
  }
  Clock::time_point next_idle_tick = Clock::now();
  while (!stop_->stopRequested()) {
    if (mavlink_) {
      serveAutopilot();
    } else if (!publisher_->handle(kHandleTimeoutMs)) {
      publisher_->maintain();
      std::this_thread::sleep_for(std::chrono::milliseconds(kHandleTimeoutMs));
    }
    // The IMU gone quiet: the stack still ticks, on the IMU's clock carried on by the steady
    // clock, so that its IMU-lost failsafe acts (a stack ticked only by samples never would).
    if (last_imu_utime_ >= 0) {
      // A lockstep simulator's pauses are not silence: its next sample carries its time on.
      if (config_.flight.lockstep) continue;
      const double silent_s = secondsSince(last_imu_arrival_);
      if (silent_s > silent_after_s) {
        ++summary_.silent_ticks;
        tick(last_imu_utime_ + static_cast<int64_t>(silent_s * 1e6));
      }
    } else if (Clock::now() >= next_idle_tick) {
      // No IMU yet (the simulator not started, the autopilot not heard): the ground's commands
      // still get their answer, and the autopilot's loss is still seen, on the wall clock.
      // Disarmed without an IMU, nothing in the stack depends on that clock.
      ++summary_.silent_ticks;
      tick(link::wallClockUtime());
      next_idle_tick = Clock::now() + std::chrono::milliseconds(kIdleTickMs);
    }
  }
  summary_.estimator_started = stack_->estimator().initialised();
  const flight::EstimatorHealth health = stack_->estimator().health();
  summary_.baro_fused = health.baro_fused;
  summary_.baro_rejected = health.baro_rejected_gate;
  summary_.mode = stack_->modes().mode();
  summary_.modes = stack_->modes().counters();
  if (autopilot_) summary_.autopilot = autopilot_->counters();
}

void ControlTask::serveAutopilot() {
  const double now_s = steadySeconds();
  const int samples = autopilot_->receive(kHandleTimeoutMs, now_s);
  for (int i = 0; i < samples; ++i) takeImu(autopilot_->imu(i));
  // Heartbeat, stream requests and the handshake go out whether or not the IMU runs yet.
  autopilot_->send(autopilot_setpoint_, steadySeconds());
}

Pose ControlTask::cameraPose(const flight::EstimatorState& state) const {
  Pose T_world_body = Pose::Identity();
  T_world_body.linear() = state.q_world_body.toRotationMatrix();
  T_world_body.translation() = state.p_world_body_m;
  return T_world_body * stack_->params().estimator.T_body_cam;
}

void ControlTask::onImu(const lcm_recv_buf_t* message, const char*, void* self) {
  static_cast<ControlTask*>(self)->handleImu(message);
}

void ControlTask::handleImu(const lcm_recv_buf_t* message) {
  if (!link::decodeMessage(message->data, message->data_size, link::DecodeBounds(), &imu_).ok() ||
      imu_.vehicle_id != config_.vehicle.id) {
    ++summary_.imu_rejected;
    return;
  }
  flight::ImuSample sample;
  sample.utime = imu_.utime;
  for (int i = 0; i < 3; ++i) {
    sample.gyro_rad_s(i) = imu_.angular_velocity_rad_s[i];
    sample.accel_m_s2(i) = imu_.linear_acceleration_m_s2[i];
  }
  if (imu_.has_pressure_altitude) sample.baro_alt_m = imu_.pressure_altitude_m;
  takeImu(sample);
}

void ControlTask::takeImu(const flight::ImuSample& sample) {
  const flight::Estimator& estimator = stack_->estimator();
  const std::optional<Pose> before =
      estimator.initialised() ? std::optional<Pose>(cameraPose(estimator.state())) : std::nullopt;
  if (!stack_->addImu(sample)) {
    ++summary_.imu_rejected;
    return;
  }
  ++summary_.imu_samples;
  // The wall clock of the ticks before the first sample gives way to the IMU's (a simulator's
  // starts anywhere): disarmed without an IMU, nothing of theirs carries over.
  if (last_imu_utime_ < 0) last_tick_utime_ = -1;
  last_imu_utime_ = sample.utime;
  last_imu_arrival_ = Clock::now();
  // Before the tick, whose rotor command a lockstep simulator waits for before it sends the next
  // depth frame: the odometry then finds this sample's pose for the frame's prior. The track
  // takes the sample's prediction only: the tick's fusions and resets move the estimate, not
  // the camera.
  if (pose_history_ != nullptr && before) {
    const Pose& T_track_cam = predicted_.step(*before, cameraPose(estimator.state()));
    // Never waits for the odometry, which holds the lock for a lookup: a sample it meets held
    // is left out (the history interpolates across it). A lockstep flight's odometry runs
    // beside this task (flight.lockstep_pose_age_s): there every sample waits its turn, so that
    // the history, and the prior, are the same on any machine.
    std::unique_lock<std::mutex> lock(pose_history_->mutex, std::defer_lock);
    if (config_.flight.lockstep) lock.lock(); else static_cast<void>(lock.try_lock());
    if (lock.owns_lock()) pose_history_->history.add(sample.utime, T_track_cam);
  }
  tick(sample.utime);
}

void ControlTask::tick(int64_t utime) {
  // Never back in time: a tick of a silent IMU, carried on by the steady clock, can run ahead of
  // the stamp of a sample that then arrives late, and the modes' timers (landed for a second,
  // the tilt held beyond its limit) take a time before their start as long ago.
  utime = std::max(utime, last_tick_utime_);
  const int64_t previous_tick_utime = last_tick_utime_;
  last_tick_utime_ = utime;
  // Fetched early (flight.lockstep_pose_age_s), a pose waits for its age: it is fused at the
  // same simulated instant however fast the odometry was. Without an age nothing waits, nor
  // compares the camera's stamps with the IMU's (a drone's may run on other clocks).
  if (!pose_held_) {
    pose_held_ = poses_->fetch();
    // Its due sample already ticked without it: the flight no longer fuses it at one instant.
    // (Ticks on the wall clock, before the first IMU sample, are no samples.)
    if (pose_held_ && pose_age_us_ > 0 && last_imu_utime_ >= 0 &&
        previous_tick_utime >= poses_->front().utime + pose_age_us_) {
      if (summary_.poses_late++ == 0)
        spdlog::warn("control: lockstep: the pose of the frame captured at {} us came after its "
                     "age ({:.3f} s) had passed: is the simulator's --pose-age-ms larger than "
                     "flight.lockstep_pose_age_s? (counted in the summary)",
                     poses_->front().utime, config_.flight.lockstep_pose_age_s);
    }
  }
  if (pose_held_ && (pose_age_us_ == 0 || utime >= poses_->front().utime + pose_age_us_)) {
    pose_held_ = false;
    const flight::AnchoredVision::Inputs vision = anchored_.take(poses_->front());
    if (vision.reset) {
      if (stack_->applyReset(*vision.reset)) {
        ++summary_.resets;
        spdlog::info("control: the ground's anchor jumped (reset {}): estimator reset",
                     vision.reset->reset_counter);
      } else {
        ++summary_.resets_rejected;
      }
    }
    const flight::VisionOutcome outcome = stack_->addVision(vision.vision);
    if (outcome == flight::VisionOutcome::kFused) {
      ++summary_.poses_fused;
    } else if (outcome == flight::VisionOutcome::kResetToPose) {
      ++summary_.pose_resets;
      spdlog::warn("control: the odometry and the IMU disagreed for {} poses in a row: estimator "
                   "reset to the odometry's pose (reset {})",
                   stack_->params().estimator.vision_reset_rejections, summary_.pose_resets);
    } else {
      ++summary_.poses_rejected;
    }
    // The autopilot's EKF gets every pose (it gates them its own way), as the body's in world.
    const flight::Estimator& estimator = stack_->estimator();
    if (autopilot_ && estimator.initialised()) {
      const flight::EstimatorParams& p = stack_->params().estimator;
      autopilot_->sendVision(vision.vision.utime,
                             estimator.T_world_odom() * vision.vision.T_odom_cam *
                                 p.T_body_cam.inverse(),
                             p.vision_pos_std_m * p.vision_pos_std_m,
                             p.vision_att_std_rad * p.vision_att_std_rad,
                             poses_->front().reset_counter);
    }
  }
  flight::TickInputs in;
  in.utime = utime;
  if (mavlink_) in.autopilot = autopilot_->state(steadySeconds());
  int64_t command_id = -1;
  if (commands_->fetch()) {
    const CommandMail& mail = commands_->front();
    command_id = mail.command_id;
    // The mission is copied in here, between the IMU's sample and the tick: the one allocation
    // of the control thread after its start, once per mission command.
    if (mail.mission) {
      if (const Status loaded = stack_->loadMission(*mail.mission); !loaded.ok()) {
        spdlog::warn("control: command {}: {}", command_id, loaded.message());
      }
    }
    in.command = mail.command;
  }
  const flight::TickOutput out = stack_->tick(in);
  ++summary_.ticks;
  if (out.modes.command) {
    const flight::CommandResult& result = *out.modes.command;
    last_command_id_ = command_id;
    last_command_ = result;
    if (result.accepted()) {
      spdlog::info("control: command {} ({}) accepted", command_id,
                   flight::toString(result.kind));
    } else {
      spdlog::warn("control: command {} ({}) refused: {}", command_id,
                   flight::toString(result.kind), flight::toString(result.refusal));
    }
  }
  for (int i = 0; i < out.modes.event_count; ++i) {
    const flight::FlightEvent& event = out.modes.events[i];
    if (flight::isFailsafe(event.reason)) {
      spdlog::warn("control: {}: {} -> {}", flight::toString(event.reason),
                   flight::toString(event.from), flight::toString(event.to));
    } else {
      spdlog::info("control: {}: {} -> {}", flight::toString(event.reason),
                   flight::toString(event.from), flight::toString(event.to));
    }
  }
  sendToBackend(out, utime);
  reportStatus(out, utime);
}

void ControlTask::reportStatus(const flight::TickOutput& out, int64_t utime) {
  // A tick earlier than the last report is a clock that started again (the IMU's first sample
  // after the wall clock's ticks): report at once.
  if (flight_status_ == nullptr ||
      (utime >= last_status_utime_ && utime - last_status_utime_ < kFlightStatusPeriodUs &&
       last_status_utime_ >= 0))
    return;
  last_status_utime_ = utime;
  // The wire's constants are the library's enums in the same order.
  static_assert(flight_status_t::MODE_HANDED_OVER ==
                static_cast<int>(flight::FlightMode::kHandedOver));
  static_assert(flight_status_t::REFUSED_AUTOPILOT_NOT_READY ==
                static_cast<int>(flight::CommandRefusal::kAutopilotNotReady));
  static_assert(flight_command_t::LAND == static_cast<int>(flight::CommandKind::kLand));
  const flight::Estimator& estimator = stack_->estimator();
  const flight::EstimatorState state = estimator.state();
  const flight::EstimatorHealth health = estimator.health();
  const flight::FlightCounters& counters = stack_->modes().counters();
  flight_status_t& s = flight_status_->back();
  s.utime = utime;
  s.vehicle_id = config_.vehicle.id;
  s.mode = static_cast<int8_t>(out.modes.mode);
  s.command_id = last_command_id_;
  s.command_kind = static_cast<int8_t>(last_command_.kind);
  s.command_result = static_cast<int8_t>(last_command_.refusal);
  s.estimator_initialised = health.initialised;
  s.estimator_diverged = health.diverged;
  const Eigen::Quaterniond q = state.q_world_body.normalized();
  const double q_xyzw[4] = {q.x(), q.y(), q.z(), q.w()};
  for (int i = 0; i < 3; ++i) {
    s.p_world_m[i] = state.p_world_body_m(i);
    s.v_world_m_s[i] = state.v_world_body_m_s(i);
    s.setpoint_world_m[i] = out.setpoint.p_world_m(i);
    s.setpoint_v_world_m_s[i] = out.setpoint.v_world_m_s(i);
  }
  std::copy(q_xyzw, q_xyzw + 4, s.q_world_body_xyzw);
  s.position_std_m = health.initialised ? static_cast<float>(std::sqrt(
                                              estimator.covariance().diagonal().head<3>().maxCoeff()))
                                        : 0.0f;
  s.vision_age_s = static_cast<float>(health.time_since_vision_s);
  s.vision_fused = health.vision_fused_count;
  s.vision_rejected = health.vision_rejected_gate + health.vision_rejected_too_old +
                      health.vision_rejected_out_of_order + health.vision_rejected_invalid;
  s.baro_fused = health.baro_fused;
  s.baro_rejected = health.baro_rejected_gate;
  s.reset_counter = health.reset_counter;
  s.resets = health.resets;
  link::writePose(estimator.T_world_odom(), &s.T_world_map);
  s.setpoint_yaw_rad = static_cast<float>(out.setpoint.yaw_rad);
  s.thrust_n = static_cast<float>(out.position.thrust_n);
  s.rotors = out.rotors == flight::RotorCommand::kNone ? flight_status_t::ROTORS_NONE
                                                        : rotorState(out.rotors);
  for (int i = 0; i < 4; ++i)
    s.rotor_speed_rad_s[i] = static_cast<float>(out.mixer.rotor_speed_rad_s(i));
  s.mode_changes = counters.mode_changes;
  s.commands_accepted = counters.commands_accepted;
  s.commands_refused = counters.commands_refused;
  s.failsafe_vision_lost = counters.vision_lost;
  s.failsafe_estimator_diverged = counters.estimator_diverged;
  s.failsafe_attitude_limit = counters.attitude_limit;
  s.failsafe_imu_lost = counters.imu_lost;
  s.failsafe_geofence = counters.geofence;
  s.failsafe_autopilot_lost = counters.autopilot_lost;
  const flight::AutopilotInputs ap =
      mavlink_ ? autopilot_->state(steadySeconds()) : flight::AutopilotInputs();
  s.autopilot_used = ap.used;
  s.autopilot_alive = ap.alive;
  s.autopilot_armed = ap.armed;
  s.autopilot_offboard = ap.offboard;
  flight_status_->publish();
}

void ControlTask::sendToBackend(const flight::TickOutput& out, int64_t utime) {
  if (mavlink_) {
    // Body rates and thrust: the autopilot runs its own rate loop, so the attitude loop here is
    // the geometric law's P part whatever flight.attitude_law says (the LQR gives moments).
    actuators::AutopilotSetpoint& sp = autopilot_setpoint_;
    const flight::EstimatorState& state = stack_->estimator().state();
    sp.want = autopilotWant(out.rotors);
    sp.q_world_body_sp = out.position.q_world_body_sp;
    sp.rate_body_rad_s = flight::geometricRateSetpointRadS(
        stack_->params().attitude.geometric, state.q_world_body, sp.q_world_body_sp);
    sp.thrust_ratio = out.position.thrust_n / stack_->vehicle().weightN();
    if (autopilot_->attitude() && stack_->estimator().initialised()) {
      summary_.max_tilt_vs_autopilot_rad =
          std::max(summary_.max_tilt_vs_autopilot_rad,
                   tiltBetweenRad(*autopilot_->attitude(), state.q_world_body));
    }
    autopilot_->send(sp, steadySeconds());
    return;
  }
  if (out.rotors == flight::RotorCommand::kNone) return;
  command_.utime = utime;
  command_.state = rotorState(out.rotors);
  for (int i = 0; i < 4; ++i)
    command_.rotor_speed_rad_s[i] = static_cast<float>(out.mixer.rotor_speed_rad_s(i));
  command_.flight_mode = static_cast<int8_t>(out.modes.mode);
  command_.tick = summary_.ticks;
  if (publisher_->publish(link::Channel::kMotorCommand, command_)) {
    ++summary_.commands_sent;
  } else {
    ++summary_.commands_unsent;
  }
}

}  // namespace kinfly::fw
