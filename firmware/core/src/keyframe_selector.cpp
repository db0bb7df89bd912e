#include "kinfly/fw/keyframe_selector.h"

#include <algorithm>
#include <cmath>
#include <sstream>

#include "kinfly/core/noise_model.h"

namespace kinfly::fw {

Status KeyframeSelector::Params::validate() const {
  std::ostringstream why;
  if (!(min_translation_m > 0.0 && min_translation_m <= 10.0))
    why << "keyframe.min_translation_m must be in (0, 10] m (got " << min_translation_m << ")";
  else if (!(min_rotation_rad > 0.0 && min_rotation_rad <= M_PI))
    why << "keyframe.min_rotation_rad must be in (0, pi] (got " << min_rotation_rad << ")";
  else if (!(max_interval_s > 0.0 && max_interval_s <= 60.0))
    why << "keyframe.max_interval_s must be in (0, 60] s (got " << max_interval_s << ")";
  else if (!(min_interval_s >= 0.0 && min_interval_s < max_interval_s))
    why << "keyframe.min_interval_s must be in [0, max_interval_s) (got " << min_interval_s
        << ")";
  else if (!(min_inlier_fraction >= 0.f && min_inlier_fraction <= 1.f))
    why << "keyframe.min_inlier_fraction must be in [0, 1] (got " << min_inlier_fraction << ")";
  else if (!(max_gap_rotation_rad > 0.0 && max_gap_rotation_rad <= M_PI))
    why << "keyframe.max_gap_rotation_rad must be in (0, pi] (got " << max_gap_rotation_rad << ")";
  else if (!(max_gap_translation_m > 0.0 && max_gap_translation_m <= 10.0))
    why << "keyframe.max_gap_translation_m must be in (0, 10] m (got " << max_gap_translation_m
        << ")";
  else if (!(min_covisibility >= 0.f && min_covisibility < 1.f))
    why << "keyframe.min_covisibility must be in [0, 1) (got " << min_covisibility << ")";
  return why.str().empty() ? Status() : Status::error(why.str());
}

KeyframeSelector::KeyframeSelector(const Params& params, int view_width, int view_height)
    : params_(params) {
  if (params_.min_covisibility > 0.f && view_width > 0 && view_height > 0)
    last_depth_m_ = Image<float>(view_width, view_height);
}

float KeyframeSelector::covisibility(const Pose& T_world_cam, const View& view) const {
  if (!last_.has_value() || !last_->has_view || view.depth_m.empty()) return 1.f;
  // Both views' depths are noisy and the poses drift a little between keyframes: three sigmas
  // of the sensor's noise, and no less than 3 cm, since the coarsest level's depth is two
  // range-gated 5x5 means of the frame's, which spread a step across its neighbours.
  constexpr float kSigmas = 3.f, kFloorM = 0.03f;
  const Eigen::Matrix4f T_last_cur = (last_->T_world_cam.inverse() * T_world_cam).matrix().cast<float>();
  const Eigen::Matrix3f R = T_last_cur.topLeftCorner<3, 3>();
  const Eigen::Vector3f t = T_last_cur.topRightCorner<3, 1>();
  const ImageView<const float> last = last_depth_m_.view();
  int seen = 0, shared = 0;
  for (int y = 0; y < view.depth_m.height(); ++y) {
    const float* row = view.depth_m.row(y);
    for (int x = 0; x < view.depth_m.width(); ++x) {
      if (!(row[x] > 0.f)) continue;
      ++seen;
      const Eigen::Vector3f q = R * view.camera.backProject(static_cast<float>(x), static_cast<float>(y), row[x]) + t;
      if (!(q.z() > 0.f)) continue;
      const Eigen::Vector2f uv = last_camera_.project(q);
      // Bounded in float, before rounding: a point near the camera's plane projects far beyond
      // int's range. Within these bounds the rounded pixel is inside the image.
      if (!(uv.x() > -0.5f && uv.x() < static_cast<float>(last.width()) - 0.5f &&
            uv.y() > -0.5f && uv.y() < static_cast<float>(last.height()) - 0.5f))
        continue;
      const int u = static_cast<int>(std::lround(uv.x())), v = static_cast<int>(std::lround(uv.y()));
      const float z = last(u, v);
      if (z > 0.f && std::abs(z - q.z()) <= std::max(kFloorM, kSigmas * kinectNoiseSigmaM(q.z())))
        ++shared;
    }
  }
  return seen > 0 ? static_cast<float>(shared) / static_cast<float>(seen) : 1.f;
}

bool KeyframeSelector::select(const Pose& T_world_cam, int64_t utime, TrackingStatus status,
                              float inlier_fraction, const View& view) {
  const bool well_tracked = status == TrackingStatus::kFirstFrame ||
                            (status == TrackingStatus::kOk &&
                             inlier_fraction >= params_.min_inlier_fraction);
  if (!well_tracked && status != TrackingStatus::kOk) return false;
  // Time running backwards means the source restarted (a replay looping, a sensor reset): the
  // old reference says nothing about this frame, nor about a later one.
  if (last_.has_value() && utime < last_->utime) last_.reset();
  bool take = !last_.has_value();
  if (take && !well_tracked) return false;
  if (!take) {
    const double elapsed_s = static_cast<double>(utime - last_->utime) * 1e-6;
    if (elapsed_s < params_.min_interval_s) return false;
    const Pose motion = last_->T_world_cam.inverse() * T_world_cam;
    const double moved_m = motion.translation().norm(), turned_rad = rotationAngleRad(motion);
    take = well_tracked ? elapsed_s >= params_.max_interval_s ||
                              moved_m >= params_.min_translation_m ||
                              turned_rad >= params_.min_rotation_rad
                        : moved_m >= std::max(params_.max_gap_translation_m,
                                              params_.min_translation_m) ||
                              turned_rad >= std::max(params_.max_gap_rotation_rad,
                                                     params_.min_rotation_rad);
    // Computed only for a frame the rules above did not take: a few thousand projections.
    take = take || (params_.min_covisibility > 0.f &&
                    covisibility(T_world_cam, view) < params_.min_covisibility);
  }
  if (!take) return false;
  last_ = Reference{T_world_cam, utime, params_.min_covisibility > 0.f && !view.depth_m.empty()};
  if (last_->has_view) {
    if (last_depth_m_.width() != view.depth_m.width() ||
        last_depth_m_.height() != view.depth_m.height())
      last_depth_m_ = Image<float>(view.depth_m.width(), view.depth_m.height());
    last_depth_m_.copyFrom(view.depth_m);
    last_camera_ = view.camera;
  }
  return true;
}

}  // namespace kinfly::fw
