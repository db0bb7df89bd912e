// Stage 8: marching cubes (Lorensen & Cline 1987) over the allocated blocks of a TSDF volume.
//
// The case table is generated once at start-up instead of transcribing the classic
// edgeTable/triTable of Lorensen and Bourke. The classic table resolves each ambiguous face by
// case number, so a face shared by two cubes can be split differently on its two sides and leave
// a crack. Here every cube face is cut into iso-line segments by one rule that looks only at that
// face's four corners (an ambiguous face always keeps its two inside corners apart), the segments
// are chained into closed loops and each loop is fanned into triangles. Two cubes that share a
// face therefore share its segments, traversed in opposite directions, which makes the mesh of a
// closed surface watertight and consistently oriented by construction; loops are triangulated
// without diagonals lying in a cube face, so no edge is shared by more than two triangles
// (tests/engine/test_marching_cubes.cpp checks all of this on a random field that exercises all
// 256 cases).
#include "kinfly/mesh/marching_cubes.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <cmath>
#include <cstdint>

#include "block_mesh.h"
#include "kinfly/volume/voxel_reader.h"

namespace kinfly {
namespace {

// ---- Cube topology -------------------------------------------------------------------------
// Corner c sits at (c & 1, (c >> 1) & 1, (c >> 2) & 1) in cube units; a case is the bit mask of
// the corners inside the surface (TSDF < 0).
Eigen::Vector3f cornerPos(int c) {
  return Eigen::Vector3f(static_cast<float>(c & 1), static_cast<float>((c >> 1) & 1),
                         static_cast<float>((c >> 2) & 1));
}

struct CubeEdge {
  int lo;    // corner with the smaller coordinate along `axis`
  int hi;    // lo + unit step along `axis`
  int axis;  // 0 x, 1 y, 2 z
};

constexpr int kCubeEdges = 12;
constexpr int kMaxCaseIndices = 36;  // at most 12 triangles per case (checked at generation)

struct CaseTable {
  std::array<CubeEdge, kCubeEdges> edges;
  // Triangles as triples of cube-edge indices, counter-clockwise seen from outside (TSDF > 0),
  // terminated by -1.
  std::array<std::array<int8_t, kMaxCaseIndices + 1>, 256> triangles;
};

int edgeBetween(const std::array<CubeEdge, kCubeEdges>& edges, int a, int b) {
  for (int e = 0; e < kCubeEdges; ++e) {
    if ((edges[e].lo == a && edges[e].hi == b) || (edges[e].lo == b && edges[e].hi == a)) return e;
  }
  assert(false && "corners are not adjacent");
  return -1;
}

// A closed iso-line around the cube: the crossed cube edges in traversal order.
struct Loop {
  std::array<int, kCubeEdges> edge;
  int len = 0;
};

bool shareFace(const CubeEdge& a, const CubeEdge& b) {
  for (int axis = 0; axis < 3; ++axis) {
    const int bit = 1 << axis;
    const int side = a.lo & bit;
    if ((a.hi & bit) == side && (b.lo & bit) == side && (b.hi & bit) == side) return true;
  }
  return false;
}

// Triangulates a loop (keeping its orientation) so that no inner diagonal joins two vertices on
// the same cube face. Such a diagonal would lie in the face, where the neighbouring cube may
// place the same diagonal, making an edge shared by four triangles. A plain fan hits this when
// a loop crosses an ambiguous face twice. Dynamic programming over sub-polygons (loops have at
// most 12 vertices). Returns false if no such triangulation exists.
bool triangulateLoop(const std::array<CubeEdge, kCubeEdges>& edges, const Loop& loop,
                     std::array<int8_t, kMaxCaseIndices + 1>* out, int* written) {
  const int n = loop.len;
  const auto allowed = [&](int i, int j) {
    const int d = j - i;
    return d == 1 || d == n - 1 || !shareFace(edges[loop.edge[i]], edges[loop.edge[j]]);
  };
  // split[i][j]: apex k of the triangle on chord (i, j), 0 if sub-polygon i..j cannot be split.
  std::array<std::array<int, kCubeEdges>, kCubeEdges> split{};
  for (int span = 2; span < n; ++span) {
    for (int i = 0; i + span < n; ++i) {
      const int j = i + span;
      for (int k = i + 1; k < j && split[i][j] == 0; ++k) {
        const bool left = k == i + 1 || split[i][k] != 0;
        const bool right = j == k + 1 || split[k][j] != 0;
        if (left && right && allowed(i, k) && allowed(k, j)) split[i][j] = k;
      }
    }
  }
  if (n < 3 || split[0][n - 1] == 0) return false;
  std::array<std::array<int, 2>, kCubeEdges> stack;
  int top = 0;
  stack[top++] = {0, n - 1};
  while (top > 0) {
    const auto [i, j] = stack[--top];
    const int k = split[i][j];
    assert(*written + 3 <= kMaxCaseIndices);
    (*out)[(*written)++] = static_cast<int8_t>(loop.edge[i]);
    (*out)[(*written)++] = static_cast<int8_t>(loop.edge[k]);
    (*out)[(*written)++] = static_cast<int8_t>(loop.edge[j]);
    if (k > i + 1) stack[top++] = {i, k};
    if (j > k + 1) stack[top++] = {k, j};
  }
  return true;
}

CaseTable buildCaseTable() {
  CaseTable table{};
  int n = 0;
  for (int axis = 0; axis < 3; ++axis) {
    for (int c = 0; c < 8; ++c) {
      if (!(c & (1 << axis))) table.edges[n++] = {c, c | (1 << axis), axis};
    }
  }

  // Faces: corners in cyclic order around the face, and the outward normal of the cube.
  struct Face {
    std::array<int, 4> corners;
    Eigen::Vector3f outward;
  };
  std::array<Face, 6> faces;
  for (int axis = 0; axis < 3; ++axis) {
    const int u = (axis + 1) % 3;
    const int w = (axis + 2) % 3;
    for (int side = 0; side < 2; ++side) {
      const int base = side << axis;
      Face& f = faces[axis * 2 + side];
      f.corners = {base, base | (1 << u), base | (1 << u) | (1 << w), base | (1 << w)};
      f.outward = Eigen::Vector3f::Zero();
      f.outward[axis] = side ? 1.f : -1.f;
    }
  }

  const auto edgeMid = [&](int e) -> Eigen::Vector3f {
    return 0.5f * (cornerPos(table.edges[e].lo) + cornerPos(table.edges[e].hi));
  };

  for (int mask = 0; mask < 256; ++mask) {
    const auto inside = [mask](int c) { return (mask >> c) & 1; };
    // next_edge[e]: the iso-line leaves cube edge e towards next_edge[e] (-1: e not crossed).
    std::array<int, kCubeEdges> next_edge;
    next_edge.fill(-1);

    for (const Face& f : faces) {
      std::array<int, 4> face_edges;  // face_edges[k] joins corners k and k+1
      int crossings = 0;
      for (int k = 0; k < 4; ++k) {
        const int a = f.corners[k];
        const int b = f.corners[(k + 1) % 4];
        face_edges[k] = edgeBetween(table.edges, a, b);
        crossings += inside(a) != inside(b);
      }
      if (crossings == 0) continue;

      // Segments as (edge, edge, direction from inside to outside within the face).
      struct Segment { int a, b; Eigen::Vector3f in_to_out; };
      std::array<Segment, 2> segments;
      int num_segments = 0;
      const auto cutCorner = [&](int k) {  // segment around corner k, between its two edges
        const int c = f.corners[k];
        const int ea = face_edges[(k + 3) % 4];
        const int eb = face_edges[k];
        const Eigen::Vector3f mid = 0.5f * (edgeMid(ea) + edgeMid(eb));
        const Eigen::Vector3f away = mid - cornerPos(c);
        segments[num_segments++] = {ea, eb, inside(c) ? away : Eigen::Vector3f(-away)};
      };
      if (crossings == 4) {
        // Ambiguous face: inside corners alternate; cut each inside corner off on its own.
        for (int k = 0; k < 4; ++k) {
          if (inside(f.corners[k])) cutCorner(k);
        }
      } else {
        int sign_changes[2];
        int found = 0;
        for (int k = 0; k < 4; ++k) {
          if (inside(f.corners[k]) != inside(f.corners[(k + 1) % 4])) sign_changes[found++] = k;
        }
        if ((sign_changes[0] + 1) % 4 == sign_changes[1] ||
            (sign_changes[1] + 1) % 4 == sign_changes[0]) {
          // Adjacent edges: one corner is cut off, the one they share.
          const int k = (sign_changes[0] + 1) % 4 == sign_changes[1] ? sign_changes[1]
                                                                      : sign_changes[0];
          cutCorner(k);
        } else {
          // Opposite edges: the face splits into an inside half and an outside half.
          Eigen::Vector3f in_sum = Eigen::Vector3f::Zero(), out_sum = Eigen::Vector3f::Zero();
          for (int c : f.corners) (inside(c) ? in_sum : out_sum) += cornerPos(c);
          segments[num_segments++] = {face_edges[sign_changes[0]], face_edges[sign_changes[1]],
                                      out_sum - in_sum};
        }
      }

      // Orient each segment so that, seen from outside the surface, the surface patch inside
      // the cube lies to its left: direction = in_to_out x outward_face_normal.
      for (int s = 0; s < num_segments; ++s) {
        const Segment& seg = segments[s];
        const Eigen::Vector3f dir = seg.in_to_out.cross(f.outward);
        const bool forward = (edgeMid(seg.b) - edgeMid(seg.a)).dot(dir) > 0.f;
        const int from = forward ? seg.a : seg.b;
        const int to = forward ? seg.b : seg.a;
        assert(next_edge[from] == -1);
        next_edge[from] = to;
      }
    }

    // Chain segments into closed loops and triangulate each loop.
    int written = 0;
    std::array<bool, kCubeEdges> used{};
    for (int start = 0; start < kCubeEdges; ++start) {
      if (next_edge[start] < 0 || used[start]) continue;
      Loop loop;
      for (int e = start; !used[e]; e = next_edge[e]) {
        used[e] = true;
        loop.edge[loop.len++] = e;
      }
      // Every loop of all 256 cases can be split this way (checked when the table was written:
      // the assert guards edits to the rules above).
      const bool split = triangulateLoop(table.edges, loop, &table.triangles[mask], &written);
      assert(split);
      (void)split;
    }
    table.triangles[mask][written] = -1;
  }
  return table;
}

const CaseTable& caseTable() {
  static const CaseTable table = buildCaseTable();
  return table;
}

// ---- Volume access --------------------------------------------------------------------------
// TSDF gradient at a voxel by central differences (one-sided next to unobserved voxels), in
// TSDF units per voxel. Zero where no neighbour along an axis is observed.
Eigen::Vector3f voxelGradient(VoxelReader* reader, const Eigen::Vector3i& g, float centre) {
  Eigen::Vector3f grad = Eigen::Vector3f::Zero();
  for (int axis = 0; axis < 3; ++axis) {
    Eigen::Vector3i step = Eigen::Vector3i::Zero();
    step[axis] = 1;
    const Eigen::Vector3i p = g + step, m = g - step;
    const Voxel* plus = reader->voxel(p.x(), p.y(), p.z());
    const Voxel* minus = reader->voxel(m.x(), m.y(), m.z());
    const bool has_plus = plus != nullptr && plus->weight > 0.f;
    const bool has_minus = minus != nullptr && minus->weight > 0.f;
    if (has_plus && has_minus) {
      grad[axis] = 0.5f * (plus->tsdf - minus->tsdf);
    } else if (has_plus) {
      grad[axis] = plus->tsdf - centre;
    } else if (has_minus) {
      grad[axis] = centre - minus->tsdf;
    }
  }
  return grad;
}

// One block's voxels plus the first layer of its +x/+y/+z neighbours, so every cube whose lower
// corner lies in the block can be read locally.
int sampleIndex(int x, int y, int z) { return (z * detail::kCornerSpan + y) * detail::kCornerSpan + x; }

void gatherBlock(const TsdfVolume& volume, const VoxelBlock& block, detail::BlockMesherScratch* s) {
  std::array<const VoxelBlock*, 8> neighbours;  // bit 0: +x, bit 1: +y, bit 2: +z
  for (int n = 0; n < 8; ++n) {
    const BlockIndex offset(n & 1, (n >> 1) & 1, (n >> 2) & 1);
    neighbours[n] = n == 0 ? &block : volume.findBlock(block.index + offset);
  }
  for (int z = 0; z < detail::kCornerSpan; ++z) {
    for (int y = 0; y < detail::kCornerSpan; ++y) {
      for (int x = 0; x < detail::kCornerSpan; ++x) {
        const int n = (x / kBlockSide) | ((y / kBlockSide) << 1) | ((z / kBlockSide) << 2);
        const int i = sampleIndex(x, y, z);
        const VoxelBlock* b = neighbours[n];
        if (b == nullptr) {
          s->tsdf[i] = 1.f;
          s->weight[i] = -1.f;
          continue;
        }
        const Voxel& v = b->voxels[VoxelBlock::linear(x % kBlockSide, y % kBlockSide,
                                                      z % kBlockSide)];
        s->tsdf[i] = v.tsdf;
        s->weight[i] = v.weight;
      }
    }
  }
}

}  // namespace

Status MarchingCubes::Params::validate() const {
  if (!(min_weight > 0.f)) return Status::error("min_weight must be > 0");
  return {};
}

MarchingCubes::MarchingCubes(const Params& params) : params_(params) {}

TriangleMesh MarchingCubes::extract(const TsdfVolume& volume) const {
  TriangleMesh mesh;
  detail::MeshAssembler assembler;
  assembler.begin(&mesh);
  detail::BlockMesherScratch scratch;
  detail::BlockMesh piece;
  for (const VoxelBlock* block : volume.allocatedBlocks()) {
    detail::meshBlock(volume, *block, params_.min_weight, &scratch, &piece);
    assembler.append(piece);
  }
  return mesh;
}

namespace detail {

namespace {

// A zero crossing is a surface only where the TSDF changes between the two voxels by no more
// than the truncation band (1 in TSDF units). A surface seen at angle theta from its normal
// changes the projective distance by at most a voxel over cos(theta) per voxel: within the band
// wherever cos(theta) >= voxel / truncation, i.e. up to 75 degrees at four voxels. A larger step
// is a depth discontinuity's: behind a foreground edge a voxel inside the edge's band borders one
// that the pixels beside the silhouette saw as free space (1), and the crossing between them is
// the classic TSDF "curtain", up to a band deep behind the silhouette. A triangle with a vertex on
// such a crossing is left out; the decision is the edge's alone, so the neighbouring cube that
// shares the edge leaves out its side too and the mesh stays consistent. On Replica office0 the
// curtains were 5 % of the mesh's vertices; what goes with them are surfaces seen only more
// obliquely than that (docs/engine.md, "Depth discontinuities").
constexpr float kMaxSurfaceStep = 1.f;

bool isDiscontinuity(const CubeEdge& edge, const std::array<float, 8>& corner_tsdf) {
  return std::abs(corner_tsdf[edge.lo] - corner_tsdf[edge.hi]) > kMaxSurfaceStep;
}

}  // namespace

void meshBlock(const TsdfVolume& volume, const VoxelBlock& block, float min_weight,
               BlockMesherScratch* scratch, BlockMesh* out) {
  const CaseTable& table = caseTable();
  const float voxel_m = volume.voxelSizeM();
  out->clear();
  out->index = block.index;
  gatherBlock(volume, block, scratch);
  if (++scratch->stamp == 0) {  // wrapped: forget every edge once
    std::fill(scratch->edge_stamp.begin(), scratch->edge_stamp.end(), 0u);
    scratch->stamp = 1;
  }
  VoxelReader reader(volume);
  const Eigen::Vector3i block_origin = block.index * kBlockSide;

  // Returns the block's vertex on cube edge `e` of the cube whose lower corner is local voxel
  // `cube`, creating it on first use. A vertex depends only on the voxels at and around its
  // edge, so a neighbouring block that makes the same vertex makes it bit for bit the same.
  const auto vertexOn = [&](const Eigen::Vector3i& cube, int e,
                            const std::array<float, 8>& corner_tsdf) {
    const CubeEdge& edge = table.edges[e];
    const Eigen::Vector3i local = cube + cornerPos(edge.lo).cast<int>();
    const int id = localEdgeId(local, edge.axis);
    if (scratch->edge_stamp[id] == scratch->stamp) return scratch->vertex_of_edge[id];

    const Eigen::Vector3i g0 = block_origin + local;
    Eigen::Vector3i g1 = g0;
    g1[edge.axis] += 1;
    const float f0 = corner_tsdf[edge.lo];
    const float f1 = corner_tsdf[edge.hi];
    const float t = f0 / (f0 - f1);  // f0, f1 have opposite signs, so t is in [0, 1]
    const Eigen::Vector3f p0 = g0.cast<float>() * voxel_m;
    const Eigen::Vector3f p1 = g1.cast<float>() * voxel_m;

    Eigen::Vector3f normal = (1.f - t) * voxelGradient(&reader, g0, f0) +
                             t * voxelGradient(&reader, g1, f1);
    if (normal.squaredNorm() > 0.f) {
      normal.normalize();
    } else {
      // No usable neighbours: the edge itself says which way the TSDF grows.
      normal = Eigen::Vector3f::Zero();
      normal[edge.axis] = f1 > f0 ? 1.f : -1.f;
    }
    const int vertex = static_cast<int>(out->vertices.size());
    out->vertices.push_back(p0 + t * (p1 - p0));
    out->normals.push_back(normal);
    out->edges.push_back(static_cast<uint16_t>(id));
    scratch->edge_stamp[id] = scratch->stamp;
    scratch->vertex_of_edge[id] = vertex;
    return vertex;
  };

  for (int z = 0; z < kBlockSide; ++z) {
    for (int y = 0; y < kBlockSide; ++y) {
      for (int x = 0; x < kBlockSide; ++x) {
        std::array<float, 8> corner_tsdf;
        int mask = 0;
        bool observed = true;
        for (int c = 0; c < 8; ++c) {
          const int i = sampleIndex(x + (c & 1), y + ((c >> 1) & 1), z + ((c >> 2) & 1));
          corner_tsdf[c] = scratch->tsdf[i];
          observed = observed && scratch->weight[i] >= min_weight;
          mask |= (scratch->tsdf[i] < 0.f) << c;
        }
        if (mask == 0 || mask == 255 || !observed) continue;

        const Eigen::Vector3i cube(x, y, z);
        const auto& tris = table.triangles[mask];
        for (int k = 0; tris[k] >= 0; k += 3) {
          if (isDiscontinuity(table.edges[tris[k]], corner_tsdf) ||
              isDiscontinuity(table.edges[tris[k + 1]], corner_tsdf) ||
              isDiscontinuity(table.edges[tris[k + 2]], corner_tsdf))
            continue;
          out->triangles.emplace_back(vertexOn(cube, tris[k], corner_tsdf),
                                      vertexOn(cube, tris[k + 1], corner_tsdf),
                                      vertexOn(cube, tris[k + 2], corner_tsdf));
        }
      }
    }
  }
}

void MeshAssembler::begin(TriangleMesh* mesh) {
  mesh_ = mesh;
  if (slots_.empty()) slots_.resize(1024);
  std::fill(slots_.begin(), slots_.end(), Slot());
  used_ = 0;
}

void MeshAssembler::append(const BlockMesh& piece) {
  TriangleMesh& mesh = *mesh_;
  const Eigen::Vector3i block_origin = piece.index * kBlockSide;
  remap_.resize(piece.vertices.size());
  for (size_t k = 0; k < piece.vertices.size(); ++k) {
    const int next = static_cast<int>(mesh.vertices.size());
    const int id = piece.edges[k];
    if (edgeOnBlockBorder(id)) {
      const int existing = findOrAdd(block_origin + edgeLower(id), edgeAxis(id), next);
      if (existing >= 0) {
        remap_[k] = existing;
        continue;
      }
    }
    remap_[k] = next;
    mesh.vertices.push_back(piece.vertices[k]);
    mesh.normals.push_back(piece.normals[k]);
  }
  for (const Eigen::Vector3i& t : piece.triangles)
    mesh.triangles.emplace_back(remap_[t.x()], remap_[t.y()], remap_[t.z()]);
}

int MeshAssembler::findOrAdd(const Eigen::Vector3i& lower, int axis, int vertex) {
  if (2 * (used_ + 1) > slots_.size()) grow();
  const size_t mask = slots_.size() - 1;
  for (size_t h = (hashBlockIndex(lower) * 3u + static_cast<size_t>(axis)) & mask;;
       h = (h + 1) & mask) {
    Slot& slot = slots_[h];
    if (slot.axis < 0) {
      slot = {lower, axis, vertex};
      ++used_;
      return -1;
    }
    if (slot.axis == axis && slot.lower == lower) return slot.vertex;
  }
}

void MeshAssembler::grow() {
  std::vector<Slot> old(2 * slots_.size());
  old.swap(slots_);
  used_ = 0;
  for (const Slot& s : old) {
    if (s.axis >= 0) findOrAdd(s.lower, s.axis, s.vertex);
  }
}

}  // namespace detail
}  // namespace kinfly
