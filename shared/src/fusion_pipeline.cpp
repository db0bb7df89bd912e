#include "kinfly/fusion_pipeline.h"

#include <chrono>
#include <sstream>

namespace kinfly {

namespace {
double msSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}
}  // namespace

std::string FusionPipeline::Params::validate(float voxel_size_m) const {
  for (const std::string& why : {preprocess.validate(), icp.validate(),
                                 integrate.validate(voxel_size_m), raycast.validate()})
    if (!why.empty()) return why;
  if (!(min_valid_depth_fraction >= 0.f && min_valid_depth_fraction < 1.f))
    return "min_valid_depth_fraction must be in [0, 1)";
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
      frame_(preprocessor_.camera()),
      model_(preprocessor_.camera()) {
  integrator_.reserve(preprocessor_.camera().width, preprocessor_.camera().height, *volume);
}

FrameResult FusionPipeline::processFrame(ImageView<const uint16_t> raw_depth, int64_t utime) {
  const auto start = std::chrono::steady_clock::now();
  const PreprocessResult pre = preprocessor_.process(raw_depth, &frame_);
  const double preprocess_ms = msSince(start);

  FrameResult result;
  result.utime = utime;
  result.T_world_cam = T_world_cam_;
  result.valid_depth_fraction = pre.valid_fraction;
  if (pre.valid_fraction < params_.min_valid_depth_fraction) {
    result.status = TrackingStatus::kLost;
    std::ostringstream why;
    why << "only " << pre.valid_fraction * 100.f << "% of pixels have valid depth";
    result.lost_reason = why.str();
    result.ms.preprocess = result.ms.total = preprocess_ms;
    return result;
  }
  if (!has_model_) {
    result.status = TrackingStatus::kFirstFrame;
    return fuse(result, preprocess_ms);
  }
  const auto track_start = std::chrono::steady_clock::now();
  // The model was raycast from the last pose, so the guess relative to it is the identity.
  const IcpResult icp = tracker_.track(frame_, model_, Pose::Identity());
  result.ms.track = msSince(track_start);
  result.status = icp.status;
  result.inlier_fraction = icp.inlier_fraction;
  result.rmse_m = icp.rmse_m;
  if (icp.status != TrackingStatus::kOk) {
    // Keep the previous pose and leave the map untouched: fusing a frame at a wrong pose
    // would corrupt the model that the next frames track against.
    result.lost_reason = icp.reason;
    result.ms.preprocess = preprocess_ms;
    result.ms.total = msSince(start);
    return result;
  }
  result.T_world_cam = orthonormalized(T_world_cam_ * icp.T_ref_cur);
  return fuse(result, preprocess_ms);
}

FrameResult FusionPipeline::processFrameAtPose(ImageView<const uint16_t> raw_depth, int64_t utime,
                                               const Pose& T_world_cam) {
  const auto start = std::chrono::steady_clock::now();
  const PreprocessResult pre = preprocessor_.process(raw_depth, &frame_);
  FrameResult result;
  result.utime = utime;
  result.T_world_cam = T_world_cam;
  result.status = TrackingStatus::kGivenPose;
  result.valid_depth_fraction = pre.valid_fraction;
  return fuse(result, msSince(start));
}

FrameResult FusionPipeline::fuse(FrameResult result, double preprocess_ms) {
  result.ms.preprocess = preprocess_ms;
  T_world_cam_ = result.T_world_cam;
  volume_->followCamera(T_world_cam_);

  auto t0 = std::chrono::steady_clock::now();
  integrator_.integrate(frame_.raw_depth_m.view(), frame_.camera[0], T_world_cam_, volume_);
  result.ms.integrate = msSince(t0);

  t0 = std::chrono::steady_clock::now();
  raycaster_.raycast(*volume_, params_.integrate.truncation_m, T_world_cam_, &model_,
                     frame_.depth_m[0].view());
  model_.buildPyramid();
  has_model_ = true;
  result.ms.raycast = msSince(t0);
  result.ms.total = result.ms.preprocess + result.ms.track + result.ms.integrate + result.ms.raycast;
  return result;
}

void FusionPipeline::renderShaded(ImageView<uint8_t> out) {
  if (!render_maps_) render_maps_ = std::make_unique<ModelMaps>(camera());
  raycaster_.raycast(*volume_, params_.integrate.truncation_m, T_world_cam_, render_maps_.get());
  Raycaster::shade(render_maps_->vertex_ref[0].view(), render_maps_->normal_ref[0].view(), out);
}

}  // namespace kinfly
