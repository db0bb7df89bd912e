#include "kinfly/mesh/incremental_mesher.h"

#include <omp.h>

#include <algorithm>
#include <chrono>

#include "block_mesh.h"
#include "parallel.h"

namespace kinfly {
namespace {

double msSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}

const std::array<BlockIndex, kMeshReadOffsetCount>& readOffsets() {
  static const std::array<BlockIndex, kMeshReadOffsetCount> offsets = meshReadOffsets();
  return offsets;
}

}  // namespace

std::array<BlockIndex, kMeshReadOffsetCount> meshReadOffsets() {
  // A cube with lower corner in block B has its corners in B and B + {0,1}^3 (local [0, 8]^3);
  // a vertex's normal takes central differences at its edge's two corners, one voxel along each
  // axis, which reaches local -1 along one axis at a time: B - x, B - y, B - z and those shifted
  // by + along the other two axes. Never two -1 at once.
  std::array<BlockIndex, kMeshReadOffsetCount> offsets;
  int n = 0;
  for (int z = -1; z <= 1; ++z)
    for (int y = -1; y <= 1; ++y)
      for (int x = -1; x <= 1; ++x)
        if ((x < 0) + (y < 0) + (z < 0) <= 1) offsets[n++] = BlockIndex(x, y, z);
  return offsets;
}

// ---------------------------------------------------------------------------------------------
// BlockIndexMap

int BlockIndexMap::find(const BlockIndex& b) const {
  if (slots_.empty()) return -1;
  const size_t mask = slots_.size() - 1;
  for (size_t h = hashBlockIndex(b) & mask;; h = (h + 1) & mask) {
    const Slot& slot = slots_[h];
    if (slot.value < 0) return -1;
    if (slot.index == b) return slot.value;
  }
}

void BlockIndexMap::insert(const BlockIndex& b, int value) {
  if (2 * (size_ + 1) > slots_.size()) grow();
  const size_t mask = slots_.size() - 1;
  size_t h = hashBlockIndex(b) & mask;
  while (slots_[h].value >= 0) h = (h + 1) & mask;
  slots_[h] = {b, value};
  ++size_;
}

void BlockIndexMap::clear() {
  std::fill(slots_.begin(), slots_.end(), Slot());
  size_ = 0;
}

void BlockIndexMap::grow() {
  std::vector<Slot> old(std::max<size_t>(64, 2 * slots_.size()));
  old.swap(slots_);
  size_ = 0;
  for (const Slot& s : old)
    if (s.value >= 0) insert(s.index, s.value);
}

// ---------------------------------------------------------------------------------------------
// MeshDelta, MeshChangeTracker

void MeshDelta::clear() {
  rebuild = false;
  remesh.clear();
  blocks_changed = 0;
  map_blocks = 0;
  collect_ms = 0;
  copies.reset();
  queued.clear();
}

void MeshChangeTracker::reset() {
  records_.clear();
  record_of_.clear();
}

void MeshChangeTracker::collect(const TsdfVolume& volume, bool copy, MeshDelta* delta) {
  const auto start = std::chrono::steady_clock::now();
  const std::vector<VoxelBlock*>& blocks = volume.allocatedBlocks();

  // 1. Changed blocks. Blocks only join the end of the list unless some left it (clear(), a
  // dense volume's shift); then every block mesh is made again.
  changed_.clear();
  bool left = blocks.size() < records_.size();
  for (size_t i = 0; i < records_.size() && !left; ++i) {
    const VoxelBlock& block = *blocks[i];
    Record& record = records_[i];
    if (!(record.index == block.index)) {
      left = true;
    } else if (record.stamp != block.touched_stamp) {
      record.stamp = block.touched_stamp;
      changed_.push_back(static_cast<int>(i));
    }
  }
  if (left) {
    reset();
    changed_.clear();
    delta->clear();
    delta->rebuild = true;
  }
  for (size_t i = records_.size(); i < blocks.size(); ++i) {
    record_of_.insert(blocks[i]->index, static_cast<int>(i));
    records_.push_back({blocks[i]->index, blocks[i]->touched_stamp, 0});
    changed_.push_back(static_cast<int>(i));
  }

  // 2. Blocks whose cubes read a changed block: B reads B + o, so a change at C reaches C - o.
  const auto nextMark = [this] {
    if (++mark_ == 0) {
      for (Record& r : records_) r.mark = 0;
      mark_ = 1;
    }
  };
  const auto gather = [this](const std::vector<int>& from, int sign, std::vector<int>* out) {
    out->clear();
    for (int c : from) {
      for (const BlockIndex& o : readOffsets()) {
        const int j = record_of_.find(records_[c].index + sign * o);
        if (j < 0 || records_[j].mark == mark_) continue;
        records_[j].mark = mark_;
        out->push_back(j);
      }
    }
  };
  nextMark();
  gather(changed_, -1, &remesh_);
  std::sort(remesh_.begin(), remesh_.end());  // allocation order: new block meshes keep it

  for (int j : remesh_) {
    const BlockIndex& b = records_[j].index;
    if (delta->queued.find(b) >= 0) continue;
    delta->queued.insert(b, static_cast<int>(delta->remesh.size()));
    delta->remesh.push_back(b);
  }

  // 3. Copies of what meshing those blocks reads. A block copied by an earlier collect into the
  // same delta and not copied now has not changed since, so the copies stay consistent.
  if (copy) {
    nextMark();
    gather(remesh_, +1, &copy_);
    if (!delta->copies) {
      HashedVolume::Params params;
      params.voxel_size_m = volume.voxelSizeM();
      params.chunk_blocks = static_cast<int>(std::max<size_t>(64, copy_.size()));
      delta->copies = std::make_unique<HashedVolume>(params);
    }
    for (int j : copy_) delta->copies->allocateBlock(records_[j].index)->voxels = blocks[j]->voxels;
  }

  delta->blocks_changed += static_cast<int>(changed_.size());
  delta->map_blocks = static_cast<int>(blocks.size());
  delta->collect_ms += msSince(start);
}

