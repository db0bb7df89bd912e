// The drone's end of the signed uplink: everything received on its correction channel goes
// through one CorrectionReceiver, which decodes within bounds, verifies, and counts each rejection.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>

#include "kinfly/link/counters.h"
#include "kinfly/link/decode.h"
#include "kinfly/link/signing.h"
#include "kinfly/pose_correction_t.hpp"

namespace kinfly::link {

class CorrectionReceiver {
 public:
  CorrectionReceiver(const Key& key, int32_t vehicle_id, const VerifierParams& verifier,
                     const DecodeBounds& bounds);

  // One received message; the correction if it is authentic, fresh and well formed.
  std::optional<pose_correction_t> receive(const void* data, size_t size, int64_t now_utime);

  const RejectCounters& rejects() const { return rejects_; }
  int64_t accepted() const { return accepted_; }
  // Copies of corrections already accepted (the ground sends each more than once): not applied
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

}  // namespace kinfly::link
