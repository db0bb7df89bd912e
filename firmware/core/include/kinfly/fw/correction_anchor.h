// Re-anchoring the onboard odometry with the ground station's corrections. The odometry and its
// dense volume keep their own frame, `odom`, untouched: a correction never makes the volume jump.
// What moves is T_world_odom, so the published pose T_world_cam = T_world_odom * T_odom_cam
// moves by exactly the correction of the keyframe it refers to.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "kinfly/core/se3.h"
#include "kinfly/core/status.h"

namespace kinfly::fw {

class CorrectionAnchor {
 public:
  struct Params {
    int history_keyframes = 256;  // [1, 65536] keyframes whose onboard pose is remembered
    Status validate() const;
  };

  enum class Outcome {
    kApplied,
    kUnknownKeyframe,  // never sent, or so old it has left the history
    kOutOfOrder,       // older than a keyframe whose correction was already applied
  };

  explicit CorrectionAnchor(const Params& params);

  // The onboard pose of a keyframe as it was sent.
  void rememberKeyframe(int64_t keyframe_id, const Pose& T_odom_cam);

  Outcome apply(int64_t keyframe_id, const Pose& T_world_cam_corrected, int32_t reset_counter);

  Pose toWorld(const Pose& T_odom_cam) const { return T_world_odom_ * T_odom_cam; }
  const Pose& T_world_odom() const { return T_world_odom_; }
  // The ground's reset counter of the last applied correction: consumers (an autopilot) treat a
  // change as a discontinuity of the pose.
  int32_t resetCounter() const { return reset_counter_; }

  // Forget everything (the odometry restarted with a new frame and keyframe ids from zero).
  void reset();

 private:
  struct Entry {
    int64_t keyframe_id = -1;
    Pose T_odom_cam = Pose::Identity();
  };
  std::vector<Entry> history_;  // ring indexed by keyframe_id modulo its size
  Pose T_world_odom_ = Pose::Identity();
  int64_t last_applied_ = -1;
  int32_t reset_counter_ = 0;
};

}  // namespace kinfly::fw
