#include "kinfly/flight/pose_history.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cstdlib>

namespace kinfly::flight {

PoseHistory::PoseHistory(int capacity, int64_t max_span_us)
    : ring_(static_cast<size_t>(std::max(capacity, 2))), max_span_us_(max_span_us) {}

void PoseHistory::add(int64_t utime, const Pose& T_world_cam) {
  if (count_ > 0 && utime <= at(count_ - 1).utime) return;
  if (count_ == static_cast<int>(ring_.size())) {
    head_ = (head_ + 1) % static_cast<int>(ring_.size());
    --count_;
  }
  ring_[(head_ + count_) % ring_.size()] = {utime, T_world_cam};
  ++count_;
}

std::optional<Pose> PoseHistory::poseAt(int64_t utime) const {
  if (count_ == 0 || utime < at(0).utime || utime > at(count_ - 1).utime) return std::nullopt;
  // The first stored pose at or after utime, by bisection over the time-ordered ring.
  int lo = 0, hi = count_ - 1;
  while (lo < hi) {
    const int mid = (lo + hi) / 2;
    if (at(mid).utime < utime) lo = mid + 1; else hi = mid;
  }
  const Entry& after = at(lo);
  if (after.utime == utime) return after.T_world_cam;
  const Entry& before = at(lo - 1);
  const double s = static_cast<double>(utime - before.utime) /
                   static_cast<double>(after.utime - before.utime);
  Pose T = Pose::Identity();
  const Eigen::Quaterniond q0(before.T_world_cam.linear()), q1(after.T_world_cam.linear());
  T.linear() = q0.slerp(s, q1).toRotationMatrix();
  T.translation() =
      (1.0 - s) * before.T_world_cam.translation() + s * after.T_world_cam.translation();
  return T;
}

std::optional<Pose> PoseHistory::motion(int64_t from_utime, int64_t to_utime) const {
  if (std::abs(to_utime - from_utime) > max_span_us_) return std::nullopt;
  const std::optional<Pose> from = poseAt(from_utime), to = poseAt(to_utime);
  if (!from || !to) return std::nullopt;
  return from->inverse() * *to;
}

const Pose& PredictedTrack::step(const Pose& before, const Pose& after) {
  T_world_cam_ = T_world_cam_ ? orthonormalized(*T_world_cam_ * (before.inverse() * after)) : after;
  return *T_world_cam_;
}

}  // namespace kinfly::flight
