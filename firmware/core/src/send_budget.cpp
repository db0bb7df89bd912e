#include "kinfly/fw/send_budget.h"

#include <algorithm>

#include "kinfly/core/range_check.h"

namespace kinfly::fw {

Status LinkRate::Params::validate() const {
  return firstError(outOfRange("link.max_rate_bps", max_bps, 0.0, 1e9, Bound::kOpen),
                    outOfRange("link.min_rate_bps", min_bps, 0.0, max_bps, Bound::kOpen),
                    outOfRange("link.start_rate_bps", start_bps, min_bps, max_bps),
                    outOfRange("link.queue_low_ms", queue_low_ms, 0.0, queue_high_ms),
                    outOfRange("link.queue_high_ms", queue_high_ms, queue_low_ms, 10000.0,
                               Bound::kOpen),
                    outOfRange("link.rate_decrease", decrease, 0.0, 0.99, Bound::kOpen),
                    outOfRange("link.rate_max_cut", max_cut, 0.0, 1.0, Bound::kOpen),
                    outOfRange("link.rate_increase_per_s", increase_per_s, 0.0, 10.0,
                               Bound::kOpen),
                    outOfRange("link.rate_hold_s", hold_s, 0.0, 10.0));
}

void LinkRate::onReport(double goodput_bps, double queue_ms, bool limited, double now_s) {
  const double since_s = last_report_s_ < 0.0 ? 0.0 : std::max(0.0, now_s - last_report_s_);
  last_report_s_ = now_s;
  if (now_s < hold_until_s_) return;
  if (queue_ms > p_.queue_high_ms) {
    // What arrived is what the link carries now; a little less lets its queue drain. Never
    // more than the budget was: a goodput measured over a second may include a faster past.
    budget_bps_ = std::clamp(std::max(std::min(budget_bps_, goodput_bps) * p_.decrease,
                                      budget_bps_ * p_.max_cut),
                             p_.min_bps, p_.max_bps);
    hold_until_s_ = now_s + p_.hold_s;
    ++decreases_;
  } else if (queue_ms < p_.queue_low_ms && limited) {
    budget_bps_ = std::min(p_.max_bps, budget_bps_ * (1.0 + p_.increase_per_s * since_s));
  }
}

Status KeyframeScale::Params::validate() const {
  return firstError(
      outOfRange("link.min_keyframe_rate_hz", min_rate_hz, 0.0, 100.0, Bound::kOpen),
      outOfRange("link.scale_hysteresis", hysteresis, 1.0, 10.0, Bound::kOpen),
      max_scale == 1 || max_scale == 2 || max_scale == 4
          ? Status()
          : Status::error("link.max_scale must be 1, 2 or 4 (got " + std::to_string(max_scale) +
                          ")"));
}

double KeyframeScale::cost(const Costs& costs, int scale) {
  if (costs[index(scale)] > 0.0) return costs[index(scale)];
  for (int distance = 1; distance <= 2; ++distance) {
    for (const int other : {scale >> distance, scale << distance}) {
      if (other < 1 || other > 4 || costs[index(other)] <= 0.0) continue;
      const double ratio = static_cast<double>(other) / scale;
      return costs[index(other)] * ratio * ratio;
    }
  }
  return 0.0;
}

int KeyframeScale::choose(const Params& p, int scale, double budget_Bps, const Costs& costs) {
  const double here = cost(costs, scale);
  if (here <= 0.0) return scale;
  if (budget_Bps / here < p.min_rate_hz && scale < p.max_scale) return scale * 2;
  if (scale > 1 && budget_Bps / cost(costs, scale / 2) >= p.min_rate_hz * p.hysteresis)
    return scale / 2;
  return scale;
}

}  // namespace kinfly::fw
