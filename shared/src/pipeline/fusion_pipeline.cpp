#include "kinfly/pipeline/fusion_pipeline.h"

#include <algorithm>
#include <array>
#include <cassert>
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
  if (!(max_prior_disagreement_m > 0.f && max_prior_disagreement_m <= 1.f))
    return Status::error("max_prior_disagreement_m must be in (0, 1]");
  if (!(max_prior_disagreement_rad > 0.f && max_prior_disagreement_rad <= 1.f))
    return Status::error("max_prior_disagreement_rad must be in (0, 1]");
  if (new_map_after_failed_frames < 0)
    return Status::error("new_map_after_failed_frames must be >= 0 (0: never)");
  if (model_level < 0 || model_level > kPyramidLevels - 2)
    return Status::error("model_level must be in [0, " + std::to_string(kPyramidLevels - 2) + "]");
  // Checked even when relocalisation is off: turning it on later must not meet a bad setting.
  if (const Status r = relocaliser.validate(); !r.ok())
    return Status::error("relocaliser: " + r.message());
  return {};
}

FusionPipeline::FusionPipeline(const PinholeCamera& input_camera, const Params& params,
                               TsdfVolume* volume)
    : params_(params),
      volume_(volume),
      preprocessor_(input_camera, params.preprocess),
      tracker_(params.icp),
      integrator_(params.integrate),
      raycaster_(preprocessor_.camera().scaled(1 << params.model_level), params.raycast),
      frame_(preprocessor_.camera()),
      model_(preprocessor_.camera(), params.model_level) {
  // validate() names the range; a caller that skipped it would index past the pyramid.
  assert(params.model_level >= 0 && params.model_level <= kPyramidLevels - 2);
  integrator_.reserve(preprocessor_.camera().width, preprocessor_.camera().height, *volume);
  if (volume->followsCamera())
    view_depths_.resize(static_cast<size_t>(frame_.depth_m.back().numPixels()));
  if (params_.relocalise) relocaliser_.emplace(params_.relocaliser);
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

int FusionPipeline::undeliveredBefore(int64_t utime) {
  if (last_utime_ < 0 || utime <= last_utime_) {
    // The first frame, a repeated time or a clock that went back (a restarted log or sensor):
    // nothing to measure a gap by, so the new time is where the next interval starts.
    last_utime_ = utime;
    return 0;
  }
  const int64_t interval = utime - last_utime_;
  last_utime_ = utime;
  intervals_[static_cast<size_t>(interval_count_ % kIntervals)] = interval;
  ++interval_count_;
  if (interval_count_ < kMinIntervals) return 0;
  // The median of the latest intervals: a few short ones (jittered or repeated times) or long
  // ones (the gaps themselves) do not move it.
  std::array<int64_t, kIntervals> sorted = intervals_;
  const int n = std::min(interval_count_, kIntervals);
  std::nth_element(sorted.begin(), sorted.begin() + n / 2, sorted.begin() + n);
  const double frames = std::min(static_cast<double>(interval) / static_cast<double>(sorted[n / 2]),
                                 static_cast<double>(kMaxMissedCounted));
  return std::max(static_cast<int>(std::lround(frames)) - 1, 0);
}

FrameResult FusionPipeline::processFrame(ImageView<const uint16_t> raw_depth, int64_t utime,
                                         const Pose* T_world_cam_prior) {
  FrameResult result;
  const int lost_before = lost_in_a_row_;
  // Frames the source never delivered since the last one (a covered or stalled camera, a full
  // queue) count as missed: the camera moved on meanwhile.
  const int missed_before = std::min(missed_ + undeliveredBefore(utime), kMaxMissedCounted);
  auto counted = [&](FrameResult r) {
    r.missed = missed_before;
    if (r.status == TrackingStatus::kLost) {
      lost_in_a_row_ = std::min(lost_before + 1, kMaxMissedCounted);
      r.lost_in_a_row = lost_in_a_row_;
      missed_ = std::min(missed_before + 1, kMaxMissedCounted);
      return r;
    }
    // Frames lost before the first had no map to be tracked against: nothing to recover. A new
    // map's first frame does end a loss.
    if (r.status != TrackingStatus::kFirstFrame || r.new_map) r.recovered_after = lost_before;
    if (params_.relocalise) {
      const auto t0 = std::chrono::steady_clock::now();
      relocaliser_->encode(frame_.depth_m[kPyramidLevels - 1].view());
      relocaliser_->harvest(r.T_world_cam);
      const double ms = msSince(t0);
      r.ms.track += ms;
      r.ms.total += ms;
    }
    return r;
  };
  if (!preprocess(raw_depth, utime, T_world_cam_, &result)) return counted(std::move(result));
  if (!has_model_) {
    result.status = TrackingStatus::kFirstFrame;
    return counted(fuse(std::move(result), /*predict_from_pose=*/true));
  }
  const float gate_scale =
      std::min(1.f + static_cast<float>(missed_before), params_.max_recovery_gate_scale);
  // With a prior, whatever try finds the pose after missed frames must agree with it within
  // max_prior_disagreement_m and _rad: the IMU carries the motion across the missed frames with
  // an error far below the free motion of one frame (3 cm after a second, in the tests). The
  // widened gates are for ICP's search. Wider agreements let a frame of the ring's corridor
  // converge 32 cm above a prior 2 frames old, and a relocalisation 16 cm along it from a prior
  // one frame old (docs/sim.md).
  const Pose* near = missed_before > 0 ? T_world_cam_prior : nullptr;
  std::string from_prior;
  if (near != nullptr) {
    model_at_pose_ = false;
    predict(*T_world_cam_prior, &result);
    FrameResult r = trackAndFuse(result, *T_world_cam_prior, Pose::Identity(), /*prior=*/true,
                                 /*predict_from_pose=*/true, gate_scale, near);
    if (r.status != TrackingStatus::kLost) return counted(std::move(r));
    from_prior = "from the prior: " + r.lost_reason + "; from the last pose: ";
    result.ms = r.ms;
  }
  if (!model_at_pose_) {
    predict(T_world_cam_, &result);
    model_at_pose_ = true;
  }
  // The model was raycast from the last pose, so without a prior the guess relative to it is
  // the identity. While recovering, the prior was tried above: this is the try from the last
  // pose, as the frame would be tracked without an IMU.
  const bool prior = T_world_cam_prior != nullptr && missed_before == 0;
  const Pose guess = prior ? T_world_cam_.inverse() * *T_world_cam_prior : Pose::Identity();
  FrameResult r = trackAndFuse(std::move(result), T_world_cam_, guess, prior,
                               /*predict_from_pose=*/true, gate_scale, near);
  if (r.status == TrackingStatus::kLost) r.lost_reason = from_prior + r.lost_reason;
  if (r.status != TrackingStatus::kLost) return counted(std::move(r));
  if (missed_before > 0 && params_.relocalise) r = relocalise(std::move(r), near);
  if (r.status != TrackingStatus::kLost) return counted(std::move(r));
  return counted(failedOrNewMap(std::move(r), T_world_cam_prior));
}

FrameResult FusionPipeline::failedOrNewMap(FrameResult lost, const Pose* T_world_cam_prior) {
  failed_since_tracked_ = std::min(failed_since_tracked_ + 1, kMaxMissedCounted);
  if (params_.new_map_after_failed_frames == 0 ||
      failed_since_tracked_ < params_.new_map_after_failed_frames || T_world_cam_prior == nullptr)
    return lost;
  // Cleared even with a prior in the old map's frame: every try said the old map does not fit
  // this view, so either the prior has drifted from it or the view is new, and fusing the new
  // view into a map it may contradict would corrupt both (onboard the volume is a window that
  // follows the camera anyway). The old map's keyframes go with it: relocalising against them
  // would raycast nothing.
  volume_->clear();
  if (relocaliser_) relocaliser_->clear();
  FrameResult r = std::move(lost);
  r.T_world_cam = *T_world_cam_prior;
  r.status = TrackingStatus::kFirstFrame;
  r.new_map = true;
  r.lost_reason.clear();
  r.inlier_fraction = r.rmse_m = 0.f;
  return fuse(std::move(r), /*predict_from_pose=*/true);
}

FrameResult FusionPipeline::relocalise(FrameResult lost, const Pose* T_world_cam_prior) {
  const auto t0 = std::chrono::steady_clock::now();
  relocaliser_->encode(frame_.depth_m[kPyramidLevels - 1].view());
  std::array<Relocaliser::Candidate, kRelocaliseCandidates> candidates;
  const int found = relocaliser_->nearest(kRelocaliseCandidates, candidates.data());
  const double ms = msSince(t0);
  lost.ms.track += ms;
  lost.ms.total += ms;
  if (found == 0) lost.lost_reason += "; no keyframe looks like it";
  for (int i = 0; i < found; ++i) {
    const Pose& T_world_kf = candidates[static_cast<size_t>(i)].T_world_cam;
    model_at_pose_ = false;
    predict(T_world_kf, &lost);
    // A keyframe is where the camera was, not where it may have moved since: the gates stay the
    // normal frame's. With an IMU, the pose must also agree with its prediction (processFrame),
    // so that a place that merely looks alike cannot move the drone.
    FrameResult r = trackAndFuse(lost, T_world_kf, Pose::Identity(), /*prior=*/false,
                                 /*predict_from_pose=*/true, /*gate_scale=*/1.f,
                                 T_world_cam_prior);
    if (r.status != TrackingStatus::kLost) {
      r.relocalised = true;
      r.lost_reason.clear();  // the other tries' reasons came along in `lost`
      return r;
    }
    lost.lost_reason += "; from keyframe " + std::to_string(i + 1) + " of " +
                        std::to_string(found) + ": " + r.lost_reason;
    lost.ms = r.ms;
    lost.inlier_fraction = r.inlier_fraction;
    lost.rmse_m = r.rmse_m;
  }
  return lost;
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
                     frame_.depth_m[params_.model_level].view());
  model_.buildPyramid();
  result->ms.raycast += msSince(t0);
}

