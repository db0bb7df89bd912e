#include "kinfly/fw/keyframe_selector.h"

#include <algorithm>
#include <cmath>
#include <sstream>

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
  return why.str().empty() ? Status() : Status::error(why.str());
}

bool KeyframeSelector::select(const Pose& T_world_cam, int64_t utime, TrackingStatus status,
                              float inlier_fraction) {
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
  }
  if (take) last_ = Reference{T_world_cam, utime};
  return take;
}

}  // namespace kinfly::fw
