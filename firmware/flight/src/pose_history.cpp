#include "kinfly/flight/pose_history.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cstdlib>

namespace kinfly::flight {

PoseHistory::PoseHistory(int capacity, int64_t max_span_us)
    : ring_(static_cast<size_t>(std::max(capacity, 2))), max_span_us_(max_span_us) {}

void PoseHistory::add(int64_t utime, const Pose& T_world_cam, int64_t epoch) {
  if (count_ > 0 && utime <= at(count_ - 1).utime) return;
  if (count_ == static_cast<int>(ring_.size())) {
    head_ = (head_ + 1) % static_cast<int>(ring_.size());
    --count_;
  }
  ring_[(head_ + count_) % ring_.size()] = {utime, T_world_cam, epoch};
  ++count_;
}

std::optional<PoseHistory::Entry> PoseHistory::poseAt(int64_t utime) const {
  if (count_ == 0 || utime < at(0).utime || utime > at(count_ - 1).utime) return std::nullopt;
  // The first stored pose at or after utime, by bisection over the time-ordered ring.
  int lo = 0, hi = count_ - 1;
  while (lo < hi) {
    const int mid = (lo + hi) / 2;
    if (at(mid).utime < utime) lo = mid + 1; else hi = mid;
  }
  const Entry& after = at(lo);
  if (after.utime == utime) return after;
  const Entry& before = at(lo - 1);
  if (before.epoch != after.epoch) return std::nullopt;
  const double s = static_cast<double>(utime - before.utime) /
                   static_cast<double>(after.utime - before.utime);
  Entry e;
  e.utime = utime;
  e.epoch = after.epoch;
  const Eigen::Quaterniond q0(before.T_world_cam.linear()), q1(after.T_world_cam.linear());
  e.T_world_cam.linear() = q0.slerp(s, q1).toRotationMatrix();
  e.T_world_cam.translation() =
      (1.0 - s) * before.T_world_cam.translation() + s * after.T_world_cam.translation();
  return e;
}

std::optional<Pose> PoseHistory::motion(int64_t from_utime, int64_t to_utime) const {
  if (std::abs(to_utime - from_utime) > max_span_us_) return std::nullopt;
  const std::optional<Entry> from = poseAt(from_utime), to = poseAt(to_utime);
  if (!from || !to || from->epoch != to->epoch) return std::nullopt;
  return from->T_world_cam.inverse() * to->T_world_cam;
}

}  // namespace kinfly::flight
