// The estimator's camera poses over the last moments, for the odometry's motion prior: the
// camera's motion between two frames' capture times as the IMU saw it, so that ICP starts there
// and keeps it along the directions the scene leaves weak (docs/flight.md, "Weak directions and
// the odometry's prior"). A ring allocated at construction; not thread-safe (the firmware guards
// it). The poses stored are a PredictedTrack's: the estimate moved by its predictions alone.
#pragma once

#include <cstdint>
#include <optional>
#include <vector>

#include "kinfly/core/se3.h"

namespace kinfly::flight {

class PoseHistory {
 public:
  // capacity > 1 entries; max_span_us > 0: the longest motion asked for. A ring that holds
  // max_span_us and more lets a lookup's answer depend on its arguments alone, not on how many
  // entries came after `to` before it was made (a lockstep flight's odometry runs beside the
  // control task, which keeps adding: docs/sim.md, "Lockstep").
  PoseHistory(int capacity, int64_t max_span_us);

  // Times must increase (others are ignored).
  void add(int64_t utime, const Pose& T_world_cam);
  // T_world_cam(from)^-1 * T_world_cam(to), each interpolated between the stored poses around
  // it; nullopt where either time lies outside the history or they lie more than max_span_us
  // apart.
  std::optional<Pose> motion(int64_t from_utime, int64_t to_utime) const;

 private:
  struct Entry {
    int64_t utime = 0;
    Pose T_world_cam = Pose::Identity();
  };
  const Entry& at(int index) const { return ring_[(head_ + index) % ring_.size()]; }
  // The pose at utime; nullopt outside the history.
  std::optional<Pose> poseAt(int64_t utime) const;

  std::vector<Entry> ring_;  // oldest at head_, count_ entries
  int64_t max_span_us_;
  int head_ = 0;
  int count_ = 0;
};

// The estimate's camera pose moved by the estimator's predictions alone: each IMU sample's
// prediction is composed on, and what moves the estimate between samples is left out: a pose
// fused (which moves it by the innovation times the gain: the prior of one frame in the ring's
// corridor moved the camera 10 cm back, docs/flight.md) and a reset (to a pose, or the
// ground's correction). Its motion over a few frames is the IMU's, from the velocity the filter
// holds; its pose drifts from the estimate, which no motion between two of its times sees.
class PredictedTrack {
 public:
  // The estimate's camera pose before a sample's prediction and after it; returns the track's
  // pose after the sample (the first call: `after`).
  const Pose& step(const Pose& before, const Pose& after);

 private:
  std::optional<Pose> T_world_cam_;
};

}  // namespace kinfly::flight