FrameResult FusionPipeline::trackAndFuse(FrameResult result, const Pose& T_world_ref,
                                         const Pose& T_ref_cur_guess, bool prior,
                                         bool predict_from_pose, float gate_scale,
                                         const Pose* T_world_cam_near) {
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
  if (T_world_cam_near != nullptr) {
    const Pose off = T_world_cam_near->inverse() * result.T_world_cam;
    if (off.translation().norm() > params_.max_prior_disagreement_m ||
        rotationAngleRad(off) > params_.max_prior_disagreement_rad) {
      std::ostringstream why;
      why << "tracked " << off.translation().norm() << " m and " << rotationAngleRad(off)
          << " rad from the prior, beyond max_prior_disagreement_m or _rad";
      result.status = TrackingStatus::kLost;
      result.T_world_cam = T_world_cam_;
      result.lost_reason = why.str();
      result.ms.total = result.ms.preprocess + result.ms.track + result.ms.raycast;
      return result;
    }
  }
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
  // No prediction: a frame tracked next raycasts the model from this pose first (processFrame)
  // or from its own guess (processFrameFromGuess). Frames fused only at given poses (mapping
  // with known poses, the ground's overlap of a new submap: 8 keyframes) raycast nothing.
  return fuse(result, /*predict_from_pose=*/false);
}

