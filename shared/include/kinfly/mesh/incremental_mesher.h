// Stage 8, incrementally: marching cubes kept per block and redone only where the TSDF changed
// since the last update, as voxblox's MeshIntegrator does with its per-block `updated` flags
// (generateMesh(only_mesh_updated_blocks, clear_updated_flag)).
//
// What changed comes from the blocks' touched stamps (TsdfIntegrator stamps every block it
// writes): a block changed when its stamp differs from the one seen at the previous update, or
// when it is new. A cube reads the voxels of its block's +x/+y/+z neighbours and its normals one
// voxel further on every side, so a block's mesh is made again when the block or one of the 19
// neighbours it reads changed (kMeshReadOffsets). The whole mesh is assembled from the kept block
// meshes on request and equals MarchingCubes::extract of the same volume, triangle for triangle.
//
// Threads: either one thread calls update(volume), or the thread that writes the volume calls
// MeshChangeTracker::collect(volume, copy = true, &delta) between integrations (it copies the
// changed blocks and what meshing them reads, nothing else) and any other thread calls
// apply(&delta) later, outside any lock the writer waits on; deltas are applied in the order
// collected (a collect into a delta not yet applied merges into it).
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "kinfly/core/status.h"
#include "kinfly/mesh/mesh.h"
#include "kinfly/volume/tsdf_volume.h"

namespace kinfly {

// Offsets from a block to the blocks its cubes read: the block itself and its +x/+y/+z
// neighbours (the cubes' far corners), and the blocks one voxel below it along a single axis
// (central differences for the normals at its low faces): {-1, 0, 1}^3 with at most one -1.
constexpr int kMeshReadOffsetCount = 20;
std::array<BlockIndex, kMeshReadOffsetCount> meshReadOffsets();

// BlockIndex -> int with open addressing, as HashedVolume's table: allocates only as it grows.
class BlockIndexMap {
 public:
  int find(const BlockIndex& b) const;           // -1 when absent
  void insert(const BlockIndex& b, int value);   // b must be absent
  size_t size() const { return size_; }
  void clear();

 private:
  struct Slot {
    BlockIndex index = BlockIndex::Zero();
    int value = -1;  // -1: empty
  };
  void grow();
  std::vector<Slot> slots_;
  size_t size_ = 0;
};

// Which blocks a mesh update must mesh again and, when it is to run on another thread than the
// one that writes the volume, copies of every block that meshing them reads.
struct MeshDelta {
  bool rebuild = false;             // blocks left the volume: drop every kept block mesh first
  std::vector<BlockIndex> remesh;   // to mesh again, in the volume's allocation order
  int blocks_changed = 0;           // written or new since the collect before (summed if merged)
  int map_blocks = 0;               // allocated blocks of the volume at the latest collect
  double collect_ms = 0;            // time spent collecting (summed if merged)
  std::unique_ptr<HashedVolume> copies;  // nullptr: apply reads the volume itself
  BlockIndexMap queued;             // remesh's members
  bool empty() const { return !rebuild && remesh.empty(); }
  void clear();
};

class MeshChangeTracker {
 public:
  // Finds the blocks of `volume` written since the previous collect and adds to `delta` every
  // block whose mesh reads one of them; with `copy`, also copies every block those meshes read
  // into delta->copies. Call it where nothing writes the volume meanwhile. The scan reads each
  // block's stamp once (one cache line per block); the rest scales with the changed blocks.
  void collect(const TsdfVolume& volume, bool copy, MeshDelta* delta);
  // Forgets every block: the next collect lists the whole volume.
  void reset();

 private:
  struct Record {
    BlockIndex index;
    uint32_t stamp;  // the block's touched_stamp at the previous collect
    uint32_t mark;   // == mark_ while listed in this collect
  };
  std::vector<Record> records_;  // the volume's blocks, in its allocation order
  BlockIndexMap record_of_;
  uint32_t mark_ = 0;
  std::vector<int> changed_, remesh_, copy_;  // record numbers, reused
};

struct MeshUpdateResult {
  int map_blocks = 0;        // allocated blocks in the volume
  int blocks_changed = 0;    // blocks written (or new) since the previous update
  int blocks_remeshed = 0;   // the changed blocks and the neighbours whose cubes read them
  int blocks_kept = 0;       // block meshes kept as they were
  bool rebuilt = false;      // blocks had left the volume: everything was meshed again
  double collect_ms = 0;     // finding the changes (and copying them, for apply)
  double mesh_ms = 0;        // marching cubes over the re-meshed blocks
  double total_ms() const { return collect_ms + mesh_ms; }
};

class IncrementalMesher {
 public:
  struct Params {
    // As MarchingCubes::Params: cubes with a corner observed less than this are skipped.
    float min_weight = 1.f;  // > 0
    Status validate() const;
  };
  explicit IncrementalMesher(const Params& params);
  ~IncrementalMesher();
  IncrementalMesher(const IncrementalMesher&) = delete;
  IncrementalMesher& operator=(const IncrementalMesher&) = delete;

  // One thread: meshes again what changed in `volume` since the previous update. `parallel`:
  // the re-meshed blocks are shared among the OpenMP threads (results do not depend on it).
  MeshUpdateResult update(const TsdfVolume& volume, bool parallel = true);
  // Two threads: meshes again the blocks of a delta that MeshChangeTracker::collect filled with
  // copies, and empties it. Never touches the volume.
  MeshUpdateResult apply(MeshDelta* delta, bool parallel = true);

  // The whole mesh, joined from the kept block meshes: vertices on block faces are merged, and
  // for a volume that only grew (a HashedVolume) it is MarchingCubes::extract's mesh exactly.
  void assemble(TriangleMesh* mesh) const;
  TriangleMesh mesh() const;

  size_t numBlocks() const;      // block meshes kept (empty ones included)
  size_t numTriangles() const;
  void clear();                  // forget every block mesh; the next update meshes everything

 private:
  MeshUpdateResult meshBlocks(const TsdfVolume& source, MeshDelta* delta, bool parallel);

  struct State;
  Params params_;
  MeshChangeTracker tracker_;  // update()'s
  MeshDelta delta_;            // update()'s, reused
  std::unique_ptr<State> state_;
};

}  // namespace kinfly
