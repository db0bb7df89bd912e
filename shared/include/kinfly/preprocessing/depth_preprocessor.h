// Stage 1-4 of the seed: raw depth -> metres with a validity mask, bilateral filter, 3-level
// discontinuity-aware pyramid, vertices and normals per level (packed for the tracker).
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <string>

#include "kinfly/core/camera.h"
#include "kinfly/core/image.h"
#include "kinfly/core/status.h"
#include "kinfly/frame/depth_frame.h"

namespace kinfly {

struct PreprocessResult {
  int valid_pixels = 0;         // level 0, after range limits
  float valid_fraction = 0.f;   // of level-0 pixels
};

// Bilateral weights, tabulated once: the spatial Gaussian per window offset and the range
// Gaussian per depth difference, because an exp() per tap would dominate the frame time.
struct BilateralKernel {
  static constexpr int kMaxRadius = 6;
  static constexpr int kRangeSteps = 64;   // table spans 4 sigma_range; beyond, weight < 3e-4
  BilateralKernel(int radius_px, float sigma_space_px, float sigma_range_m);
  int radius;
  float range_index_per_m;
  std::array<float, (2 * kMaxRadius + 1) * (2 * kMaxRadius + 1)> spatial{};
  // One entry past the table is zero, the weight of any larger difference.
  std::array<float, kRangeSteps + 1> range{};
};

class DepthPreprocessor {
 public:
  struct Params {
    double depth_scale_m = 1.0 / 5000.0;  // [m per raw unit] > 0; TUM 1/5000, OpenNI 1/1000
    float min_depth_m = 0.3f;             // [m] >= 0; Kinect v1 sees nothing nearer than ~0.4 m
    float max_depth_m = 4.0f;             // [m] > min_depth_m; noise grows as z^2 (4 cm at 5 m)
    int downsample = 1;                   // {1, 2, 4}: input subsampling before everything else
    int bilateral_radius_px = 2;          // [px] 0..6; 0 disables the filter
    float bilateral_sigma_space_px = 1.5f;  // [px] > 0
    float bilateral_sigma_range_m = 0.03f;  // [m] > 0; KinFu's 30 mm
    // Pyramid: pixels whose depth differs from the centre by more than this many sigma_range
    // are left out of the average (KinFu pyrDown), so levels do not smear across edges.
    float pyramid_range_sigmas = 3.f;     // > 0

    Status validate() const;
  };

  // `input_camera` describes the raw images given to process(), before downsampling.
  DepthPreprocessor(const PinholeCamera& input_camera, const Params& params);

  const PinholeCamera& inputCamera() const { return input_camera_; }
  // Camera of pyramid level 0 (after downsampling).
  const PinholeCamera& camera() const { return camera_; }
  const Params& params() const { return params_; }

  // `raw` must be inputCamera().width x height. Never throws on content; all-zero depth gives
  // valid_pixels == 0.
  PreprocessResult process(ImageView<const uint16_t> raw, DepthFrame* frame) const;

 private:
  PinholeCamera input_camera_;
  PinholeCamera camera_;
  Params params_;
  BilateralKernel kernel_;
};

// The stages one pixel or one map at a time: the definitions that process() must reproduce to
// the bit (unit tests check it does). process() filters with a loop that weighs each pair of
// pixels once; the pyramid and maps use the same per-pixel kernels four pixels at a time.
// Invalid (0) taps never contribute, and an invalid centre stays invalid.
float bilateralPixel(ImageView<const float> depth_m, int x, int y, const BilateralKernel& kernel);
// KinFu pyrDown: mean of the valid 5x5 neighbours of fine pixel (2x, 2y) within `max_diff_m` of
// the centre.
float pyrDownPixel(ImageView<const float> fine_m, int x, int y, float max_diff_m);
void computeVertexMap(ImageView<const float> depth_m, const PinholeCamera& camera,
                      ImageView<Eigen::Vector3f> vertex_cam);
void computeNormalMap(ImageView<const Eigen::Vector3f> vertex_cam,
                      ImageView<Eigen::Vector3f> normal_cam);
// The pixels of one level where both maps above are valid, packed for the tracker, in one pass
// over its depth image: vertices and normals exactly as the two functions give them.
void computePackedPoints(ImageView<const float> depth_m, const PinholeCamera& camera,
                         PackedPoints* points);

}  // namespace kinfly
