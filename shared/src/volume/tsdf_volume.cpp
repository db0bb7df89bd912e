#include "kinfly/volume/tsdf_volume.h"

#include <algorithm>
#include <sstream>

namespace kinfly {

void VoxelBlock::reset(const BlockIndex& new_index) {
  voxels.fill(Voxel());
  index = new_index;
  touched_stamp = 0;
}

// ---------------------------------------------------------------------------------------------
// DenseVolume

Status DenseVolume::Params::validate() const {
  std::ostringstream why;
  if (resolution_vox < 16 || resolution_vox > 512 || resolution_vox % kBlockSide != 0)
    why << "resolution_vox must be a multiple of 8 in [16, 512] (got " << resolution_vox << ")";
  else if (!(voxel_size_m > 0.f && voxel_size_m <= 0.2f))
    why << "voxel_size_m must be in (0, 0.2] (got " << voxel_size_m << ")";
  else if (!(lookahead_m >= 0.f && lookahead_m <= 10.f))
    why << "lookahead_m must be in [0, 10] (got " << lookahead_m << ")";
  else if (!(max_lookahead_m >= 0.f && max_lookahead_m <= 10.f))
    why << "max_lookahead_m must be in [0, 10] (got " << max_lookahead_m << ")";
  else if (shift_threshold_blocks < 1 || shift_threshold_blocks > 64)
    why << "shift_threshold_blocks must be in [1, 64] (got " << shift_threshold_blocks << ")";
  return why.str().empty() ? Status() : Status::error(why.str());
}

DenseVolume::DenseVolume(const Params& params)
    : TsdfVolume(params.voxel_size_m),
      params_(params),
      blocks_per_side_(params.resolution_vox / kBlockSide) {
  const size_t n = static_cast<size_t>(blocks_per_side_) * blocks_per_side_ * blocks_per_side_;
  slots_.resize(n);
  slot_observed_.assign(n, 0);
  observed_.reserve(n);
  origin_ = BlockIndex::Constant(-blocks_per_side_ / 2);
}

bool DenseVolume::contains(const BlockIndex& b) const {
  const BlockIndex r = b - origin_;
  return r.minCoeff() >= 0 && r.maxCoeff() < blocks_per_side_;
}

size_t DenseVolume::slotOf(const BlockIndex& b) const {
  // Ring-buffer addressing: a block keeps its slot while the window moves, so shifting copies
  // nothing.
  const int n = blocks_per_side_;
  auto wrap = [n](int i) { return static_cast<size_t>(((i % n) + n) % n); };
  return (wrap(b.z()) * n + wrap(b.y())) * n + wrap(b.x());
}

const VoxelBlock* DenseVolume::findBlock(const BlockIndex& b) const {
  if (!contains(b)) return nullptr;
  const size_t s = slotOf(b);
  return slot_observed_[s] ? &slots_[s] : nullptr;
}

VoxelBlock* DenseVolume::allocateBlock(const BlockIndex& b) {
  if (!contains(b)) return nullptr;
  const size_t s = slotOf(b);
  if (!slot_observed_[s]) {
    slots_[s].reset(b);
    slot_observed_[s] = 1;
    observed_.push_back(&slots_[s]);  // capacity reserved for every slot: never reallocates
  }
  return &slots_[s];
}

size_t DenseVolume::memoryBytes() const {
  return slots_.capacity() * sizeof(VoxelBlock) + slot_observed_.capacity() +
         observed_.capacity() * sizeof(VoxelBlock*);
}

void DenseVolume::shiftTo(const BlockIndex& new_origin) {
  origin_ = new_origin;
  auto left = [this](VoxelBlock* blk) {
    if (contains(blk->index)) return false;
    slot_observed_[static_cast<size_t>(blk - slots_.data())] = 0;
    return true;
  };
  observed_.erase(std::remove_if(observed_.begin(), observed_.end(), left), observed_.end());
  ++shift_count_;
}

void DenseVolume::followCamera(const Pose& T_world_cam, float view_depth_m) {
  // Never nearer than lookahead_m, whatever the limit. A depth not known keeps lookahead_m: 0
  // by the max, NaN since std::min passes it on and std::max then keeps its first argument.
  const float ahead =
      std::max(params_.lookahead_m, std::min(view_depth_m, params_.max_lookahead_m));
  const Eigen::Vector3d centre =
      T_world_cam.translation() + T_world_cam.linear().col(2) * static_cast<double>(ahead);
  const BlockIndex wanted =
      blockOf(centre.cast<float>()) - BlockIndex::Constant(blocks_per_side_ / 2);
  if ((wanted - origin_).cwiseAbs().maxCoeff() >= params_.shift_threshold_blocks) shiftTo(wanted);
}

void DenseVolume::clear() {
  std::fill(slot_observed_.begin(), slot_observed_.end(), 0);
  observed_.clear();
}

// ---------------------------------------------------------------------------------------------
// HashedVolume

Status HashedVolume::Params::validate() const {
  std::ostringstream why;
  if (!(voxel_size_m > 0.f)) why << "voxel_size_m must be > 0";
  else if (chunk_blocks <= 0) why << "chunk_blocks must be > 0";
  return why.str().empty() ? Status() : Status::error(why.str());
}

HashedVolume::HashedVolume(const Params& params) : TsdfVolume(params.voxel_size_m), params_(params) {
  size_t capacity = 1;
  while (capacity < 2 * static_cast<size_t>(params.chunk_blocks)) capacity <<= 1;
  rehash(capacity);
  blocks_.reserve(static_cast<size_t>(params.chunk_blocks));
}

const VoxelBlock* HashedVolume::findBlock(const BlockIndex& b) const {
  for (size_t h = hashBlockIndex(b) & mask_;; h = (h + 1) & mask_) {
    const VoxelBlock* blk = table_[h];
    if (blk == nullptr) return nullptr;
    if (blk->index == b) return blk;
  }
}

VoxelBlock* HashedVolume::allocateBlock(const BlockIndex& b) {
  size_t h = hashBlockIndex(b) & mask_;
  for (; table_[h] != nullptr; h = (h + 1) & mask_)
    if (table_[h]->index == b) return table_[h];
  VoxelBlock* blk = newBlock();
  blk->reset(b);
  table_[h] = blk;
  blocks_.push_back(blk);
  // Keep the load factor under one half so probe sequences stay short.
  if (2 * blocks_.size() > table_.size()) rehash(2 * table_.size());
  return blk;
}

VoxelBlock* HashedVolume::newBlock() {
  const size_t chunk = static_cast<size_t>(params_.chunk_blocks);
  if (chunks_.empty() || used_in_last_chunk_ == chunk) {
    chunks_.push_back(std::make_unique<VoxelBlock[]>(chunk));
    used_in_last_chunk_ = 0;
    blocks_.reserve(chunks_.size() * chunk);
  }
  return &chunks_.back()[used_in_last_chunk_++];
}

void HashedVolume::rehash(size_t new_capacity) {
  table_.assign(new_capacity, nullptr);
  mask_ = new_capacity - 1;
  for (VoxelBlock* blk : blocks_) {
    size_t h = hashBlockIndex(blk->index) & mask_;
    while (table_[h] != nullptr) h = (h + 1) & mask_;
    table_[h] = blk;
  }
}

size_t HashedVolume::memoryBytes() const {
  return chunks_.size() * static_cast<size_t>(params_.chunk_blocks) * sizeof(VoxelBlock) +
         table_.capacity() * sizeof(VoxelBlock*) + blocks_.capacity() * sizeof(VoxelBlock*);
}

void HashedVolume::clear() {
  chunks_.clear();
  used_in_last_chunk_ = 0;
  blocks_.clear();
  std::fill(table_.begin(), table_.end(), nullptr);
}

}  // namespace kinfly
