// Counts of received messages that were dropped, by reason: reported in both sides' status.
#pragma once

#include <cstdint>

#include "kinfly/link/decode.h"
#include "kinfly/link/signing.h"
#include "kinfly/drone_status_t.hpp"

namespace kinfly::link {

struct RejectCounters {
  int64_t unsigned_messages = 0;
  int64_t wrong_key = 0;
  int64_t bad_mac = 0;
  int64_t stale = 0;
  int64_t replayed = 0;
  int64_t malformed = 0;
  int64_t unknown_channel = 0;
  int64_t wrong_vehicle = 0;

  // Counts a verifier's rejection (kAccepted counts nothing here).
  void count(Verdict verdict);
  // Counts a failed decode (kOk counts nothing).
  void count(DecodeStatus status);
  RejectCounters& operator+=(const RejectCounters& other);
  int64_t total() const;
  void writeTo(drone_status_t* status) const;
};

}  // namespace kinfly::link
