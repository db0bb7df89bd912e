#include "kinfly/pipeline/fusion_pipeline.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <sstream>
#include <string>

namespace kinfly {

namespace {
double msSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}
}  // namespace

Status FusionPipeline::Params::validate(float voxel_size_m) const {
  for (const Status& stage : {preprocess.validate(), icp.validate(), integrate.validate(voxel_size_m),
                              raycast.validate()})
    if (!stage.ok()) return stage;
  if (!(min_valid_depth_fraction >= 0.f && min_valid_depth_fraction < 1.f))
    return Status::error("min_valid_depth_fraction must be in [0, 1)");
  if (!(max_recovery_gate_scale >= 1.f))
    return Status::error("max_recovery_gate_scale must be >= 1");
  if (relocalise) {
    const Status r = relocaliser.validate();
    if (!r.ok()) return Status::error("relocaliser: " + r.message());
  }
  return {};
}

FusionPipeline::FusionPipeline(const PinholeCamera& input_camera, const Params& params,
                               TsdfVolume* volume)
    : params_(params),
      volume_(volume),
      preprocessor_(input_camera, params.preprocess),
      tracker_(params.icp),
      integrator_(params.integrate),
      raycaster_(preprocessor_.camera(), params.raycast),
      relocaliser_(params.relocaliser),
      frame_(preprocessor_.camera()),
      model_(preprocessor_.camera()) {
  integrator_.reserve(preprocessor_.camera().width, preprocessor_.camera().height, *volume);
}

bool FusionPipeline::preprocess(ImageView<const uint16_t> raw_depth, int64_t utime,
                                const Pose& T_world_cam, FrameResult* result) {
  const auto start = std::chrono::steady_clock::now();
  const PreprocessResult pre = preprocessor_.process(raw_depth, &frame_);
  result->utime = utime;
  result->T_world_cam = T_world_cam;
  result->valid_depth_fraction = pre.valid_fraction;
  result->ms.preprocess = result->ms.total = msSince(start);
  if (pre.valid_fraction >= params_.min_valid_depth_fraction) return true;
  result->status = TrackingStatus::kLost;
  std::ostringstream why;
  why << "only " << pre.valid_fraction * 100.f << "% of pixels have valid depth";
  result->lost_reason = why.str();
  return false;
}

FrameResult FusionPipeline::processFrame(ImageView<const uint16_t> raw_depth, int64_t utime,
                                         const Pose* T_world_cam_prior) {
  FrameResult result;
  const int lost_before = lost_in_a_row_;
  // Frames the source never delivered since the last one (a covered or stalled camera, a full
  // queue) count as missed: the camera moved on meanwhile.
  int undelivered = 0;
  if (last_utime_ >= 0 && utime > last_utime_) {
    const int64_t interval = utime - last_utime_;
    if (frame_interval_us_ == 0 || interval < frame_interval_us_) frame_interval_us_ = interval;
    undelivered = static_cast<int>(
        std::lround(static_cast<double>(interval) / static_cast<double>(frame_interval_us_)) - 1);
  }
  last_utime_ = utime;
  const int missed_before = missed_ + undelivered;
  auto counted = [&](FrameResult r) {
    if (r.status == TrackingStatus::kLost) {
      r.lost_in_a_row = lost_in_a_row_ = lost_before + 1;
      missed_ = missed_before + 1;
    } else {
      lost_in_a_row_ = missed_ = 0;
      r.recovered_after = lost_before;
      if (params_.relocalise) {
        relocaliser_.encode(frame_.depth_m[kPyramidLevels - 1].view());
        relocaliser_.harvest(r.T_world_cam);
      }
    }
    return r;
  };
  if (!preprocess(raw_depth, utime, T_world_cam_, &result)) return counted(result);
  if (!has_model_) {
    result.status = TrackingStatus::kFirstFrame;
    return counted(fuse(result, /*predict_from_pose=*/true));
  }
  const float gate_scale =
      std::min(1.f + static_cast<float>(missed_before), params_.max_recovery_gate_scale);
  std::string from_prior;
  if (missed_before > 0 && T_world_cam_prior != nullptr) {
    model_at_pose_ = false;
    predict(*T_world_cam_prior, &result);
    FrameResult r = trackAndFuse(result, *T_world_cam_prior, Pose::Identity(), /*prior=*/true,
                                 /*predict_from_pose=*/true, gate_scale);
    if (r.status != TrackingStatus::kLost) return counted(r);
    from_prior = "from the prior: " + r.lost_reason + "; from the last pose: ";
    result.ms = r.ms;
  }
  if (!model_at_pose_) predict(T_world_cam_, &result);
  // The model was raycast from the last pose, so without a prior the guess relative to it is
  // the identity. While recovering, the prior was tried above: this is the try from the last
  // pose, as the frame would be tracked without an IMU.
  const bool prior = T_world_cam_prior != nullptr && missed_before == 0;
  const Pose guess = prior ? T_world_cam_.inverse() * *T_world_cam_prior : Pose::Identity();
  FrameResult r = trackAndFuse(result, T_world_cam_, guess, prior, /*predict_from_pose=*/true,
                               gate_scale);
  if (r.status != TrackingStatus::kLost || missed_before == 0 || !params_.relocalise)
    return counted(r);
  return counted(relocalise(result, from_prior + r.lost_reason));
}

