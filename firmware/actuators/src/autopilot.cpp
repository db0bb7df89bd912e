#include "kinfly/actuators/autopilot.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <thread>
#include <utility>

#include "kinfly/core/range_check.h"
#include "mavlink/common/mavlink.h"

namespace kinfly::actuators {
namespace {

constexpr mavlink_channel_t kChannel = MAVLINK_COMM_0;
constexpr double kHeartbeatPeriodS = 1.0;
// [s] between attempts to open a port that failed again.
constexpr double kReopenS = 1.0;
// PX4's custom mode: main mode in bits 16-23; offboard is 6. ArduPilot Copter: GUIDED_NOGPS (20)
// takes attitude and rate setpoints without a position of its own.
constexpr uint32_t kPx4MainModeOffboard = 6;
constexpr uint32_t kArduCopterGuidedNoGps = 20;
// MAVLink signing's clock: 10 µs units since 2015-01-01 00:00:00 UTC.
constexpr int64_t kSigningEpochUnixUs = 1420070400LL * 1000000LL;
constexpr uint16_t kAllImuFields = 0x3F;  // HIGHRES_IMU fields_updated: x/y/z acc and gyro
constexpr uint16_t kPressureAltField = 1 << 11;  // ... and pressure_alt
constexpr double kMilliG = 9.80665e-3;   // [m/s² per mG] SCALED_IMU
constexpr double kNoReading = std::numeric_limits<double>::quiet_NaN();  // ImuSample::baro_alt_m

const char* autopilotName(int type) {
  switch (type) {
    case MAV_AUTOPILOT_PX4: return "PX4";
    case MAV_AUTOPILOT_ARDUPILOTMEGA: return "ArduPilot";
    default: return "an autopilot";
  }
}

}  // namespace

int64_t ClockMap::map(int64_t remote_us, int64_t arrival_utime) {
  const int64_t delay_offset = arrival_utime - remote_us;
  // A restart: its time fell back, or (after an outage longer than its uptime before) the
  // sample would have been on its way for longer than any link delays one, or than this
  // computer stalls for without the IMU-lost failsafe long since acting.
  if (!have_offset_ || remote_us + offset_us_ < last_utime_ - kRestartUs ||
      delay_offset - offset_us_ > kLateRestartUs) {
    offset_us_ = delay_offset;
    have_offset_ = true;
  } else {
    const auto grown = static_cast<int64_t>(std::ceil(
        kDrift * static_cast<double>(arrival_utime - last_arrival_utime_)));
    offset_us_ = std::min(offset_us_ + grown, delay_offset);
  }
  last_arrival_utime_ = arrival_utime;
  // A smaller offset can map a sample before the last: time must increase for the estimator.
  last_utime_ = std::max(remote_us + offset_us_, last_utime_ + 1);
  return last_utime_;
}

Status AutopilotParams::validate() const {
  return firstError(outOfRange("mavlink.system_id", system_id, 1, 255),
                    outOfRange("mavlink.component_id", component_id, 1, 255),
                    outOfRange("mavlink.heartbeat_timeout_s", heartbeat_timeout_s, 0, 10,
                               Bound::kOpen),
                    outOfRange("mavlink.setpoint_rate_hz", setpoint_rate_hz, 100, 1000),
                    outOfRange("mavlink.imu_rate_hz", imu_rate_hz, 50, 1000),
                    outOfRange("mavlink.attitude_rate_hz", attitude_rate_hz, 1, 500),
                    outOfRange("mavlink.request_interval_s", request_interval_s, 0.05, 10),
                    outOfRange("mavlink.prestream_s", prestream_s, 0, 10),
                    outOfRange("mavlink.hover_thrust", hover_thrust, 0.05, 0.95));
}

struct Autopilot::Mavlink {
  mavlink_message_t rx{};
  mavlink_status_t rx_status{};
  mavlink_message_t tx{};
  mavlink_signing_t signing{};
  mavlink_signing_streams_t streams{};
  uint8_t buffer[MAVLINK_MAX_PACKET_LEN]{};
};

StatusOr<std::unique_ptr<Autopilot>> Autopilot::open(const AutopilotParams& params,
                                                     const std::string& url, int baud,
                                                     const std::optional<link::Key>& key) {
  if (Status valid = params.validate(); !valid.ok()) return valid;
  if (Status form = MavlinkPort::checkUrl(url); !form.ok()) return form;
  std::unique_ptr<Autopilot> autopilot(new Autopilot(params, url, baud));
  Mavlink& m = *autopilot->mavlink_;
  // The channel's status holds the parser's state, our sequence number and the signing.
  mavlink_status_t* status = mavlink_get_channel_status(kChannel);
  *status = mavlink_status_t{};
  if (key) {
    std::memcpy(m.signing.secret_key, key->bytes.data(), sizeof(m.signing.secret_key));
    m.signing.link_id = static_cast<uint8_t>(kChannel);
    m.signing.flags = MAVLINK_SIGNING_FLAG_SIGN_OUTGOING;
    m.signing.timestamp =
        static_cast<uint64_t>((link::wallClockUtime() - kSigningEpochUnixUs) / 10);
    // No accept_unsigned_callback: an unsigned or wrongly signed frame is dropped and counted,
    // whatever its message (PX4 lets some through unsigned; kinfly has nothing to gain).
    status->signing = &m.signing;
    status->signing_streams = &m.streams;
    spdlog::info("mavlink: {}: MAVLink 2, signed (key {:08x})", url, key->id);
  } else {
    spdlog::warn("mavlink: {}: MAVLink 2 unsigned (no flight.mavlink_key): anyone on this link "
                 "can command the autopilot, and one that requires signing ignores us",
                 url);
  }
  // Opened now if it can be; if not (a USB adapter not there yet), by receive(), every second.
  autopilot->reopen(0.0);
  return autopilot;
}

Autopilot::Autopilot(const AutopilotParams& params, const std::string& url, int baud)
    : params_(params), url_(url), baud_(baud), mavlink_(std::make_unique<Mavlink>()) {}

bool Autopilot::reopen(double now_s) {
  if (now_s < next_reopen_s_) return false;
  auto port = MavlinkPort::open(url_, baud_);
  if (!port.ok()) {
    // Said once for each time the port is missing, not every second.
    if (!reopen_failing_)
      spdlog::error("mavlink: {} (trying again every {:.0f} s)", port.status().message(),
                    kReopenS);
    reopen_failing_ = true;
    next_reopen_s_ = now_s + kReopenS;
    return false;
  }
  port_ = std::move(*port);
  reopen_failing_ = false;
  spdlog::info("mavlink: {} open", url_);
  return true;
}

Autopilot::~Autopilot() {
  // The channel's status points into mavlink_.
  mavlink_status_t* status = mavlink_get_channel_status(kChannel);
  status->signing = nullptr;
  status->signing_streams = nullptr;
}

bool Autopilot::alive(double now_s) const {
  return heard_ && last_heartbeat_s_ >= 0.0 &&
         now_s - last_heartbeat_s_ <= params_.heartbeat_timeout_s;
}

flight::AutopilotInputs Autopilot::state(double now_s) const {
  flight::AutopilotInputs in;
  in.used = true;
  in.alive = alive(now_s);
  in.armed = in.alive && armed_;
  in.offboard = in.alive && offboard_;
  return in;
}

int Autopilot::receive(int timeout_ms, double now_s) {
  imu_count_ = 0;
  if (!port_ && !reopen(now_s)) {
    std::this_thread::sleep_for(std::chrono::milliseconds(timeout_ms));
    return 0;
  }
  uint8_t bytes[2048];
  const ssize_t n = port_->read(bytes, sizeof(bytes), timeout_ms);
  if (n < 0) {
    // A device that went away (a USB serial adapter unplugged): closed, and opened again by
    // its path every kReopenS; its heartbeat times out meanwhile (the autopilot-lost failsafe).
    ++counters_.port_errors;
    spdlog::error("mavlink: reading {} failed: the autopilot link is down; opening it again "
                  "every {:.0f} s",
                  url_, kReopenS);
    port_.reset();
    next_reopen_s_ = now_s + kReopenS;
    return 0;
  }
  const int64_t arrival_utime = link::wallClockUtime();
  Mavlink& m = *mavlink_;
  for (ssize_t i = 0; i < n; ++i) {
    switch (mavlink_frame_char(kChannel, bytes[i], &m.rx, &m.rx_status)) {
      case MAVLINK_FRAMING_OK: handle(now_s, arrival_utime); break;
      case MAVLINK_FRAMING_BAD_SIGNATURE:
        if (counters_.bad_signature++ == 0)
          spdlog::warn("mavlink: dropped a frame unsigned or signed with another key "
                       "(flight.mavlink_key must hold the autopilot's); the rest are counted");
        break;
      case MAVLINK_FRAMING_BAD_CRC: ++counters_.bad_crc; break;
      default: break;
    }
  }
  return imu_count_;
}

void Autopilot::handle(double now_s, int64_t arrival_utime) {
  const mavlink_message_t& msg = mavlink_->rx;
  if (msg.msgid == MAVLINK_MSG_ID_HEARTBEAT && !heard_) {
    mavlink_heartbeat_t hb;
    mavlink_msg_heartbeat_decode(&msg, &hb);
    // GCSs, companions and gimbals send INVALID.
    if (hb.autopilot != MAV_AUTOPILOT_INVALID) {
      heard_ = true;
      target_system_ = msg.sysid;
      target_component_ = msg.compid;
      autopilot_type_ = hb.autopilot;
      spdlog::info("mavlink: heard {} (system {}, component {})", autopilotName(hb.autopilot),
                   msg.sysid, msg.compid);
      if (hb.autopilot != MAV_AUTOPILOT_PX4 && hb.autopilot != MAV_AUTOPILOT_ARDUPILOTMEGA)
        spdlog::warn("mavlink: autopilot type {}: kinfly knows the offboard modes of PX4 and "
                     "ArduPilot only, so it will never fly it",
                     hb.autopilot);
    }
  }
  if (!heard_ || msg.sysid != target_system_ || msg.compid != target_component_) {
    ++counters_.other_source;
    return;
  }
  // Framed, signed (with a key) and the autopilot's: where replies go on a udpin port.
  port_->keepPeer();
  switch (msg.msgid) {
    case MAVLINK_MSG_ID_HEARTBEAT: {
      mavlink_heartbeat_t hb;
      mavlink_msg_heartbeat_decode(&msg, &hb);
      ++counters_.heartbeats;
      if (!alive(now_s)) spdlog::info("mavlink: {} alive", autopilotName(autopilot_type_));
      last_heartbeat_s_ = now_s;
      const bool armed = (hb.base_mode & MAV_MODE_FLAG_SAFETY_ARMED) != 0;
      const bool offboard =
          autopilot_type_ == MAV_AUTOPILOT_PX4
              ? ((hb.custom_mode >> 16) & 0xFF) == kPx4MainModeOffboard
              : autopilot_type_ == MAV_AUTOPILOT_ARDUPILOTMEGA &&
                    hb.custom_mode == kArduCopterGuidedNoGps;
      if (armed != armed_) spdlog::info("mavlink: autopilot {}", armed ? "armed" : "disarmed");
      if (offboard != offboard_)
        spdlog::info("mavlink: autopilot {} offboard (custom mode {:#x})",
                     offboard ? "in" : "out of", hb.custom_mode);
      armed_ = armed;
      offboard_ = offboard;
      break;
    }
    case MAVLINK_MSG_ID_HIGHRES_IMU: {
      mavlink_highres_imu_t imu;
      mavlink_msg_highres_imu_decode(&msg, &imu);
      highres_seen_ = true;
      last_imu_s_ = now_s;
      if ((imu.fields_updated & kAllImuFields) != kAllImuFields) {
        ++counters_.imu_rejected;
        break;
      }
      addImu(imu.time_usec, Eigen::Vector3d(imu.xgyro, imu.ygyro, imu.zgyro),
             Eigen::Vector3d(imu.xacc, imu.yacc, imu.zacc),
             (imu.fields_updated & kPressureAltField) != 0 ? imu.pressure_alt : kNoReading,
             arrival_utime);
      break;
    }
    case MAVLINK_MSG_ID_SCALED_IMU: {
      if (highres_seen_) break;  // the same sensor, coarser
      mavlink_scaled_imu_t imu;
      mavlink_msg_scaled_imu_decode(&msg, &imu);
      last_imu_s_ = now_s;
      addImu(static_cast<uint64_t>(imu.time_boot_ms) * 1000,
             Eigen::Vector3d(imu.xgyro, imu.ygyro, imu.zgyro) * 1e-3,
             Eigen::Vector3d(imu.xacc, imu.yacc, imu.zacc) * kMilliG, kNoReading, arrival_utime);
      break;
    }
    case MAVLINK_MSG_ID_ATTITUDE_QUATERNION: {
      mavlink_attitude_quaternion_t att;
      mavlink_msg_attitude_quaternion_decode(&msg, &att);
      const Eigen::Quaterniond q(att.q1, att.q2, att.q3, att.q4);  // MAVLink's (w, x, y, z)
      if (std::isfinite(q.norm()) && q.norm() > 0.5) {
        attitude_ = q.normalized();
        ++counters_.attitudes;
      }
      break;
    }
    case MAVLINK_MSG_ID_COMMAND_ACK: {
      mavlink_command_ack_t ack;
      mavlink_msg_command_ack_decode(&msg, &ack);
      if (ack.target_system != 0 && ack.target_system != params_.system_id) break;
      if (ack.result == MAV_RESULT_ACCEPTED) {
        ++counters_.commands_accepted;
      } else if (ack.result != MAV_RESULT_IN_PROGRESS) {
        ++counters_.commands_refused;
        spdlog::warn("mavlink: the autopilot refused command {} (result {})", ack.command,
                     ack.result);
      }
      break;
    }
    default: break;
  }
}

void Autopilot::addImu(uint64_t remote_us, const Eigen::Vector3d& gyro_rad_s,
                       const Eigen::Vector3d& accel_m_s2, double baro_alt_m,
                       int64_t arrival_utime) {
  if (!gyro_rad_s.allFinite() || !accel_m_s2.allFinite() || std::isinf(baro_alt_m) ||
      imu_count_ == static_cast<int>(imu_.size())) {
    ++counters_.imu_rejected;
    return;
  }
  flight::ImuSample& sample = imu_[static_cast<size_t>(imu_count_++)];
  sample.utime = clock_.map(static_cast<int64_t>(remote_us), arrival_utime);
  sample.gyro_rad_s = gyro_rad_s;
  sample.accel_m_s2 = accel_m_s2;
  sample.baro_alt_m = baro_alt_m;
  ++counters_.imu_samples;
}

bool Autopilot::sendMessage() {
  Mavlink& m = *mavlink_;
  const uint16_t len = mavlink_msg_to_send_buffer(m.buffer, &m.tx);
  if (port_ && port_->write(m.buffer, len)) return true;
  ++counters_.send_failures;
  return false;
}

void Autopilot::sendCommand(uint16_t command, float p1, float p2, float p3, float p4) {
  mavlink_msg_command_long_pack_chan(
      static_cast<uint8_t>(params_.system_id), static_cast<uint8_t>(params_.component_id),
      kChannel, &mavlink_->tx, static_cast<uint8_t>(target_system_),
      static_cast<uint8_t>(target_component_), command, 0, p1, p2, p3, p4, 0.0f, 0.0f, 0.0f);
  sendMessage();
}

void Autopilot::send(const AutopilotSetpoint& setpoint, double now_s) {
  const auto sys = static_cast<uint8_t>(params_.system_id);
  const auto comp = static_cast<uint8_t>(params_.component_id);
  Mavlink& m = *mavlink_;
  if (now_s - last_heartbeat_sent_s_ >= kHeartbeatPeriodS) {
    mavlink_msg_heartbeat_pack_chan(sys, comp, kChannel, &m.tx, MAV_TYPE_ONBOARD_CONTROLLER,
                                    MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE);
    sendMessage();
    last_heartbeat_sent_s_ = now_s;
  }
  const bool alive_now = alive(now_s);
  if (was_alive_ && !alive_now) {
    ++counters_.lost;
    spdlog::warn("mavlink: {} lost: no heartbeat for {:.1f} s", autopilotName(autopilot_type_),
                 now_s - last_heartbeat_s_);
  }
  was_alive_ = alive_now;
  if (!alive_now) {
    streaming_since_s_ = -1.0;
    return;
  }
  const double interval_s = params_.request_interval_s;
  // Whenever its IMU is not coming (at the start, after the autopilot restarted), ask for the
  // streams kinfly flies on.
  if (now_s - last_imu_s_ >= interval_s && now_s - last_stream_request_s_ >= interval_s) {
    sendCommand(MAV_CMD_SET_MESSAGE_INTERVAL, MAVLINK_MSG_ID_HIGHRES_IMU,
                static_cast<float>(1e6 / params_.imu_rate_hz), 0.0f);
    sendCommand(MAV_CMD_SET_MESSAGE_INTERVAL, MAVLINK_MSG_ID_ATTITUDE_QUATERNION,
                static_cast<float>(1e6 / params_.attitude_rate_hz), 0.0f);
    last_stream_request_s_ = now_s;
  }

  // The autopilot took kinfly's setpoints since kinfly armed; once it has, kinfly never asks
  // for offboard or arming again in this arming: leaving them is the pilot's or the autopilot's
  // choice (a mode switch, its own failsafe or disarm), which the flight modes answer by handing
  // over or disarming on their next tick. Only an autopilot kinfly flew is ever disarmed.
  if (armed_ && offboard_ &&
      (setpoint.want == AutopilotWant::kIdle || setpoint.want == AutopilotWant::kFly))
    flown_ = true;
  switch (setpoint.want) {
    case AutopilotWant::kNothing:
      streaming_since_s_ = -1.0;
      flown_ = false;
      return;
    case AutopilotWant::kDisarm:
      streaming_since_s_ = -1.0;
      if (!armed_) flown_ = false;
      if (flown_ && now_s - last_disarm_request_s_ >= interval_s) {
        sendCommand(MAV_CMD_COMPONENT_ARM_DISARM, 0.0f, 0.0f, 0.0f);
        ++counters_.disarm_requests;
        last_disarm_request_s_ = now_s;
      }
      return;
    case AutopilotWant::kIdle:
    case AutopilotWant::kFly: break;
  }
  if (now_s - last_setpoint_s_ >= 1.0 / params_.setpoint_rate_hz) {
    const bool idle = setpoint.want == AutopilotWant::kIdle;
    const Eigen::Quaterniond& q = setpoint.q_world_body_sp;
    const float q_wxyz[4] = {static_cast<float>(q.w()), static_cast<float>(q.x()),
                             static_cast<float>(q.y()), static_cast<float>(q.z())};
    const Eigen::Vector3d rate = idle ? Eigen::Vector3d::Zero() : setpoint.rate_body_rad_s;
    const double thrust =
        idle ? 0.0 : std::clamp(params_.hover_thrust * setpoint.thrust_ratio, 0.0, 1.0);
    const int64_t remote_us = clock_.toRemote(link::wallClockUtime());
    mavlink_msg_set_attitude_target_pack_chan(
        sys, comp, kChannel, &m.tx, static_cast<uint32_t>(remote_us / 1000),
        static_cast<uint8_t>(target_system_), static_cast<uint8_t>(target_component_),
        ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE, q_wxyz, static_cast<float>(rate.x()),
        static_cast<float>(rate.y()), static_cast<float>(rate.z()), static_cast<float>(thrust));
    if (sendMessage()) ++counters_.setpoints_sent;
    last_setpoint_s_ = now_s;
    if (streaming_since_s_ < 0.0) streaming_since_s_ = now_s;
  }
  // The handshake, on the ground only (kIdle): offboard once the setpoints have streamed a
  // while, then arming.
  if (setpoint.want != AutopilotWant::kIdle || flown_) return;
  if (!offboard_) {
    if (streaming_since_s_ >= 0.0 && now_s - streaming_since_s_ >= params_.prestream_s &&
        now_s - last_mode_request_s_ >= interval_s) {
      const bool px4 = autopilot_type_ == MAV_AUTOPILOT_PX4;
      sendCommand(MAV_CMD_DO_SET_MODE, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                  static_cast<float>(px4 ? kPx4MainModeOffboard : kArduCopterGuidedNoGps),
                  0.0f);
      ++counters_.mode_requests;
      last_mode_request_s_ = now_s;
    }
  } else if (!armed_ && now_s - last_arm_request_s_ >= interval_s) {
    sendCommand(MAV_CMD_COMPONENT_ARM_DISARM, 1.0f, 0.0f, 0.0f);
    ++counters_.arm_requests;
    last_arm_request_s_ = now_s;
  }
}

void Autopilot::sendVision(int64_t capture_utime, const Pose& T_world_body,
                           double position_var_m2, double attitude_var_rad2,
                           int32_t reset_counter) {
  if (!heard_ || !clock_.ready()) return;  // nobody to send to, or no clock to stamp it on
  const Eigen::Vector3d p = T_world_body.translation();
  const Eigen::Quaterniond q(T_world_body.rotation());
  const float q_wxyz[4] = {static_cast<float>(q.w()), static_cast<float>(q.x()),
                           static_cast<float>(q.y()), static_cast<float>(q.z())};
  const float nan = std::numeric_limits<float>::quiet_NaN();
  // The upper triangle of the 6x6 (x, y, z, roll, pitch, yaw) row by row: the diagonal is at
  // 0, 6, 11, 15, 18, 20. Velocity unknown: NaN first, as MAVLink specifies.
  float pose_cov[21] = {};
  for (int i : {0, 6, 11}) pose_cov[i] = static_cast<float>(position_var_m2);
  for (int i : {15, 18, 20}) pose_cov[i] = static_cast<float>(attitude_var_rad2);
  float velocity_cov[21] = {};
  velocity_cov[0] = nan;
  mavlink_msg_odometry_pack_chan(
      static_cast<uint8_t>(params_.system_id), static_cast<uint8_t>(params_.component_id),
      kChannel, &mavlink_->tx,
      static_cast<uint64_t>(std::max<int64_t>(0, clock_.toRemote(capture_utime))),
      MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD, static_cast<float>(p.x()),
      static_cast<float>(p.y()), static_cast<float>(p.z()), q_wxyz, nan, nan, nan, nan, nan, nan,
      pose_cov, velocity_cov, static_cast<uint8_t>(reset_counter & 0xFF),
      MAV_ESTIMATOR_TYPE_VISION, 0);
  if (sendMessage()) ++counters_.odometry_sent;
}

}  // namespace kinfly::actuators
