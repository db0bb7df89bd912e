// When the ground asks the drone again for a keyframe's missing chunks (docs/wire.md, "Repair").
// A resend can be lost as well: at 5 % loss in runs of 5, a burst of a few resent chunks, or the
// request itself, is lost about one time in ten, and the keyframe with it. So an incomplete group
// is asked for at once, then again every retry_s while it stays incomplete, at most max_asks
// times: the drone keeps a keyframe's chunks only for its last few keyframes, and a group it can
// no longer answer must not be asked for forever.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "kinfly/chunk_request_t.hpp"
#include "kinfly/core/status.h"
#include "kinfly/link/chunking.h"

namespace kinfly::link {

class RepairScheduler {
 public:
  struct Params {
    int max_asks = 3;       // [1, 16] per (keyframe, group)
    double retry_s = 0.2;   // [s] [0.01, 10] between asks for the same group
    Status validate() const;
  };
  // params must validate().
  explicit RepairScheduler(const Params& params);

  // Fills (*out)[0..n) with the requests due at NOW_US (any monotonic clock, microseconds) for
  // ASSEMBLER's incomplete groups and returns n; *out only grows. INCLUDE_NEWEST as
  // ChunkAssembler::repairRequests().
  int due(const ChunkAssembler& assembler, bool include_newest, int64_t now_us,
          std::vector<chunk_request_t>* out);

  // Whether any group of the keyframe (capture time, id) has been asked for; a keyframe that
  // completes is remembered until the next due().
  bool asked(int64_t utime, int64_t keyframe_id) const;
  // Requests handed out by due(), all asks counted.
  int64_t requests() const { return requests_; }

 private:
  struct Asked {
    int64_t utime = 0;  // the keyframe's capture time: ids start again when the drone restarts
    int64_t keyframe_id = -1;
    int16_t group = -1;
    int asks = 0;
    int64_t last_us = 0;
    bool is(const chunk_request_t& request) const;  // the group REQUEST asks for
  };
  Asked* find(const chunk_request_t& request);

  Params params_;
  // The groups asked for that the assembler still holds incomplete: it bounds them, and the
  // vector keeps its capacity, so nothing allocates once it has grown.
  std::vector<Asked> asked_;
  int64_t requests_ = 0;
  std::vector<chunk_request_t> incomplete_;  // the assembler's requests, reused
};

}  // namespace kinfly::link
