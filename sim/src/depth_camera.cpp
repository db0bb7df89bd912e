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
      outOfRange("camera.depth_scale_m", depth_scale_m, 0.0, 0.01, Bound::kOpen),
      outOfRange("camera.threads", threads, 1, 64));
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

double roundHalfUp(double x) {
  if (!(std::abs(x) < 0x1.0p52)) return x;  // integral already, or not a number
  const double truncated = static_cast<double>(static_cast<int64_t>(x));
  // Added, not chosen: which way a pixel rounds is a coin toss a branch would mispredict.
  return truncated + static_cast<double>(x - truncated >= 0.5);
}

namespace {

// fn(begin, end) over [0, count) in `threads` contiguous parts. OpenMP's team persists between
// frames; one thread enters no parallel region at all. The engine's loops (shared/src/parallel.h)
// take the process's thread count; a camera has its own.
template <class Fn>
void forEachPart(size_t count, int threads, Fn&& fn) {
  const size_t parts = static_cast<size_t>(threads);
  if (parts == 1) {
    fn(size_t{0}, count);
    return;
  }
#pragma omp parallel for num_threads(threads) schedule(static, 1)
  for (size_t part = 0; part < parts; ++part) fn(count * part / parts, count * (part + 1) / parts);
}

}  // namespace

void DepthCamera::render(const Pose& T_world_cam, ImageView<uint16_t> raw) {
  const PinholeCamera& camera = params_.camera;
  assert(raw.width() == camera.width && raw.height() == camera.height);
  const Eigen::Matrix3f R_world_cam = T_world_cam.linear().cast<float>();
  const Eigen::Vector3f origin = T_world_cam.translation().cast<float>();
  const size_t width = static_cast<size_t>(camera.width);
  const size_t height = static_cast<size_t>(camera.height);
  depth_m_.resize(width * height);
  // The rays, rows split over the threads: each pixel's exact depth, or 0 for no return.
  forEachPart(height, params_.threads, [&](size_t row_begin, size_t row_end) {
    // Directions (x, y, 1) in the camera: a hit's distance along one is its depth z.
    const float max_distance = static_cast<float>(params_.max_range_m) * 1.01f;
    Eigen::Vector3f directions[8];
    bool active[8];
    float depth[8];
    float cos_incidence[8];
    for (size_t v = row_begin; v < row_end; ++v) {
      float* row = depth_m_.data() + v * width;
      for (int u0 = 0; u0 < camera.width; u0 += 8) {
        for (int i = 0; i < 8; ++i) {
          const int u = u0 + i;
          active[i] = u < camera.width;
          directions[i] =
              R_world_cam * Eigen::Vector3f((static_cast<float>(u) - camera.cx) / camera.fx,
                                            (static_cast<float>(v) - camera.cy) / camera.fy, 1.0f);
        }
        scene_.cast8(origin, directions, active, max_distance, depth, cos_incidence);
        for (int i = 0; i < 8 && u0 + i < camera.width; ++i) {
          const double z = depth[i];
          const bool returned = z >= params_.min_range_m && z <= params_.max_range_m &&
                                cos_incidence[i] >= min_cos_incidence_;
          row[u0 + i] = returned ? depth[i] : 0.0f;
        }
      }
    }
  });
  // One deviate a return, in pixel order, as the sensor's noise was always drawn.
  first_noise_.resize(height + 1);
  first_noise_[0] = 0;
  for (size_t v = 0; v < height; ++v) {
    const float* row = depth_m_.data() + v * width;
    first_noise_[v + 1] = first_noise_[v] + static_cast<size_t>(
        std::count_if(row, row + width, [](float z) { return z > 0.0f; }));
  }
  if (params_.noise) {
    noise_.resize(first_noise_[height]);
    for (double& deviate : noise_) deviate = random_();
  }
  const double bf_px_m = params_.baseline_m * params_.disparity_focal_px;
  const double step = params_.disparity_step_px;
  // Disparities counted in steps, and depths in units, by multiplying: two divisions a return
  // fewer (VGA on one thread: 17.9 to 17.1 ms a frame).
  const double bf_steps_m = step > 0.0 ? bf_px_m / step : 0.0;
  const double units_per_m = 1.0 / params_.depth_scale_m;
  const double max_raw = 65535.0;
  forEachPart(height, params_.threads, [&](size_t row_begin, size_t row_end) {
    for (size_t v = row_begin; v < row_end; ++v) {
      const float* depth = depth_m_.data() + v * width;
      uint16_t* row = raw.row(static_cast<int>(v));
      size_t next_noise = first_noise_[v];
      for (size_t u = 0; u < width; ++u) {
        if (depth[u] == 0.0f) {
          row[u] = 0;
          continue;
        }
        const double z = depth[u];
        double measured = z;
        if (params_.noise) {
          measured += kinectNoiseSigmaM(static_cast<float>(z)) * noise_[next_noise++];
          if (step > 0.0 && measured > 0.0) {
            const double disparity = std::max(step, roundHalfUp(bf_steps_m / measured) * step);
            measured = bf_px_m / disparity;
          }
        }
        const double units = roundHalfUp(measured * units_per_m);
        row[u] = static_cast<uint16_t>(std::clamp(units, 0.0, max_raw));
      }
    }
  });
}

}  // namespace kinfly::sim