// ---------------------------------------------------------------------------------------------
// IncrementalMesher

struct IncrementalMesher::State {
  std::vector<detail::BlockMesh> pieces;  // in the order the blocks first appeared
  BlockIndexMap piece_of;
  std::vector<int> todo;
  std::vector<std::unique_ptr<detail::BlockMesherScratch>> scratch;  // one per thread
  size_t triangles = 0;
};

Status IncrementalMesher::Params::validate() const {
  if (!(min_weight > 0.f)) return Status::error("min_weight must be > 0");
  return {};
}

IncrementalMesher::IncrementalMesher(const Params& params)
    : params_(params), state_(std::make_unique<State>()) {}

IncrementalMesher::~IncrementalMesher() = default;

MeshUpdateResult IncrementalMesher::update(const TsdfVolume& volume, bool parallel) {
  tracker_.collect(volume, /*copy=*/false, &delta_);
  return meshBlocks(volume, &delta_, parallel);
}

MeshUpdateResult IncrementalMesher::apply(MeshDelta* delta, bool parallel) {
  if (!delta->copies) {
    // Nothing to mesh again (else collect would have copied it): only the counts change.
    HashedVolume::Params params;
    params.chunk_blocks = 1;
    delta->copies = std::make_unique<HashedVolume>(params);
  }
  return meshBlocks(*delta->copies, delta, parallel);
}

MeshUpdateResult IncrementalMesher::meshBlocks(const TsdfVolume& source, MeshDelta* delta,
                                               bool parallel) {
  const auto start = std::chrono::steady_clock::now();
  State& s = *state_;
  if (delta->rebuild) {
    s.pieces.clear();
    s.piece_of.clear();
  }
  s.todo.clear();
  for (const BlockIndex& b : delta->remesh) {
    int p = s.piece_of.find(b);
    if (p < 0) {
      p = static_cast<int>(s.pieces.size());
      s.piece_of.insert(b, p);
      s.pieces.emplace_back();
    }
    s.todo.push_back(p);
  }
  const int threads = std::max(1, omp_get_max_threads());
  while (static_cast<int>(s.scratch.size()) < threads)
    s.scratch.push_back(std::make_unique<detail::BlockMesherScratch>());

  // Each block mesh is written by one thread from its own scratch: the result does not depend
  // on the threads.
  const int n = static_cast<int>(s.todo.size());
  forEachDynamic(n, 4, parallel, [&](int i) {
    detail::BlockMesh& piece = s.pieces[static_cast<size_t>(s.todo[i])];
    const VoxelBlock* block = source.findBlock(delta->remesh[i]);
    if (block == nullptr) {  // cannot happen for a delta from collect; stay empty if it does
      piece.clear();
      piece.index = delta->remesh[i];
      return;
    }
    detail::meshBlock(source, *block, params_.min_weight,
                      s.scratch[static_cast<size_t>(omp_get_thread_num())].get(), &piece);
  });
  s.triangles = 0;
  for (const detail::BlockMesh& piece : s.pieces) s.triangles += piece.triangles.size();

  MeshUpdateResult result;
  result.map_blocks = delta->map_blocks;
  result.blocks_changed = delta->blocks_changed;
  result.blocks_remeshed = n;
  result.blocks_kept = static_cast<int>(s.pieces.size()) - n;
  result.rebuilt = delta->rebuild;
  result.collect_ms = delta->collect_ms;
  delta->clear();
  result.mesh_ms = msSince(start);
  return result;
}

void IncrementalMesher::assemble(TriangleMesh* mesh) const {
  size_t vertices = 0;
  for (const detail::BlockMesh& piece : state_->pieces) vertices += piece.vertices.size();
  mesh->vertices.clear();
  mesh->normals.clear();
  mesh->triangles.clear();
  mesh->vertices.reserve(vertices);  // before merging: an upper bound
  mesh->normals.reserve(vertices);
  mesh->triangles.reserve(state_->triangles);
  detail::MeshAssembler assembler;
  assembler.begin(mesh);
  for (const detail::BlockMesh& piece : state_->pieces) assembler.append(piece);
}

TriangleMesh IncrementalMesher::mesh() const {
  TriangleMesh mesh;
  assemble(&mesh);
  return mesh;
}

size_t IncrementalMesher::numBlocks() const { return state_->pieces.size(); }
size_t IncrementalMesher::numTriangles() const { return state_->triangles; }

void IncrementalMesher::clear() {
  state_->pieces.clear();
  state_->piece_of.clear();
  state_->triangles = 0;
  tracker_.reset();
  delta_.clear();
}

}  // namespace kinfly
