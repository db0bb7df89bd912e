#include "kinfly/sim/scene.h"

#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <initializer_list>
#include <iterator>
#include <map>

#include "kinfly/sim/mesh_file.h"

namespace kinfly::sim {

namespace {

// A flat face with its corners in order around it, as a fan of triangles over its own vertices
// (so the normals stay the face's), wound counter-clockwise seen from `facing`, the side in free
// space.
void addFace(TriangleMesh* mesh, std::initializer_list<Eigen::Vector3f> corners,
             const Eigen::Vector3f& facing) {
  const Eigen::Vector3f* c = corners.begin();
  Eigen::Vector3f normal = (c[1] - c[0]).cross(c[2] - c[0]).normalized();
  const bool flip = normal.dot(facing) < 0.0f;
  if (flip) normal = -normal;
  const int base = static_cast<int>(mesh->vertices.size());
  for (const Eigen::Vector3f& v : corners) {
    mesh->vertices.push_back(v);
    mesh->normals.push_back(normal);
  }
  for (int i = 1; i + 1 < static_cast<int>(corners.size()); ++i) {
    mesh->triangles.emplace_back(base, base + (flip ? i + 1 : i), base + (flip ? i : i + 1));
  }
}

void addQuad(TriangleMesh* mesh, const Eigen::Vector3f& a, const Eigen::Vector3f& b,
             const Eigen::Vector3f& c, const Eigen::Vector3f& d, const Eigen::Vector3f& facing) {
  addFace(mesh, {a, b, c, d}, facing);
}

void addTriangle(TriangleMesh* mesh, const Eigen::Vector3f& a, const Eigen::Vector3f& b,
                 const Eigen::Vector3f& c, const Eigen::Vector3f& facing) {
  addFace(mesh, {a, b, c}, facing);
}

// A ramp on the floor rising from x = x0 (floor height) to x = x1 (height h above the floor),
// across y0 < y1: a sloped face, a vertical back and two triangular sides. Sloped surfaces hold
// the odometry's height where walls (vertical) and a floor seen edge-on (a landed drone's camera
// is a hand's width above it) do not.
void addRamp(TriangleMesh* mesh, float x0, float x1, float y0, float y1, float h) {
  // The surface z = -h (x - x0) / (x1 - x0); its upward normal (z down).
  const Eigen::Vector3f slope_normal = Eigen::Vector3f(-h / (x1 - x0), 0.0f, -1.0f).normalized();
  addQuad(mesh, {x0, y0, 0.0f}, {x0, y1, 0.0f}, {x1, y1, -h}, {x1, y0, -h}, slope_normal);
  addQuad(mesh, {x1, y0, 0.0f}, {x1, y1, 0.0f}, {x1, y1, -h}, {x1, y0, -h},
          (x1 > x0 ? 1.0f : -1.0f) * Eigen::Vector3f::UnitX());
  addTriangle(mesh, {x0, y0, 0.0f}, {x1, y0, 0.0f}, {x1, y0, -h}, -Eigen::Vector3f::UnitY());
  addTriangle(mesh, {x0, y1, 0.0f}, {x1, y1, 0.0f}, {x1, y1, -h}, Eigen::Vector3f::UnitY());
}

// An axis-aligned box from lo to hi; inward: its faces look into it (a room), else out of it.
void addBox(TriangleMesh* mesh, const Eigen::Vector3f& lo, const Eigen::Vector3f& hi,
            bool inward = false) {
  const auto corner = [&](int i) {
    return Eigen::Vector3f((i & 1) ? hi.x() : lo.x(), (i & 2) ? hi.y() : lo.y(),
                           (i & 4) ? hi.z() : lo.z());
  };
  // Each face's corners in order around it (bit 0: x, 1: y, 2: z at hi), and its outward axis.
  struct Face {
    int corners[4];
    Eigen::Vector3f outward;
  };
  const Face faces[6] = {
      {{0, 2, 6, 4}, -Eigen::Vector3f::UnitX()}, {{1, 3, 7, 5}, Eigen::Vector3f::UnitX()},
      {{0, 1, 5, 4}, -Eigen::Vector3f::UnitY()}, {{2, 3, 7, 6}, Eigen::Vector3f::UnitY()},
      {{0, 1, 3, 2}, -Eigen::Vector3f::UnitZ()}, {{4, 5, 7, 6}, Eigen::Vector3f::UnitZ()},
  };
  for (const Face& face : faces) {
    addQuad(mesh, corner(face.corners[0]), corner(face.corners[1]), corner(face.corners[2]),
            corner(face.corners[3]), inward ? Eigen::Vector3f(-face.outward) : face.outward);
  }
}

// A vertical cylinder of radius r between heights z_top (z down: the smaller) and z_bottom, as a
// prism of `sides` faces without caps (pillars stand from floor to ceiling).
void addPillar(TriangleMesh* mesh, const Eigen::Vector2f& centre, float radius, float z_top,
               float z_bottom, int sides = 16) {
  for (int i = 0; i < sides; ++i) {
    const float a0 = 2.0f * static_cast<float>(M_PI) * static_cast<float>(i) / static_cast<float>(sides);
    const float a1 = 2.0f * static_cast<float>(M_PI) * static_cast<float>(i + 1) / static_cast<float>(sides);
    const Eigen::Vector2f p0 = centre + radius * Eigen::Vector2f(std::cos(a0), std::sin(a0));
    const Eigen::Vector2f p1 = centre + radius * Eigen::Vector2f(std::cos(a1), std::sin(a1));
    const Eigen::Vector2f mid = 0.5f * (p0 + p1) - centre;
    addQuad(mesh, {p0.x(), p0.y(), z_bottom}, {p1.x(), p1.y(), z_bottom}, {p1.x(), p1.y(), z_top},
            {p0.x(), p0.y(), z_top}, {mid.x(), mid.y(), 0.0f});
  }
}

void addFloor(Scene* scene, const Eigen::Vector2f& lo, const Eigen::Vector2f& hi) {
  // Seen from above: -z, z down.
  addQuad(&scene->mesh, {lo.x(), lo.y(), 0.0f}, {lo.x(), hi.y(), 0.0f}, {hi.x(), hi.y(), 0.0f},
          {hi.x(), lo.y(), 0.0f}, -Eigen::Vector3f::UnitZ());
  scene->floor_triangles = static_cast<int>(scene->mesh.triangles.size());
  scene->floor_z_m = 0.0;
}

// The walls and ceiling of a box room over a floor already added (its floor face left out).
void addRoomShell(TriangleMesh* mesh, const Eigen::Vector3f& lo, const Eigen::Vector3f& hi) {
  TriangleMesh shell;
  addBox(&shell, lo, hi, /*inward=*/true);
  // addBox's last face is +z, the floor: the room's own floor is the Scene's.
  const int kept_vertices = static_cast<int>(shell.vertices.size()) - 4;
  const int base = static_cast<int>(mesh->vertices.size());
  for (int i = 0; i < kept_vertices; ++i) {
    mesh->vertices.push_back(shell.vertices[i]);
    mesh->normals.push_back(shell.normals[i]);
  }
  for (size_t t = 0; t + 2 < shell.triangles.size(); ++t) {
    mesh->triangles.push_back(shell.triangles[t] + Eigen::Vector3i::Constant(base));
  }
}

}  // namespace

StatusOr<Scene> loadMeshScene(const std::string& path, const Eigen::Vector2d& start_xy_m,
                              double start_heading_rad) {
  // Faces within this of horizontal (18 degrees) are the floor's candidates.
  constexpr float kHorizontalCos = 0.95f;
  constexpr double kFloorBandM = 0.01;
  constexpr double kFloorAreaShare = 0.25;
  // A scan's floor is not flat: Replica office0's spans 5 cm.
  constexpr double kFloorToleranceM = 0.03;
  // Beyond this a vertex is no room's in metres (millimetres, or a broken file).
  constexpr float kMaxCoordinateM = 1e4f;
  StatusOr<TriangleMesh> file = readMeshFile(path);
  if (!file.ok()) return file.status();
  TriangleMesh mesh = std::move(file.value());
  // Into the simulator's world (z down): a half turn about x, which keeps the faces' winding.
  for (Eigen::Vector3f& v : mesh.vertices) {
    if (!v.allFinite() || v.cwiseAbs().maxCoeff() > kMaxCoordinateM) {
      return Status::error(path + ": a vertex is not finite or lies beyond 10 km: not a scene in "
                           "metres");
    }
    v = Eigen::Vector3f(v.x(), -v.y(), -v.z());
  }

  // Each face once: its normal twice its area long (as wound) and its height.
  struct Face {
    Eigen::Vector3f cross;
    double z_m;
    bool horizontal;
  };
  std::vector<Face> faces(mesh.triangles.size());
  std::map<long, double> horizontal_area_by_band;
  for (size_t t = 0; t < mesh.triangles.size(); ++t) {
    const Eigen::Vector3i& tri = mesh.triangles[t];
    Face& face = faces[t];
    face.cross = (mesh.vertices[tri[1]] - mesh.vertices[tri[0]])
                     .cross(mesh.vertices[tri[2]] - mesh.vertices[tri[0]]);
    face.z_m = (mesh.vertices[tri[0]].z() + mesh.vertices[tri[1]].z() +
                mesh.vertices[tri[2]].z()) / 3.0;
    const float area2 = face.cross.norm();
    face.horizontal = area2 > 0.0f && std::abs(face.cross.z()) >= kHorizontalCos * area2;
    if (face.horizontal) {
      horizontal_area_by_band[std::lround(std::floor(face.z_m / kFloorBandM))] += 0.5 * area2;
    }
  }
  if (horizontal_area_by_band.empty()) {
    return Status::error(path + ": the mesh has no horizontal face: no floor");
  }
  // The floor: each 1 cm band weighed by the horizontal area within the tolerance of it (a scan's
  // floor spreads over several bands, a flat ceiling sits in one, and often has more area than a
  // furnished floor: office0's 16 against 10 m^2); the lowest band with a quarter of the most,
  // then up to the top of that hill.
  const long reach = std::lround(kFloorToleranceM / kFloorBandM);
  std::map<long, double> weight_by_band;
  double most = 0.0;
  for (const auto& [band, area] : horizontal_area_by_band) {
    double weight = 0.0;
    for (auto it = horizontal_area_by_band.lower_bound(band - reach);
         it != horizontal_area_by_band.end() && it->first <= band + reach; ++it) {
      weight += it->second;
    }
    weight_by_band[band] = weight;
    most = std::max(most, weight);
  }
  // z down: the lowest band has the largest z.
  auto floor_band = weight_by_band.rbegin();
  while (floor_band->second < kFloorAreaShare * most) ++floor_band;
  for (auto up = std::next(floor_band); up != weight_by_band.rend() && up->second >= floor_band->second &&
                                        floor_band->first - up->first <= reach;
       ++up) {
    floor_band = up;
  }
  const double band_mid_m = (static_cast<double>(floor_band->first) + 0.5) * kFloorBandM;
  double floor_area = 0.0, floor_weighted_z = 0.0;
  for (const Face& face : faces) {
    if (face.horizontal && std::abs(face.z_m - band_mid_m) <= kFloorToleranceM) {
      floor_area += face.cross.norm();
      floor_weighted_z += face.cross.norm() * face.z_m;
    }
  }
  Scene scene;
  scene.name = std::filesystem::path(path).stem().string();
  scene.floor_z_m = floor_weighted_z / floor_area;  // the band's own faces: floor_area > 0

  // The floor's faces first (Scene::floor_triangles): every face within the tolerance of it, the
  // slopes of its bumps too. Each vertex's normal is the area-weighted mean of its faces' as the
  // file winds them.
  std::vector<Eigen::Vector3i> floor_faces, other_faces;
  mesh.normals.assign(mesh.vertices.size(), Eigen::Vector3f::Zero());
  for (size_t t = 0; t < mesh.triangles.size(); ++t) {
    const Eigen::Vector3i& tri = mesh.triangles[t];
    bool floor = true;
    for (int k = 0; k < 3; ++k) {
      mesh.normals[tri[k]] += faces[t].cross;
      floor = floor && std::abs(mesh.vertices[tri[k]].z() - scene.floor_z_m) <= kFloorToleranceM;
    }
    (floor ? floor_faces : other_faces).push_back(tri);
  }
  for (Eigen::Vector3f& n : mesh.normals) {
    n = n.squaredNorm() > 0.0f ? Eigen::Vector3f(n.normalized())
                               : Eigen::Vector3f(-Eigen::Vector3f::UnitZ());
  }
  scene.mesh.vertices = std::move(mesh.vertices);
  scene.mesh.normals = std::move(mesh.normals);
  scene.mesh.triangles = std::move(floor_faces);
  scene.floor_triangles = static_cast<int>(scene.mesh.triangles.size());
  scene.mesh.triangles.insert(scene.mesh.triangles.end(), other_faces.begin(), other_faces.end());
  scene.start_xy_m = Eigen::Vector2d(start_xy_m.x(), -start_xy_m.y());
  scene.start_yaw_rad = -start_heading_rad;
  return scene;
}

Scene furnishedRoom() {
  Scene scene;
  scene.name = "room";
  addFloor(&scene, {-3.0f, -2.5f}, {3.0f, 2.5f});
  TriangleMesh& mesh = scene.mesh;
  addRoomShell(&mesh, {-3.0f, -2.5f, -2.7f}, {3.0f, 2.5f, 0.0f});
  // Boxes against and away from the walls, of different heights.
  addBox(&mesh, {2.0f, -2.2f, -0.8f}, {2.8f, -1.4f, 0.0f});
  addBox(&mesh, {2.1f, -1.2f, -0.5f}, {2.7f, -0.6f, 0.0f});
  addBox(&mesh, {-2.8f, 1.4f, -1.2f}, {-1.9f, 2.3f, 0.0f});
  addBox(&mesh, {-0.8f, 1.9f, -0.6f}, {0.4f, 2.4f, 0.0f});
  // Two pillars, floor to ceiling.
  addPillar(&mesh, {1.2f, 0.9f}, 0.2f, -2.7f, 0.0f);
  addPillar(&mesh, {-1.4f, -1.1f}, 0.25f, -2.7f, 0.0f);
  // A table: top 1.2 x 0.8 m at 0.75 m, four legs.
  addBox(&mesh, {-2.7f, -2.2f, -0.78f}, {-1.5f, -1.4f, -0.74f});
  for (const float x : {-2.65f, -1.59f}) {
    for (const float y : {-2.15f, -1.49f}) addBox(&mesh, {x, y, -0.74f}, {x + 0.04f, y + 0.04f, 0.0f});
  }
  // Ramps ahead of the start and behind it, rising toward the walls.
  addRamp(&mesh, 1.9f, 2.9f, -0.4f, 1.2f, 0.6f);
  addRamp(&mesh, -2.0f, -2.9f, -1.0f, 0.8f, 0.5f);
  // Steps up to a platform in the +x, +y corner, each 0.3 m deep and 0.2 m high.
  for (int i = 0; i < 4; ++i) {
    const float x0 = 1.8f + 0.3f * static_cast<float>(i);
    addBox(&mesh, {x0, 1.5f, -0.2f * static_cast<float>(i + 1)}, {3.0f, 2.5f, 0.0f});
  }
  scene.start_xy_m = {0.0, 0.0};
  scene.start_yaw_rad = 0.0;
  return scene;
}

Scene corridor() {
  Scene scene;
  scene.name = "corridor";
  addFloor(&scene, {-2.0f, -1.0f}, {28.0f, 1.0f});
  addRoomShell(&scene.mesh, {-2.0f, -1.0f, -2.5f}, {28.0f, 1.0f, 0.0f});
  scene.start_xy_m = {-1.0, 0.0};
  scene.start_yaw_rad = 0.0;
  return scene;
}

Scene ringCorridor() {
  Scene scene;
  scene.name = "ring";
  addFloor(&scene, {-7.0f, -6.0f}, {7.0f, 6.0f});
  TriangleMesh& mesh = scene.mesh;
  addRoomShell(&mesh, {-7.0f, -6.0f, -2.5f}, {7.0f, 6.0f, 0.0f});
  // The block the corridors run round, floor to ceiling.
  addBox(&mesh, {-4.0f, -3.0f, -2.5f}, {4.0f, 3.0f, 0.0f});
  // Down a corridor its floor, walls and ceiling all run along it, and ICP could not tell motion
  // along it (the corridor scene): partitions stand out from alternate walls every few metres,
  // 0.2 m thick and 0.9 m into the 3 m corridor (2.1 m left beside them, the flight line along
  // its middle 0.6 m from their ends), their faces square to the corridor. Crates between them,
  // of different sizes, keep one stretch from looking like the next. Each is
  // {x0, y0, x1, y1, height}.
  struct Part {
    float x0, y0, x1, y1, h;
  };
  static const Part parts[] = {
      // The first corridor (y in [-6, -3]): partitions, then crates.
      {-3.1f, -6.0f, -2.9f, -5.1f, 2.5f}, {-0.1f, -3.9f, 0.1f, -3.0f, 2.5f},
      {2.9f, -6.0f, 3.1f, -5.1f, 2.5f},
      {-1.8f, -6.0f, -1.0f, -5.5f, 1.2f}, {1.2f, -3.5f, 2.2f, -3.0f, 0.9f},
      // The second (x in [4, 7]). The camera looks +x all the lap, so here it faces the outer
      // wall, 1.5 m off: shallower partitions (0.5 m) on that wall only, closer together, keep
      // one in every view.
      {6.5f, -3.1f, 7.0f, -2.9f, 2.5f}, {6.5f, -1.7f, 7.0f, -1.5f, 1.8f},
      {6.5f, -0.2f, 7.0f, 0.0f, 2.5f}, {6.5f, 1.2f, 7.0f, 1.4f, 2.2f},
      {6.5f, 2.7f, 7.0f, 2.9f, 2.5f},
      {6.7f, -4.2f, 7.0f, -3.6f, 0.8f}, {6.6f, 0.4f, 7.0f, 1.0f, 1.2f},
      // The third (y in [3, 6]).
      {2.4f, 5.1f, 2.6f, 6.0f, 2.5f}, {-0.6f, 3.0f, -0.4f, 3.9f, 2.5f},
      {-3.1f, 5.1f, -2.9f, 6.0f, 2.2f},
      {0.8f, 5.6f, 1.6f, 6.0f, 0.7f}, {-2.3f, 3.0f, -1.3f, 3.4f, 1.4f},
      // The fourth (x in [-7, -4]): the camera faces the block, 1.5 m off; the same there.
      {-4.5f, 2.3f, -4.0f, 2.5f, 2.5f}, {-4.5f, 0.9f, -4.0f, 1.1f, 2.0f},
      {-4.5f, -0.6f, -4.0f, -0.4f, 2.5f}, {-4.5f, -2.0f, -4.0f, -1.8f, 2.2f},
      {-4.4f, -1.4f, -4.0f, -0.9f, 0.6f}, {-4.3f, 1.5f, -4.0f, 2.0f, 1.3f},
  };
  for (const Part& c : parts) addBox(&mesh, {c.x0, c.y0, -c.h}, {c.x1, c.y1, 0.0f});
  // From a camera standing on the ground the floor is too grazing to return, and no crate top
  // is below it: a ramp ahead of the start, rising 0.6 m towards the first partition, shows it
  // which way is up (the room's ramps do the same).
  addRamp(&mesh, -4.6f, -3.1f, -6.0f, -4.9f, 0.6f);
  scene.start_xy_m = {-5.5, -4.5};
  scene.start_yaw_rad = 0.0;
  return scene;
}

// The floor in view from 2.6 m on at flying height; crates and pillars 2.4-3.5 m out give
// structure at that range (test_fusion_pipeline's far hall, flown).
Scene hall() {
  Scene scene;
  scene.name = "hall";
  addFloor(&scene, {-3.6f, -3.6f}, {3.6f, 3.6f});
  TriangleMesh& mesh = scene.mesh;
  addRoomShell(&mesh, {-3.6f, -3.6f, -3.0f}, {3.6f, 3.6f, 0.0f});
  addBox(&mesh, {2.6f, -1.4f, -0.9f}, {3.4f, -0.6f, 0.0f});
  addBox(&mesh, {2.4f, 0.8f, -0.5f}, {3.0f, 1.6f, 0.0f});
  addBox(&mesh, {-1.0f, 2.7f, -1.2f}, {0.0f, 3.5f, 0.0f});
  addBox(&mesh, {1.0f, 2.5f, -0.6f}, {1.6f, 3.1f, 0.0f});
  addBox(&mesh, {-3.5f, -0.5f, -0.7f}, {-2.7f, 0.5f, 0.0f});
  addPillar(&mesh, {-2.6f, 1.8f}, 0.25f, -3.0f, 0.0f);
  addBox(&mesh, {-1.8f, -3.5f, -1.0f}, {-0.8f, -2.8f, 0.0f});
  addBox(&mesh, {0.2f, -3.4f, -0.4f}, {0.8f, -2.6f, 0.0f});
  addPillar(&mesh, {1.5f, -2.7f}, 0.2f, -3.0f, 0.0f);
  scene.start_xy_m = {0.0, 0.0};
  scene.start_yaw_rad = 0.0;
  return scene;
}

const std::vector<std::string>& sceneNames() {
  static const std::vector<std::string> names = {"room", "corridor", "ring", "hall"};
  return names;
}

StatusOr<Scene> makeScene(const std::string& name) {
  if (name == "room") return furnishedRoom();
  if (name == "corridor") return corridor();
  if (name == "ring") return ringCorridor();
  if (name == "hall") return hall();
  std::string known;
  for (const std::string& n : sceneNames()) known += (known.empty() ? "" : ", ") + n;
  return Status::error("scene '" + name + "' is unknown (known: " + known + ")");
}

}  // namespace kinfly::sim
