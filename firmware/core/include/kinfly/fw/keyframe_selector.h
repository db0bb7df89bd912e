// Which onboard frames become keyframes for the ground station: enough motion since the last
// keyframe (translation or rotation), or enough time, never faster than a minimum interval, and
// only from frames the odometry tracked well, or tracked at all once the camera is about to
// leave the last keyframe's view (turned or moved far, or seeing little of what it saw).
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "kinfly/core/camera.h"
#include "kinfly/core/image.h"
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
    // An angle is a proxy for what the views share. In the hall each 30 degree turn past a
    // corner (5 m off, beyond the sensor's 4 m) left the next keyframe seeing 3 % of what the
    // map held, and the ground could not register 3 in a row (docs/firmware.md, "Keyframes").
    // With this above 0, a frame ICP tracked is also a keyframe once less than this share of the
    // points it sees (its coarsest pyramid level) were seen by the last keyframe: projected into
    // its depth image they land on a depth within the sensor's noise. At 0.6 the ground
    // registered 55 of 56 keyframes in the hall instead of 39 of 47, but then refined the return
    // to the first view 22 cm off (its map 3.5 degrees apart from itself there), and its
    // corrections moved the drone by as much; off (0) until the ground closes that loop.
    float min_covisibility = 0.f;  // [0, 1)
    Status validate() const;  // an error names the value and its range
  };

  // What a frame sees, for the covisibility with the last keyframe: a depth image in metres
  // (NaN or <= 0 where nothing was measured) and its camera. Empty: the rule is not applied.
  struct View {
    ImageView<const float> depth_m;
    PinholeCamera camera;
  };

  // With min_covisibility > 0, the copy of the last keyframe's view is allocated here for views
  // of view_width x view_height, so that flight allocates nothing.
  explicit KeyframeSelector(const Params& params, int view_width = 0, int view_height = 0);

  // Decides for one processed frame; when it returns true the frame is the new reference, and,
  // with min_covisibility > 0, keeps a copy of `view` (allocated anew only when the view's size
  // is not the one given at construction).
  bool select(const Pose& T_world_cam, int64_t utime, TrackingStatus status,
              float inlier_fraction, const View& view = {});

  // The share of `view`'s measured points that the last keyframe saw (1 when it has none, or
  // when there is no last keyframe's view to compare with).
  float covisibility(const Pose& T_world_cam, const View& view) const;

  // Forget the reference (after the odometry restarts), so the next good frame is a keyframe.
  void reset() { last_.reset(); }

 private:
  struct Reference {
    Pose T_world_cam;
    int64_t utime;
    bool has_view;
  };
  Params params_;
  std::optional<Reference> last_;
  Image<float> last_depth_m_;  // the last keyframe's view, when it had one
  PinholeCamera last_camera_;
};

}  // namespace kinfly::fw
