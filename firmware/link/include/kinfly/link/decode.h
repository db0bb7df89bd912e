// Bounded decoding of received LCM messages. lcm-gen's C++ decoder sizes a variable array from
// the count it reads before checking that the bytes are there, so a forged count would make it
// allocate up to 2 GB. Every received message therefore goes through decodeMessage(), which checks
// the fingerprint, the declared sizes against the datagram and the bounds, and then the fields.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

#include "kinfly/chunk_request_t.hpp"
#include "kinfly/core/status.h"
#include "kinfly/depth_keyframe_t.hpp"
#include "kinfly/drone_status_t.hpp"
#include "kinfly/flight_command_t.hpp"
#include "kinfly/flight_status_t.hpp"
#include "kinfly/ground_status_t.hpp"
#include "kinfly/ground_truth_t.hpp"
#include "kinfly/imu_t.hpp"
#include "kinfly/keyframe_chunk_t.hpp"
#include "kinfly/motor_command_t.hpp"
#include "kinfly/odometry_t.hpp"
#include "kinfly/pose_correction_t.hpp"
#include "kinfly/signed_t.hpp"

namespace kinfly::link {

// The defaults are the wire's own (proto/kinfly/*.lcm constants).
struct DecodeBounds {
  int max_width_px = camera_t::MAX_WIDTH_PX;    // [px] (0, 8192]
  int max_height_px = camera_t::MAX_HEIGHT_PX;  // [px] (0, 8192]
  int max_keyframe_payload_bytes = depth_keyframe_t::MAX_PAYLOAD_BYTES;  // [bytes] (0, 64 MiB]
  int max_signed_payload_bytes = signed_t::MAX_PAYLOAD_BYTES;            // [bytes] (0, 1 MiB]
  Status validate() const;
};

// [bytes] An encoded depth_keyframe_t with the largest payload the bounds allow: the bound on a
// chunked keyframe's message_bytes.
int64_t maxKeyframeMessageBytes(const DecodeBounds& bounds);

enum class DecodeStatus {
  kOk,
  kWrongType,      // the fingerprint is another type's (or not a kinfly type at all)
  kTruncated,      // fewer bytes than the message declares
  kTrailingBytes,  // more bytes than the message declares
  kOutOfBounds,    // a declared size beyond DecodeBounds
  kBadField,       // decoded, but a field holds an impossible value (NaN pose, unknown enum, ...)
};
const char* toString(DecodeStatus status);

// A per-message outcome that receivers count by status (RejectCounters), not a Status
// (kinfly/core/status.h); `detail` is what a Status message would say, for the log.
struct DecodeResult {
  DecodeStatus status = DecodeStatus::kOk;
  std::string detail;  // names the field or size at fault; empty when kOk
  bool ok() const { return status == DecodeStatus::kOk; }
};

// True when data starts with T's fingerprint: lets a receiver tell an unsigned correction from an
// envelope before decoding either.
template <class T>
bool hasFingerprint(const void* data, size_t size);

template <class T>
DecodeResult decodeMessage(const void* data, size_t size, const DecodeBounds& bounds, T* out);

}  // namespace kinfly::link
