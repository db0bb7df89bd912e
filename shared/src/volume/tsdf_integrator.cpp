#include "kinfly/volume/tsdf_integrator.h"

#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>

#include "kinfly/core/lanes.h"
#include <sstream>
#include "parallel.h"

namespace kinfly {

using lanes::Floats;
using lanes::Ints;
using lanes::kWidth;

Status TsdfIntegrator::Params::validate(float voxel_size_m) const {
  std::ostringstream why;
  if (!(truncation_m > 2.f * voxel_size_m))
    why << "truncation_m (" << truncation_m << ") must exceed two voxels (" << 2.f * voxel_size_m << " m)";
  else if (!(max_weight > 0.f)) why << "max_weight must be > 0";
  else if (allocation_stride_px < 1) why << "allocation_stride_px must be >= 1";
  return why.str().empty() ? Status() : Status::error(why.str());
}

namespace {

// The running weighted average of the seed's steps 10-14 for four neighbouring voxels, where
// `measured` (a pixel with a depth): the truncated distance averaged in with weight one, the
// weight capped. Far behind the surface (sdf below -truncation) is unknown, not free, and left
// as it is. All four lanes are computed and all four voxels stored, the unchanged ones as they
// were: branching per voxel costs more in mispredictions than the arithmetic of four.
void updateVoxels(Voxel* voxels, Floats sdf_m, Ints measured, float truncation_m,
                  float max_weight) {
  const Ints update = measured & ~(sdf_m < -truncation_m);
  if (lanes::none(update)) return;
  static_assert(sizeof(Voxel) == 2 * sizeof(float), "a voxel is its distance, then its weight");
  Floats lo, hi;
  std::memcpy(&lo, voxels, sizeof lo);
  std::memcpy(&hi, voxels + 2, sizeof hi);
  const Floats tsdf = lanes::shuffle<0, 2, 4, 6>(lo, hi);
  const Floats weight = lanes::shuffle<1, 3, 5, 7>(lo, hi);
  const Floats measured_tsdf = sdf_m >= truncation_m ? 1.f : sdf_m / truncation_m;
  const Floats next_weight = weight + 1.f;
  const Floats averaged = update ? (tsdf * weight + measured_tsdf) / next_weight : tsdf;
  const Floats capped =
      update ? (next_weight < max_weight ? next_weight : lanes::splat(max_weight)) : weight;
  lo = lanes::shuffle<0, 4, 1, 5>(averaged, capped);
  hi = lanes::shuffle<2, 6, 3, 7>(averaged, capped);
  std::memcpy(static_cast<void*>(voxels), &lo, sizeof lo);
  std::memcpy(static_cast<void*>(voxels + 2), &hi, sizeof hi);
}

}  // namespace

TsdfIntegrator::TsdfIntegrator(const Params& params) : params_(params) {}

int TsdfIntegrator::samplesPerBand(const TsdfVolume& volume) const {
  const float sample_step_m = 0.5f * volume.blockSizeM();
  return 1 + static_cast<int>(std::ceil(2.f * params_.truncation_m / sample_step_m));
}

void TsdfIntegrator::reserve(int width_px, int height_px, const TsdfVolume& volume) {
  const int stride = params_.allocation_stride_px;
  const int rows = (height_px + stride - 1) / stride;
  const int columns = (width_px + stride - 1) / stride;
  const size_t per_pixel = static_cast<size_t>(samplesPerBand(volume)) + 1;
  size_t total = 0;
  for (int c = 0; c < kAllocationChunks; ++c) {
    const int chunk_rows = rows * (c + 1) / kAllocationChunks - rows * c / kAllocationChunks;
    candidates_[c].reserve(static_cast<size_t>(chunk_rows) * columns * per_pixel);
    total += candidates_[c].capacity();
  }
  touched_.reserve(total);
}

IntegrateResult TsdfIntegrator::integrate(ImageView<const float> depth_m, const PinholeCamera& camera,
                                          const Pose& T_world_cam, TsdfVolume* volume,
                                          bool parallel) {
  IntegrateResult result;
  if (++stamp_ == 0) ++stamp_;  // 0 marks "never touched"
  touched_.clear();
  const float mu = params_.truncation_m;
  const Eigen::Matrix3f R_wc = T_world_cam.linear().cast<float>();
  const Eigen::Vector3f t_wc = T_world_cam.translation().cast<float>();
  const size_t before = volume->numAllocatedBlocks();

  // 1. Blocks within the truncation band of every (strided) measurement. Rows are scanned in
  // parallel, in fixed chunks, each dropping the blocks it has just listed (a small
  // direct-mapped cache: neighbouring pixels share their blocks); the short candidate lists are
  // then allocated serially, in chunk order, so the block order does not depend on the threads.
  // Samples are placed in block units (block b spans [b, b + 1) per axis): along a pixel's ray
  // that is one multiply-add per sample, without the rotation and division of
  // TsdfVolume::blockOf.
  const float blocks_per_m = 1.f / volume->blockSizeM();
  const Eigen::Vector3f origin_blk = t_wc * blocks_per_m;
  // Every band gets the same number of samples; one cut short by the near limit is only sampled
  // more densely. A count fixed per frame also keeps the sample loop's branch predictable.
  const int samples = samplesPerBand(*volume);
  const int stride = params_.allocation_stride_px;
  const int rows = (depth_m.height() + stride - 1) / stride;
  forEachDynamic(kAllocationChunks, 1, parallel, [&](int c) {
    std::vector<BlockIndex>& candidates = candidates_[c];
    candidates.clear();
    std::array<BlockIndex, kRecentBlocks> recent;
    recent.fill(BlockIndex::Constant(INT32_MIN));
    // The blocks of the previous pixel's samples, four to a group, sample by sample: a
    // neighbouring pixel's band mostly crosses the same blocks, and a block listed before in
    // this chunk may be left out (the blocks' order is that of their first listing). The
    // comparison spares the hash of the recent blocks for most samples.
    constexpr int kComparedGroups = 4;
    std::array<Ints, kComparedGroups> previous_x, previous_y, previous_z;
    previous_x.fill(lanes::Ints{} + INT32_MIN);
    previous_y = previous_z = previous_x;
    for (int r = rows * c / kAllocationChunks; r < rows * (c + 1) / kAllocationChunks; ++r) {
      const int y = r * stride;
      const float* row = depth_m.row(y);
      for (int x = 0; x < depth_m.width(); x += stride) {
        const float d = row[x];
        if (!(d > 0.f)) continue;
        const Eigen::Vector3f ray = camera.backProject(static_cast<float>(x), static_cast<float>(y), 1.f);
        const float ray_len = ray.norm();
        const float z0 = std::max(d - mu / ray_len, 1e-3f), z1 = d + mu / ray_len;
        const Eigen::Vector3f ray_blk = R_wc * ray * blocks_per_m;  // blocks per metre of depth
        const float dz = (z1 - z0) / static_cast<float>(samples);
        for (int i = 0, g = 0; i <= samples; i += kWidth, ++g) {
          const Ints sample = i + Ints{0, 1, 2, 3};
          const Floats along = z0 + dz * lanes::toFloat(sample);
          const Ints bx = lanes::floorToInt(origin_blk.x() + ray_blk.x() * along);
          const Ints by = lanes::floorToInt(origin_blk.y() + ray_blk.y() * along);
          const Ints bz = lanes::floorToInt(origin_blk.z() + ray_blk.z() * along);
          Ints listed = sample > samples;
          if (g < kComparedGroups) {
            listed |= (bx == previous_x[g]) & (by == previous_y[g]) & (bz == previous_z[g]);
            previous_x[g] = bx, previous_y[g] = by, previous_z[g] = bz;
          }
          for (int l = 0; l < kWidth; ++l) {
            if (listed[l]) continue;
            const BlockIndex b(bx[l], by[l], bz[l]);
            BlockIndex& slot = recent[hashBlockIndex(b) % kRecentBlocks];
            if (slot == b) continue;
            slot = b;
            candidates.push_back(b);
          }
        }
      }
    }
  });
  for (const std::vector<BlockIndex>& candidates : candidates_)
    for (const BlockIndex& b : candidates) {
      VoxelBlock* blk = volume->allocateBlock(b);
      if (blk == nullptr) {
        ++result.blocks_rejected;
        continue;
      }
      if (blk->touched_stamp == stamp_) continue;
      blk->touched_stamp = stamp_;
      touched_.push_back(blk);
    }
  result.blocks_updated = static_cast<int>(touched_.size());
  result.blocks_allocated = static_cast<int>(volume->numAllocatedBlocks() - before);

  // 2. Projective update of every voxel of those blocks.
  const Pose T_cam_world = T_world_cam.inverse();
  const Eigen::Matrix3f R = T_cam_world.linear().cast<float>();
  const Eigen::Vector3f t = T_cam_world.translation().cast<float>();
  const float vs = volume->voxelSizeM();
  const Eigen::Matrix3f R_step = R * vs;  // camera-frame offset of one voxel along x, y, z
  const float max_weight = params_.max_weight;
  const float width = static_cast<float>(depth_m.width());
  const float height = static_cast<float>(depth_m.height());
  const int n = static_cast<int>(touched_.size());
  forEachDynamic(n, 16, parallel, [&](int i) {
    VoxelBlock* blk = touched_[i];
    const Eigen::Vector3f origin_cam = R * volume->voxelCentre(blk->index, 0, 0, 0) + t;
    for (int z = 0; z < kBlockSide; ++z)
      for (int y = 0; y < kBlockSide; ++y) {
        const Eigen::Vector3f row_cam = origin_cam + R_step.col(1) * static_cast<float>(y) +
                                        R_step.col(2) * static_cast<float>(z);
        Voxel* voxel = &blk->voxels[VoxelBlock::linear(0, y, z)];
        // Four voxels of the row at a time up to their pixel and ray scale: the division and
        // square root of each voxel cost as much for four lanes as for one.
        static_assert(kBlockSide % kWidth == 0, "block rows split into groups of four");
        for (int x0 = 0; x0 < kBlockSide; x0 += kWidth) {
          const Floats xs = lanes::coordinate<Floats>(x0);
          const Floats px = row_cam.x() + R_step(0, 0) * xs;
          const Floats py = row_cam.y() + R_step(1, 0) * xs;
          const Floats pz = row_cam.z() + R_step(2, 0) * xs;
          const Floats inv_z = 1.f / pz;
          const Floats xn = px * inv_z, yn = py * inv_z;
          const Floats uf = camera.fx * xn + camera.cx, vf = camera.fy * yn + camera.cy;
          // Pixel coordinates round half away from zero (as roundToInt); only (-0.5, size) can
          // round into the image, and converting nothing else keeps the conversion defined.
          const Ints near = (pz > 0.f) & (uf > -0.5f) & (vf > -0.5f) & (uf < width) &
                            (vf < height);
          const Ints u = lanes::truncate((near ? uf : 0.f) + 0.5f);
          const Ints v = lanes::truncate((near ? vf : 0.f) + 0.5f);
          const Ints inside = near & (u < depth_m.width()) & (v < depth_m.height());
          if (lanes::none(inside)) continue;
          int pixels[kWidth];
          lanes::store(pixels, inside ? v * depth_m.width() + u : 0);
          const Floats d = lanes::lookup(depth_m.data(), pixels);
          // Signed distance along the pixel ray, as KinFu computes it (depth scaled by lambda
          // minus range): the ray's scale here, the depth per voxel below.
          const Floats ray_scale = lanes::sqrt(1.f + xn * xn + yn * yn);
          updateVoxels(voxel + x0, (d - pz) * ray_scale, inside & (d > 0.f), mu, max_weight);
        }
      }
  });
  return result;
}

}  // namespace kinfly