float FusionPipeline::medianViewDepthM() {
  // The coarsest level: a few thousand depths, a few microseconds, nothing allocated.
  const Image<float>& depth = frame_.depth_m.back();
  if (view_depths_.size() < static_cast<size_t>(depth.numPixels())) return 0.f;
  size_t n = 0;
  for (const float* d = depth.data(); d != depth.data() + depth.numPixels(); ++d)
    if (*d > 0.f) view_depths_[n++] = *d;
  if (n == 0) return 0.f;
  const auto end = view_depths_.begin() + static_cast<std::ptrdiff_t>(n);
  const auto middle = view_depths_.begin() + static_cast<std::ptrdiff_t>(n / 2);
  std::nth_element(view_depths_.begin(), middle, end);
  return *middle;
}

FrameResult FusionPipeline::fuse(FrameResult result, bool predict_from_pose) {
  // Whatever fused it (tracked, a given pose, a new map), the frame ends any loss.
  lost_in_a_row_ = missed_ = failed_since_tracked_ = 0;
  T_world_cam_ = result.T_world_cam;
  if (volume_->followsCamera()) volume_->followCamera(T_world_cam_, medianViewDepthM());

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
  if (!render_maps_) {
    if (params_.model_level > 0)
      render_raycaster_ = std::make_unique<Raycaster>(camera(), params_.raycast);
    render_maps_ = std::make_unique<ModelMaps>(camera());
  }
  Raycaster& raycaster = render_raycaster_ ? *render_raycaster_ : raycaster_;
  raycaster.raycast(*volume_, params_.integrate.truncation_m, T_world_cam_, render_maps_.get());
  Raycaster::shade(render_maps_->vertex_ref[0].view(), render_maps_->normal_ref[0].view(), out);
}

void FusionPipeline::shadeModel(ImageView<uint8_t> out) const {
  assert(out.width() == model_.camera[0].width && out.height() == model_.camera[0].height);
  Raycaster::shade(model_.vertex_ref[0].view(), model_.normal_ref[0].view(), out);
}

}  // namespace kinfly
