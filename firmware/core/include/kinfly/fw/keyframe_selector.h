// Which onboard frames become keyframes for the ground station: enough motion since the last
// keyframe (translation or rotation), or enough time, never faster than a minimum interval, and
// only from frames the odometry tracked well, or tracked at all once the camera is about to
// leave the last keyframe's view.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "kinfly/core/se3.h"
#include "kinfly/core/status.h"
#include "kinfly/frame/tracking_status.h"

namespace kinfly::fw {

class KeyframeSelector {
 public:
  struct Params {
    double min_translation_m = 0.10;   // [m] (0, 10]: camera travel since the last keyframe
    double min_rotation_rad = 0.1745;  // [rad] (0, pi]: 10 degrees of rotation since it
    double max_interval_s = 1.0;       // [s] (0, 60]: a keyframe at least this often, moving or not
    double min_interval_s = 0.1;       // [s] [0, max_interval_s): never faster (10 Hz link budget)
    // [0, 1]: tracking quality a keyframe's pose needs. Pixels beyond the dense volume have no
    // model to match, so well-tracked real frames sit near 0.5 (ICP calls < 0.1 lost).
    float min_inlier_fraction = 0.25f;
    // The ground registers each keyframe against its map, seen from the last ones: a view
    // turned by the camera's field (about 60 degrees) from the last keyframe shares nothing with
    // it. In the simulated hall, 3.6 m from its walls, ICP's inlier fraction while turning was
    // 0.13-0.28 (the sensor's noise at that range), no frame reached min_inlier_fraction for 79
    // degrees, and the ground could not register 6 of 41 keyframes (docs/firmware.md,
    // "Keyframes"). So once the motion since the last keyframe reaches either of these, a frame
    // ICP tracked (kOk) is a keyframe whatever its inlier fraction: 30 degrees leaves half the
    // view in common. Never below min_rotation_rad and min_translation_m, whatever they are.
    double max_gap_rotation_rad = 0.5236;  // [rad] (0, pi]: 30 degrees
    double max_gap_translation_m = 0.5;    // [m] (0, 10]
    Status validate() const;  // an error names the value and its range
  };

  explicit KeyframeSelector(const Params& params) : params_(params) {}

  // Decides for one processed frame; when it returns true the frame is the new reference.
  bool select(const Pose& T_world_cam, int64_t utime, TrackingStatus status,
              float inlier_fraction);

  // Forget the reference (after the odometry restarts), so the next good frame is a keyframe.
  void reset() { last_.reset(); }

 private:
  struct Reference {
    Pose T_world_cam;
    int64_t utime;
  };
  Params params_;
  std::optional<Reference> last_;
};

}  // namespace kinfly::fw
