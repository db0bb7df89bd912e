// Stage 7: raycasting. Marches each pixel's ray through the TSDF, finds the zero crossing by
// linear refinement on trilinearly interpolated values, and takes the normal from the TSDF
// gradient. Gives the model maps for tracking and a shaded image.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "kinfly/core/camera.h"
#include "kinfly/core/image.h"
#include "kinfly/core/se3.h"
#include "kinfly/core/status.h"
#include "kinfly/frame/model_maps.h"
#include "kinfly/volume/tsdf_volume.h"

namespace kinfly {

struct RaycastResult {
  int hits = 0;           // pixels with a surface
  float hit_fraction = 0.f;
};

// Trilinear TSDF sample at a world point. Returns false where any of the 8 voxels is
// unobserved. `gradient` (optional) receives dTSDF/dp in 1/voxel units.
bool sampleTsdf(const TsdfVolume& volume, const Eigen::Vector3f& p_world, float* tsdf,
                Eigen::Vector3f* gradient = nullptr);

class Raycaster {
 public:
  struct Params {
    float min_depth_m = 0.3f;   // [m] >= 0
    float max_depth_m = 4.0f;   // [m] > min_depth_m
    // Step through observed space as a fraction of the truncation band (KinFu: 0.8); smaller
    // never misses a thin surface, larger is faster.
    float step_fraction = 0.8f;  // (0, 1]
    // Ray ranges come from projecting allocated blocks onto tiles of this many pixels.
    int range_tile_px = 8;       // >= 1
    // With a depth hint (the frame just fused), a ray starts Newton's method at the measured
    // depth and, should that fail, marches only this far either side of it: the tracker's
    // correspondence gate (0.1 m) discards anything further.
    float hint_margin_m = 0.1f;  // [m] > 0
    Status validate() const;
  };

  Raycaster(const PinholeCamera& camera, const Params& params);
  const Params& params() const { return params_; }

  // Writes level 0 of `maps` (vertex and normal in the camera frame of T_world_cam), invalid
  // where no surface is found. Without `depth_hint_m` every pixel is cast (a render). With it
  // (the frame just fused, same size as the camera, 0 = no measurement) only measured pixels are
  // cast, each searching near its measurement: these are the model maps for tracking, where the
  // next frame's measurements associate (a camera that saw nothing at a pixel rarely does one
  // frame later), and a third of a Kinect image can be holes whose rays would otherwise march
  // through all the empty space behind the scene.
  RaycastResult raycast(const TsdfVolume& volume, float truncation_m, const Pose& T_world_cam,
                        ModelMaps* maps, ImageView<const float> depth_hint_m = {});

  // Lambertian shading with the light at the camera; black where there is no surface.
  static void shade(ImageView<const Eigen::Vector3f> vertex_cam,
                    ImageView<const Eigen::Vector3f> normal_cam, ImageView<uint8_t> out);

 private:
  void computeRanges(const TsdfVolume& volume, const Pose& T_cam_world);

  PinholeCamera camera_;
  Params params_;
  Image<Eigen::Vector2f> tile_range_;  // per tile: [near, far] depth of allocated blocks
  // Pixel (x, y)'s ray at unit depth is (ray_x_[x], ray_y_[y], 1) in the camera frame: tabulated,
  // because the divisions of a back-projection would start every ray's chain of dependent steps.
  std::vector<float> ray_x_, ray_y_;
  // Per raycast, the same ray in voxel units in the world frame, split into a column and a row
  // term: R (ray_x, 0, 0) / voxel and R (0, ray_y, 1) / voxel.
  std::vector<Eigen::Vector3f> column_vox_, row_vox_;
};

}  // namespace kinfly
