// The drone's sending on a link whose capacity is unknown and changes (Wi-Fi: distance, walls,
// other stations). Keyframes could fill any link; what else the drone sends (its status, the
// odometry, telemetry) is small and must never queue behind them. So keyframe chunks go out only
// as fast as a budget allows (a token bucket), and the budget follows what the link carries
// (LinkRate): it shrinks as soon as the ground station sees chunks queueing, and grows slowly
// while the queue stays short. A paced sender keeps the queues of the drone's socket, its Wi-Fi
// driver and the access point short, which is what lets a small message through at once.
// Pure: time comes in as arguments.
#pragma once

#include <algorithm>
#include <array>

#include "kinfly/core/status.h"

namespace kinfly::fw {

class TokenBucket {
 public:
  // rate [bytes/s] > 0; burst [bytes] > 0: what may go out at once after a quiet spell.
  TokenBucket(double rate_Bps, double burst_bytes)
      : rate_Bps_(rate_Bps), burst_bytes_(burst_bytes), tokens_(burst_bytes) {}

  void setRate(double rate_Bps) { rate_Bps_ = rate_Bps; }
  double rate() const { return rate_Bps_; }

  // Spends `bytes` when the bucket holds them (refilled for the time since the last call).
  bool take(double bytes, double now_s) {
    refill(now_s);
    if (tokens_ < bytes) return false;
    tokens_ -= bytes;
    return true;
  }
  // Spends `bytes` that had to go out now (an answer the ground waits for, the small messages):
  // the bucket may go into debt, which what can wait then pays off; a second's worth at most,
  // so that what must go out can never starve what waits for good.
  void charge(double bytes, double now_s) {
    refill(now_s);
    tokens_ = std::max(tokens_ - bytes, -rate_Bps_ * kMaxDebtS);
  }
  static constexpr double kMaxDebtS = 1.0;
  // [s] until `bytes` can be taken, 0 when they can be now.
  double waitS(double bytes, double now_s) {
    refill(now_s);
    return tokens_ >= bytes ? 0.0 : (bytes - tokens_) / rate_Bps_;
  }

 private:
  void refill(double now_s) {
    if (last_s_ >= 0.0 && now_s > last_s_)
      tokens_ = std::min(burst_bytes_, tokens_ + (now_s - last_s_) * rate_Bps_);
    last_s_ = std::max(last_s_, now_s);
  }

  double rate_Bps_, burst_bytes_, tokens_;
  double last_s_ = -1.0;
};

// Bandwidth adaptation from the ground station's reports (ground_status_t, 10 Hz). Random loss
// is not a reason to send less (erasure coding pays for it); queueing is: the ground measures
// how much longer chunks take than the fastest it saw lately (one-way delay above its running
// minimum, so the two clocks' offset cancels), and a growing queue is the only sign that the
// drone sends more than the link carries, long before the queue overflows into loss. A
// delay-based rule in the manner of LEDBAT (RFC 6817) and WebRTC's delay-based estimate.
class LinkRate {
 public:
  struct Params {
    double start_bps = 8e6;               // [bit/s] [min_bps, max_bps] before any report
    double min_bps = 0.25e6;              // [bit/s] (0, max_bps]: never below this
    double max_bps = 20e6;                // [bit/s] (0, 1e9]: never above this
    double queue_high_ms = 40.0;          // [ms] (queue_low_ms, 10000]: queueing: send less
    double queue_low_ms = 15.0;           // [ms] [0, queue_high_ms): no queue: may send more
    double decrease = 0.85;               // (0, 1): the new budget, as a part of the goodput
    // (0, 1]: a decrease keeps at least this part of the budget. The goodput of a second that
    // began idle (the flight's first keyframe, the first after a pause) understates the link:
    // cutting to it would drop a start at 8 Mbit/s into a 2 Mbit/s link to the floor, from
    // which the budget needs many seconds to climb back. A real drop takes one hold per halving.
    double max_cut = 0.5;
    double increase_per_s = 0.3;          // [1/s] (0, 10]: growth per second, relative
    double hold_s = 0.5;                  // [s] [0, 10]: after a decrease, let it take effect
    Status validate() const;
  };

  explicit LinkRate(const Params& params) : p_(params), budget_bps_(params.start_bps) {}

  // One report. goodput [bit/s]: the keyframe chunks the ground received over its last
  // second; queue_ms: their queueing delay; limited: the drone had more to send than its
  // budget since the last report (otherwise growing the budget proves nothing).
  void onReport(double goodput_bps, double queue_ms, bool limited, double now_s);

  double budgetBps() const { return budget_bps_; }
  int decreases() const { return decreases_; }

 private:
  Params p_;
  double budget_bps_;
  double last_report_s_ = -1.0, hold_until_s_ = -1.0;
  int decreases_ = 0;
};

// Smaller keyframes when even a slow stream of full-size ones exceeds the budget: the depth
// image is sent at 1/scale of its width and height (stated in the message's camera), so a
// keyframe costs about 1/scale² of the bytes: about, because a subsampled depth image
// compresses worse (measured: a half-size keyframe costs 2.3 times a quarter-size one, not 4),
// so what a size cost when it was last sent wins over the estimate.
struct KeyframeScale {
  struct Params {
    double min_rate_hz = 1.0;  // [Hz] (0, 100]: below this keyframe rate the images shrink
    double hysteresis = 1.5;   // (1, 10]: a larger scale returns only at this much spare
    int max_scale = 4;         // {1, 2, 4}: the smallest image is 1/max_scale per side
    Status validate() const;
  };
  // [bytes] what the last keyframe sent at scale 1, 2 and 4 cost on the wire (with
  // redundancy); 0 for a scale not sent yet.
  using Costs = std::array<double, 3>;
  static size_t index(int scale) { return scale >= 4 ? 2 : scale >= 2 ? 1 : 0; }
  // [bytes] a keyframe at `scale`: its cost, or one estimated from the nearest scale sent (a
  // step costing four times the bytes); 0 before any keyframe was sent.
  static double cost(const Costs& costs, int scale);
  // The scale for the next keyframe. budget_Bps [bytes/s] for keyframes.
  static int choose(const Params& params, int scale, double budget_Bps, const Costs& costs);
};

}  // namespace kinfly::fw
