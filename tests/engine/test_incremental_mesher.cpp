// IncrementalMesher against MarchingCubes::extract of the same volume: after integrations that
// touch different parts of a synthetic room, after edits right at block borders, through the
// two-thread path (collect with copies, apply later) and after the volume was cleared. And the
// count of re-meshed blocks: exactly the changed ones and the blocks whose cubes read them,
// derived here voxel by voxel from what a cube reads.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <set>
#include <memory>
#include <tuple>
#include <utility>
#include <vector>

#include "kinfly/mesh/incremental_mesher.h"
#include "kinfly/mesh/marching_cubes.h"
#include "kinfly/volume/tsdf_integrator.h"
#include "kinfly/volume/tsdf_volume.h"
#include "test_util.h"

namespace kinfly {
namespace {

constexpr float kVoxelM = 0.02f;
constexpr float kTruncationM = 0.08f;  // 4 voxels, the engine's default ratio
// Both meshers run the same per-block code on the same voxels (the build turns FMA contraction
// off), so vertices agree bit for bit; the tolerances only keep the comparison meaningful if a
// compiler ever reorders that arithmetic.
constexpr float kSameVertexM = 1e-6f;
constexpr float kSameNormal = 1e-5f;

PinholeCamera quarterCamera() { return test::tumCamera().scaled(4); }

using Corner = std::array<float, 6>;  // position, normal
using Triangle = std::array<Corner, 3>;

// Each triangle as its three corners, rotated to start at the smallest (orientation kept), the
// list sorted: equal lists mean the same triangles up to order and vertex numbering.
std::vector<Triangle> canonicalTriangles(const TriangleMesh& mesh) {
  std::vector<Triangle> out;
  out.reserve(mesh.triangles.size());
  for (const Eigen::Vector3i& t : mesh.triangles) {
    Triangle tri;
    for (int k = 0; k < 3; ++k) {
      const Eigen::Vector3f& p = mesh.vertices[static_cast<size_t>(t[k])];
      const Eigen::Vector3f& n = mesh.normals[static_cast<size_t>(t[k])];
      tri[static_cast<size_t>(k)] = {p.x(), p.y(), p.z(), n.x(), n.y(), n.z()};
    }
    const auto first = std::min_element(tri.begin(), tri.end());
    std::rotate(tri.begin(), first, tri.end());
    out.push_back(tri);
  }
  std::sort(out.begin(), out.end());
  return out;
}

void expectSameTriangles(const TriangleMesh& incremental, const TriangleMesh& full) {
  ASSERT_EQ(incremental.triangles.size(), full.triangles.size());
  EXPECT_EQ(incremental.vertices.size(), full.vertices.size());  // merged across blocks alike
  const std::vector<Triangle> a = canonicalTriangles(incremental);
  const std::vector<Triangle> b = canonicalTriangles(full);
  int differing = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    for (size_t k = 0; k < 3; ++k) {
      for (size_t c = 0; c < 6; ++c) {
        const float tol = c < 3 ? kSameVertexM : kSameNormal;
        differing += std::abs(a[i][k][c] - b[i][k][c]) > tol;
      }
    }
  }
  EXPECT_EQ(differing, 0);
}

TriangleMesh fullMesh(const TsdfVolume& volume) {
  return MarchingCubes(MarchingCubes::Params()).extract(volume);
}

class Flight {
 public:
  Flight() : volume_(volumeParams()), integrator_(integratorParams()), camera_(quarterCamera()),
             raw_(camera_.width, camera_.height), depth_(camera_.width, camera_.height) {}

  // One noisy frame of the corner room from `eye` towards `target`.
  void fuse(const Eigen::Vector3d& eye, const Eigen::Vector3d& target, uint32_t seed) {
    test::renderNoisyMetres(scene_, camera_, lookAtPose(eye, target), seed, raw_.view(),
                            depth_.view());
    integrator_.integrate(std::as_const(depth_).view(), camera_, lookAtPose(eye, target), &volume_);
  }
  HashedVolume& volume() { return volume_; }

