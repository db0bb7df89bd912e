// The mavlink backend's clock mapping (actuators::ClockMap): the autopilot's boot-time stamps on
// the wall clock the depth frames are stamped with, from arrival times alone. A simulated link
// with a known offset, a minimum delay and seeded jitter, at the 250 Hz of the autopilot's IMU.
#include <gtest/gtest.h>

#include <cstdint>
#include <cstdio>
#include <random>

#include "kinfly/actuators/autopilot.h"

namespace kinfly::actuators {
namespace {

constexpr int64_t kPeriodUs = 4000;          // 250 Hz
constexpr int64_t kClockOffsetUs = 1'700'000'000'000'000;  // the wall clock at the autopilot's boot
constexpr int64_t kMinDelayUs = 3000;        // UART and parsing, never less
constexpr int64_t kJitterUs = 5000;          // on top, uniform: a busy companion computer
// After a second the mapping is the capture time plus the minimum delay, within this: the
// offset creeps up by the drift allowance (100 µs/s) between the samples that arrive fastest,
// and the creep measured here stays below 0.3 ms. 1 ms is a millimetre of the estimator's fused
// position at 1 m/s.
constexpr int64_t kSettledToleranceUs = 1000;
constexpr int kSettleSamples = 250;

// One run of samples through the link; `remote(i)` gives sample i's autopilot time, `wall(i)`
// its true capture time on our clock. Returns the largest error after settling.
template <class Remote, class Wall>
int64_t worstError(ClockMap& clock, int samples, Remote&& remote, Wall&& wall, uint32_t seed,
                   int settle_from = 0) {
  std::mt19937 rng(seed);
  std::uniform_int_distribution<int64_t> jitter(0, kJitterUs);
  int64_t worst = 0, last = -1;
  for (int i = 0; i < samples; ++i) {
    const int64_t arrival = wall(i) + kMinDelayUs + jitter(rng);
    const int64_t mapped = clock.map(remote(i), arrival);
    EXPECT_GT(mapped, last) << "sample " << i;
    last = mapped;
    if (i >= settle_from + kSettleSamples) {
      worst = std::max(worst, std::abs(mapped - (wall(i) + kMinDelayUs)));
    }
  }
  return worst;
}

TEST(ClockMap, FindsTheOffsetFromTheSmallestDelay) {
  ClockMap clock;
  EXPECT_FALSE(clock.ready());
  const int samples = 250 * 60;
  const int64_t worst = worstError(
      clock, samples, [](int i) { return int64_t{i} * kPeriodUs; },
      [](int i) { return kClockOffsetUs + int64_t{i} * kPeriodUs; }, 1);
  std::printf("[clock] constant offset, 3-8 ms delays: worst %lld us\n",
              static_cast<long long>(worst));
  EXPECT_LE(worst, kSettledToleranceUs);
  EXPECT_TRUE(clock.ready());
  // And back: our time on the autopilot's clock.
  const int64_t remote = int64_t{samples} * kPeriodUs;
  EXPECT_NEAR(static_cast<double>(clock.toRemote(kClockOffsetUs + kMinDelayUs + remote)),
              static_cast<double>(remote), kSettledToleranceUs);
}

TEST(ClockMap, FollowsAClockThatRunsSlowerThanOurs) {
  // The autopilot's crystal 50 ppm slow: its stamps fall behind ours by 50 µs a second, the
  // offset must grow, which the minimum alone never would.
  constexpr double kSlow = 1.0 - 50e-6;
  ClockMap clock;
  const int64_t worst = worstError(
      clock, 250 * 600,
      [](int i) { return static_cast<int64_t>(static_cast<double>(i) * kPeriodUs * kSlow); },
      [](int i) { return kClockOffsetUs + int64_t{i} * kPeriodUs; }, 2);
  // Ten minutes: without the drift allowance the error would reach 30 ms.
  std::printf("[clock] 50 ppm slow, 10 min: worst %lld us\n", static_cast<long long>(worst));
  EXPECT_LE(worst, kSettledToleranceUs);
}

TEST(ClockMap, StartsAgainWhenTheAutopilotRestarts) {
  ClockMap clock;
  constexpr int kRestartAt = 250 * 30;  // its time falls back to 0 after 30 s
  const auto remote = [](int i) {
    return int64_t{i < kRestartAt ? i : i - kRestartAt} * kPeriodUs;
  };
  const int64_t worst = worstError(
      clock, 250 * 60, remote, [](int i) { return kClockOffsetUs + int64_t{i} * kPeriodUs; }, 3,
      kRestartAt);
  std::printf("[clock] after a restart: worst %lld us\n", static_cast<long long>(worst));
  EXPECT_LE(worst, kSettledToleranceUs);
}

TEST(ClockMap, ABurstAfterAStallOfThisComputerKeepsTheOffset) {
  // Ten seconds as usual, then this computer stalls for a second: that second's samples all
  // arrive at its end. Late as they look, they are no restart.
  ClockMap clock;
  const auto wall = [](int i) { return kClockOffsetUs + int64_t{i} * kPeriodUs; };
  worstError(clock, 2500, [](int i) { return int64_t{i} * kPeriodUs; }, wall, 5);
  const int64_t offset = clock.offsetUs();
  for (int i = 2500; i < 2750; ++i) clock.map(int64_t{i} * kPeriodUs, wall(2750) + kMinDelayUs);
  // At most the drift allowance over the second.
  EXPECT_LE(clock.offsetUs() - offset, static_cast<int64_t>(ClockMap::kDrift * 1e6) + 1);
}

TEST(ClockMap, StartsAgainAfterAnOutageLongerThanTheUptimeBefore) {
  // Up for half a second, then gone for five (a battery swap), then up again from 0: its time
  // hardly falls back, but the samples would seem 5 s late.
  ClockMap clock;
  constexpr int kUp = 125, kGapSamples = 250 * 5;
  const auto wall = [](int i) {
    return kClockOffsetUs + int64_t{i < kUp ? i : i + kGapSamples} * kPeriodUs;
  };
  const auto remote = [](int i) { return int64_t{i < kUp ? i : i - kUp} * kPeriodUs; };
  const int64_t worst = worstError(clock, 250 * 20, remote, wall, 4, kUp);
  std::printf("[clock] after an outage longer than the uptime before: worst %lld us\n",
              static_cast<long long>(worst));
  EXPECT_LE(worst, kSettledToleranceUs);
}

}  // namespace
}  // namespace kinfly::actuators
