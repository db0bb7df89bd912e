// The drone's end of the signed uplink: everything received on its correction channel goes
// through one CorrectionReceiver, and everything on its command channel through one
// CommandReceiver: each decodes within bounds, verifies with a Verifier of its own (a command
// sender and the ground station each number their messages), and counts each rejection.
#pragma once

#include <array>
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

// The commands taken lately, by command_id. A sender that hears no answer sends its command
// again, signed anew: to the Verifier that is a new message, not a copy. Acting on it twice
// would be wrong: a take-off taken twice is refused the second time, and that refusal would
// replace, in the flight status, the answer the sender waits for.
class RecentCommands {
 public:
  // True the first time COMMAND_ID comes among the last kKept ids; false for a repeat.
  bool first(int64_t command_id);
  int64_t repeats() const { return repeats_; }

 private:
  // Two operators' resends may interleave; a handful of ids covers them.
  static constexpr size_t kKept = 16;
  std::array<int64_t, kKept> ids_{};
  size_t held_ = 0, next_ = 0;
  int64_t repeats_ = 0;
};

}  // namespace kinfly::link
