// The drone's end of the signed uplink: everything received on its correction channel goes
// through one CorrectionReceiver, and everything on its command channel through one
// CommandReceiver: each decodes within bounds, verifies with a Verifier of its own (a command
// sender and the ground station each number their messages), and counts each rejection.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>

#include "kinfly/flight_command_t.hpp"
#include "kinfly/link/counters.h"
#include "kinfly/link/decode.h"
#include "kinfly/link/signing.h"
#include "kinfly/pose_correction_t.hpp"

namespace kinfly::link {

// Inner: pose_correction_t or flight_command_t (explicitly instantiated in uplink.cpp).
template <class Inner>
class SignedReceiver {
 public:
  SignedReceiver(const Key& key, int32_t vehicle_id, const VerifierParams& verifier,
                 const DecodeBounds& bounds);

  // One received message; the inner message if it is authentic, fresh and well formed.
  std::optional<Inner> receive(const void* data, size_t size, int64_t now_utime);

  const RejectCounters& rejects() const { return rejects_; }
  int64_t accepted() const { return accepted_; }
  // Copies of messages already accepted (the ground sends each more than once): not taken
  // again, and not rejections.
  int64_t duplicates() const { return duplicates_; }

 private:
  int32_t vehicle_id_;
  Verifier verifier_;
  DecodeBounds bounds_;
  RejectCounters rejects_;
  int64_t accepted_ = 0, duplicates_ = 0;
  signed_t envelope_;  // reused: its payload buffer keeps its capacity between messages
};

using CorrectionReceiver = SignedReceiver<pose_correction_t>;
using CommandReceiver = SignedReceiver<flight_command_t>;

}  // namespace kinfly::link
