// Which onboard frames become keyframes for the ground station: enough motion since the last
// keyframe (translation or rotation), or enough time, never faster than a minimum interval, and
// only from frames the odometry tracked well.
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
