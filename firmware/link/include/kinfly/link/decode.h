// Bounded decoding of received LCM messages. lcm-gen's C++ decoder sizes a variable array from
// the count it reads before checking that the bytes are there, so a forged count would make it
// allocate up to 2 GB. Every received message therefore goes through decodeMessage(), which checks
// the fingerprint, the declared sizes against the datagram and the bounds, and then the fields.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

#include "kinfly/depth_keyframe_t.hpp"
#include "kinfly/imu_t.hpp"
#include "kinfly/odometry_t.hpp"
#include "kinfly/pose_correction_t.hpp"
#include "kinfly/pose_t.hpp"
#include "kinfly/signed_t.hpp"
#include "kinfly/status_t.hpp"

namespace kinfly::link {

struct DecodeBounds {
  int max_width_px = 1280;               // [px] (0, 8192]
  int max_height_px = 1024;              // [px] (0, 8192]
  // [bytes] (0, 64 MiB]; a raw 1280x1024 frame is 2.5 MiB
  int max_keyframe_payload_bytes = 8 << 20;
  int max_signed_payload_bytes = 4096;   // [bytes] (0, 1 MiB]; corrections are ~100 bytes
  std::string validate() const;          // empty when valid, else what is wrong
};

enum class DecodeStatus {
  kOk,
  kWrongType,      // the fingerprint is another type's (or not a kinfly type at all)
  kTruncated,      // fewer bytes than the message declares
  kTrailingBytes,  // more bytes than the message declares
  kOutOfBounds,    // a declared size beyond DecodeBounds
  kBadField,       // decoded, but a field holds an impossible value (NaN pose, unknown enum, ...)
};
const char* toString(DecodeStatus status);

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
