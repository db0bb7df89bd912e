// The ground's link meter (firmware/link/link_meter.h) against streams whose figures are known by
// construction: goodput of a regular stream, a clock offset that changes nothing, a delay step that
// shows and is forgotten after the base window, the keyframe figures, and memory fixed at
// construction whatever arrives.
#include <gtest/gtest.h>

#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <limits>
#include <new>
#include <random>

#include "kinfly/link/link_meter.h"

#include "count_allocations.h"  // g_allocations: for the steady-state test

namespace kinfly::link {
namespace {

constexpr int64_t kStart = 1'700'000'000'000'000;  // [us] the ground's clock at the first chunk
constexpr int64_t kChunkPeriodUs = 1'000;          // a chunk every millisecond
constexpr size_t kDatagramBytes = 1'400;
constexpr uint32_t kSeed = 20261214;
// A regular stream fills every bin of the window exactly when the snapshot is taken at the last
// arrival; the only error left is double round-off.
constexpr double kRoundoff = 1e-9;
// Jittered delays in [0, kJitterUs): their mean above their minimum is about half of it.
constexpr int64_t kJitterUs = 4'000;

// Feeds chunks every kChunkPeriodUs in [from, to) of the ground's clock; delay_us(arrival) is the
// one-way delay, offset_us the drone's clock minus the ground's.
template <class Delay>
int64_t feed(LinkMeter& meter, int64_t from, int64_t to, int64_t offset_us, Delay delay_us) {
  keyframe_chunk_t chunk;
  int64_t last = from;
  for (int64_t arrival = from; arrival < to; arrival += kChunkPeriodUs) {
    chunk.sent_utime = arrival - delay_us(arrival) + offset_us;
    meter.onChunk(chunk, arrival, kDatagramBytes);
    last = arrival;
  }
  return last;
}

TEST(LinkMeter, ParamsAreValidated) {
  EXPECT_TRUE(LinkMeter::Params().validate().ok());
  LinkMeter::Params p;
  p.bin_us = 1'000;
  EXPECT_FALSE(p.validate().ok());
  p = {};
  p.delay_window_us = 2 * p.goodput_window_us;
  EXPECT_FALSE(p.validate().ok());
  p = {};
  p.base_window_us = p.delay_window_us;  // the minimum must span twice the mean's window
  EXPECT_FALSE(p.validate().ok());
  p = {};
  p.goodput_window_us = 60'000'000;
  EXPECT_FALSE(p.validate().ok());
}

TEST(LinkMeter, GoodputOfARegularStream) {
  LinkMeter meter({});
  const LinkQuality before = meter.quality(kStart);
  EXPECT_EQ(before.goodput_bps, 0.0);
  EXPECT_FALSE(before.has_delay);
  EXPECT_FALSE(before.has_keyframe);

  const int64_t last = feed(meter, kStart, kStart + 3'000'000, 0, [](int64_t) { return 2'000; });
  // 1000 datagrams of 1400 bytes a second.
  const double expected_bps = 1'000.0 * kDatagramBytes * 8.0;
  EXPECT_NEAR(meter.quality(last).goodput_bps, expected_bps, kRoundoff * expected_bps);
  // Half a window later half the stream is still in it (to within a bin: 1 %).
  const LinkMeter::Params p;
  const double bin_fraction =
      static_cast<double>(p.bin_us) / static_cast<double>(p.goodput_window_us);
  EXPECT_NEAR(meter.quality(last + p.goodput_window_us / 2).goodput_bps, expected_bps / 2,
              bin_fraction * expected_bps);
  // A window of silence: nothing.
  const LinkQuality silent = meter.quality(last + p.goodput_window_us + p.bin_us);
  EXPECT_EQ(silent.goodput_bps, 0.0);
  EXPECT_FALSE(silent.has_delay);
}

TEST(LinkMeter, AClockOffsetDoesNotChangeTheQueueDelay) {
  std::mt19937 rng(kSeed);
  std::vector<int64_t> jitter(5'000);
  for (int64_t& j : jitter) j = static_cast<int64_t>(rng() % kJitterUs);
  const auto delay = [&](int64_t arrival) {
    return 3'000 + jitter[static_cast<size_t>((arrival - kStart) / kChunkPeriodUs) % jitter.size()];
  };
  // The drone's clock as the ground's, an hour ahead, and unset (1970) on a drone without RTC.
  double reference_ms = -1.0;
  for (const int64_t offset_us : {int64_t{0}, int64_t{3'600'000'000}, -kStart}) {
    LinkMeter meter({});
    const int64_t last = feed(meter, kStart, kStart + 4'000'000, offset_us, delay);
    const LinkQuality q = meter.quality(last);
    ASSERT_TRUE(q.has_delay);
    // The mean of uniform jitter above its minimum, whatever the 3 ms the link always takes.
    EXPECT_NEAR(q.queue_delay_ms, kJitterUs * 1e-3 / 2, 0.1 * kJitterUs * 1e-3);
    if (reference_ms < 0) reference_ms = q.queue_delay_ms;
    EXPECT_NEAR(q.queue_delay_ms, reference_ms, kRoundoff);
  }
}

TEST(LinkMeter, ADelayStepShowsAndIsForgottenAfterTheBaseWindow) {
  const LinkMeter::Params p;
  LinkMeter meter(p);
  constexpr int64_t kBaseUs = 5'000, kStepUs = 40'000;
  // The step comes 2.5 s into a half-window bucket: the worst case for forgetting it.
  const int64_t step_at = kStart - kStart % (p.base_window_us / 2) + 20'000'000 + 2'500'000;
  const auto delay = [&](int64_t arrival) { return arrival < step_at ? kBaseUs : kBaseUs + kStepUs; };
  const double step_ms = kStepUs * 1e-3;

  int64_t last = feed(meter, kStart, step_at, 0, delay);
  EXPECT_NEAR(meter.quality(last).queue_delay_ms, 0.0, kRoundoff);
  // One delay window after the step, its whole mean is the step above the old minimum.
  last = feed(meter, step_at, step_at + p.delay_window_us, 0, delay);
  EXPECT_NEAR(meter.quality(last).queue_delay_ms, step_ms, kRoundoff);
  // Still remembered half a base window later: a standing queue is not taken for the base at
  // once.
  last = feed(meter, last + kChunkPeriodUs, step_at + p.base_window_us / 2, 0, delay);
  EXPECT_NEAR(meter.quality(last).queue_delay_ms, step_ms, kRoundoff);
  // A whole base window after the step the old minimum is gone: the new delay is the base.
  last = feed(meter, last + kChunkPeriodUs, step_at + p.base_window_us, 0, delay);
  EXPECT_NEAR(meter.quality(last).queue_delay_ms, 0.0, kRoundoff);

  // A step down is the new base at once.
  LinkMeter down(p);
  last = feed(down, kStart, kStart + 3'000'000, 0, [](int64_t) { return 50'000; });
  last = feed(down, last + kChunkPeriodUs, last + 1'000'000, 0, [](int64_t) { return 10'000; });
  EXPECT_NEAR(down.quality(last).queue_delay_ms, 0.0, kRoundoff);
}

TEST(LinkMeter, WholeKeyframesAgeFromCaptureAndTheirRedundancy) {
  LinkMeter meter({});
  meter.onKeyframe(-1, kStart, kStart + 85'000, 8.0 / 37.0);
  meter.onKeyframe(-1, kStart + 200'000, kStart + 262'500, 3.0 / 37.0);
  const LinkQuality q = meter.quality(kStart + 300'000);
  EXPECT_TRUE(q.has_keyframe);
  EXPECT_NEAR(q.keyframe_age_ms, 62.5, kRoundoff);
  EXPECT_NEAR(q.redundancy, 3.0 / 37.0, kRoundoff);
  meter.onKeyframe(-1, kStart, kStart + 1, 0.0);  // a whole keyframe: no redundancy
  EXPECT_EQ(meter.quality(kStart + 1).redundancy, 0.0);
}

TEST(LinkMeter, AChunkedKeyframesAgeIsItsTimeOnTheLinkWhateverTheClocks) {
  // The drone's clock an hour ahead, a replayed flight's capture times years old: neither shows.
  constexpr int64_t kOffsetUs = 3'600'000'000, kBaseDelayUs = 2'000, kCaptureUs = 42;
  for (const int64_t queued_us : {int64_t{0}, int64_t{30'000}}) {
    LinkMeter meter({});
    keyframe_chunk_t chunk;
    // Keyframe 4 alone on an empty link: the least delay is learnt from it.
    chunk.keyframe_id = 4;
    for (int i = 0; i < 40; ++i) {
      chunk.sent_utime = kStart + kOffsetUs + i * 1'000;
      meter.onChunk(chunk, kStart + i * 1'000 + kBaseDelayUs, kDatagramBytes);
    }
    // Keyframe 5: its 40 chunks sent over 39 ms, the last one queued queued_us more.
    chunk.keyframe_id = 5;
    int64_t arrival = 0;
    for (int i = 0; i < 40; ++i) {
      chunk.sent_utime = kStart + kOffsetUs + 100'000 + i * 1'000;
      arrival = kStart + 100'000 + i * 1'000 + kBaseDelayUs + (i == 39 ? queued_us : 0);
      meter.onChunk(chunk, arrival, kDatagramBytes);
    }
    meter.onKeyframe(5, kCaptureUs, arrival, 3.0 / 37.0);
    EXPECT_NEAR(meter.quality(arrival).keyframe_age_ms,
                39.0 + static_cast<double>(queued_us) * 1e-3, kRoundoff)
        << queued_us;
  }
}

TEST(LinkMeter, MemoryIsFixedAtConstructionWhateverArrives) {
  LinkMeter meter({});
  const size_t bins = meter.bins();
  std::mt19937_64 rng(kSeed);
  keyframe_chunk_t chunk;
  const int64_t before = g_allocations.load();
  int64_t arrival = kStart;
  for (int i = 0; i < 200'000; ++i) {
    // Mostly forward, sometimes back or far ahead; any sent time, overflowing ones included.
    arrival += static_cast<int64_t>(rng() % 2'000) - (i % 97 == 0 ? 5'000'000 : 0) +
               (i % 1'009 == 0 ? 30'000'000 : 0);
    chunk.sent_utime = i % 13 == 0 ? static_cast<int64_t>(rng()) : arrival - 4'000;
    meter.onChunk(chunk, arrival, static_cast<size_t>(rng() % 9'000));
    const LinkQuality q = meter.quality(arrival);
    ASSERT_TRUE(std::isfinite(q.goodput_bps) && q.goodput_bps >= 0.0);
    ASSERT_TRUE(std::isfinite(q.queue_delay_ms) && q.queue_delay_ms >= 0.0);
  }
  chunk.sent_utime = std::numeric_limits<int64_t>::min();
  meter.onChunk(chunk, std::numeric_limits<int64_t>::max(), 1);
  EXPECT_EQ(g_allocations.load(), before);
  EXPECT_EQ(meter.bins(), bins);
}

}  // namespace
}  // namespace kinfly::link
