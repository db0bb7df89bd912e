#include "odometry_task.h"

#include <omp.h>
#include <spdlog/spdlog.h>

#include <optional>
#include <thread>

#include "kinfly/link/conversions.h"

namespace kinfly::fw {

Status OdometryTask::engineParams(const FirmwareConfig& config, const PinholeCamera& camera,
                                  double depth_scale_m, DenseVolume::Params* volume,
                                  FusionPipeline::Params* pipeline) {
  if (camera.width % config.odometry.downsample != 0 ||
      camera.height % config.odometry.downsample != 0)
    return Status::error("odometry.downsample " + std::to_string(config.odometry.downsample) +
                         " does not divide the " + std::to_string(camera.width) + "x" +
                         std::to_string(camera.height) + " image");
  *volume = config.odometry.volume;
  pipeline->preprocess.depth_scale_m = depth_scale_m;
  pipeline->preprocess.downsample = config.odometry.downsample;
  pipeline->integrate.truncation_m = 4.f * volume->voxel_size_m;
  pipeline->icp.iterations_coarse_to_fine.back() = config.odometry.icp_fine_iterations;
  pipeline->model_level = config.odometry.model_level;
  if (Status valid = volume->validate(); !valid.ok()) return valid;
  return pipeline->validate(volume->voxel_size_m);
}

OdometryTask::OdometryTask(const FirmwareConfig& config, const PinholeCamera& camera,
                           const DenseVolume::Params& volume,
                           const FusionPipeline::Params& pipeline, SharedAnchor* anchor,
                           Counters* counters,
                           BoundedQueue<DepthCapture>* frames,
                           BoundedQueue<KeyframeJob>* keyframes,
                           LatestValue<OdometryPose>* poses, SharedPoseHistory* history,
                           const StopToken* stop)
    : config_(config), volume_(volume), pipeline_(camera, pipeline, &volume_),
      selector_(config.keyframe, pipeline_.frame().camera[kPyramidLevels - 1].width,
                pipeline_.frame().camera[kPyramidLevels - 1].height),
      publisher_("odometry", config.link.effectiveLcmUrl(), config.vehicle.id, {},
                 unicastPeers(config.link, /*listen_port=*/0, {})),
      anchor_(anchor), counters_(counters),
      frames_(frames), keyframes_(keyframes), poses_(poses), history_(history), stop_(stop),
      job_(withDepthImage<KeyframeJob>(camera)) {
  publisher_.chargeTo(&counters->priority_bytes);
  odometry_.vehicle_id = config.vehicle.id;
  truth_.vehicle_id = config.vehicle.id;
}

void OdometryTask::run() {
  // OpenMP's thread count is a per-thread setting: a new thread starts from OMP_NUM_THREADS or
  // the core count, not from what main() set.
  omp_set_num_threads(config_.odometry.threads);
  DepthCapture capture = withDepthImage<DepthCapture>(pipeline_.inputCamera());
  while (!stop_->stopRequested()) {
    if (!frames_->pop(&capture, kPollPeriod)) {
      if (counters_->capture_done && frames_->size() == 0) break;
      continue;
    }
    process(capture);
  }
}

void OdometryTask::process(const DepthCapture& capture) {
  std::optional<Pose> prior;
  if (history_ != nullptr && pose_utime_ >= 0) {
    std::lock_guard<std::mutex> lock(history_->mutex);
    if (const std::optional<Pose> motion = history_->history.motion(pose_utime_, capture.utime))
      prior = pipeline_.pose() * *motion;
  }
  const FrameResult r = pipeline_.processFrame(capture.depth.view(), capture.utime,
                                               prior ? &*prior : nullptr);
  ++counters_->frames_processed;
  counters_->tracking.store(r.status);
  if (r.status != TrackingStatus::kLost) pose_utime_ = r.utime;
  if (r.weak.count > 0) {
    ++counters_->frames_weak;
    if (weak_log_.allow(secondsSince(began_)))
      spdlog::warn("odometry: frame {}: the scene constrains {} of the six directions of motion "
                   "only (the weakest {:.4f}); {} along the rest ({} more such frames since the "
                   "last report)",
                   capture.frame_id, 6 - r.weak.count, r.weakest_fraction,
                   prior ? "the IMU's motion carries the pose" : "ICP's weak answer stands",
                   weak_log_.suppressed());
  }
  if (r.status == TrackingStatus::kLost) {
    ++counters_->frames_lost;
    if (lost_log_.allow(secondsSince(began_)))
      spdlog::warn("odometry: frame {} lost: {} ({} more lost since the last report)",
                   capture.frame_id, r.lost_reason, lost_log_.suppressed());
  } else if (r.recovered_after > 0) {
    ++counters_->recoveries;
    if (r.relocalised) ++counters_->relocalisations;
    if (r.new_map) ++counters_->new_maps;
    if (r.recovered_after > counters_->longest_loss_frames)
      counters_->longest_loss_frames = r.recovered_after;
    if (recovery_log_.allow(secondsSince(began_)))
      spdlog::info("odometry: frame {}: tracking back after {} lost frame(s){} ({} more such "
                   "recoveries since the last report)",
                   capture.frame_id, r.recovered_after,
                   r.relocalised ? ", relocalised against a keyframe"
                   : r.new_map   ? ", in a new map (the old one no longer fitted)"
                                 : "",
                   recovery_log_.suppressed());
  }
  // A new map's first frame is always a keyframe: the ground learns where the new map began.
  if (r.new_map) selector_.reset();
  const DepthFrame& frame = pipeline_.frame();
  const bool keyframe =
      selector_.select(r.T_world_cam, r.utime, r.status, r.inlier_fraction,
                       {frame.depth_m[kPyramidLevels - 1].view(), frame.camera[kPyramidLevels - 1]});
  Pose T_world_odom;
  int32_t reset_counter = 0;
  {
    std::lock_guard<std::mutex> lock(anchor_->mutex);
    if (keyframe) anchor_->anchor.rememberKeyframe(next_keyframe_id_, r.T_world_cam);
    T_world_odom = anchor_->anchor.T_world_odom();
    reset_counter = anchor_->anchor.resetCounter();
  }
  const Pose T_world_cam = T_world_odom * r.T_world_cam;
  // A new map's first pose is the IMU's prediction handed back, not a measurement: the
  // estimator must not take it for one, nor its vision-lost failsafe for vision.
  if (poses_ != nullptr && r.status != TrackingStatus::kLost && !r.new_map) {
    poses_->back() = OdometryPose{r.utime, r.T_world_cam, T_world_odom, reset_counter, r.weak};
    poses_->publish();
  }
  link::fillOdometry(r, capture.frame_id, T_world_cam, reset_counter, &odometry_);
  // Not sent while the network is down: the publisher says so once, the pose still counts.
  publisher_.publish(link::Channel::kOdometry, odometry_);
  if (capture.has_ground_truth) {
    link::fillGroundTruth(capture.utime, capture.T_world_cam_truth, &truth_);
    publisher_.publish(link::Channel::kGroundTruth, truth_);
    if (!config_.output.ground_truth.empty())
      ground_truth_.push_back({static_cast<double>(r.utime) * 1e-6, capture.T_world_cam_truth});
  }
  if (!config_.output.trajectory.empty())
    trajectory_.push_back({static_cast<double>(r.utime) * 1e-6, T_world_cam});
  if (!keyframe) return;
  // Sources deliver every frame at their camera's size, the size every image was made with.
  job_.depth.copyFrom(capture.depth.view());
  job_.utime = r.utime;
  job_.frame_id = capture.frame_id;
  const int64_t keyframe_id = next_keyframe_id_++;
  job_.keyframe_id = keyframe_id;
  job_.T_world_cam = T_world_cam;
  job_.tracking = r.status;
  if (!keyframes_->push(job_) && keyframe_drop_log_.allow(secondsSince(began_)))
    spdlog::warn("odometry: link busy, oldest keyframe dropped ({} dropped in all)",
                 keyframes_->dropped());
  // job_ now holds the queue slot it was swapped with.
  if (config_.source.lockstep) awaitGround(keyframe_id);
}

void OdometryTask::awaitGround(int64_t keyframe_id) {
  using namespace std::chrono_literals;
  if (unanswered_since_status_) {
    if (counters_->ground_statuses == *unanswered_since_status_) return;
    spdlog::info("odometry: lockstep: the ground station is heard again; waiting for its "
                 "answers from keyframe {} on", keyframe_id);
    unanswered_since_status_.reset();
  }
  const auto deadline = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                           std::chrono::duration<double>(config_.link.final_wait_s));
  while (counters_->ground_done_keyframe < keyframe_id && !stop_->stopRequested()) {
    if (Clock::now() >= deadline) {
      const int64_t statuses = counters_->ground_statuses;
      if (counters_->ground_done_keyframe >= keyframe_id) return;  // answered at the deadline
      spdlog::warn("odometry: lockstep: no answer from the ground station to keyframe {} within "
                   "{:.1f} s; going on without waiting until it is heard again",
                   keyframe_id, config_.link.final_wait_s);
      unanswered_since_status_ = statuses;
      return;
    }
    std::this_thread::sleep_for(1ms);
  }
}

}  // namespace kinfly::fw
