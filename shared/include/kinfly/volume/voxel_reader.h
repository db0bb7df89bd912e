// Voxel access by global index for the loops that walk the TSDF (raycasting, meshing).
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <array>

#include "kinfly/core/lanes.h"
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
    const VoxelBlock* blk = block(gx >> 3, gy >> 3, gz >> 3);
    return blk == nullptr ? nullptr : &blk->voxels[VoxelBlock::linear(gx & 7, gy & 7, gz & 7)];
  }

  // Trilinear TSDF and its gradient (per voxel) at a point in voxel units.
  bool trilinear(const Eigen::Vector3f& p_vox, float* tsdf, Eigen::Vector3f* gradient) {
    const int gx = floorToInt(p_vox.x()), gy = floorToInt(p_vox.y()), gz = floorToInt(p_vox.z());
    const float ax = p_vox.x() - static_cast<float>(gx), ay = p_vox.y() - static_cast<float>(gy),
                az = p_vox.z() - static_cast<float>(gz);
    const int lx = gx & 7, ly = gy & 7, lz = gz & 7;
    const int bx = gx >> 3, by = gy >> 3, bz = gz >> 3;
    const VoxelBlock* base = block(bx, by, bz);
    if (base == nullptr) return false;
    // The cell's four x-edges (y, z = 00, 10, 01, 11), each as {tsdf, weight} of its two ends:
    // whole voxels, as stored, so that an edge inside a block is one load.
    using lanes::Floats;
    using lanes::shuffle;
    static_assert(sizeof(Voxel) == 2 * sizeof(float), "a voxel is {tsdf, weight}");
    Floats edge[4];
    // Bit a set where the cell's far corners along axis a lie in the next block.
    const int cross = (lx == 7) | ((ly == 7) << 1) | ((lz == 7) << 2);
    if (cross == 0) {
      // All eight corners in one block (343 of 512 cells): fixed offsets.
      const Voxel* v0 = &base->voxels[VoxelBlock::linear(lx, ly, lz)];
      constexpr int kDy = kBlockSide, kDz = kBlockSide * kBlockSide;
      edge[0] = lanes::load<Floats>(&v0[0].tsdf);
      edge[1] = lanes::load<Floats>(&v0[kDy].tsdf);
      edge[2] = lanes::load<Floats>(&v0[kDz].tsdf);
      edge[3] = lanes::load<Floats>(&v0[kDz + kDy].tsdf);
    } else if (!edgesAcrossBlocks(base, bx, by, bz, lx, ly, lz, cross, edge)) {
      return false;
    }
    // Transposed: a = corners c0, c2, c4, c6 (x near), b = c1, c3, c5, c7 (x far).
    const Floats lo01 = shuffle<0, 4, 1, 5>(edge[0], edge[1]);
    const Floats hi01 = shuffle<2, 6, 3, 7>(edge[0], edge[1]);
    const Floats lo23 = shuffle<0, 4, 1, 5>(edge[2], edge[3]);
    const Floats hi23 = shuffle<2, 6, 3, 7>(edge[2], edge[3]);
    const Floats a = shuffle<0, 1, 4, 5>(lo01, lo23), weight_a = shuffle<2, 3, 6, 7>(lo01, lo23);
    const Floats b = shuffle<0, 1, 4, 5>(hi01, hi23), weight_b = shuffle<2, 3, 6, 7>(hi01, hi23);
    // The smallest of the eight weights, by halves: cheaper than collecting the mask's bits.
    const Floats w4 = lanes::min(weight_a, weight_b);
    const Floats w2 = lanes::min(w4, shuffle<2, 3, 2, 3>(w4, w4));
    if (!(std::min(w2[0], w2[1]) > 0.f)) return false;
    // Interpolate along x, then y, then z, the four edges (then their two pairs) a lane each; the
    // gradient is the derivative of the same polynomial, its x and y parts carried in the spare
    // lanes. Each lane does the scalar definition's operations in its order, so the result is
    // the same to the bit.
    const Floats dx = b - a;                       // c1 - c0, c3 - c2, c5 - c4, c7 - c6
    const Floats along_x = a + dx * ax;            // c00, c10, c01, c11
    const Floats p = shuffle<0, 2, 4, 6>(along_x, dx), q = shuffle<1, 3, 5, 7>(along_x, dx);
    const Floats dy = q - p;                       // c10 - c00, c11 - c01, ...
    const Floats along_y = p + dy * ay;            // c0, c1, dTSDF/dx at z0, at z1
    const Floats s = shuffle<0, 2, 4, 5>(along_y, dy), t = shuffle<1, 3, 5, 5>(along_y, dy);
    const Floats dz = t - s;
    const Floats along_z = s + dz * az;            // TSDF, dTSDF/dx, dTSDF/dy
    *tsdf = along_z[0];
    if (gradient != nullptr) (*gradient) << along_z[1], along_z[2], dz[0];
    return true;
  }

 private:
  // The edges of a cell whose far corners lie in the next block along the axes set in `cross`:
  // corner i lies in the block displaced by (i & cross), each looked up once, instead of once
  // per corner. Out of line, so that the common cell inside one block keeps its registers.
  [[gnu::noinline]] bool edgesAcrossBlocks(const VoxelBlock* base, int bx, int by, int bz,
                                           int lx, int ly, int lz, int cross,
                                           lanes::Floats edge[4]) {
    std::array<const VoxelBlock*, 8> blocks;
    blocks[0] = base;
    for (int d = 1; d < 8; ++d) {
      if ((d & cross) != d) continue;
      blocks[d] = block(bx + (d & 1), by + ((d >> 1) & 1), bz + (d >> 2));
      if (blocks[d] == nullptr) return false;
    }
    const int xs[2] = {lx, (lx + 1) & 7}, ys[2] = {ly, (ly + 1) & 7}, zs[2] = {lz, (lz + 1) & 7};
    for (int e = 0; e < 4; ++e) {
      const int i = 2 * e;  // the edge's near corner; i + 1 is its far one along x
      const Voxel& near =
          blocks[i & cross]->voxels[VoxelBlock::linear(xs[0], ys[(i >> 1) & 1], zs[i >> 2])];
      const Voxel& far =
          blocks[(i + 1) & cross]->voxels[VoxelBlock::linear(xs[1], ys[(i >> 1) & 1], zs[i >> 2])];
      edge[e] = lanes::Floats{near.tsdf, near.weight, far.tsdf, far.weight};
    }
    return true;
  }

  // The block at block coordinates b; nullptr if unallocated.
  const VoxelBlock* block(int bx, int by, int bz) {
    const BlockIndex b(bx, by, bz);
    const int slot = (bx & 1) | ((by & 1) << 1) | ((bz & 1) << 2);
    if (!valid_[slot] || !(index_[slot] == b)) {
      index_[slot] = b;
      block_[slot] = volume_.findBlock(b);
      valid_[slot] = true;
    }
    return block_[slot];
  }

  const TsdfVolume& volume_;
  std::array<BlockIndex, 8> index_;
  std::array<const VoxelBlock*, 8> block_{};
  std::array<bool, 8> valid_{};
};

}  // namespace kinfly
