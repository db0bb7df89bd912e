#include "kinfly/link/link_meter.h"

#include <algorithm>
#include <limits>

namespace kinfly::link {

Status LinkMeter::Params::validate() const {
  if (bin_us < 10'000 || bin_us > goodput_window_us)
    return Status::error("bin_us must be in [10 ms, goodput_window_us]");
  if (goodput_window_us < bin_us || goodput_window_us > 10'000'000)
    return Status::error("goodput_window_us must be in [bin_us, 10 s]");
  if (delay_window_us < bin_us || delay_window_us > goodput_window_us)
    return Status::error("delay_window_us must be in [bin_us, goodput_window_us]");
  // The minimum must cover the delay window, or the mean could sit below it.
  if (base_window_us < 2 * std::max(bin_us, delay_window_us) || base_window_us > 600'000'000)
    return Status::error("base_window_us must be in [2 * delay_window_us, 600 s]");
  return {};
}

LinkMeter::LinkMeter(const Params& params)
    : params_(params),
      // The window's bins and the one being filled.
      bins_(static_cast<size_t>((params.goodput_window_us + params.bin_us - 1) / params.bin_us + 1)) {}

int64_t LinkMeter::floorDiv(int64_t a, int64_t b) {
  const int64_t q = a / b;
  return (a % b != 0 && a < 0) ? q - 1 : q;
}

void LinkMeter::forgetDelays() {
  for (Bin& bin : bins_) bin.delay_sum_us = bin.samples = 0;
  current_ = previous_ = MinBucket();
  has_reference_ = false;
}

void LinkMeter::onChunk(const keyframe_chunk_t& chunk, int64_t arrival_utime,
                        size_t datagram_bytes) {
  if (chunk.keyframe_id >= 0) {
    FirstSent& first = first_sent_[static_cast<size_t>(chunk.keyframe_id % 8)];
    if (first.keyframe_id != chunk.keyframe_id) first = {chunk.keyframe_id, chunk.sent_utime};
    first.sent_utime = std::min(first.sent_utime, chunk.sent_utime);
  }
  const int64_t index = floorDiv(arrival_utime, params_.bin_us);
  const auto size = static_cast<int64_t>(bins_.size());
  Bin& bin = bins_[static_cast<size_t>(((index % size) + size) % size)];
  if (index < bin.index) return;  // older than every bin held: outside all windows
  if (index > bin.index) bin = Bin{index, 0, 0, 0};
  bin.bytes += static_cast<int64_t>(std::min<size_t>(datagram_bytes, std::numeric_limits<int32_t>::max()));

  // sent_utime is the drone's clock and unauthenticated: a difference that overflows is no
  // delay at all.
  int64_t delay_us = 0;
  if (__builtin_sub_overflow(arrival_utime, chunk.sent_utime, &delay_us)) return;
  int64_t relative_us = 0;
  if (has_reference_ &&
      (__builtin_sub_overflow(delay_us, reference_delay_us_, &relative_us) ||
       relative_us > kMaxDelaySpreadUs || relative_us < -kMaxDelaySpreadUs))
    forgetDelays();
  if (!has_reference_) {
    has_reference_ = true;
    reference_delay_us_ = delay_us;
    relative_us = 0;
  }
  bin.delay_sum_us += relative_us;
  ++bin.samples;

  // The windowed minimum: two buckets of half the base window each.
  const int64_t bucket = floorDiv(arrival_utime, params_.base_window_us / 2);
  if (bucket > current_.index) {
    previous_ = bucket == current_.index + 1 ? current_ : MinBucket();
    current_ = MinBucket{bucket, relative_us};
  } else if (bucket == current_.index) {
    current_.min_delay_us = std::min(current_.min_delay_us, relative_us);
  } else if (bucket == previous_.index) {
    previous_.min_delay_us = std::min(previous_.min_delay_us, relative_us);
  }
}

void LinkMeter::onKeyframe(int64_t keyframe_id, int64_t capture_utime, int64_t arrival_utime,
                           double redundancy) {
  int64_t age_us = 0;
  const FirstSent& first = first_sent_[static_cast<size_t>(std::max<int64_t>(keyframe_id, 0) % 8)];
  int64_t base_us = 0, delay_us = 0;
  if (keyframe_id >= 0 && first.keyframe_id == keyframe_id && has_reference_ &&
      baseDelay(arrival_utime, &base_us) &&
      !__builtin_sub_overflow(arrival_utime, first.sent_utime, &delay_us)) {
    // Both differences hold the clocks' offset once: it cancels.
    age_us = std::max<int64_t>(0, delay_us - reference_delay_us_ - base_us);
  } else if (__builtin_sub_overflow(arrival_utime, capture_utime, &age_us)) {
    age_us = 0;
  }
  keyframe_.keyframe_age_ms = static_cast<double>(age_us) * 1e-3;
  keyframe_.redundancy = redundancy;
  keyframe_.has_keyframe = true;
}

bool LinkMeter::baseDelay(int64_t now_utime, int64_t* base_us) const {
  const int64_t bucket = floorDiv(now_utime, params_.base_window_us / 2);
  bool has_base = false;
  for (const MinBucket* b : {&current_, &previous_}) {
    if (b->index < 0 || b->index < bucket - 1 || b->index > bucket) continue;
    *base_us = has_base ? std::min(*base_us, b->min_delay_us) : b->min_delay_us;
    has_base = true;
  }
  return has_base;
}

LinkQuality LinkMeter::quality(int64_t now_utime) const {
  LinkQuality q = keyframe_;
  const int64_t now_bin = floorDiv(now_utime, params_.bin_us);
  const int64_t goodput_bins = (params_.goodput_window_us + params_.bin_us - 1) / params_.bin_us;
  const int64_t delay_bins = (params_.delay_window_us + params_.bin_us - 1) / params_.bin_us;
  int64_t bytes = 0, delay_sum_us = 0, samples = 0;
  for (const Bin& bin : bins_) {
    if (bin.index < 0 || bin.index > now_bin) continue;
    const int64_t age_bins = now_bin - bin.index;  // 0: the bin now being filled
    if (age_bins < goodput_bins) bytes += bin.bytes;
    if (age_bins < delay_bins) {
      delay_sum_us += bin.delay_sum_us;
      samples += bin.samples;
    }
  }
  q.goodput_bps = static_cast<double>(bytes) * 8.0 /
                  (static_cast<double>(goodput_bins * params_.bin_us) * 1e-6);

  int64_t base_us = 0;
  if (samples > 0 && baseDelay(now_utime, &base_us)) {
    const double mean_us = static_cast<double>(delay_sum_us) / static_cast<double>(samples);
    q.queue_delay_ms = std::max(0.0, mean_us - static_cast<double>(base_us)) * 1e-3;
    q.has_delay = true;
  }
  return q;
}

}  // namespace kinfly::link
