// Voxel access by global index for the loops that walk the TSDF (raycasting, meshing).
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <array>

#include "kinfly/core/numeric.h"
#include "kinfly/volume/tsdf_volume.h"

namespace kinfly {

// Voxel reads with a small block cache. Slots are chosen by the parity of the block
// coordinates, so the (up to) eight blocks around one trilinear sample never evict each other and
// consecutive blocks along a ray land in different slots: most reads skip the hash lookup.
class VoxelReader {
 public:
  explicit VoxelReader(const TsdfVolume& volume) : volume_(volume) {}

  // Global voxel index g (voxel centre at g * voxel size); nullptr if unallocated.
  const Voxel* voxel(int gx, int gy, int gz) {
    // Arithmetic shift floors negative indices, as block indices require.
    const BlockIndex b(gx >> 3, gy >> 3, gz >> 3);
    const int slot = (b.x() & 1) | ((b.y() & 1) << 1) | ((b.z() & 1) << 2);
    if (!valid_[slot] || !(index_[slot] == b)) {
      index_[slot] = b;
      block_[slot] = volume_.findBlock(b);
      valid_[slot] = true;
    }
    const VoxelBlock* blk = block_[slot];
    return blk == nullptr ? nullptr : &blk->voxels[VoxelBlock::linear(gx & 7, gy & 7, gz & 7)];
  }

  // Trilinear TSDF and its gradient (per voxel) at a point in voxel units.
  bool trilinear(const Eigen::Vector3f& p_vox, float* tsdf, Eigen::Vector3f* gradient) {
    const int gx = floorToInt(p_vox.x()), gy = floorToInt(p_vox.y()), gz = floorToInt(p_vox.z());
    const float ax = p_vox.x() - static_cast<float>(gx), ay = p_vox.y() - static_cast<float>(gy),
                az = p_vox.z() - static_cast<float>(gz);
    float c[8];
    const int lx = gx & 7, ly = gy & 7, lz = gz & 7;
    if (lx < 7 && ly < 7 && lz < 7) {
      // All eight corners in one block (343 of 512 cells): one lookup, fixed offsets.
      const Voxel* v0 = voxel(gx, gy, gz);
      if (v0 == nullptr) return false;
      constexpr int kDy = kBlockSide, kDz = kBlockSide * kBlockSide;
      static constexpr int kOffset[8] = {0,   1,       kDy,       kDy + 1,
                                         kDz, kDz + 1, kDz + kDy, kDz + kDy + 1};
      // One test for the eight weights instead of eight branches.
      float min_weight = v0[0].weight;
      for (int i = 0; i < 8; ++i) {
        const Voxel& v = v0[kOffset[i]];
        min_weight = std::min(min_weight, v.weight);
        c[i] = v.tsdf;
      }
      if (!(min_weight > 0.f)) return false;
    } else {
      for (int i = 0; i < 8; ++i) {
        const Voxel* v = voxel(gx + (i & 1), gy + ((i >> 1) & 1), gz + ((i >> 2) & 1));
        if (v == nullptr || v->weight <= 0.f) return false;
        c[i] = v->tsdf;
      }
    }
    // Interpolate along x, then y, then z; the gradient is the derivative of the same polynomial.
    const float c00 = c[0] + (c[1] - c[0]) * ax, c10 = c[2] + (c[3] - c[2]) * ax;
    const float c01 = c[4] + (c[5] - c[4]) * ax, c11 = c[6] + (c[7] - c[6]) * ax;
    const float c0 = c00 + (c10 - c00) * ay, c1 = c01 + (c11 - c01) * ay;
    *tsdf = c0 + (c1 - c0) * az;
    if (gradient != nullptr) {
      const float dx0 = (c[1] - c[0]) + ((c[3] - c[2]) - (c[1] - c[0])) * ay;
      const float dx1 = (c[5] - c[4]) + ((c[7] - c[6]) - (c[5] - c[4])) * ay;
      (*gradient) << dx0 + (dx1 - dx0) * az, (c10 - c00) + ((c11 - c01) - (c10 - c00)) * az,
          c1 - c0;
    }
    return true;
  }

 private:
  const TsdfVolume& volume_;
  std::array<BlockIndex, 8> index_;
  std::array<const VoxelBlock*, 8> block_{};
  std::array<bool, 8> valid_{};
};

}  // namespace kinfly
