// TSDF storage: the hashed volume finds every block it allocated and grows with surface, not
// extent; the dense volume holds a window of blocks that moves with the camera; VoxelReader's
// trilinear sample is the per-corner definition, inside blocks and across their faces.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <random>
#include <set>
#include <tuple>
#include <vector>

#include "kinfly/volume/tsdf_volume.h"
#include "kinfly/volume/voxel_reader.h"
#include "test_util.h"

namespace kinfly {
namespace {

std::tuple<int, int, int> key(const BlockIndex& b) { return {b.x(), b.y(), b.z()}; }

// Distinct random block indices in [-half_range, half_range]^3.
std::vector<BlockIndex> randomBlocks(int count, int half_range, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_int_distribution<int> coord(-half_range, half_range);
  std::set<std::tuple<int, int, int>> seen;
  std::vector<BlockIndex> out;
  while (static_cast<int>(out.size()) < count) {
    const BlockIndex b(coord(rng), coord(rng), coord(rng));
    if (seen.insert(key(b)).second) out.push_back(b);
  }
  return out;
}

TEST(HashedVolume, AllocateThenFind) {
  HashedVolume volume(HashedVolume::Params{});
  const BlockIndex a(1, -2, 3), b(-1000, 5, 77);
  EXPECT_EQ(volume.findBlock(a), nullptr);
  VoxelBlock* pa = volume.allocateBlock(a);
  ASSERT_NE(pa, nullptr);
  EXPECT_EQ(pa->index, a);
  EXPECT_EQ(volume.findBlock(a), pa);
  EXPECT_EQ(volume.allocateBlock(a), pa) << "allocating twice must return the same block";
  EXPECT_EQ(volume.findBlock(b), nullptr);
  EXPECT_EQ(volume.numAllocatedBlocks(), 1u);
  // A fresh block is unobserved free space.
  for (const Voxel& v : pa->voxels) {
    ASSERT_EQ(v.weight, 0.f);
    ASSERT_EQ(v.tsdf, 1.f);
  }
}

TEST(HashedVolume, ManyBlocksSurviveRehashAndNewChunks) {
  HashedVolume::Params params;
  params.chunk_blocks = 64;  // small, so 5000 blocks need ~80 chunks and several rehashes
  HashedVolume volume(params);
  const std::vector<BlockIndex> blocks = randomBlocks(5000, 200, 1);
  std::vector<VoxelBlock*> pointers;
  for (size_t i = 0; i < blocks.size(); ++i) {
    VoxelBlock* p = volume.allocateBlock(blocks[i]);
    ASSERT_NE(p, nullptr);
    p->voxels[0].tsdf = static_cast<float>(i);  // a marker to find the block's data again
    p->voxels[0].weight = 1.f;
    pointers.push_back(p);
  }
  ASSERT_EQ(volume.numAllocatedBlocks(), blocks.size());
  for (size_t i = 0; i < blocks.size(); ++i) {
    const VoxelBlock* p = volume.findBlock(blocks[i]);
    ASSERT_EQ(p, pointers[i]) << "blocks must not move when the table grows";
    ASSERT_EQ(p->index, blocks[i]);
    ASSERT_EQ(p->voxels[0].tsdf, static_cast<float>(i));
  }
  // Neighbours of allocated blocks that were not allocated are still absent.
  const std::vector<BlockIndex> others = randomBlocks(2000, 200, 2);
  std::set<std::tuple<int, int, int>> allocated;
  for (const BlockIndex& b : blocks) allocated.insert(key(b));
  for (const BlockIndex& b : others) {
    if (!allocated.count(key(b))) {
      ASSERT_EQ(volume.findBlock(b), nullptr);
    }
  }
  // allocatedBlocks() lists each block once, in allocation order.
  const auto& listed = volume.allocatedBlocks();
  for (size_t i = 0; i < blocks.size(); ++i) ASSERT_EQ(listed[i], pointers[i]);

  volume.clear();
  EXPECT_EQ(volume.numAllocatedBlocks(), 0u);
  EXPECT_EQ(volume.findBlock(blocks[0]), nullptr);
  VoxelBlock* again = volume.allocateBlock(blocks[0]);
  ASSERT_NE(again, nullptr);
  EXPECT_EQ(again->voxels[0].weight, 0.f) << "a block allocated after clear() starts empty";
}

TEST(HashedVolume, MemoryGrowsWithBlocksNotExtent) {
  HashedVolume::Params params;
  params.chunk_blocks = 256;
  constexpr int kBlocks = 1500;
  // 1 m at 1 cm voxels is 12.5 blocks across; 1 km is 12500.
  const int near_half = 6, far_half = 6250;
  HashedVolume near_volume(params), far_volume(params);
  for (const BlockIndex& b : randomBlocks(kBlocks, near_half, 3)) near_volume.allocateBlock(b);
  for (const BlockIndex& b : randomBlocks(kBlocks, far_half, 4)) far_volume.allocateBlock(b);
  const double chunk_bytes = static_cast<double>(params.chunk_blocks) * sizeof(VoxelBlock);
  EXPECT_NEAR(static_cast<double>(near_volume.memoryBytes()),
              static_cast<double>(far_volume.memoryBytes()), chunk_bytes);
  // Storage is at least the blocks themselves, and not wildly more: a chunk of slack plus an
  // index of a few pointers per block.
  const double block_bytes = static_cast<double>(kBlocks) * sizeof(VoxelBlock);
  EXPECT_GE(static_cast<double>(far_volume.memoryBytes()), block_bytes);
  EXPECT_LE(static_cast<double>(far_volume.memoryBytes()), block_bytes + chunk_bytes + 64.0 * kBlocks);

  HashedVolume bigger(params);
  for (const BlockIndex& b : randomBlocks(4 * kBlocks, near_half * 2, 5)) bigger.allocateBlock(b);
  EXPECT_GE(static_cast<double>(bigger.memoryBytes()), 4 * block_bytes);
}

DenseVolume::Params smallDense() {
  DenseVolume::Params params;
  params.resolution_vox = 64;  // 8 blocks per side
  params.voxel_size_m = 0.05f;
  params.lookahead_m = 1.0f;
  params.shift_threshold_blocks = 2;
  return params;
}

bool inWindow(const DenseVolume& v, const BlockIndex& b) {
  const BlockIndex r = b - v.originBlock();
  return r.minCoeff() >= 0 && r.maxCoeff() < v.blocksPerSide();
}

TEST(DenseVolume, HoldsOnlyItsWindow) {
  DenseVolume volume(smallDense());
  ASSERT_EQ(volume.blocksPerSide(), 8);
  const BlockIndex o = volume.originBlock();
  const BlockIndex inside = o + BlockIndex(3, 0, 7);
  const BlockIndex outside = o + BlockIndex(8, 0, 0);
  const BlockIndex below = o + BlockIndex(0, -1, 0);
  EXPECT_EQ(volume.findBlock(inside), nullptr) << "not allocated yet";
  VoxelBlock* p = volume.allocateBlock(inside);
  ASSERT_NE(p, nullptr);
  EXPECT_EQ(p->index, inside);
  EXPECT_EQ(volume.findBlock(inside), p);
  EXPECT_EQ(volume.allocateBlock(outside), nullptr);
  EXPECT_EQ(volume.allocateBlock(below), nullptr);
  EXPECT_EQ(volume.findBlock(outside), nullptr);
  EXPECT_EQ(volume.numAllocatedBlocks(), 1u);
  // Fixed memory: all 512 blocks are reserved up front.
  EXPECT_GE(volume.memoryBytes(), 512 * sizeof(VoxelBlock));
  const size_t memory = volume.memoryBytes();
  for (int x = 0; x < 8; ++x) volume.allocateBlock(o + BlockIndex(x, 1, 1));
  EXPECT_EQ(volume.memoryBytes(), memory);
}

TEST(DenseVolume, ShiftKeepsOverlapAndClearsWhatLeaves) {
  DenseVolume volume(smallDense());
  const BlockIndex o = volume.originBlock();
  // Mark every block of one row along x with its x offset.
  for (int x = 0; x < 8; ++x) {
    VoxelBlock* p = volume.allocateBlock(o + BlockIndex(x, 2, 2));
    ASSERT_NE(p, nullptr);
    p->voxels[5].tsdf = -0.25f * static_cast<float>(x) / 8.f;
    p->voxels[5].weight = 3.f + static_cast<float>(x);
  }
  const int shifts_before = volume.shiftCount();
  volume.shiftTo(o + BlockIndex(3, 0, 0));
  EXPECT_EQ(volume.shiftCount(), shifts_before + 1);
  EXPECT_EQ(volume.originBlock(), o + BlockIndex(3, 0, 0));
  for (int x = 0; x < 3; ++x) {
    EXPECT_EQ(volume.findBlock(o + BlockIndex(x, 2, 2)), nullptr) << "block " << x << " left";
  }
  for (int x = 3; x < 8; ++x) {
    const VoxelBlock* p = volume.findBlock(o + BlockIndex(x, 2, 2));
    ASSERT_NE(p, nullptr) << "block " << x << " stays";
    EXPECT_EQ(p->index, o + BlockIndex(x, 2, 2));
    EXPECT_EQ(p->voxels[5].weight, 3.f + static_cast<float>(x));
    EXPECT_EQ(p->voxels[5].tsdf, -0.25f * static_cast<float>(x) / 8.f);
  }
  EXPECT_EQ(volume.numAllocatedBlocks(), 5u);
  for (const VoxelBlock* p : volume.allocatedBlocks()) EXPECT_TRUE(inWindow(volume, p->index));
  // Blocks entering the window reuse the slots of those that left: they must come back empty.
  for (int x = 8; x < 11; ++x) {
    const BlockIndex b = o + BlockIndex(x, 2, 2);
    const VoxelBlock* found = volume.findBlock(b);
    if (found != nullptr) {
      for (const Voxel& v : found->voxels) ASSERT_EQ(v.weight, 0.f);
    }
    VoxelBlock* p = volume.allocateBlock(b);
    ASSERT_NE(p, nullptr);
    EXPECT_EQ(p->index, b);
    for (const Voxel& v : p->voxels) ASSERT_EQ(v.weight, 0.f) << "stale data in block " << x;
  }
}

TEST(DenseVolume, FollowCameraShiftsOnlyBeyondThreshold) {
  const DenseVolume::Params params = smallDense();
  DenseVolume volume(params);
  const float block_m = volume.blockSizeM();  // 0.4 m
  volume.followCamera(Pose::Identity(), 0.f);
  const int settled = volume.shiftCount();
  const BlockIndex settled_origin = volume.originBlock();
  volume.followCamera(Pose::Identity(), 0.f);
  EXPECT_EQ(volume.shiftCount(), settled) << "no motion, no shift";

  // Half a block sideways is below the 2-block threshold.
  volume.followCamera(test::makePose(Eigen::Vector3d::Zero(),
                                     Eigen::Vector3d(0.5 * block_m, 0.0, 0.0)),
                      0.f);
  EXPECT_EQ(volume.shiftCount(), settled);
  EXPECT_EQ(volume.originBlock(), settled_origin);

  // Five blocks along x, turned 90 degrees to look along +x: the window must follow, and the
  // point the camera looks at must be inside it.
  const Pose far = test::makePose(Eigen::Vector3d(0.0, test::kPi / 2, 0.0),
                                  Eigen::Vector3d(5.0 * block_m, 0.0, 0.0));
  volume.followCamera(far, 0.f);
  EXPECT_GT(volume.shiftCount(), settled);
  const Eigen::Vector3d look = far * Eigen::Vector3d(0.0, 0.0, params.lookahead_m);
  EXPECT_TRUE(inWindow(volume, volume.blockOf(look.cast<float>())));
  const Eigen::Vector3d cam = far.translation();
  EXPECT_TRUE(inWindow(volume, volume.blockOf(cam.cast<float>())));
}

// The window goes out to where the camera sees its scene, no nearer than lookahead_m and no
// further than max_lookahead_m, and stays at lookahead_m where the depth is not known.
TEST(DenseVolume, TheWindowFollowsHowFarTheCameraSees) {
  DenseVolume::Params params = smallDense();  // 3.2 m cube of 0.4 m blocks, 1 m ahead
  params.max_lookahead_m = 3.0f;
  DenseVolume volume(params);
  const auto origin_for = [&](double ahead_m) {
    return BlockIndex(volume.blockOf(Eigen::Vector3f(0.f, 0.f, static_cast<float>(ahead_m))) -
                      BlockIndex::Constant(volume.blocksPerSide() / 2));
  };
  const BlockIndex far_point = volume.blockOf(Eigen::Vector3f(0.f, 0.f, 4.3f));
  volume.followCamera(Pose::Identity(), 0.f);
  EXPECT_EQ(volume.originBlock(), origin_for(params.lookahead_m));
  EXPECT_FALSE(inWindow(volume, far_point));
  volume.followCamera(Pose::Identity(), std::numeric_limits<float>::quiet_NaN());
  EXPECT_EQ(volume.originBlock(), origin_for(params.lookahead_m)) << "a depth not known";
  // Between the limits the centre is the depth itself (each step beyond the shift threshold).
  volume.followCamera(Pose::Identity(), 2.1f);
  EXPECT_EQ(volume.originBlock(), origin_for(2.1));
  volume.followCamera(Pose::Identity(), 0.2f);  // a near view: back to lookahead_m
  EXPECT_EQ(volume.originBlock(), origin_for(params.lookahead_m));
  volume.followCamera(Pose::Identity(), 10.f);  // a scene beyond the limit
  EXPECT_EQ(volume.originBlock(), origin_for(params.max_lookahead_m));
  EXPECT_TRUE(inWindow(volume, far_point));
  // A limit below lookahead_m keeps the window there.
  params.max_lookahead_m = 0.5f;
  ASSERT_TRUE(params.validate().ok());
  DenseVolume held(params);
  held.followCamera(Pose::Identity(), 10.f);
  EXPECT_EQ(held.originBlock(), origin_for(params.lookahead_m));
}

// The trilinear TSDF and its gradient as defined, one corner at a time through
// TsdfVolume::findBlock: false where a corner's block is unallocated or the corner unobserved.
bool trilinearReference(const TsdfVolume& volume, const Eigen::Vector3f& p_vox, float* tsdf,
                        Eigen::Vector3f* gradient) {
  const int gx = static_cast<int>(std::floor(p_vox.x()));
  const int gy = static_cast<int>(std::floor(p_vox.y()));
  const int gz = static_cast<int>(std::floor(p_vox.z()));
  float c[8];
  for (int i = 0; i < 8; ++i) {
    const int x = gx + (i & 1), y = gy + ((i >> 1) & 1), z = gz + (i >> 2);
    const VoxelBlock* blk = volume.findBlock(BlockIndex(x >> 3, y >> 3, z >> 3));
    if (blk == nullptr) return false;
    const Voxel& v = blk->voxels[VoxelBlock::linear(x & 7, y & 7, z & 7)];
    if (!(v.weight > 0.f)) return false;
    c[i] = v.tsdf;
  }
  const float ax = p_vox.x() - static_cast<float>(gx), ay = p_vox.y() - static_cast<float>(gy),
              az = p_vox.z() - static_cast<float>(gz);
  const float c00 = c[0] + (c[1] - c[0]) * ax, c10 = c[2] + (c[3] - c[2]) * ax;
  const float c01 = c[4] + (c[5] - c[4]) * ax, c11 = c[6] + (c[7] - c[6]) * ax;
  const float c0 = c00 + (c10 - c00) * ay, c1 = c01 + (c11 - c01) * ay;
  *tsdf = c0 + (c1 - c0) * az;
  const float dx0 = (c[1] - c[0]) + ((c[3] - c[2]) - (c[1] - c[0])) * ay;
  const float dx1 = (c[5] - c[4]) + ((c[7] - c[6]) - (c[5] - c[4])) * ay;
  *gradient << dx0 + (dx1 - dx0) * az, (c10 - c00) + ((c11 - c01) - (c10 - c00)) * az, c1 - c0;
  return true;
}

// Random TSDF values in a 2x2x2 group of blocks with one block of the 3x3x3 around them left
// unallocated and a few voxels unobserved, sampled at random points and at every kind of cell:
// inside a block, across one, two and three block faces, next to the missing block. The reader
// looks blocks up once per cell rather than once per corner and interpolates four lanes at a
// time; it must give the definition's values to the bit, and fail exactly where it does.
template <typename Volume>
void expectTrilinearAsDefined(Volume* volume) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> tsdf(-1.f, 1.f);
  std::uniform_int_distribution<int> percent(0, 99);
  for (int b = 0; b < 27; ++b) {
    const BlockIndex index(b % 3 - 1, (b / 3) % 3 - 1, b / 9 - 1);
    if (index == BlockIndex(1, 1, 0)) continue;  // never allocated
    VoxelBlock* blk = volume->allocateBlock(index);
    ASSERT_NE(blk, nullptr);
    for (Voxel& v : blk->voxels) {
      v.tsdf = tsdf(rng);
      v.weight = percent(rng) < 3 ? 0.f : 1.f + static_cast<float>(percent(rng));
    }
  }
  std::uniform_real_distribution<float> coord(-9.f, 16.f);  // voxel units, about the blocks
  std::vector<Eigen::Vector3f> points;
  for (int i = 0; i < 20000; ++i) points.emplace_back(coord(rng), coord(rng), coord(rng));
  // Cells whose far corners cross block faces: local index 7 along one, two or three axes.
  for (const float x : {3.25f, 7.5f, 15.75f, -0.5f})
    for (const float y : {2.5f, 7.25f, 15.5f, -1.f + 0.125f})
      for (const float z : {6.75f, 7.75f, -0.25f}) points.emplace_back(x, y, z);
  VoxelReader reader(*volume);
  int found = 0, crossing = 0;
  for (const Eigen::Vector3f& p : points) {
    float expected = 0.f, got = 0.f;
    Eigen::Vector3f expected_gradient, got_gradient;
    const bool defined = trilinearReference(*volume, p, &expected, &expected_gradient);
    ASSERT_EQ(reader.trilinear(p, &got, &got_gradient), defined) << p.transpose();
    if (!defined) continue;
    ++found;
    const Eigen::Vector3i g = p.array().floor().cast<int>();
    crossing += (g.x() & 7) == 7 || (g.y() & 7) == 7 || (g.z() & 7) == 7;
    // Bit for bit: the raycast's output must not depend on how the corners were gathered.
    EXPECT_EQ(got, expected) << p.transpose();
    EXPECT_EQ(got_gradient, expected_gradient) << p.transpose();
    float without_gradient = 0.f;
    ASSERT_TRUE(reader.trilinear(p, &without_gradient, nullptr));
    EXPECT_EQ(without_gradient, expected);
  }
  EXPECT_GT(found, 1000);
  EXPECT_GT(crossing, 300) << "cells across block faces must be exercised";
}

TEST(VoxelReader, TrilinearIsTheDefinitionInDenseVolume) {
  DenseVolume volume(smallDense());
  expectTrilinearAsDefined(&volume);
}

TEST(VoxelReader, TrilinearIsTheDefinitionInHashedVolume) {
  HashedVolume::Params params;
  params.voxel_size_m = 0.05f;
  HashedVolume volume(params);
  expectTrilinearAsDefined(&volume);
}

}  // namespace
}  // namespace kinfly
