// Stage 6 storage: a TSDF in 8^3 voxel blocks behind one interface. DenseVolume (fixed N^3,
// fixed memory, follows the camera: onboard) and HashedVolume (spatial hash, grows with observed
// surface: ground). Integrator, raycaster and marching cubes only see this interface.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cmath>
#include <memory>
#include <string>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "kinfly/core/numeric.h"
#include "kinfly/core/se3.h"
#include "kinfly/core/status.h"

namespace kinfly {

constexpr int kBlockSide = 8;                                   // voxels per block edge
constexpr int kBlockVoxels = kBlockSide * kBlockSide * kBlockSide;

struct Voxel {
  float tsdf = 1.f;    // truncated signed distance / truncation, in [-1, 1]; + in front of surface
  float weight = 0.f;  // accumulated observation weight; 0 = never observed
};

using BlockIndex = Eigen::Vector3i;  // block coordinates: floor(p_world / block size)

struct VoxelBlock {
  std::array<Voxel, kBlockVoxels> voxels;
  BlockIndex index = BlockIndex::Zero();
  // Last integration pass that touched this block, so a frame lists each block once without a
  // per-frame set.
  uint32_t touched_stamp = 0;

  static int linear(int x, int y, int z) { return (z * kBlockSide + y) * kBlockSide + x; }
  void reset(const BlockIndex& new_index);
};

// Hash for block coordinates: the primes of Teschner et al. (2003, as in voxel hashing), then a
// multiplicative mix, because the table is indexed by the low bits and the plain XOR of
// neighbouring blocks clusters there.
inline size_t hashBlockIndex(const BlockIndex& b) {
  const uint64_t h = (static_cast<uint64_t>(static_cast<uint32_t>(b.x())) * 73856093u) ^
                     (static_cast<uint64_t>(static_cast<uint32_t>(b.y())) * 19349669u) ^
                     (static_cast<uint64_t>(static_cast<uint32_t>(b.z())) * 83492791u);
  return static_cast<size_t>((h * 0x9E3779B97F4A7C15ull) >> 20);
}

class TsdfVolume {
 public:
  explicit TsdfVolume(float voxel_size_m) : voxel_size_m_(voxel_size_m) {}
  virtual ~TsdfVolume() = default;
  TsdfVolume(const TsdfVolume&) = delete;
  TsdfVolume& operator=(const TsdfVolume&) = delete;

  float voxelSizeM() const { return voxel_size_m_; }
  float blockSizeM() const { return voxel_size_m_ * kBlockSide; }

  // nullptr when the block has not been allocated (or lies outside a dense volume).
  virtual const VoxelBlock* findBlock(const BlockIndex& b) const = 0;
  VoxelBlock* findBlock(const BlockIndex& b) {
    return const_cast<VoxelBlock*>(static_cast<const TsdfVolume*>(this)->findBlock(b));
  }
  // Finds or creates the block; nullptr when this volume cannot hold it (outside a dense
  // volume). Not thread-safe: the integrator allocates serially, then updates in parallel.
  virtual VoxelBlock* allocateBlock(const BlockIndex& b) = 0;
  // Blocks that hold observations, in allocation order.
  virtual const std::vector<VoxelBlock*>& allocatedBlocks() const = 0;
  size_t numAllocatedBlocks() const { return allocatedBlocks().size(); }
  // Bytes reserved for voxel storage and its index, whether used or not.
  virtual size_t memoryBytes() const = 0;
  // Volumes of bounded extent move so the space in front of the camera stays inside, as far
  // ahead as it sees its scene (`view_depth_m`, the frame's median depth; 0: not known); an
  // unbounded volume ignores this, and says so here.
  virtual bool followsCamera() const { return false; }
  virtual void followCamera(const Pose& /*T_world_cam*/, float /*view_depth_m*/) {}
  virtual void clear() = 0;

  BlockIndex blockOf(const Eigen::Vector3f& p_world) const {
    const float inv = 1.f / blockSizeM();
    return {floorToInt(p_world.x() * inv), floorToInt(p_world.y() * inv),
            floorToInt(p_world.z() * inv)};
  }
  // Voxel centres sit at integer multiples of the voxel size: global voxel g is at g * voxel.
  Eigen::Vector3f voxelCentre(const BlockIndex& b, int x, int y, int z) const {
    return Eigen::Vector3f(static_cast<float>(b.x() * kBlockSide + x),
                           static_cast<float>(b.y() * kBlockSide + y),
                           static_cast<float>(b.z() * kBlockSide + z)) * voxel_size_m_;
  }

