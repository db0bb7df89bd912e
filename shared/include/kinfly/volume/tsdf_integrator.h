// Stage 6: TSDF integration (seed pseudocode steps 1-14): projective signed distance along the
// pixel ray, truncation, running weighted average, weight cap.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "kinfly/core/camera.h"
#include "kinfly/core/image.h"
#include "kinfly/core/se3.h"
#include "kinfly/core/status.h"
#include "kinfly/volume/tsdf_volume.h"

namespace kinfly {

struct IntegrateResult {
  int blocks_updated = 0;     // blocks within the truncation band of this frame
  int blocks_allocated = 0;   // of which new this frame
  // Listings of blocks outside a bounded volume; a block listed by several pixels' bands may
  // count more than once.
  int blocks_rejected = 0;
};

class TsdfIntegrator {
 public:
  struct Params {
    float truncation_m = 0.04f;   // [m] > 2 voxels: band of the signed distance
    float max_weight = 128.f;     // > 0: cap so the map can still follow change
    // Allocation samples every n-th pixel: the band of one pixel spans a whole block, so
    // neighbouring pixels add nothing (a block is >= 8 pixels wide at any range we keep).
    int allocation_stride_px = 2;  // >= 1
    Status validate(float voxel_size_m) const;
  };

  explicit TsdfIntegrator(const Params& params);
  const Params& params() const { return params_; }

  // Makes room for the largest frame of width x height pixels into `volume`, so that integrate()
  // never allocates (the drone's odometry must not, frame after frame): every sampled pixel's
  // band in the candidate lists, and as many touched blocks.
  void reserve(int width_px, int height_px, const TsdfVolume& volume);

  // Integrates metric depth (not > 0: invalid) seen from T_world_cam into `volume`.
  IntegrateResult integrate(ImageView<const float> depth_m, const PinholeCamera& camera,
                            const Pose& T_world_cam, TsdfVolume* volume, bool parallel = true);

 private:
  static constexpr int kAllocationChunks = 32;
  static constexpr int kRecentBlocks = 64;

  // Samples along each pixel's band: enough for the full band (2 mu along the ray) at half a
  // block apart.
  int samplesPerBand(const TsdfVolume& volume) const;

  Params params_;
  uint32_t stamp_ = 0;
  // Reused every frame; reserve() sizes them for the largest frame.
  std::array<std::vector<BlockIndex>, kAllocationChunks> candidates_;
  std::vector<VoxelBlock*> touched_;
};

}  // namespace kinfly
