// The firmware's logic: the drop-oldest capture queue, keyframe selection, re-anchoring of the
// odometry by ground corrections, the sensor watch, log throttling and the link's send budget.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <chrono>
#include <thread>
#include <vector>

#include "kinfly/fw/backoff.h"
#include "kinfly/fw/bounded_queue.h"
#include "kinfly/fw/correction_anchor.h"
#include "kinfly/fw/keyframe_selector.h"
#include "kinfly/fw/latest_value.h"
#include "kinfly/fw/log_throttle.h"
#include "kinfly/core/range_check.h"
#include "kinfly/fw/send_budget.h"
#include "kinfly/fw/sensor_watch.h"
#include "kinfly/core/camera.h"
#include "kinfly/core/image.h"
#include "test_util.h"

namespace kinfly::fw {
namespace {

using namespace std::chrono_literals;

constexpr double kPoseTolerance = 1e-9;  // double-precision composition of a few transforms

Pose poseAt(double x_m, double yaw_deg = 0.0) {
  Pose T = Pose::Identity();
  T.translation() = Eigen::Vector3d(x_m, 0.0, 0.0);
  T.linear() = Eigen::AngleAxisd(test::degToRad(yaw_deg), Eigen::Vector3d::UnitY()).matrix();
  return T;
}

double poseError(const Pose& a, const Pose& b) {
  return (a.matrix() - b.matrix()).cwiseAbs().maxCoeff();
}

// ---- BoundedQueue -----------------------------------------------------------------------------

TEST(BoundedQueue, DropsTheOldestWhenFullAndCountsIt) {
  BoundedQueue<int> queue(3);
  for (int i = 0; i < 3; ++i) {
    int item = i;
    EXPECT_TRUE(queue.push(item));
  }
  int item = 3;
  EXPECT_FALSE(queue.push(item));
  item = 4;
  EXPECT_FALSE(queue.push(item));
  EXPECT_EQ(queue.dropped(), 2);
  std::vector<int> got;
  while (queue.pop(&item, 0ms)) got.push_back(item);
  EXPECT_EQ(got, (std::vector<int>{2, 3, 4}));
}

TEST(BoundedQueue, PopWaitsAndCloseWakesIt) {
  BoundedQueue<int> queue(2);
  int item = 0;
  EXPECT_FALSE(queue.pop(&item, 10ms));
  std::thread producer([&] {
    std::this_thread::sleep_for(20ms);
    int value = 7;
    queue.push(value);
  });
  EXPECT_TRUE(queue.pop(&item, 5s));
  EXPECT_EQ(item, 7);
  producer.join();
  std::thread closer([&] {
    std::this_thread::sleep_for(20ms);
    queue.close();
  });
  const auto start = std::chrono::steady_clock::now();
  EXPECT_FALSE(queue.pop(&item, 5s));
  EXPECT_LT(std::chrono::steady_clock::now() - start, 4s);  // woken by close, not the timeout
  closer.join();
}

// Frames swap through the slots, so once every slot has held an image the producer gets a
// buffer of the right size back with every push: no allocation in steady state.
TEST(BoundedQueue, ImagesKeepTheirBuffersThroughTheSlots) {
  BoundedQueue<Image<uint16_t>> queue(2);
  std::vector<const uint16_t*> buffers;
  Image<uint16_t> frame(4, 3), out;
  for (int i = 0; i < 6; ++i) {
    if (frame.width() != 4) frame = Image<uint16_t>(4, 3);
    frame(0, 0) = static_cast<uint16_t>(i);
    buffers.push_back(frame.data());
    queue.push(frame);
  }
  ASSERT_TRUE(queue.pop(&out, 0ms));
  EXPECT_EQ(out(0, 0), 4);
  // Six pushes through two slots and the producer's own image: three buffers, reused.
  std::sort(buffers.begin(), buffers.end());
  EXPECT_LE(std::unique(buffers.begin(), buffers.end()) - buffers.begin(), 3);
}

// ---- LatestValue ------------------------------------------------------------------------------

TEST(LatestValue, TheReaderGetsTheNewestPublishedValueOnce) {
  LatestValue<int> latest(-1);
  EXPECT_FALSE(latest.fetch());  // nothing published yet
  latest.back() = 1;
  latest.publish();
  latest.back() = 2;
  latest.publish();  // overwrites 1, which was never fetched
  ASSERT_TRUE(latest.fetch());
  EXPECT_EQ(latest.front(), 2);
  EXPECT_FALSE(latest.fetch());  // no newer value: front() stays
  EXPECT_EQ(latest.front(), 2);
  latest.back() = 3;
  latest.publish();
  ASSERT_TRUE(latest.fetch());
  EXPECT_EQ(latest.front(), 3);
}

TEST(LatestValue, AReaderBesideAWriterNeverSeesATornOrOlderValue) {
  // Every word of a value is the same sequence number: a torn read mixes two of them.
  using Value = std::array<int64_t, 32>;
  constexpr int64_t kWrites = 200000;
  LatestValue<Value> latest(Value{});
  std::atomic<bool> done{false};
  std::thread writer([&] {
    for (int64_t n = 1; n <= kWrites; ++n) {
      latest.back().fill(n);
      latest.publish();
    }
    done = true;
  });
  int64_t last = 0, fetched = 0, torn = 0, backwards = 0;
  // The last fetch after `done` is read is sure to find the writer's final value.
  for (bool finished = false; !finished;) {
    finished = done.load();
    if (!latest.fetch()) continue;
    const Value& v = latest.front();
    ++fetched;
    if (std::any_of(v.begin(), v.end(), [&](int64_t w) { return w != v[0]; })) ++torn;
    if (v[0] <= last) ++backwards;
    last = v[0];
  }
  writer.join();
  EXPECT_EQ(torn, 0);
  EXPECT_EQ(backwards, 0);
  EXPECT_EQ(last, kWrites);
  EXPECT_GT(fetched, 0);
}

// ---- KeyframeSelector -------------------------------------------------------------------------

constexpr int64_t kSecond = 1'000'000;

TEST(KeyframeSelector, MotionOrTimeMakesAKeyframeButNotFasterThanTheMinimum) {
  KeyframeSelector::Params p;
  ASSERT_TRUE(p.validate().ok());
  KeyframeSelector selector(p);
  int64_t t = 0;
  EXPECT_TRUE(selector.select(poseAt(0.0), t, TrackingStatus::kFirstFrame, 1.f));
  t += kSecond / 5;
  EXPECT_FALSE(selector.select(poseAt(0.05), t, TrackingStatus::kOk, 0.9f));  // too little
  t += kSecond / 5;
  EXPECT_TRUE(selector.select(poseAt(0.12), t, TrackingStatus::kOk, 0.9f));   // 12 cm
  t += kSecond / 20;
  EXPECT_FALSE(selector.select(poseAt(0.5), t, TrackingStatus::kOk, 0.9f));   // within 0.1 s
  t += kSecond / 5;
  EXPECT_TRUE(selector.select(poseAt(0.12, 11.0), t, TrackingStatus::kOk, 0.9f));  // 11 degrees
  t += kSecond;
  EXPECT_TRUE(selector.select(poseAt(0.12, 11.0), t, TrackingStatus::kOk, 0.9f));  // 1 s, still
}

TEST(KeyframeSelector, LostFramesAndAPoorFirstFrameAreNeverKeyframes) {
  const KeyframeSelector::Params p;
  KeyframeSelector selector(p);
  EXPECT_FALSE(selector.select(poseAt(0.0), 0, TrackingStatus::kLost, 0.f));
  EXPECT_FALSE(selector.select(poseAt(0.0), 0, TrackingStatus::kOk, p.min_inlier_fraction * 0.9f));
  EXPECT_TRUE(selector.select(poseAt(0.0), 0, TrackingStatus::kOk, p.min_inlier_fraction));
  EXPECT_FALSE(selector.select(poseAt(1.0), 5 * kSecond, TrackingStatus::kLost, 0.f));
}

// A frame tracked, but below min_inlier_fraction (far range's noise), becomes a keyframe only
// once the camera is about to leave the last keyframe's view: past max_gap_rotation_rad or
// max_gap_translation_m; a lost frame never; and time alone never makes one of it.
TEST(KeyframeSelector, APoorlyTrackedFrameIsAKeyframeBeforeTheViewIsLeft) {
  const KeyframeSelector::Params p;
  const float poor = p.min_inlier_fraction * 0.5f;
  const double gap_deg = p.max_gap_rotation_rad * 180.0 / M_PI;
  KeyframeSelector selector(p);
  int64_t t = 0;
  ASSERT_TRUE(selector.select(poseAt(0.0), t, TrackingStatus::kFirstFrame, 1.f));
  t += 5 * kSecond;  // long past max_interval_s
  EXPECT_FALSE(selector.select(poseAt(0.0, gap_deg * 0.9), t, TrackingStatus::kOk, poor));
  t += kSecond / 5;
  EXPECT_FALSE(selector.select(poseAt(0.0, gap_deg * 1.1), t, TrackingStatus::kLost, 0.f));
  EXPECT_TRUE(selector.select(poseAt(0.0, gap_deg * 1.1), t, TrackingStatus::kOk, poor));
  t += kSecond / 5;
  EXPECT_FALSE(selector.select(poseAt(p.max_gap_translation_m * 0.9, gap_deg * 1.1), t,
                               TrackingStatus::kOk, poor));
  EXPECT_TRUE(selector.select(poseAt(p.max_gap_translation_m * 1.1, gap_deg * 1.1), t,
                              TrackingStatus::kOk, poor));
  // Never faster than min_interval_s.
  t += kSecond / 20;
  EXPECT_FALSE(selector.select(poseAt(2.0, 3.0 * gap_deg), t, TrackingStatus::kOk, poor));
  // The first frame after a restart is a keyframe only if it is well tracked, and time running
  // backwards forgets the old reference for the poorly tracked frames after it as well.
  KeyframeSelector fresh(p);
  EXPECT_FALSE(fresh.select(poseAt(0.0), 0, TrackingStatus::kOk, poor));
  ASSERT_TRUE(fresh.select(poseAt(0.0), 10 * kSecond, TrackingStatus::kFirstFrame, 1.f));
  EXPECT_FALSE(fresh.select(poseAt(0.0), 1 * kSecond, TrackingStatus::kOk, poor));
  EXPECT_FALSE(fresh.select(poseAt(2.0, 3.0 * gap_deg), 11 * kSecond, TrackingStatus::kOk, poor))
      << "compared with the pose from before the restart";
  // A gap set below the normal thresholds is held at them.
  KeyframeSelector::Params low = p;
  low.max_gap_rotation_rad = 0.01;
  low.max_gap_translation_m = 0.01;
  ASSERT_TRUE(low.validate().ok());
  KeyframeSelector held(low);
  ASSERT_TRUE(held.select(poseAt(0.0), 0, TrackingStatus::kFirstFrame, 1.f));
  EXPECT_FALSE(held.select(poseAt(0.05, 5.0), kSecond, TrackingStatus::kOk, poor));
}

// What a camera at T_world_cam sees of a wall 3.6 m ahead of the world's origin (z = 3.6),
// where only the part at x >= x_min_m is within the sensor's range (the rest, like the hall's
// corners, is too far to measure): the coarsest level of the drone's 320x240 pyramid.
struct WallView {
  PinholeCamera camera{65.6f, 65.6f, 39.5f, 29.5f, 80, 60};
  Image<float> depth_m{80, 60};
  KeyframeSelector::View view() const { return {depth_m.view(), camera}; }
};

WallView wallView(const Pose& T_world_cam, double x_min_m) {
  WallView w;
  const Eigen::Matrix3d R = T_world_cam.linear();
  for (int y = 0; y < w.camera.height; ++y)
    for (int x = 0; x < w.camera.width; ++x) {
      const Eigen::Vector3d ray = w.camera.backProject(static_cast<float>(x), static_cast<float>(y), 1.f).cast<double>();  // z = 1
      const Eigen::Vector3d d = R * ray;
      const double t = (3.6 - T_world_cam.translation().z()) / d.z();  // camera z = t
      const double x_world = T_world_cam.translation().x() + t * d.x();
      w.depth_m(x, y) = d.z() > 0.0 && x_world >= x_min_m ? static_cast<float>(t) : NAN;
    }
  return w;
}

// The same 20 degree turn, short of max_gap_rotation_rad, by a frame tracked poorly (far
// range): a keyframe when the last keyframe saw only the wall's right end (the turn brings in
// mostly what it never saw), not when it saw the whole wall (two thirds are shared).
TEST(KeyframeSelector, AFrameSeeingLittleOfWhatTheLastKeyframeSawIsAKeyframe) {
  KeyframeSelector::Params p;
  p.min_covisibility = 0.6f;  // the value measured in the hall (keyframe_selector.h)
  ASSERT_TRUE(p.validate().ok());
  const float poor = p.min_inlier_fraction * 0.5f;
  const double turn_deg = 20.0;
  ASSERT_LT(test::degToRad(turn_deg), p.max_gap_rotation_rad);
  for (const double x_min_m : {-100.0, 0.5}) {
    SCOPED_TRACE(x_min_m);
    KeyframeSelector selector(p);
    const WallView first = wallView(poseAt(0.0), x_min_m);
    ASSERT_TRUE(selector.select(poseAt(0.0), 0, TrackingStatus::kFirstFrame, 1.f, first.view()));
    EXPECT_NEAR(selector.covisibility(poseAt(0.0), first.view()), 1.f, 1e-6f)
        << "the keyframe's own view is all shared";
    const WallView turned = wallView(poseAt(0.0, turn_deg), x_min_m);
    const float shared = selector.covisibility(poseAt(0.0, turn_deg), turned.view());
    std::printf("covisibility after a %.0f degree turn, the wall measured from x = %.1f m: %.3f\n",
                turn_deg, x_min_m, shared);
    const bool taken =
        selector.select(poseAt(0.0, turn_deg), kSecond, TrackingStatus::kOk, poor, turned.view());
    if (x_min_m < 0.0) {
      EXPECT_GT(shared, p.min_covisibility);
      EXPECT_FALSE(taken);
    } else {
      EXPECT_LT(shared, p.min_covisibility);
      EXPECT_TRUE(taken);
    }
  }
  // Something that came 0.5 m nearer than the wall the keyframe saw is not what it saw.
  KeyframeSelector selector(p);
  const WallView wall = wallView(poseAt(0.0), -100.0);
  ASSERT_TRUE(selector.select(poseAt(0.0), 0, TrackingStatus::kFirstFrame, 1.f, wall.view()));
  WallView nearer = wallView(poseAt(0.0), -100.0);
  for (int i = 0; i < nearer.depth_m.numPixels(); ++i) nearer.depth_m.data()[i] -= 0.5f;
  EXPECT_EQ(selector.covisibility(poseAt(0.0), nearer.view()), 0.f);
  // Without a view (or with the rule off) only the motion rules decide.
  EXPECT_EQ(selector.covisibility(poseAt(0.0), {}), 1.f);
  KeyframeSelector::Params off = p;
  off.min_covisibility = 0.f;
  KeyframeSelector blind(off);
  const WallView corner = wallView(poseAt(0.0), 0.5);
  ASSERT_TRUE(blind.select(poseAt(0.0), 0, TrackingStatus::kFirstFrame, 1.f, corner.view()));
  const WallView turned = wallView(poseAt(0.0, turn_deg), 0.5);
  EXPECT_FALSE(blind.select(poseAt(0.0, turn_deg), kSecond, TrackingStatus::kOk, poor, turned.view()));
}

TEST(KeyframeSelector, TimeRunningBackwardsRestartsTheReference) {
  KeyframeSelector selector(KeyframeSelector::Params{});
  EXPECT_TRUE(selector.select(poseAt(0.0), 10 * kSecond, TrackingStatus::kFirstFrame, 1.f));
  EXPECT_TRUE(selector.select(poseAt(0.0), 1 * kSecond, TrackingStatus::kFirstFrame, 1.f));
}

TEST(KeyframeSelector, ValidateNamesTheBadValue) {
  KeyframeSelector::Params p;
  p.min_interval_s = 2.0;
  EXPECT_NE(p.validate().message().find("min_interval_s"), std::string::npos);
  p = KeyframeSelector::Params{};
  p.min_translation_m = -1.0;
  EXPECT_NE(p.validate().message().find("min_translation_m"), std::string::npos);
  p = KeyframeSelector::Params{};
  p.max_gap_rotation_rad = 4.0;
  EXPECT_NE(p.validate().message().find("max_gap_rotation_rad"), std::string::npos);
  p = KeyframeSelector::Params{};
  p.max_gap_translation_m = 0.0;
  EXPECT_NE(p.validate().message().find("max_gap_translation_m"), std::string::npos);
  p = KeyframeSelector::Params{};
  p.min_covisibility = 1.f;
  EXPECT_NE(p.validate().message().find("min_covisibility"), std::string::npos);
}

// ---- CorrectionAnchor -------------------------------------------------------------------------

TEST(CorrectionAnchor, MovesThePublishedPoseByTheKeyframesCorrection) {
  CorrectionAnchor anchor(CorrectionAnchor::Params{});
  const Pose kf_odom = poseAt(1.0, 20.0);
  anchor.rememberKeyframe(5, kf_odom);
  // The ground says keyframe 5 was really 3 cm further and rotated 1 degree more.
  const Pose kf_world = poseAt(1.03, 21.0);
  ASSERT_EQ(anchor.apply(5, kf_world, 0), CorrectionAnchor::Outcome::kApplied);
  // The keyframe itself maps exactly onto its correction ...
  EXPECT_LT(poseError(anchor.toWorld(kf_odom), kf_world), kPoseTolerance);
  // ... and a later frame keeps its odometry motion relative to the keyframe.
  const Pose later_odom = kf_odom * poseAt(0.2, 5.0);
  EXPECT_LT(poseError(anchor.toWorld(later_odom), kf_world * poseAt(0.2, 5.0)), kPoseTolerance);
}

TEST(CorrectionAnchor, UnknownAndOutOfOrderCorrectionsAreRefused) {
  CorrectionAnchor::Params p;
  p.history_keyframes = 4;
  CorrectionAnchor anchor(p);
  for (int64_t id = 0; id < 6; ++id) anchor.rememberKeyframe(id, poseAt(0.1 * static_cast<double>(id)));
  EXPECT_EQ(anchor.apply(1, poseAt(0.1), 0), CorrectionAnchor::Outcome::kUnknownKeyframe);  // evicted
  EXPECT_EQ(anchor.apply(9, poseAt(0.1), 0), CorrectionAnchor::Outcome::kUnknownKeyframe);  // future
  EXPECT_EQ(anchor.apply(-1, poseAt(0.1), 0), CorrectionAnchor::Outcome::kUnknownKeyframe);
  EXPECT_EQ(anchor.apply(5, poseAt(0.52), 1), CorrectionAnchor::Outcome::kApplied);
  const Pose before = anchor.T_world_odom();
  EXPECT_EQ(anchor.apply(4, poseAt(0.9), 2), CorrectionAnchor::Outcome::kOutOfOrder);
  EXPECT_LT(poseError(anchor.T_world_odom(), before), kPoseTolerance);
  EXPECT_EQ(anchor.resetCounter(), 1);
}

TEST(SensorWatch, AStallIsCountedOnceAndItsLengthReportedWhenFramesResume) {
  SensorWatch::Params p;
  p.stall_timeout_s = 1.0;
  SensorWatch watch(p);
  EXPECT_EQ(watch.update(0.0, -1.0, false, false), SensorWatch::Change::kNone);
  EXPECT_EQ(watch.update(0.5, 0.4, false, false), SensorWatch::Change::kNone);
  EXPECT_EQ(watch.update(1.3, 0.4, false, false), SensorWatch::Change::kNone);  // 0.9 s: not yet
  EXPECT_EQ(watch.update(1.5, 0.4, false, false), SensorWatch::Change::kStalled);
  EXPECT_EQ(watch.state(), SensorWatch::State::kStalled);
  EXPECT_EQ(watch.update(3.0, 0.4, false, false), SensorWatch::Change::kNone);  // same stall
  EXPECT_EQ(watch.update(3.2, 3.1, false, false), SensorWatch::Change::kResumed);
  EXPECT_NEAR(watch.lastStallS(), 2.7, 1e-9);
  EXPECT_EQ(watch.stalls(), 1);
  EXPECT_EQ(watch.update(5.0, 3.1, false, false), SensorWatch::Change::kStalled);
  EXPECT_EQ(watch.stalls(), 2);
}

TEST(SensorWatch, NoFirstFrameWithinTheTimeoutIsAStall) {
  SensorWatch watch(SensorWatch::Params{});
  EXPECT_EQ(watch.update(10.0, -1.0, false, false), SensorWatch::Change::kNone);
  EXPECT_EQ(watch.update(11.5, -1.0, false, false), SensorWatch::Change::kStalled);
}

TEST(SensorWatch, WaitingForTheDeviceAndTheEndAreNotStalls) {
  SensorWatch watch(SensorWatch::Params{});
  EXPECT_EQ(watch.update(0.0, -1.0, true, false), SensorWatch::Change::kWaiting);
  EXPECT_EQ(watch.update(30.0, -1.0, true, false), SensorWatch::Change::kNone);
  EXPECT_EQ(watch.state(), SensorWatch::State::kWaiting);
  EXPECT_EQ(watch.update(30.1, 30.05, false, false), SensorWatch::Change::kNone);
  EXPECT_EQ(watch.state(), SensorWatch::State::kStreaming);
  EXPECT_EQ(watch.update(40.0, 30.05, false, true), SensorWatch::Change::kEnded);
  EXPECT_EQ(watch.update(41.0, 30.05, false, true), SensorWatch::Change::kNone);
  EXPECT_EQ(watch.stalls(), 0);
}

TEST(SensorWatch, ValidateNamesTheBadValue) {
  SensorWatch::Params p;
  p.stall_timeout_s = 0.0;
  EXPECT_NE(p.validate().message().find("source.stall_timeout_s"), std::string::npos);
}

TEST(LogThrottle, FirstThenAtMostOncePerPeriodWithTheCountLeftOut) {
  LogThrottle throttle(1.0);
  EXPECT_TRUE(throttle.allow(0.0));
  EXPECT_EQ(throttle.suppressed(), 0);
  for (int i = 1; i <= 9; ++i) EXPECT_FALSE(throttle.allow(0.1 * i));
  EXPECT_TRUE(throttle.allow(1.0));
  EXPECT_EQ(throttle.suppressed(), 9);
  EXPECT_TRUE(throttle.allow(5.0));
  EXPECT_EQ(throttle.suppressed(), 0);
}

TEST(Backoff, DoublesUpToTheCeilingAndStartsOverAfterAReset) {
  Backoff backoff(0.5, 3.0);
  EXPECT_DOUBLE_EQ(backoff.next(), 0.5);
  EXPECT_DOUBLE_EQ(backoff.next(), 1.0);
  EXPECT_DOUBLE_EQ(backoff.next(), 2.0);
  EXPECT_DOUBLE_EQ(backoff.next(), 3.0);
  EXPECT_DOUBLE_EQ(backoff.next(), 3.0);
  backoff.reset();
  EXPECT_DOUBLE_EQ(backoff.next(), 0.5);
}

TEST(RangeCheck, NamesTheKeyTheRangeAndTheValue) {
  EXPECT_TRUE(outOfRange("source.speed", 1.0, 0, 100, Bound::kOpen).ok());
  EXPECT_EQ(outOfRange("source.speed", 0.0, 0, 100, Bound::kOpen).message(),
            "source.speed must be in (0, 100] (got 0)");
  EXPECT_TRUE(outOfRange("link.final_wait_s", 0.0, 0, 60).ok());
  EXPECT_EQ(outOfRange("link.final_wait_s", 61.0, 0, 60).message(),
            "link.final_wait_s must be in [0, 60] (got 61)");
  EXPECT_FALSE(outOfRange("odometry.threads", std::nan(""), 1, 64).ok());
}

TEST(RangeCheck, FirstErrorIsTheFirstFailedCheck) {
  EXPECT_EQ(firstError(Status(), Status::error("b"), Status::error("c")).message(), "b");
  EXPECT_TRUE(firstError(Status(), Status()).ok());
}

// ---- Send budget ------------------------------------------------------------------------------

TEST(TokenBucket, SendsAtItsRateAfterTheBurst) {
  TokenBucket bucket(/*rate_Bps=*/10000.0, /*burst_bytes=*/3000.0);
  constexpr double kPacket = 1000.0, kStep_s = 1e-3;
  double sent = 0.0;
  for (double t = 0.0; t < 10.0; t += kStep_s)
    while (bucket.take(kPacket, t)) sent += kPacket;
  // 10 s at the rate plus the first burst, within one packet (the last one not yet due).
  EXPECT_NEAR(sent, 10.0 * 10000.0 + 3000.0, kPacket);
  // A new rate holds from the next refill on: an empty bucket at 1000 B/s needs 1 s per packet.
  bucket.setRate(1000.0);
  const double wait_s = bucket.waitS(kPacket, 10.0);
  EXPECT_GT(wait_s, 0.0);
  EXPECT_LE(wait_s, 1.0);
}

TEST(TokenBucket, WaitIsExactlyTheTimeTheTokensNeed) {
  TokenBucket bucket(1000.0, 500.0);
  ASSERT_TRUE(bucket.take(500.0, 0.0));
  EXPECT_DOUBLE_EQ(bucket.waitS(200.0, 0.0), 0.2);
  EXPECT_DOUBLE_EQ(bucket.waitS(200.0, 0.1), 0.1);
  EXPECT_FALSE(bucket.take(200.0, 0.1));
  EXPECT_TRUE(bucket.take(200.0, 0.2));
  EXPECT_DOUBLE_EQ(bucket.waitS(1.0, 0.2), 0.001);
  // What had to go out at once is paid for by what can wait.
  bucket.charge(1000.0, 0.2);
  EXPECT_DOUBLE_EQ(bucket.waitS(100.0, 0.2), 1.1);
}

// The drone's order of precedence (docs/wire.md, "Priorities"): small messages go out at once
// and are charged to the bucket; keyframes get what they leave of the budget.
TEST(TokenBucket, SmallMessagesGoFirstAndKeyframesGetWhatTheyLeave) {
  constexpr double kRate_Bps = 10000.0, kBurst = 3000.0, kChunk = 1000.0, kStep_s = 1e-3;
  constexpr double kSmall = 50.0, kSmallPeriod_s = 0.025;  // 2000 B/s of status and poses
  TokenBucket bucket(kRate_Bps, kBurst);
  double keyframe_bytes = 0.0, small_bytes = 0.0, next_small_s = 0.0;
  for (double t = 0.0; t < 10.0; t += kStep_s) {
    if (t >= next_small_s) {
      bucket.charge(kSmall, t);
      small_bytes += kSmall;
      next_small_s += kSmallPeriod_s;
    }
    while (bucket.take(kChunk, t)) keyframe_bytes += kChunk;
  }
  EXPECT_NEAR(small_bytes, 10.0 * 2000.0, kSmall);
  // Together no more than the budget (and its first burst); keyframes had the rest.
  EXPECT_NEAR(keyframe_bytes + small_bytes, 10.0 * kRate_Bps + kBurst, kChunk + kSmall);
}

// A bottleneck as a fluid queue: the drone offers its whole budget (it always has keyframes to
// send), the link carries capacity_bps, the excess waits in the queue; the ground reports the
// goodput over the last second and the queueing delay, one report every 0.1 s, heard 20 ms
// later. Returns the budget's and the queue's medians over [from_s, to_s).
struct Bottleneck {
  explicit Bottleneck(double capacity, double random_loss = 0.0, double queue_limit = 1e9)
      : capacity_bps(capacity), loss(random_loss), queue_limit_ms(queue_limit) {}
  double capacity_bps;
  double loss;  // random loss: fewer bits arrive, nothing queues
  double queue_limit_ms;  // beyond it the queue drops what is offered, as a tbf cap
  double queue_bits = 0.0;
  std::vector<double> delivered_bps;  // per 10 ms step, the last second's worth

