// The camera swings around the objects of the corner room and bobs up and down, as a hovering
// drone would.
#include <cmath>
#include <random>

#include "kinfly/sources/synthetic_source.h"

#include "kinfly/core/range_check.h"
#include "kinfly/synthetic/synthetic_scene.h"

namespace kinfly::fw {
namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kDepthScaleM = 0.001;  // OpenNI's millimetres, as a real sensor would give
constexpr float kMaxDepthM = 5.0f;      // a Kinect sees nothing further
constexpr float kKinectFxAt640 = 525.f; // [px] the usual Kinect focal length at 640x480
// The swing: yaw around the objects (amplitude and period), and a slower vertical bob. Peak
// speed ~0.55 m/s and ~15 deg/s: a gentle indoor flight, ~2 cm a frame at 30 Hz.
constexpr double kSwingRad = 0.35, kSwingPeriodS = 8.0;
constexpr double kBobM = 0.10, kBobPeriodS = 5.6;

class SyntheticSource : public DepthSource {
 public:
  SyntheticSource(const SyntheticSourceParams& params, const PinholeCamera& camera)
      : params_(params), camera_(camera), scene_(SyntheticScene::cornerRoom()),
        rng_(static_cast<uint32_t>(params.seed)), still_(params.motion == "still"),
        T_first_world_(poseAt(0.0).inverse()) {}

  const PinholeCamera& camera() const override { return camera_; }
  double depthScaleM() const override { return kDepthScaleM; }
  std::string describe() const override {
    return "synthetic corner room, " + std::to_string(camera_.width) + "x" +
           std::to_string(camera_.height) + " at " + std::to_string(static_cast<int>(std::lround(params_.rate_hz))) +
           " Hz, seed " + std::to_string(params_.seed);
  }

  SourceStatus next(DepthCapture* out, std::string* why) override {
    if (params_.drop_late && params_.clock && frames_ > 0) {
      // So that on a busy machine the stamps never fall further behind the clock than a
      // frame: a pose that old would be fused late, or not at all.
      if (const int64_t now = params_.clock(); now >= frameUtime(frames_ + 1)) {
        *why = "synthetic: frame " + std::to_string(frames_) + " dropped, " +
               std::to_string((now - frameUtime(frames_)) / 1000) +
               " ms late (rendering slower than source.rate_hz)";
        ++frames_;
        return SourceStatus::kSkipped;
      }
    }
    const double t_s = static_cast<double>(frames_) / params_.rate_hz;
    const Pose T_world_cam = poseAt(still_ ? 0.0 : t_s);
    if (out->depth.width() != camera_.width || out->depth.height() != camera_.height)
      out->depth = Image<uint16_t>(camera_.width, camera_.height);
    scene_.renderRawDepth(camera_, T_world_cam, kMaxDepthM, kDepthScaleM, &rng_,
                          out->depth.view());
    // After the render, where the capture's pacing starts too: were it read before, a slow
    // first render would leave every frame that much later than its stamp, and from two
    // periods on every other frame would be dropped for good.
    if (params_.clock && frames_ == 0) first_utime_ = params_.clock();
    out->utime = frameUtime(frames_);
    out->has_ground_truth = true;
    out->T_world_cam_truth = T_first_world_ * T_world_cam;
    ++frames_;
    return SourceStatus::kFrame;
  }

 private:
  int64_t frameUtime(int64_t frame) const {
    return first_utime_ + std::llround(static_cast<double>(frame) / params_.rate_hz * 1e6);
  }

  // In the scene's frame: the first camera sits at the origin looking along +z at the objects.
  static Pose poseAt(double t_s) {
    const Eigen::Vector3d target(0.0, 0.3, 2.0);
    const double yaw = kSwingRad * std::sin(2.0 * kPi * t_s / kSwingPeriodS);
    Eigen::Vector3d eye =
        target + Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitY()) * (Eigen::Vector3d::Zero() - target);
    eye.y() += kBobM * std::sin(2.0 * kPi * t_s / kBobPeriodS);
    return lookAtPose(eye, target);
  }

  SyntheticSourceParams params_;
  PinholeCamera camera_;
  SyntheticScene scene_;
  std::mt19937 rng_;
  bool still_;
  Pose T_first_world_;
  int64_t frames_ = 0;
  int64_t first_utime_ = 0;
};

}  // namespace

Status SyntheticSourceParams::validate() const {
  if (motion != "swing" && motion != "still")
    return Status::error("source.motion must be swing or still (got \"" + motion + "\")");
  return firstError(checkSourceSize(width_px, height_px),
                      outOfRange("source.rate_hz", rate_hz, 0, 1000, Bound::kOpen),
                      outOfRange("source.seed", seed, 0, 2147483647));
}

StatusOr<std::unique_ptr<DepthSource>> openSyntheticSource(const SyntheticSourceParams& params) {
  if (Status valid = params.validate(); !valid.ok()) return valid;
  StatusOr<PinholeCamera> camera =
      sourceCamera(kKinectFxAt640, params.width_px, params.height_px, params.intrinsics);
  if (!camera.ok()) return camera.status();
  return std::make_unique<SyntheticSource>(params, *camera);
}

}  // namespace kinfly::fw