 private:
  float voxel_size_m_;
};

class DenseVolume final : public TsdfVolume {
 public:
  struct Params {
    int resolution_vox = 128;     // voxels per edge, multiple of 8 in [16, 512]
    float voxel_size_m = 0.03f;   // [m] (0, 0.2]; 128 x 3 cm = 3.84 m cube
    // The volume is kept centred along the camera's optical axis this far in front of it, or
    // where the camera sees its scene (the frame's median depth) up to max_lookahead_m. A
    // 3.84 m cube centred 2 m ahead ends 3.9 m ahead, less up to the shift threshold's 0.5 m:
    // a scene 3.6 m off (a hall's far end) lay mostly outside it, its 12 cm band behind the
    // surface too, and every frame of it was lost (docs/engine.md, departure 9). Centred 2.7 m
    // ahead it reaches the sensor's 4 m and the band at every shift; it then leaves out what is
    // nearer than 0.8-1.3 m, which a view whose median is that far holds little of. A limit
    // at or below lookahead_m keeps the cube at lookahead_m. The window shifts whenever the
    // wanted centre moves by the shift threshold, so a view whose median swings across the
    // 0.7 m between the two shifts it back and forth.
    float lookahead_m = 2.0f;      // [m] [0, 10]
    float max_lookahead_m = 2.7f;  // [m] [0, 10]
    // Re-centre only when the wanted centre has moved this many blocks, so shifts are rare.
    int shift_threshold_blocks = 2;  // [1, 64]
    Status validate() const;
  };
  explicit DenseVolume(const Params& params);

  const VoxelBlock* findBlock(const BlockIndex& b) const override;
  using TsdfVolume::findBlock;
  VoxelBlock* allocateBlock(const BlockIndex& b) override;
  const std::vector<VoxelBlock*>& allocatedBlocks() const override { return observed_; }
  size_t memoryBytes() const override;
  bool followsCamera() const override { return true; }
  void followCamera(const Pose& T_world_cam, float view_depth_m) override;
  void clear() override;

  // The block range [origin, origin + blocks_per_side) currently held.
  const BlockIndex& originBlock() const { return origin_; }
  int blocksPerSide() const { return blocks_per_side_; }
  int shiftCount() const { return shift_count_; }
  // Moves the window so it starts at `new_origin`; blocks leaving it are forgotten, blocks that
  // stay keep their data (ring-buffer addressing, nothing is copied).
  void shiftTo(const BlockIndex& new_origin);

 private:
  bool contains(const BlockIndex& b) const;
  size_t slotOf(const BlockIndex& b) const;

  Params params_;
  int blocks_per_side_;
  BlockIndex origin_ = BlockIndex::Zero();
  std::vector<VoxelBlock> slots_;
  std::vector<uint8_t> slot_observed_;
  std::vector<VoxelBlock*> observed_;
  int shift_count_ = 0;
};

class HashedVolume final : public TsdfVolume {
 public:
  struct Params {
    float voxel_size_m = 0.01f;       // [m] > 0
    // Block storage grows in chunks of this many blocks (4 KiB each), so adding surface costs an
    // allocation only once per chunk, never per frame.
    int chunk_blocks = 4096;          // > 0
    Status validate() const;
  };
  explicit HashedVolume(const Params& params);

  const VoxelBlock* findBlock(const BlockIndex& b) const override;
  using TsdfVolume::findBlock;
  VoxelBlock* allocateBlock(const BlockIndex& b) override;
  const std::vector<VoxelBlock*>& allocatedBlocks() const override { return blocks_; }
  size_t memoryBytes() const override;
  void clear() override;

 private:
  // Open addressing with linear probing; slots hold a block pointer or nullptr.
  void rehash(size_t new_capacity);
  VoxelBlock* newBlock();

  Params params_;
  std::vector<VoxelBlock*> table_;
  size_t mask_ = 0;
  std::vector<std::unique_ptr<VoxelBlock[]>> chunks_;
  size_t used_in_last_chunk_ = 0;
  std::vector<VoxelBlock*> blocks_;
};

}  // namespace kinfly