  void step(double offered_bps, double dt_s) {
    queue_bits = std::min(queue_bits + offered_bps * dt_s, queue_limit_ms * 1e-3 * capacity_bps);
    const double out = std::min(queue_bits, capacity_bps * dt_s);
    queue_bits -= out;
    delivered_bps.push_back(out * (1.0 - loss) / dt_s);
    if (delivered_bps.size() > 100) delivered_bps.erase(delivered_bps.begin());
  }
  double goodputBps() const {
    double sum = 0.0;
    for (double b : delivered_bps) sum += b;
    return delivered_bps.empty() ? 0.0 : sum / static_cast<double>(delivered_bps.size());
  }
  double queueMs() const { return 1e3 * queue_bits / capacity_bps; }
};

double median(std::vector<double> values) {
  std::nth_element(values.begin(), values.begin() + static_cast<long>(values.size() / 2),
                   values.end());
  return values[values.size() / 2];
}

struct Flight {
  std::vector<double> t_s, budget_bps, queue_ms;
  double medianOf(const std::vector<double>& v, double from_s, double to_s) const {
    std::vector<double> in;
    for (size_t i = 0; i < t_s.size(); ++i)
      if (t_s[i] >= from_s && t_s[i] < to_s) in.push_back(v[i]);
    return median(in);
  }
};

Flight fly(LinkRate* rate, Bottleneck* link, double seconds,
           double capacity_after_bps = 0.0, double change_s = 1e9) {
  constexpr double kDt_s = 0.01, kReportEvery_s = 0.1, kReportDelay_s = 0.02;
  Flight flight;
  struct Report { double at_s, goodput_bps, queue_ms; };
  std::vector<Report> in_flight;
  double next_report_s = kReportEvery_s;
  for (double t = 0.0; t < seconds; t += kDt_s) {
    if (t >= change_s && capacity_after_bps > 0.0) link->capacity_bps = capacity_after_bps;
    link->step(rate->budgetBps(), kDt_s);
    if (t >= next_report_s) {
      in_flight.push_back({t + kReportDelay_s, link->goodputBps(), link->queueMs()});
      next_report_s += kReportEvery_s;
    }
    while (!in_flight.empty() && in_flight.front().at_s <= t) {
      rate->onReport(in_flight.front().goodput_bps, in_flight.front().queue_ms,
                     /*limited=*/true, t);
      in_flight.erase(in_flight.begin());
    }
    flight.t_s.push_back(t);
    flight.budget_bps.push_back(rate->budgetBps());
    flight.queue_ms.push_back(link->queueMs());
  }
  return flight;
}

TEST(LinkRate, FindsTheCapacityAndKeepsTheQueueShort) {
  LinkRate rate{LinkRate::Params()};  // starts at 8 Mbit/s
  Bottleneck link(5e6);
  const Flight f = fly(&rate, &link, 60.0);
  const double budget = f.medianOf(f.budget_bps, 10.0, 60.0);
  // Settles below the capacity (it backs off to 0.85 of the goodput and climbs back), and not
  // far below: at least 70 % of the link used.
  EXPECT_GT(budget, 0.7 * 5e6);
  EXPECT_LT(budget, 1.05 * 5e6);
  EXPECT_LT(f.medianOf(f.queue_ms, 10.0, 60.0), LinkRate::Params().queue_high_ms);
}

TEST(LinkRate, FollowsACapacityDropWithinTwoSeconds) {
  LinkRate rate{LinkRate::Params()};
  Bottleneck link(5e6);
  const Flight f = fly(&rate, &link, 40.0, /*capacity_after_bps=*/2e6, /*change_s=*/20.0);
  EXPECT_LT(f.medianOf(f.budget_bps, 22.0, 24.0), 2e6);
  EXPECT_GT(f.medianOf(f.budget_bps, 30.0, 40.0), 0.7 * 2e6);
  EXPECT_LT(f.medianOf(f.queue_ms, 25.0, 40.0), LinkRate::Params().queue_high_ms);
}

// A start at 8 Mbit/s into a 2 Mbit/s link whose first reported second was mostly idle (the
// first keyframe came late in it): the budget halves at most per report, so it does not drop to
// the floor and spend seconds climbing back.
TEST(LinkRate, AColdStartIntoASlowLinkDoesNotFallToTheFloor) {
  LinkRate rate{LinkRate::Params()};  // starts at 8 Mbit/s
  Bottleneck link(2e6, 0.0, /*queue_limit_ms=*/100.0);  // a tbf cap's queue
  link.delivered_bps.assign(90, 0.0);  // 0.9 s idle before the first keyframe
  const Flight f = fly(&rate, &link, 10.0);
  EXPECT_GT(*std::min_element(f.budget_bps.begin(), f.budget_bps.end()), 0.5 * 2e6);
  EXPECT_GT(f.medianOf(f.budget_bps, 2.0, 10.0), 0.7 * 2e6);
  EXPECT_LT(f.medianOf(f.queue_ms, 2.0, 10.0), LinkRate::Params().queue_high_ms);
}

TEST(LinkRate, RandomLossWithoutAQueueIsNoReasonToSendLess) {
  LinkRate::Params params;
  params.start_bps = 4e6;
  LinkRate rate(params);
  Bottleneck link(50e6, /*random_loss=*/0.10);  // far more capacity than max_bps: never a queue
  fly(&rate, &link, 30.0);
  EXPECT_EQ(rate.decreases(), 0);
  EXPECT_DOUBLE_EQ(rate.budgetBps(), params.max_bps);
}

TEST(LinkRate, DoesNotGrowWhenTheDroneHadLessToSend) {
  LinkRate rate{LinkRate::Params()};
  for (int i = 0; i < 100; ++i) rate.onReport(1e6, 0.0, /*limited=*/false, 0.1 * i);
  EXPECT_DOUBLE_EQ(rate.budgetBps(), LinkRate::Params().start_bps);
}

TEST(LinkRate, ValidateNamesTheBadValue) {
  LinkRate::Params params;
  params.queue_low_ms = 50.0;  // above queue_high_ms
  EXPECT_EQ(params.validate().message(), "link.queue_low_ms must be in [0, 40] (got 50)");
  EXPECT_TRUE(LinkRate::Params().validate().ok());
}

TEST(KeyframeScale, ShrinksBelowTheMinimumRateAndGrowsBackWithSpare) {
  const KeyframeScale::Params p;  // 1 Hz minimum, hysteresis 1.5, down to 1/4
  constexpr double kFull = 100e3;  // [bytes] a full-size keyframe on the wire
  EXPECT_EQ(KeyframeScale::choose(p, 1, 2 * kFull, {kFull, 0, 0}), 1);
  EXPECT_EQ(KeyframeScale::choose(p, 1, 0.5 * kFull, {kFull, 0, 0}), 2);
  EXPECT_EQ(KeyframeScale::choose(p, 2, 0.1 * kFull, {kFull, kFull / 4, 0}), 4);
  EXPECT_EQ(KeyframeScale::choose(p, 4, 0.01 * kFull, {0, 0, kFull / 16}), 4);  // the smallest
  // Back to full size only when full-size keyframes would come at 1.5 Hz.
  EXPECT_EQ(KeyframeScale::choose(p, 2, 1.2 * kFull, {0, kFull / 4, 0}), 2);
  EXPECT_EQ(KeyframeScale::choose(p, 2, 1.6 * kFull, {0, kFull / 4, 0}), 1);
  EXPECT_EQ(KeyframeScale::choose(p, 1, kFull, {0, 0, 0}), 1);  // nothing sent yet
}

// A subsampled image compresses worse: what a larger size cost when it was last sent decides
// when it returns, not the four times the bytes a step would cost by the pixel count.
TEST(KeyframeScale, AMeasuredCostWinsOverTheEstimate) {
  const KeyframeScale::Params p;
  constexpr double kQuarter = 6e3, kHalf = 14e3;  // [bytes] as measured: 2.3 times, not 4
  EXPECT_DOUBLE_EQ(KeyframeScale::cost({0, 0, kQuarter}, 2), 4 * kQuarter);
  EXPECT_DOUBLE_EQ(KeyframeScale::cost({0, 0, kQuarter}, 1), 16 * kQuarter);
  EXPECT_DOUBLE_EQ(KeyframeScale::cost({0, kHalf, kQuarter}, 1), 4 * kHalf);
  // 25 kB/s: half-size keyframes at 1.8 Hz as measured, above 1.5 x 1 Hz; by the estimate only
  // at 1.04 Hz.
  EXPECT_EQ(KeyframeScale::choose(p, 4, 25e3, {0, kHalf, kQuarter}), 2);
  EXPECT_EQ(KeyframeScale::choose(p, 4, 25e3, {0, 0, kQuarter}), 4);
}

TEST(KeyframeScale, ParamsAreValidated) {
  KeyframeScale::Params bad;
  bad.max_scale = 3;
  EXPECT_EQ(bad.validate().message(), "link.max_scale must be 1, 2 or 4 (got 3)");
}

}  // namespace
}  // namespace kinfly::fw
