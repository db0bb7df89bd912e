// The odometry thread: the engine at QVGA in a dense volume that follows the drone, one pose
// published per frame, keyframe selection, keyframes handed to the link. With a flight stack,
// ICP starts from the motion the estimator saw since the last tracked frame, and keeps it where
// the scene leaves a direction weak. It never waits for the
// link: a full keyframe queue drops its oldest keyframe. Only a lockstep replay
// (source.lockstep) waits, after each keyframe, for the ground station's answer.
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "config.h"
#include "kinfly/pipeline/fusion_pipeline.h"
#include "kinfly/fw/bounded_queue.h"
#include "kinfly/fw/keyframe_selector.h"
#include "kinfly/fw/latest_value.h"
#include "kinfly/fw/log_throttle.h"
#include "kinfly/ground_truth_t.hpp"
#include "kinfly/odometry_t.hpp"
#include "kinfly/sources/depth_source.h"
#include "kinfly/volume/tsdf_volume.h"
#include "kinfly/io/tum_dataset.h"
#include "publisher.h"
#include "runtime.h"

namespace kinfly::fw {

class OdometryTask {
 public:
  // The engine's parameters for this configuration and source; an error says which value is
  // wrong.
  static Status engineParams(const FirmwareConfig& config, const PinholeCamera& camera,
                                  double depth_scale_m, DenseVolume::Params* volume,
                                  FusionPipeline::Params* pipeline);

  // Every buffer is allocated here, none per frame.
  OdometryTask(const FirmwareConfig& config, const PinholeCamera& camera,
               const DenseVolume::Params& volume, const FusionPipeline::Params& pipeline,
               SharedAnchor* anchor, Counters* counters,
               BoundedQueue<DepthCapture>* frames, BoundedQueue<KeyframeJob>* keyframes,
               LatestValue<OdometryPose>* poses, SharedPoseHistory* history,
               const StopToken* stop);

  // Until a stop is requested, or the frame queue is closed and empty.
  void run();

  // Kept only when the configuration asks for them (in flight they would grow without bound).
  const std::vector<StampedPose>& trajectory() const { return trajectory_; }
  const std::vector<StampedPose>& groundTruth() const { return ground_truth_; }

 private:
  void process(const DepthCapture& capture);
  // source.lockstep: until the ground station reports keyframe `keyframe_id` done (its
  // correction is applied by then), link.final_wait_s at most, or a stop. After a wait that
  // ran out, none until a ground status is heard again: a ground station that is gone (killed,
  // out of range) would otherwise cost every keyframe the whole wait, and a restarted one is
  // waited for from its first keyframe on.
  void awaitGround(int64_t keyframe_id);

  const FirmwareConfig& config_;
  DenseVolume volume_;
  FusionPipeline pipeline_;
  KeyframeSelector selector_;
  Publisher publisher_;
  SharedAnchor* anchor_;
  Counters* counters_;
  BoundedQueue<DepthCapture>* frames_;
  BoundedQueue<KeyframeJob>* keyframes_;
  LatestValue<OdometryPose>* poses_;  // to the control task; nullptr without one
  SharedPoseHistory* history_;        // from the control task; nullptr without one
  // [µs] capture of the pipeline's pose (its last tracked frame), -1 before one
  int64_t pose_utime_ = -1;
  const StopToken* stop_;
  odometry_t odometry_{};
  ground_truth_t truth_{};
  KeyframeJob job_;
  int64_t next_keyframe_id_ = 0;
  // Counters::ground_statuses when a lockstep wait ran out; none while the ground answers.
  std::optional<int64_t> unanswered_since_status_;
  Clock::time_point began_ = Clock::now();
  LogThrottle lost_log_, keyframe_drop_log_, weak_log_, recovery_log_;
  std::vector<StampedPose> trajectory_, ground_truth_;
};


}  // namespace kinfly::fw