 private:
  static HashedVolume::Params volumeParams() {
    HashedVolume::Params p;
    p.voxel_size_m = kVoxelM;
    p.chunk_blocks = 1024;
    return p;
  }
  static TsdfIntegrator::Params integratorParams() {
    TsdfIntegrator::Params p;
    p.truncation_m = kTruncationM;
    return p;
  }
  SyntheticScene scene_ = SyntheticScene::cornerRoom();
  HashedVolume volume_;
  TsdfIntegrator integrator_;
  PinholeCamera camera_;
  Image<uint16_t> raw_;
  Image<float> depth_;
};

// Views of different parts of the room: the sphere, the box, the left wall, the floor.
const std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>>& views() {
  static const std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>> v = {
      {{0.0, 0.0, 0.0}, {-0.45, 0.25, 1.9}},
      {{0.2, -0.1, 0.3}, {0.45, 0.55, 2.1}},
      {{0.3, 0.0, 0.5}, {-1.4, 0.3, 1.5}},
      {{0.0, -0.3, 0.8}, {0.0, 0.9, 2.2}},
      {{-0.1, 0.0, 0.1}, {-0.45, 0.25, 1.9}},
  };
  return v;
}

TEST(IncrementalMesher, EqualsFullRemeshAfterIntegrationsInDifferentRegions) {
  Flight flight;
  IncrementalMesher mesher(IncrementalMesher::Params{});
  int kept_total = 0;
  uint32_t seed = 1;
  for (const auto& [eye, target] : views()) {
    flight.fuse(eye, target, seed++);
    const MeshUpdateResult r = mesher.update(flight.volume());
    EXPECT_EQ(r.map_blocks, static_cast<int>(flight.volume().numAllocatedBlocks()));
    EXPECT_EQ(r.blocks_remeshed + r.blocks_kept, r.map_blocks);
    EXPECT_GE(r.blocks_remeshed, r.blocks_changed);
    EXPECT_FALSE(r.rebuilt);
    kept_total += r.blocks_kept;
    const TriangleMesh full = fullMesh(flight.volume());
    const TriangleMesh incremental = mesher.mesh();
    ASSERT_GT(full.triangles.size(), 1000u);
    expectSameTriangles(incremental, full);
    // Blocks kept in allocation order: the very same arrays, vertex numbering included.
    EXPECT_TRUE(incremental.vertices == full.vertices);
    EXPECT_TRUE(incremental.triangles == full.triangles);
  }
  EXPECT_GT(kept_total, 0);  // the later views kept what the earlier ones meshed

  // Nothing changed: nothing is meshed again.
  const MeshUpdateResult idle = mesher.update(flight.volume());
  EXPECT_EQ(idle.blocks_changed, 0);
  EXPECT_EQ(idle.blocks_remeshed, 0);
  EXPECT_EQ(idle.blocks_kept, idle.map_blocks);
}

// A fully observed 6x6x6-block region crossed by a tilted plane: every block has all its
// neighbours, and every cube is observed.
std::unique_ptr<HashedVolume> planeRegion() {
  HashedVolume::Params p;
  p.voxel_size_m = kVoxelM;
  auto region = std::make_unique<HashedVolume>(p);
  HashedVolume& volume = *region;
  const Eigen::Vector3f n = Eigen::Vector3f(0.3f, 1.f, 0.2f).normalized();
  const float offset = n.dot(Eigen::Vector3f::Constant(3.f * kBlockSide * kVoxelM));
  for (int bz = 0; bz < 6; ++bz)
    for (int by = 0; by < 6; ++by)
      for (int bx = 0; bx < 6; ++bx) {
        const BlockIndex b(bx, by, bz);
        VoxelBlock* block = volume.allocateBlock(b);
        block->touched_stamp = 1;
        for (int z = 0; z < kBlockSide; ++z)
          for (int y = 0; y < kBlockSide; ++y)
            for (int x = 0; x < kBlockSide; ++x) {
              const float sdf = n.dot(volume.voxelCentre(b, x, y, z)) - offset;
              Voxel& v = block->voxels[VoxelBlock::linear(x, y, z)];
              v.tsdf = std::clamp(sdf / kTruncationM, -1.f, 1.f);
              v.weight = 1.f;
            }
      }
  return region;
}

// The blocks whose cubes read a voxel of a touched block, from first principles: a cube with
// lower corner in block B reads its 8 corners (local [0, 8]^3), and each corner's normal reads
// one voxel further along each axis.
std::set<std::tuple<int, int, int>> readersOf(const TsdfVolume& volume,
                                              const std::vector<BlockIndex>& touched) {
  std::set<std::tuple<int, int, int>> readers;
  const auto isTouched = [&](const Eigen::Vector3i& g) {
    const BlockIndex b(static_cast<int>(std::floor(g.x() / 8.0)),
                       static_cast<int>(std::floor(g.y() / 8.0)),
                       static_cast<int>(std::floor(g.z() / 8.0)));
    return std::find(touched.begin(), touched.end(), b) != touched.end();
  };
  for (const VoxelBlock* block : volume.allocatedBlocks()) {
    bool reads = false;
    for (int z = 0; z <= kBlockSide && !reads; ++z)
      for (int y = 0; y <= kBlockSide && !reads; ++y)
        for (int x = 0; x <= kBlockSide && !reads; ++x) {
          const Eigen::Vector3i corner = block->index * kBlockSide + Eigen::Vector3i(x, y, z);
          reads = isTouched(corner);
          for (int axis = 0; axis < 3 && !reads; ++axis) {
            const Eigen::Vector3i step = Eigen::Vector3i::Unit(axis);
            reads = isTouched(corner + step) || isTouched(corner - step);
          }
        }
    if (reads) readers.insert({block->index.x(), block->index.y(), block->index.z()});
  }
  return readers;
}

// Moves the surface at one voxel of a block (a corner, edge or face voxel of the block, where
// the neighbours' cubes read it) and stamps the block as the integrator would.
void editVoxel(HashedVolume* volume, const BlockIndex& b, const Eigen::Vector3i& local,
               uint32_t stamp) {
  VoxelBlock* block = volume->findBlock(b);
  ASSERT_NE(block, nullptr);
  Voxel& v = block->voxels[VoxelBlock::linear(local.x(), local.y(), local.z())];
  v.tsdf = v.tsdf < 0.f ? 0.3f : -0.3f;
  block->touched_stamp = stamp;
}

TEST(IncrementalMesher, RemeshesOnlyTouchedBlocksAndTheNeighboursReadingThem) {
  std::unique_ptr<HashedVolume> region = planeRegion();
  HashedVolume& volume = *region;
  IncrementalMesher mesher(IncrementalMesher::Params{});
  const MeshUpdateResult first = mesher.update(volume);
  EXPECT_EQ(first.blocks_remeshed, 216);
  EXPECT_EQ(first.blocks_kept, 0);

  // One interior block: itself, the 7 whose cubes reach into it from below, and 12 more whose
  // normals read its first voxel layer.
  struct Case {
    std::vector<BlockIndex> blocks;
    std::vector<Eigen::Vector3i> voxels;  // edited voxel per block
  };
  const std::vector<Case> cases = {
      {{BlockIndex(3, 3, 3)}, {Eigen::Vector3i(0, 0, 0)}},
      {{BlockIndex(2, 3, 2)}, {Eigen::Vector3i(7, 7, 7)}},
      {{BlockIndex(1, 1, 1), BlockIndex(4, 4, 4)}, {Eigen::Vector3i(0, 4, 7), Eigen::Vector3i(4, 0, 4)}},
      {{BlockIndex(2, 2, 2), BlockIndex(3, 2, 2)}, {Eigen::Vector3i(7, 3, 3), Eigen::Vector3i(0, 3, 3)}},
      {{BlockIndex(0, 0, 0), BlockIndex(5, 5, 5), BlockIndex(5, 0, 2)},
       {Eigen::Vector3i(0, 0, 0), Eigen::Vector3i(7, 7, 7), Eigen::Vector3i(7, 0, 3)}},
  };
  uint32_t stamp = 2;
  for (const Case& c : cases) {
    for (size_t i = 0; i < c.blocks.size(); ++i) editVoxel(&volume, c.blocks[i], c.voxels[i], stamp);
    ++stamp;
    const MeshUpdateResult r = mesher.update(volume);
    const size_t expected = readersOf(volume, c.blocks).size();
    EXPECT_EQ(r.blocks_changed, static_cast<int>(c.blocks.size()));
    EXPECT_EQ(r.blocks_remeshed, static_cast<int>(expected));
    EXPECT_EQ(r.blocks_kept, 216 - static_cast<int>(expected));
    expectSameTriangles(mesher.mesh(), fullMesh(volume));
  }
  EXPECT_EQ(readersOf(volume, {BlockIndex(3, 3, 3)}).size(), 20u);  // the count named above
}

TEST(IncrementalMesher, NewNeighbourBlocksRemeshTheBlocksBesideThem) {
  // A block appearing next to meshed ones gives their border cubes the far corners they lacked.
  const std::unique_ptr<HashedVolume> full = planeRegion();
  HashedVolume::Params p;
  p.voxel_size_m = kVoxelM;
  HashedVolume growing(p);
  IncrementalMesher mesher(IncrementalMesher::Params{});
  int step = 0;
  for (const VoxelBlock* block : full->allocatedBlocks()) {
    VoxelBlock* copy = growing.allocateBlock(block->index);
    copy->voxels = block->voxels;
    copy->touched_stamp = 1;
    if (++step % 37 != 0) continue;
    mesher.update(growing);
    expectSameTriangles(mesher.mesh(), fullMesh(growing));
  }
  mesher.update(growing);
  expectSameTriangles(mesher.mesh(), fullMesh(growing));
}

TEST(IncrementalMesher, CollectedCopiesMeshLaterWhileTheVolumeChanges) {
  Flight flight;
  IncrementalMesher mesher(IncrementalMesher::Params{});
  MeshChangeTracker tracker;
  MeshDelta delta;
  uint32_t seed = 10;
  TriangleMesh expected;
  for (size_t i = 0; i < views().size(); ++i) {
    flight.fuse(views()[i].first, views()[i].second, seed++);
    tracker.collect(flight.volume(), /*copy=*/true, &delta);
    expected = fullMesh(flight.volume());
    if (i % 2 == 0) continue;  // left pending: the next collect merges into it
    // The writer goes on before the mesher gets to the delta.
    flight.fuse(views()[i].first + Eigen::Vector3d(0.05, 0.0, 0.0), views()[i].second, seed++);
    const MeshUpdateResult r = mesher.apply(&delta);
    EXPECT_TRUE(delta.empty());
    EXPECT_EQ(r.blocks_remeshed + r.blocks_kept, r.map_blocks);
    expectSameTriangles(mesher.mesh(), expected);
    tracker.collect(flight.volume(), /*copy=*/true, &delta);  // what the extra frame changed
    expected = fullMesh(flight.volume());
  }
  mesher.apply(&delta);
  expectSameTriangles(mesher.mesh(), expected);
}

TEST(IncrementalMesher, ThreadsDoNotChangeTheMesh) {
  Flight flight;
  IncrementalMesher serial(IncrementalMesher::Params{}), threaded(IncrementalMesher::Params{});
  uint32_t seed = 20;
  for (const auto& [eye, target] : views()) {
    flight.fuse(eye, target, seed++);
    serial.update(flight.volume(), /*parallel=*/false);
    threaded.update(flight.volume(), /*parallel=*/true);
    const TriangleMesh a = serial.mesh(), b = threaded.mesh();
    EXPECT_TRUE(a.vertices == b.vertices);
    EXPECT_TRUE(a.normals == b.normals);
    EXPECT_TRUE(a.triangles == b.triangles);
  }
}

TEST(IncrementalMesher, AClearedVolumeIsMeshedAgainFromScratch) {
  Flight flight;
  IncrementalMesher mesher(IncrementalMesher::Params{});
  flight.fuse(views()[0].first, views()[0].second, 30);
  mesher.update(flight.volume());
  flight.volume().clear();
  flight.fuse(views()[1].first, views()[1].second, 31);
  const MeshUpdateResult r = mesher.update(flight.volume());
  EXPECT_TRUE(r.rebuilt);
  EXPECT_EQ(r.blocks_kept, 0);
  EXPECT_EQ(r.blocks_remeshed, r.map_blocks);
  expectSameTriangles(mesher.mesh(), fullMesh(flight.volume()));
}

TEST(IncrementalMesher, ReadOffsetsAreTheBlocksACubeReads) {
  // The offsets the tracker uses, against the voxel-level derivation for one block.
  const auto readers = readersOf(*planeRegion(), {BlockIndex(3, 3, 3)});
  std::set<std::tuple<int, int, int>> from_offsets;
  for (const BlockIndex& o : meshReadOffsets()) {
    const BlockIndex b = BlockIndex(3, 3, 3) - o;
    from_offsets.insert({b.x(), b.y(), b.z()});
  }
  EXPECT_EQ(readers, from_offsets);
}

TEST(IncrementalMesher, ParamsValidate) {
  IncrementalMesher::Params p;
  EXPECT_TRUE(p.validate().ok());
  p.min_weight = 0.f;
  EXPECT_FALSE(p.validate().ok());
}

}  // namespace
}  // namespace kinfly