FrameResult FusionPipeline::relocalise(FrameResult result, const std::string& why_lost) {
  relocaliser_.encode(frame_.depth_m[kPyramidLevels - 1].view());
  std::array<Relocaliser::Candidate, kRelocaliseCandidates> candidates;
  const int found = relocaliser_.nearest(kRelocaliseCandidates, candidates.data());
  std::string reason = why_lost;
  for (int i = 0; i < found; ++i) {
    const Pose& T_world_kf = candidates[static_cast<size_t>(i)].T_world_cam;
    model_at_pose_ = false;
    predict(T_world_kf, &result);
    FrameResult r = trackAndFuse(result, T_world_kf, Pose::Identity(), /*prior=*/false,
                                 /*predict_from_pose=*/true, params_.max_recovery_gate_scale);
    if (r.status != TrackingStatus::kLost) {
      r.relocalised = true;
      return r;
    }
    reason += "; from keyframe " + std::to_string(i + 1) + " of " + std::to_string(found) + ": " +
              r.lost_reason;
    result.ms = r.ms;
  }
  if (found == 0) reason += "; no keyframe looks like it";
  result.status = TrackingStatus::kLost;
  result.T_world_cam = T_world_cam_;
  result.lost_reason = reason;
  return result;
}

FrameResult FusionPipeline::processFrameFromGuess(ImageView<const uint16_t> raw_depth,
                                                  int64_t utime, const Pose& T_world_cam_guess) {
  FrameResult result;
  if (!preprocess(raw_depth, utime, T_world_cam_guess, &result)) {
    if (has_model_) result.T_world_cam = T_world_cam_;  // lost: the last fused pose, as below
    return result;
  }
  // The next frame brings its own guess to raycast from: no prediction after fusing.
  if (!has_model_) {
    result.status = TrackingStatus::kFirstFrame;
    return fuse(result, /*predict_from_pose=*/false);
  }
  model_at_pose_ = false;
  predict(T_world_cam_guess, &result);
  return trackAndFuse(result, T_world_cam_guess, Pose::Identity(), /*prior=*/false,
                      /*predict_from_pose=*/false);
}

void FusionPipeline::predict(const Pose& T_world_cam, FrameResult* result) {
  const auto t0 = std::chrono::steady_clock::now();
  raycaster_.raycast(*volume_, params_.integrate.truncation_m, T_world_cam, &model_,
                     frame_.depth_m[0].view());
  model_.buildPyramid();
  result->ms.raycast += msSince(t0);
}

FrameResult FusionPipeline::trackAndFuse(FrameResult result, const Pose& T_world_ref,
                                         const Pose& T_ref_cur_guess, bool prior,
                                         bool predict_from_pose, float gate_scale) {
  const auto t0 = std::chrono::steady_clock::now();
  const IcpResult icp = tracker_.track(frame_, model_, T_ref_cur_guess, prior, gate_scale);
  result.ms.track += msSince(t0);
  result.status = icp.status;
  result.inlier_fraction = icp.inlier_fraction;
  result.rmse_m = icp.rmse_m;
  if (icp.status != TrackingStatus::kOk) {
    // Keep the previous pose and leave the map untouched: fusing a frame at a wrong pose
    // would corrupt the model that the next frames track against.
    result.T_world_cam = T_world_cam_;
    result.lost_reason = icp.reason;
    result.ms.total = result.ms.preprocess + result.ms.track + result.ms.raycast;
    return result;
  }
  result.T_world_cam = orthonormalized(T_world_ref * icp.T_ref_cur);
  // A twist [w; t] of T_ref_cur moves the camera's position in the reference frame by
  // w x p + t and turns the camera by R_ref_cur^T w in its own frame.
  const Eigen::Matrix3d R_ref_cur = icp.T_ref_cur.linear();
  const Eigen::Vector3d p_ref_cur = icp.T_ref_cur.translation();
  result.weakest_fraction = icp.weakest_fraction;
  result.weak.count = icp.weak_directions;
  for (int i = 0; i < icp.weak_directions; ++i) {
    const Eigen::Vector3d w = icp.weak[i].head<3>(), t = icp.weak[i].tail<3>();
    result.weak.d[i] << T_world_ref.linear() * (w.cross(p_ref_cur) + t), R_ref_cur.transpose() * w;
    result.weak.d[i].normalize();
  }
  return fuse(result, predict_from_pose);
}

FrameResult FusionPipeline::processFrameAtPose(ImageView<const uint16_t> raw_depth, int64_t utime,
                                               const Pose& T_world_cam) {
  FrameResult result;
  preprocess(raw_depth, utime, T_world_cam, &result);
  // A given pose is fused whatever the depth holds: the caller vouches for it.
  result.status = TrackingStatus::kGivenPose;
  result.lost_reason.clear();
  return fuse(result, /*predict_from_pose=*/true);
}

FrameResult FusionPipeline::fuse(FrameResult result, bool predict_from_pose) {
  T_world_cam_ = result.T_world_cam;
  volume_->followCamera(T_world_cam_);

  const auto t0 = std::chrono::steady_clock::now();
  integrator_.integrate(frame_.raw_depth_m.view(), frame_.camera[0], T_world_cam_, volume_);
  result.ms.integrate = msSince(t0);
  has_model_ = true;
  model_at_pose_ = predict_from_pose;
  if (predict_from_pose) predict(T_world_cam_, &result);
  result.ms.total = result.ms.preprocess + result.ms.track + result.ms.integrate + result.ms.raycast;
  return result;
}

void FusionPipeline::renderShaded(ImageView<uint8_t> out) {
  if (!render_maps_) render_maps_ = std::make_unique<ModelMaps>(camera());
  raycaster_.raycast(*volume_, params_.integrate.truncation_m, T_world_cam_, render_maps_.get());
  Raycaster::shade(render_maps_->vertex_ref[0].view(), render_maps_->normal_ref[0].view(), out);
}

void FusionPipeline::shadeModel(ImageView<uint8_t> out) const {
  Raycaster::shade(model_.vertex_ref[0].view(), model_.normal_ref[0].view(), out);
}

}  // namespace kinfly
