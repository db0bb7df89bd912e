// The odometry's poses as the ground anchors them, turned into what the estimator takes. The
// ground's corrections re-anchor the odometry in the ground's map (T_map_odom, fw_core's
// CorrectionAnchor); the estimator follows the map, so that a go-to or a mission given in the
// map's coordinates flies there whatever the odometry drifted:
//   - its poses are T_map_cam = T_map_odom · T_odom_cam, so each keyframe's small refinement is
//     fused as a measurement, smoothly, like any other pose;
//   - a jump of the anchor (the ground's reset_counter changed: a relocalisation, a loop closure)
//     is a reset of the estimator (OdomReset) before the first pose in the new anchor, so that
//     the jump is taken at once instead of being gated out as an outlier.
// docs/flight.md, "Corrections from the ground: resets".
#pragma once

#include <cstdint>
#include <optional>

#include "kinfly/core/se3.h"
#include "kinfly/flight/estimator.h"

namespace kinfly::flight {

struct AnchoredPose {
  int64_t utime = 0;  // [µs] capture of the depth frame
  Pose T_odom_cam = Pose::Identity();  // the odometry's own pose
  Pose T_map_odom = Pose::Identity();  // the ground's anchor when the pose was made
  int32_t reset_counter = 0;           // the ground's, of the anchor's last jump
  WeakDirections weak;                 // the odometry's, the position parts in odom
};

class AnchoredVision {
 public:
  struct Inputs {
    std::optional<OdomReset> reset;  // apply first, where the anchor jumped
    VisionPose vision;               // then fuse, in the map's frame
  };

  // reset_template: the standard deviations a reset carries (the correction message has none).
  explicit AnchoredVision(const OdomReset& reset_template = OdomReset())
      : template_(reset_template) {}

  Inputs take(const AnchoredPose& pose);

 private:
  OdomReset template_;
  bool seen_ = false;
  int32_t reset_counter_ = 0;
  Pose T_map_odom_ = Pose::Identity();
};

}  // namespace kinfly::flight
