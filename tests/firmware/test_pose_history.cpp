// PoseHistory: the camera's motion between two times, interpolated between stored poses, and
// none outside what is stored; PredictedTrack: the estimate's jumps between samples are no
// motion.
#include <gtest/gtest.h>

#include <cmath>

#include "kinfly/flight/pose_history.h"

namespace kinfly::flight {
namespace {

constexpr double kTol = 1e-9;  // [m] and [rad]: interpolation is exact for these motions
constexpr int64_t kAnySpanUs = 1'000'000'000;  // [µs] longer than any motion asked for here

// A camera turning about z at 1 rad/s and moving along x at 1 m/s, from t = 0.
Pose cameraAt(int64_t utime) {
  const double t = static_cast<double>(utime) * 1e-6;
  Pose T = Pose::Identity();
  T.linear() = Eigen::AngleAxisd(t, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(t, 0.0, 0.0);
  return T;
}

double poseError(const Pose& a, const Pose& b) {
  const Pose d = a.inverse() * b;
  return d.translation().norm() + Eigen::AngleAxisd(d.linear()).angle();
}

TEST(PoseHistory, MotionBetweenTwoTimesIsInterpolatedBetweenSamples) {
  PoseHistory history(100, kAnySpanUs);
  for (int64_t u = 0; u <= 50000; u += 5000) history.add(u, cameraAt(u));
  // Between samples (12.5 ms and 37.5 ms): slerp and a straight line are exact for a constant
  // rate and speed.
  const std::optional<Pose> motion = history.motion(12500, 37500);
  ASSERT_TRUE(motion.has_value());
  EXPECT_LT(poseError(*motion, cameraAt(12500).inverse() * cameraAt(37500)), kTol);
  // Between stored times, and from a time to itself: no motion.
  ASSERT_TRUE(history.motion(5000, 50000).has_value());
  EXPECT_LT(poseError(*history.motion(5000, 50000), cameraAt(5000).inverse() * cameraAt(50000)),
            kTol);
  ASSERT_TRUE(history.motion(20000, 20000).has_value());
  EXPECT_LT(poseError(*history.motion(20000, 20000), Pose::Identity()), kTol);
}

TEST(PoseHistory, NoMotionOutsideTheHistory) {
  PoseHistory history(4, kAnySpanUs);
  for (int64_t u = 0; u <= 50000; u += 5000) history.add(u, cameraAt(u));
  // The ring kept the last four: 35, 40, 45 and 50 ms.
  EXPECT_FALSE(history.motion(30000, 40000).has_value());  // forgotten
  EXPECT_FALSE(history.motion(40000, 55000).has_value());  // not yet seen
  EXPECT_TRUE(history.motion(35000, 40000).has_value());
  EXPECT_TRUE(history.motion(42000, 48000).has_value());
  // A time that does not increase is ignored.
  history.add(50000, Pose::Identity());
  ASSERT_TRUE(history.motion(45000, 50000).has_value());
  EXPECT_LT(poseError(*history.motion(45000, 50000), cameraAt(45000).inverse() * cameraAt(50000)),
            kTol);
}

// An estimate that follows the camera but jumps between samples: by a fused pose's pull along
// the view and by a reset that moves and turns it. The track keeps each sample's step only, so
// its motion is the camera's across both; the estimate's own poses would carry the jumps into
// the odometry's prior.
TEST(PredictedTrack, JumpsOfTheEstimateBetweenSamplesAreNoMotion) {
  Pose pull = Pose::Identity(), reset = Pose::Identity();
  pull.translation() = Eigen::Vector3d(0.0, 0.0, -0.13);
  reset.linear() = Eigen::AngleAxisd(0.2, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  reset.translation() = Eigen::Vector3d(1.0, -2.0, 0.5);
  const auto offset = [&](int64_t u) {
    return u < 20000 ? Pose::Identity() : u < 35000 ? pull : reset * pull;
  };
  PoseHistory history(100, kAnySpanUs), estimate(100, kAnySpanUs);
  PredictedTrack track;
  for (int64_t u = 5000; u <= 50000; u += 5000) {
    // The sample's prediction moves the estimate, as it stood after the last tick, with the
    // camera; the jump comes in the tick after it.
    const Pose before = offset(u - 5000) * cameraAt(u - 5000), after = offset(u - 5000) * cameraAt(u);
    history.add(u, track.step(before, after));
    estimate.add(u, offset(u) * cameraAt(u));
  }
  const Pose truth = cameraAt(10000).inverse() * cameraAt(45000);
  ASSERT_TRUE(history.motion(10000, 45000).has_value());
  EXPECT_LT(poseError(*history.motion(10000, 45000), truth), kTol);
  EXPECT_GT(poseError(*estimate.motion(10000, 45000), truth), 0.1) << "the estimate's jumps";
}

TEST(PoseHistory, AMotionLongerThanTheSpanIsNone) {
  constexpr int64_t kSpanUs = 20000;
  PoseHistory history(100, kSpanUs);
  for (int64_t u = 0; u <= 50000; u += 5000) history.add(u, cameraAt(u));
  EXPECT_TRUE(history.motion(10000, 10000 + kSpanUs).has_value());
  EXPECT_FALSE(history.motion(10000, 10000 + kSpanUs + 1).has_value());
  EXPECT_FALSE(history.motion(10000 + kSpanUs + 1, 10000).has_value());
}

// The odometry's lookup of a lockstep flight runs while the control task adds samples: with the
// span's worth and the control task's lead in the ring, what came after `to` never changes the
// answer, and a lookup at the span's edge is answered or refused alike.
TEST(PoseHistory, TheAnswerDoesNotDependOnWhatCameAfter) {
  constexpr int64_t kStepUs = 1000, kSpanUs = 100000, kLeadUs = 40000;
  constexpr int kCapacity = static_cast<int>((kSpanUs + kLeadUs) / kStepUs) + 1;
  PoseHistory early(kCapacity, kSpanUs), late(kCapacity, kSpanUs);
  constexpr int64_t kTo = 500000;
  for (int64_t u = 0; u <= kTo; u += kStepUs) early.add(u, cameraAt(u));
  for (int64_t u = 0; u <= kTo + kLeadUs; u += kStepUs) late.add(u, cameraAt(u));
  for (const int64_t from : {kTo - kSpanUs - 1, kTo - kSpanUs, kTo - kSpanUs / 2}) {
    const std::optional<Pose> a = early.motion(from, kTo), b = late.motion(from, kTo);
    ASSERT_EQ(a.has_value(), b.has_value()) << "from " << from;
    if (a) {
      EXPECT_EQ(a->matrix(), b->matrix()) << "from " << from;
    }
  }
  EXPECT_FALSE(late.motion(kTo - kSpanUs - 1, kTo).has_value());
  EXPECT_TRUE(late.motion(kTo - kSpanUs, kTo).has_value());
}

}  // namespace
}  // namespace kinfly::flight
