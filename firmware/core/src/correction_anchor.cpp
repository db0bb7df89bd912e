#include "kinfly/fw/correction_anchor.h"

namespace kinfly::fw {

Status CorrectionAnchor::Params::validate() const {
  if (history_keyframes < 1 || history_keyframes > 65536)
    return Status::error("corrections.history_keyframes must be in [1, 65536] (got " +
                         std::to_string(history_keyframes) + ")");
  return {};
}

CorrectionAnchor::CorrectionAnchor(const Params& params)
    : history_(static_cast<size_t>(params.history_keyframes)) {}

void CorrectionAnchor::rememberKeyframe(int64_t keyframe_id, const Pose& T_odom_cam) {
  Entry& slot = history_[static_cast<size_t>(keyframe_id) % history_.size()];
  slot.keyframe_id = keyframe_id;
  slot.T_odom_cam = T_odom_cam;
}

CorrectionAnchor::Outcome CorrectionAnchor::apply(int64_t keyframe_id,
                                                  const Pose& T_world_cam_corrected,
                                                  int32_t reset_counter) {
  if (keyframe_id < 0) return Outcome::kUnknownKeyframe;
  const Entry& slot = history_[static_cast<size_t>(keyframe_id) % history_.size()];
  if (slot.keyframe_id != keyframe_id) return Outcome::kUnknownKeyframe;
  // A late correction of an older keyframe would undo a newer one's.
  if (keyframe_id < last_applied_) return Outcome::kOutOfOrder;
  T_world_odom_ = orthonormalized(T_world_cam_corrected * slot.T_odom_cam.inverse());
  last_applied_ = keyframe_id;
  reset_counter_ = reset_counter;
  return Outcome::kApplied;
}

void CorrectionAnchor::reset() {
  for (Entry& entry : history_) entry = Entry();
  T_world_odom_ = Pose::Identity();
  last_applied_ = -1;
  // reset_counter_ stays: it is the ground's count, and only the ground moves it.
}

}  // namespace kinfly::fw
