// Marching cubes one block at a time, and the joining of block meshes into one mesh: what
// MarchingCubes::extract (every block) and IncrementalMesher (the changed blocks) share, so the
// two give the same mesh by construction. Private to shared/src.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include "kinfly/mesh/mesh.h"
#include "kinfly/volume/tsdf_volume.h"

namespace kinfly::detail {

// Cube edges are named within a block by the local lower corner of the edge, in [0, 8]^3 (the
// corners of the block's cubes), and its axis: id = axis * 729 + (z * 9 + y) * 9 + x.
constexpr int kCornerSpan = kBlockSide + 1;
constexpr int kCornersPerBlock = kCornerSpan * kCornerSpan * kCornerSpan;
constexpr int kEdgesPerBlock = 3 * kCornersPerBlock;

inline int localEdgeId(const Eigen::Vector3i& lower, int axis) {
  return axis * kCornersPerBlock + (lower.z() * kCornerSpan + lower.y()) * kCornerSpan + lower.x();
}
inline int edgeAxis(int id) { return id / kCornersPerBlock; }
inline Eigen::Vector3i edgeLower(int id) {
  const int c = id % kCornersPerBlock;
  return {c % kCornerSpan, (c / kCornerSpan) % kCornerSpan, c / (kCornerSpan * kCornerSpan)};
}
// An edge is used by the four cubes around it; when its lower corner lies on a face of the block
// across the axis, some of those cubes belong to a neighbouring block, which makes its own copy
// of the vertex. Only these vertices need merging between blocks.
inline bool edgeOnBlockBorder(int id) {
  const int axis = edgeAxis(id);
  const Eigen::Vector3i lower = edgeLower(id);
  for (int a = 0; a < 3; ++a) {
    if (a != axis && (lower[a] == 0 || lower[a] == kBlockSide)) return true;
  }
  return false;
}

// The triangles of the cubes whose lower corner lies in one block, with vertices of their own.
struct BlockMesh {
  BlockIndex index = BlockIndex::Zero();
  std::vector<Eigen::Vector3f> vertices;   // [m] world frame
  std::vector<Eigen::Vector3f> normals;    // unit, into free space
  std::vector<Eigen::Vector3i> triangles;  // indices into this block's vertices
  std::vector<uint16_t> edges;             // per vertex: the local edge id it lies on
  void clear() {
    vertices.clear();
    normals.clear();
    triangles.clear();
    edges.clear();
  }
};

// What one thread reuses from block to block: the block's samples and its edge -> vertex table
// (valid where the stamp is current, so nothing is cleared per block).
struct BlockMesherScratch {
  BlockMesherScratch()
      : tsdf(kCornersPerBlock), weight(kCornersPerBlock), vertex_of_edge(kEdgesPerBlock),
        edge_stamp(kEdgesPerBlock, 0) {}
  std::vector<float> tsdf;    // the block's voxels and the first layer of its +x/+y/+z neighbours
  std::vector<float> weight;  // -1 where that neighbour is not allocated
  std::vector<int> vertex_of_edge;
  std::vector<uint32_t> edge_stamp;
  uint32_t stamp = 0;
};

// Marching cubes over the cubes of `block` (a block of `volume`), reading its neighbours in
// `volume`: the +x/+y/+z ones for the cubes' far corners, and one more voxel on every side for
// the normals (BlockNeighbourhood in incremental_mesher.cpp lists them).
void meshBlock(const TsdfVolume& volume, const VoxelBlock& block, float min_weight,
               BlockMesherScratch* scratch, BlockMesh* out);

// Appends block meshes to one TriangleMesh, merging the vertices that neighbouring blocks both
// made on their shared faces. Appending every block of a volume in allocation order numbers the
// vertices in the order of their first use, as a single pass over the volume would.
class MeshAssembler {
 public:
  // Starts over on an empty `mesh` (kept by the caller); the merge table keeps its memory.
  void begin(TriangleMesh* mesh);
  void append(const BlockMesh& piece);

 private:
  struct Slot {
    Eigen::Vector3i lower;  // global voxel index of the edge's lower corner
    int axis = -1;          // -1: empty slot
    int vertex = -1;
  };
  // The vertex already made on this edge, or -1 after recording `vertex` for it.
  int findOrAdd(const Eigen::Vector3i& lower, int axis, int vertex);
  void grow();

  TriangleMesh* mesh_ = nullptr;
  std::vector<Slot> slots_;  // open addressing, linear probing, load <= 1/2
  size_t used_ = 0;
  std::vector<int> remap_;   // block vertex -> mesh vertex
};

}  // namespace kinfly::detail
