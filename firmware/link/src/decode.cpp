#include "kinfly/link/decode.h"

#include <cmath>
#include <limits>
#include <type_traits>

#include "kinfly/link/channels.h"
#include "kinfly/link/chunking.h"

namespace kinfly::link {
namespace {

// A signed big-endian integer of 2, 4 or 8 bytes.
int64_t readBigEndian(const uint8_t* p, int bytes) {
  uint64_t v = 0;
  for (int i = 0; i < bytes; ++i) v = (v << 8) | p[i];
  if (bytes == 2) return static_cast<int16_t>(static_cast<uint16_t>(v));
  if (bytes == 4) return static_cast<int32_t>(static_cast<uint32_t>(v));
  return static_cast<int64_t>(v);
}

// Types whose last two fields are a count and an array of that many, `int32_t payload_size;
// byte payload[payload_size];` or an int16 count (a unit test checks the layout against the
// generated encoder): the count's width, 0 for the types without such an array ...
template <class T>
constexpr int kTrailingCountBytes =
    std::is_same_v<T, depth_keyframe_t> || std::is_same_v<T, signed_t> ||
            std::is_same_v<T, flight_command_t>                                  ? 4
    : std::is_same_v<T, keyframe_chunk_t> || std::is_same_v<T, chunk_request_t> ? 2
                                                                                  : 0;
// ... and the bytes of each of its elements: a mission's waypoints are three doubles.
template <class T>
constexpr int kTrailingElementBytes = std::is_same_v<T, flight_command_t> ? 3 * 8 : 1;

template <class T>
int payloadBound(const DecodeBounds& bounds) {
  if constexpr (std::is_same_v<T, depth_keyframe_t>) return bounds.max_keyframe_payload_bytes;
  if constexpr (std::is_same_v<T, keyframe_chunk_t>) return keyframe_chunk_t::MAX_BLOCK_BYTES;
  if constexpr (std::is_same_v<T, chunk_request_t>) return chunk_request_t::MAX_INDICES;
  if constexpr (std::is_same_v<T, flight_command_t>) return flight_command_t::MAX_WAYPOINTS;
  return bounds.max_signed_payload_bytes;
}

DecodeResult fail(DecodeStatus status, std::string detail) { return {status, std::move(detail)}; }

bool finite(const double* v, int n) {
  for (int i = 0; i < n; ++i)
    if (!std::isfinite(v[i])) return false;
  return true;
}

// A pose on the wire: finite, and a quaternion that is unit to well within float rounding of
// whatever produced it.
std::string poseProblem(const pose3d_t& pose) {
  const double* q = pose.orientation_xyzw;
  if (!finite(pose.position_m, 3)) return "position_m is not finite";
  if (!finite(q, 4)) return "orientation_xyzw is not finite";
  const double norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  if (std::abs(norm - 1.0) > pose3d_t::UNIT_QUATERNION_TOLERANCE)
    return "orientation_xyzw is not a unit quaternion (norm " + std::to_string(norm) + ")";
  return {};
}

bool validTracking(int8_t status) {
  return status >= odometry_t::TRACKING_NONE && status <= odometry_t::TRACKING_GIVEN;
}

std::string vehicleProblem(int32_t vehicle_id) {
  if (vehicle_id < 0 || vehicle_id > kMaxVehicleId)
    return "vehicle_id " + std::to_string(vehicle_id) + " outside [0, " +
           std::to_string(kMaxVehicleId) + "]";
  return {};
}

std::string fieldProblem(const depth_keyframe_t& m, const DecodeBounds& bounds) {
  if (auto why = vehicleProblem(m.vehicle_id); !why.empty()) return why;
  const camera_t& c = m.camera;
  if (c.width <= 0 || c.width > bounds.max_width_px || c.height <= 0 ||
      c.height > bounds.max_height_px)
    return "image " + std::to_string(c.width) + "x" + std::to_string(c.height) +
           " outside 1x1.." + std::to_string(bounds.max_width_px) + "x" +
           std::to_string(bounds.max_height_px);
  const float k[4] = {c.fx, c.fy, c.cx, c.cy};
  for (float v : k)
    if (!std::isfinite(v)) return "intrinsics are not finite";
  if (!(c.fx > 0.f) || !(c.fy > 0.f)) return "focal lengths must be positive";
  if (!(m.depth_scale_m > 0.0) || !std::isfinite(m.depth_scale_m))
    return "depth_scale_m must be positive and finite";
  if (m.encoding < depth_keyframe_t::ENCODING_RAW16 ||
      m.encoding > depth_keyframe_t::ENCODING_PALETTE_RVL_ZSTD)
    return "unknown encoding " + std::to_string(m.encoding);
  if (!validTracking(m.tracking_status))
    return "unknown tracking_status " + std::to_string(m.tracking_status);
  if (m.tracking_status != odometry_t::TRACKING_NONE)
    return poseProblem(m.T_world_cam);
  return {};
}

std::string fieldProblem(const odometry_t& m, const DecodeBounds&) {
  if (auto why = vehicleProblem(m.vehicle_id); !why.empty()) return why;
  if (!validTracking(m.tracking_status))
    return "unknown tracking_status " + std::to_string(m.tracking_status);
  if (!std::isfinite(m.inlier_fraction) || m.inlier_fraction < 0.f || m.inlier_fraction > 1.f)
    return "inlier_fraction outside [0, 1]";
  return poseProblem(m.T_world_cam);
}

std::string fieldProblem(const imu_t& m, const DecodeBounds&) {
  if (auto why = vehicleProblem(m.vehicle_id); !why.empty()) return why;
  if (!finite(m.angular_velocity_rad_s, 3) || !finite(m.linear_acceleration_m_s2, 3))
    return "IMU sample is not finite";
  if (m.has_pressure_altitude && !std::isfinite(m.pressure_altitude_m))
    return "pressure_altitude_m is not finite";
  return {};
}

std::string fieldProblem(const motor_command_t& m, const DecodeBounds&) {
  if (auto why = vehicleProblem(m.vehicle_id); !why.empty()) return why;
  if (m.state < motor_command_t::STOPPED || m.state > motor_command_t::FLYING)
    return "unknown state " + std::to_string(m.state);
  for (const float speed : m.rotor_speed_rad_s)
    if (!std::isfinite(speed) || speed < 0.0f) return "a rotor speed is negative or not finite";
  return {};
}

std::string fieldProblem(const ground_truth_t& m, const DecodeBounds&) {
  if (auto why = vehicleProblem(m.vehicle_id); !why.empty()) return why;
  return poseProblem(m.T_world_cam);
}

std::string fieldProblem(const pose_correction_t& m, const DecodeBounds&) {
  if (auto why = vehicleProblem(m.vehicle_id); !why.empty()) return why;
  if (m.keyframe_id < 0) return "keyframe_id is negative";
  if (m.reset_counter < 0) return "reset_counter is negative";
  return poseProblem(m.T_world_cam);
}

std::string fieldProblem(const flight_command_t& m, const DecodeBounds&) {
  if (auto why = vehicleProblem(m.vehicle_id); !why.empty()) return why;
  if (m.kind < flight_command_t::ARM || m.kind > flight_command_t::LAND)
    return "unknown kind " + std::to_string(m.kind);
  if (!std::isfinite(m.height_m) || !finite(m.target_world_m, 3) ||
      !std::isfinite(m.max_speed_m_s) || (m.has_yaw && !std::isfinite(m.yaw_rad)))
    return "a field is not finite";
  if (m.kind == flight_command_t::MISSION && m.waypoint_count < 2)
    return "a mission needs at least 2 waypoints (got " + std::to_string(m.waypoint_count) + ")";
  for (const auto& waypoint : m.waypoints_world_m)
    if (waypoint.size() != 3 || !finite(waypoint.data(), 3)) return "a waypoint is not finite";
  return {};
}

template <class StatusMessage>
std::string statusProblem(const StatusMessage& m) {
  if (auto why = vehicleProblem(m.vehicle_id); !why.empty()) return why;
  if (m.run_state != StatusMessage::RUN_ACTIVE && m.run_state != StatusMessage::RUN_FINAL)
    return "unknown run_state " + std::to_string(m.run_state);
  if (m.last_keyframe_id < -1) return "last_keyframe_id below -1";
  return {};
}

std::string fieldProblem(const flight_status_t& m, const DecodeBounds&) {
  if (auto why = vehicleProblem(m.vehicle_id); !why.empty()) return why;
  if (m.mode < flight_status_t::MODE_DISARMED || m.mode > flight_status_t::MODE_HANDED_OVER)
    return "unknown mode " + std::to_string(m.mode);
  if (m.command_kind < flight_command_t::ARM || m.command_kind > flight_command_t::LAND)
    return "unknown command_kind " + std::to_string(m.command_kind);
  if (m.command_result < flight_status_t::ACCEPTED ||
      m.command_result > flight_status_t::REFUSED_AUTOPILOT_NOT_READY)
    return "unknown command_result " + std::to_string(m.command_result);
  if (m.rotors < flight_status_t::ROTORS_NONE || m.rotors > motor_command_t::FLYING)
    return "unknown rotors " + std::to_string(m.rotors);
  if (!finite(m.p_world_m, 3) || !finite(m.v_world_m_s, 3) || !finite(m.q_world_body_xyzw, 4) ||
      !finite(m.setpoint_world_m, 3) || !finite(m.setpoint_v_world_m_s, 3))
    return "a state or setpoint is not finite";
  return poseProblem(m.T_world_map);
}

std::string fieldProblem(const drone_status_t& m, const DecodeBounds&) {
  return statusProblem(m);
}

std::string fieldProblem(const ground_status_t& m, const DecodeBounds&) {
  return statusProblem(m);
}

std::string fieldProblem(const signed_t& m, const DecodeBounds&) {
  return vehicleProblem(m.vehicle_id);
}

std::string fieldProblem(const keyframe_chunk_t& m, const DecodeBounds& bounds) {
  if (auto why = vehicleProblem(m.vehicle_id); !why.empty()) return why;
  return chunkProblem(m, maxKeyframeMessageBytes(bounds));
}

std::string fieldProblem(const chunk_request_t& m, const DecodeBounds&) {
  if (auto why = vehicleProblem(m.vehicle_id); !why.empty()) return why;
  if (m.keyframe_id < 0) return "keyframe_id is negative";
  if (m.group < 0) return "group is negative";
  if (m.index_count < 1) return "no indices";
  return {};
}

}  // namespace

Status DecodeBounds::validate() const {
  if (max_width_px <= 0 || max_width_px > 8192)
    return Status::error("max_width_px must be in (0, 8192]");
  if (max_height_px <= 0 || max_height_px > 8192)
    return Status::error("max_height_px must be in (0, 8192]");
  if (max_keyframe_payload_bytes <= 0 || max_keyframe_payload_bytes > (64 << 20))
    return Status::error("max_keyframe_payload_bytes must be in (0, 64 MiB]");
  if (max_signed_payload_bytes <= 0 || max_signed_payload_bytes > (1 << 20))
    return Status::error("max_signed_payload_bytes must be in (0, 1 MiB]");
  return {};
}

int64_t maxKeyframeMessageBytes(const DecodeBounds& bounds) {
  return depth_keyframe_t().getEncodedSize() + int64_t{bounds.max_keyframe_payload_bytes};
}

const char* toString(DecodeStatus status) {
  switch (status) {
    case DecodeStatus::kOk: return "ok";
    case DecodeStatus::kWrongType: return "wrong type";
    case DecodeStatus::kTruncated: return "truncated";
    case DecodeStatus::kTrailingBytes: return "trailing bytes";
    case DecodeStatus::kOutOfBounds: return "out of bounds";
    case DecodeStatus::kBadField: return "bad field";
  }
  return "?";
}

template <class T>
bool hasFingerprint(const void* data, size_t size) {
  if (data == nullptr || size < 8) return false;
  return static_cast<uint64_t>(readBigEndian(static_cast<const uint8_t*>(data), 8)) ==
         static_cast<uint64_t>(T::getHash());
}

template <class T>
DecodeResult decodeMessage(const void* data, size_t size, const DecodeBounds& bounds, T* out) {
  if (size > static_cast<size_t>(std::numeric_limits<int>::max()))
    return fail(DecodeStatus::kOutOfBounds, std::to_string(size) + " bytes");
  if (!hasFingerprint<T>(data, size))
    return fail(size < 8 ? DecodeStatus::kTruncated : DecodeStatus::kWrongType,
                std::string("not a ") + T::getTypeName());
  const auto* bytes = static_cast<const uint8_t*>(data);
  // Encoded size with an empty variable part: the fingerprint and every fixed field.
  const size_t fixed_size = static_cast<size_t>(T().getEncodedSize());
  size_t expected = fixed_size;
  if constexpr (kTrailingCountBytes<T> != 0) {
    if (size < fixed_size) return fail(DecodeStatus::kTruncated, "header");
    const int count_bytes = kTrailingCountBytes<T>;
    const int64_t declared = readBigEndian(bytes + fixed_size - count_bytes, count_bytes);
    if (declared < 0 || declared > payloadBound<T>(bounds))
      return fail(DecodeStatus::kOutOfBounds,
                  "array size " + std::to_string(declared) + " outside [0, " +
                      std::to_string(payloadBound<T>(bounds)) + "]");
    expected += static_cast<size_t>(declared) * kTrailingElementBytes<T>;
  }
  if (size < expected)
    return fail(DecodeStatus::kTruncated,
                std::to_string(size) + " of " + std::to_string(expected) + " bytes");
  if (size > expected)
    return fail(DecodeStatus::kTrailingBytes,
                std::to_string(size) + " bytes for a " + std::to_string(expected) +
                    "-byte message");
  if (out->decode(data, 0, static_cast<int>(size)) != static_cast<int>(size))
    return fail(DecodeStatus::kTruncated, "decoder stopped early");
  if (std::string why = fieldProblem(*out, bounds); !why.empty())
    return fail(DecodeStatus::kBadField, std::move(why));
  return {};
}

#define KINFLY_INSTANTIATE_DECODE(T)                                               \
  template bool hasFingerprint<T>(const void*, size_t);                            \
  template DecodeResult decodeMessage<T>(const void*, size_t, const DecodeBounds&, T*);
KINFLY_INSTANTIATE_DECODE(depth_keyframe_t)
KINFLY_INSTANTIATE_DECODE(drone_status_t)
KINFLY_INSTANTIATE_DECODE(ground_status_t)
KINFLY_INSTANTIATE_DECODE(ground_truth_t)
KINFLY_INSTANTIATE_DECODE(imu_t)
KINFLY_INSTANTIATE_DECODE(odometry_t)
KINFLY_INSTANTIATE_DECODE(pose_correction_t)
KINFLY_INSTANTIATE_DECODE(signed_t)
KINFLY_INSTANTIATE_DECODE(keyframe_chunk_t)
KINFLY_INSTANTIATE_DECODE(chunk_request_t)
KINFLY_INSTANTIATE_DECODE(flight_command_t)
KINFLY_INSTANTIATE_DECODE(flight_status_t)
KINFLY_INSTANTIATE_DECODE(motor_command_t)
#undef KINFLY_INSTANTIATE_DECODE

}  // namespace kinfly::link
