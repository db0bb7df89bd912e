// The ground's measure of one vehicle's keyframe link (docs/wire.md, "The ground's measurement"):
// what ground_status_t reports back so that the drone can choose its send budget and redundancy.
// Pure: every time is passed in (int64 utime, microseconds), nothing reads a clock.
//
//   goodput_bps      chunk datagram bytes received over the last goodput_window_us, x 8
//   queue_delay_ms   the mean one-way delay (arrival - sent_utime) of the chunks of the last
//                    delay_window_us, less its minimum over the last base_window_us. The two
//                    clocks' offset is in every sample and cancels; what is left is the delay the
//                    link's queues add above the emptiest they were recently. The minimum is a
//                    windowed one (two buckets of base_window_us / 2), so a base that shifted
//                    (a clock step, a route change) is forgotten within base_window_us.
//   keyframe_age_ms  the last keyframe's arrival - capture (both clocks: they must agree, as for
//                    the signing window)
//   redundancy       the last keyframe's recovery chunks per original (m / k)
//
// Memory is fixed at construction: chunks are summed into time bins, so however many arrive the
// meter holds goodput_window_us / bin_us bins and two minima.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "kinfly/core/status.h"
#include "kinfly/keyframe_chunk_t.hpp"

namespace kinfly::link {

// A snapshot of the link (LinkMeter::quality). Figures without data are 0.
struct LinkQuality {
  double goodput_bps = 0.0;     // [bit/s]
  double queue_delay_ms = 0.0;  // [ms] >= 0
  // [ms] the last keyframe's time on the link: from its first chunk's sending to its
  // completion here, less the link's least one-way delay (so the clocks' offset cancels); for a
  // whole keyframe, capture to arrival (the clocks must agree). 0 before the first.
  double keyframe_age_ms = 0.0;
  double redundancy = 0.0;      // m / k of the last keyframe; 0 for a whole (unchunked) one
  bool has_delay = false;       // chunks arrived within delay_window_us
  bool has_keyframe = false;    // a keyframe arrived since the start
};

class LinkMeter {
 public:
  struct Params {
    // [us] [10 ms, goodput_window_us]: chunks are summed per bin; the windows move by bins, so
    // a figure covers its window to within one bin.
    int64_t bin_us = 10'000;
    // [us] [bin_us, 10 s]: goodput is over this long.
    int64_t goodput_window_us = 1'000'000;
    // [us] [bin_us, goodput_window_us]: queue delay is the mean over this long.
    int64_t delay_window_us = 500'000;
    // [us] [2 * bin_us, 600 s]: the minimum delay is over the last base_window_us / 2 to
    // base_window_us (two buckets of half each).
    int64_t base_window_us = 10'000'000;
    Status validate() const;
  };

  // params must validate(). Allocates its bins here, never after.
  explicit LinkMeter(const Params& params);

  // A chunk that decoded (whatever the assembler then made of it: duplicates and surplus use the
  // link too). datagram_bytes: the LCM datagram's payload as received.
  void onChunk(const keyframe_chunk_t& chunk, int64_t arrival_utime, size_t datagram_bytes);
  // A keyframe that arrived whole or was rebuilt from chunks; redundancy m / k (0: whole).
  void onKeyframe(int64_t keyframe_id, int64_t capture_utime, int64_t arrival_utime,
                  double redundancy);

  // The link as of now_utime (normally the latest arrival or later). Arrivals older than the
  // oldest bin still held are not counted.
  LinkQuality quality(int64_t now_utime) const;

  // Bins held (fixed by the params): the meter's memory.
  size_t bins() const { return bins_.size(); }

 private:
  struct Bin {
    int64_t index = -1;  // arrival_utime / bin_us of what it holds; -1: empty
    int64_t bytes = 0;
    int64_t delay_sum_us = 0;
    int64_t samples = 0;
  };
  struct MinBucket {
    int64_t index = -1;  // arrival_utime / (base_window_us / 2); -1: empty
    int64_t min_delay_us = 0;
  };
  struct FirstSent {
    int64_t keyframe_id = -1;
    int64_t sent_utime = 0;  // [us] the earliest of its chunks seen, on the drone's clock
  };
  static int64_t floorDiv(int64_t a, int64_t b);
  void forgetDelays();
  // The least delay (relative to reference_delay_us_) of the base window ending at now_utime.
  bool baseDelay(int64_t now_utime, int64_t* base_us) const;

  Params params_;
  // Delays are held relative to the first one (exact int64 sums whatever the clocks' offset);
  // a delay further than kMaxDelaySpreadUs from it (a clock stepped by days) starts afresh.
  static constexpr int64_t kMaxDelaySpreadUs = int64_t{1} << 40;  // [us] about 12.7 days
  bool has_reference_ = false;
  int64_t reference_delay_us_ = 0;
  std::vector<Bin> bins_;  // a ring indexed by bin index mod size
  MinBucket current_, previous_;
  LinkQuality keyframe_;  // keyframe_age_ms, redundancy, has_keyframe
  std::array<FirstSent, 8> first_sent_;  // the keyframes being received, by id mod 8
};

}  // namespace kinfly::link
