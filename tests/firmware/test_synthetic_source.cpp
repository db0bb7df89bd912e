// The synthetic camera's clock (sources/synthetic_source.h): frame 0 is stamped once it is
// rendered, not when the source was opened, and a frame whose successor is already due is
// dropped as a camera's would be, so that a late host never sees stamps more than a frame old.
// A hand-driven clock stands in for the wall clock.
#include <gtest/gtest.h>

#include <cstdint>
#include <memory>
#include <string>
#include <utility>

#include "kinfly/sources/synthetic_source.h"

namespace kinfly::fw {
namespace {

constexpr double kRateHz = 10.0;
constexpr int64_t kPeriodUs = 100'000;
constexpr int64_t kOpenedUs = 5'000'000;  // the clock when the source is opened
constexpr int64_t kStartUs = 5'300'000;   // ... and at the first frame, after a slow start

// The source on the clock NOW; null (the test failed) where it does not open.
std::unique_ptr<DepthSource> opened(int64_t* now, bool drop_late) {
  SyntheticSourceParams params;
  params.width_px = 32;
  params.height_px = 24;
  params.rate_hz = kRateHz;
  params.motion = "still";
  params.clock = [now] { return *now; };
  params.drop_late = drop_late;
  StatusOr<std::unique_ptr<DepthSource>> source = openSyntheticSource(params);
  if (!source.ok()) {
    ADD_FAILURE() << source.status().message();
    return nullptr;
  }
  return *std::move(source);
}

TEST(SyntheticSource, StampsFromTheFirstFrameAndDropsWhatTheHostWasTooLateFor) {
  int64_t now = kOpenedUs;
  const std::unique_ptr<DepthSource> source = opened(&now, true);
  ASSERT_NE(source, nullptr);
  DepthCapture capture;
  std::string why;
  now = kStartUs;
  ASSERT_EQ(source->next(&capture, &why), SourceStatus::kFrame);
  EXPECT_EQ(capture.utime, kStartUs);
  // On time (frame 1 is due but frame 2 is not): delivered, stamped on the schedule.
  now = kStartUs + kPeriodUs + kPeriodUs / 2;
  ASSERT_EQ(source->next(&capture, &why), SourceStatus::kFrame);
  EXPECT_EQ(capture.utime, kStartUs + kPeriodUs);
  // 2.5 periods late: frames 2 and 3 are dropped, each saying so; frame 4 is the next.
  now = kStartUs + 4 * kPeriodUs + kPeriodUs / 2;
  for (int frame : {2, 3}) {
    ASSERT_EQ(source->next(&capture, &why), SourceStatus::kSkipped);
    EXPECT_NE(why.find("frame " + std::to_string(frame) + " dropped"), std::string::npos) << why;
  }
  ASSERT_EQ(source->next(&capture, &why), SourceStatus::kFrame);
  EXPECT_EQ(capture.utime, kStartUs + 4 * kPeriodUs);
  EXPECT_LT(now - capture.utime, kPeriodUs);
}

TEST(SyntheticSource, WithoutDroppingEveryFrameComesOnItsSchedule) {
  int64_t now = kOpenedUs;
  const std::unique_ptr<DepthSource> source = opened(&now, false);
  ASSERT_NE(source, nullptr);
  DepthCapture capture;
  std::string why;
  for (int frame = 0; frame < 4; ++frame) {
    ASSERT_EQ(source->next(&capture, &why), SourceStatus::kFrame);
    EXPECT_EQ(capture.utime, kOpenedUs + frame * kPeriodUs);
    now += 10 * kPeriodUs;  // however late the host
  }
}

}  // namespace
}  // namespace kinfly::fw
