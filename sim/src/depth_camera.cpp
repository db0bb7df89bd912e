#include "kinfly/sim/depth_camera.h"

#include <algorithm>
#include <cassert>
#include <cmath>

#include "kinfly/core/noise_model.h"
#include "kinfly/core/range_check.h"

namespace kinfly::sim {

Status DepthCameraParams::validate() const {
  if (Status status = camera.validate(); !status.ok()) return status;
  return firstError(
      outOfRange("camera.rate_hz", rate_hz, 0.0, 120.0, Bound::kOpen),
      outOfRange("camera.latency_s", latency_s, 0.0, 1.0),
      outOfRange("camera.max_range_m", max_range_m, 0.0, 20.0, Bound::kOpen),
      outOfRange("camera.min_range_m", min_range_m, 0.0, std::nextafter(max_range_m, 0.0),
                 Bound::kOpen),
      outOfRange("camera.max_incidence_deg", max_incidence_deg, 0.0, 90.0, Bound::kOpen),
      outOfRange("camera.baseline_m", baseline_m, 0.0, 1.0, Bound::kOpen),
      outOfRange("camera.disparity_focal_px", disparity_focal_px, 0.0, 5000.0, Bound::kOpen),
      outOfRange("camera.disparity_step_px", disparity_step_px, 0.0, 1.0),
      outOfRange("camera.depth_scale_m", depth_scale_m, 0.0, 0.01, Bound::kOpen));
}

Pose forwardBodyCam() {
  Pose T = Pose::Identity();
  T.linear() << 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0;
  return T;
}

DepthCamera::DepthCamera(const RayScene& scene, const DepthCameraParams& params)
    : scene_(scene),
      params_(params),
      random_(params.seed),
      min_cos_incidence_(static_cast<float>(std::cos(params.max_incidence_deg * M_PI / 180.0))) {}

void DepthCamera::render(const Pose& T_world_cam, ImageView<uint16_t> raw) {
  const PinholeCamera& camera = params_.camera;
  assert(raw.width() == camera.width && raw.height() == camera.height);
  const Eigen::Matrix3f R_world_cam = T_world_cam.linear().cast<float>();
  const Eigen::Vector3f origin = T_world_cam.translation().cast<float>();
  // Directions (x, y, 1) in the camera: a hit's distance along one is its depth z.
  const float max_distance = static_cast<float>(params_.max_range_m) * 1.01f;
  const double bf_px_m = params_.baseline_m * params_.disparity_focal_px;
  const double max_raw = 65535.0;
  Eigen::Vector3f directions[8];
  bool active[8];
  float depth[8];
  float cos_incidence[8];
  for (int v = 0; v < camera.height; ++v) {
    uint16_t* row = raw.row(v);
    for (int u0 = 0; u0 < camera.width; u0 += 8) {
      for (int i = 0; i < 8; ++i) {
        const int u = u0 + i;
        active[i] = u < camera.width;
        directions[i] = R_world_cam * Eigen::Vector3f((static_cast<float>(u) - camera.cx) / camera.fx,
                                                      (static_cast<float>(v) - camera.cy) / camera.fy,
                                                      1.0f);
      }
      scene_.cast8(origin, directions, active, max_distance, depth, cos_incidence);
      for (int i = 0; i < 8 && u0 + i < camera.width; ++i) {
        const double z = depth[i];
        if (z < params_.min_range_m || z > params_.max_range_m ||
            cos_incidence[i] < min_cos_incidence_) {
          row[u0 + i] = 0;
          continue;
        }
        double measured = z;
        if (params_.noise) {
          measured += kinectNoiseSigmaM(static_cast<float>(z)) * random_();
          if (params_.disparity_step_px > 0.0 && measured > 0.0) {
            const double step = params_.disparity_step_px;
            const double disparity = std::max(step, std::round(bf_px_m / measured / step) * step);
            measured = bf_px_m / disparity;
          }
        }
        const double units = std::round(measured / params_.depth_scale_m);
        row[u0 + i] = static_cast<uint16_t>(std::clamp(units, 0.0, max_raw));
      }
    }
  }
}

}  // namespace kinfly::sim
