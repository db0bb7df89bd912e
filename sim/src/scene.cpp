#include "kinfly/sim/scene.h"

#include <CGAL/IO/polygon_soup_io.h>
#include <CGAL/Simple_cartesian.h>

#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <initializer_list>
#include <map>

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
  // Faces within this of horizontal are the floor's candidates: a scan's floor is not flat.
  constexpr float kHorizontalCos = 0.95f;
  constexpr double kFloorBandM = 0.01;
  constexpr double kFloorAreaShare = 0.25;
  // A scan's floor is not flat: Replica office0's spans 5 cm.
  constexpr double kFloorToleranceM = 0.03;
  if (!std::filesystem::is_regular_file(path)) return Status::error(path + ": no such file");
  std::vector<CGAL::Simple_cartesian<double>::Point_3> points;
  std::vector<std::vector<std::size_t>> polygons;
  // CGAL's reader, not Assimp's: Debian 12's Assimp (5.2.5) hangs on a PLY cut short in its
  // header and crashes on one cut short in its faces, where CGAL's says no.
  if (!CGAL::IO::read_polygon_soup(path, points, polygons, CGAL::parameters::verbose(false))) {
    return Status::error(path + ": cannot read a mesh from it (PLY, OBJ, OFF or STL): malformed, "
                         "cut short, or of another format");
  }
  Scene scene;
  scene.name = std::filesystem::path(path).stem().string();
  TriangleMesh read;
  // Into the simulator's world (z down): a half turn about x, which keeps the faces' winding.
  for (const auto& p : points) {
    read.vertices.emplace_back(static_cast<float>(p.x()), static_cast<float>(-p.y()),
                               static_cast<float>(-p.z()));
  }
  for (size_t f = 0; f < polygons.size(); ++f) {
    const std::vector<std::size_t>& polygon = polygons[f];
    for (const std::size_t index : polygon) {
      if (index >= points.size()) {
        return Status::error(path + ": face " + std::to_string(f) + " names vertex " +
                             std::to_string(index) + " of " + std::to_string(points.size()));
      }
    }
    // A polygon as a fan of triangles (a scan's are triangles; others are taken to be convex).
    for (size_t i = 1; i + 1 < polygon.size(); ++i) {
      read.triangles.emplace_back(static_cast<int>(polygon[0]), static_cast<int>(polygon[i]),
                                  static_cast<int>(polygon[i + 1]));
    }
  }
  if (read.triangles.empty()) return Status::error(path + ": the mesh has no triangles");
  for (const Eigen::Vector3f& v : read.vertices) {
    if (!v.allFinite()) return Status::error(path + ": the mesh has a vertex that is not finite");
  }

  // The floor: the lowest 1 cm band of heights whose horizontal faces have a quarter of the area
  // of the band with the most (a ceiling may have more; stray faces below a scan's floor less).
  std::vector<Eigen::Vector3f> face_normals(read.triangles.size());
  std::map<long, double> area_by_band;
  for (size_t t = 0; t < read.triangles.size(); ++t) {
    const Eigen::Vector3i& tri = read.triangles[t];
    const Eigen::Vector3f cross = (read.vertices[tri[1]] - read.vertices[tri[0]])
                                      .cross(read.vertices[tri[2]] - read.vertices[tri[0]]);
    face_normals[t] = cross;
    const float area2 = cross.norm();
    if (area2 <= 0.0f || std::abs(cross.z()) < kHorizontalCos * area2) continue;
    const double z = (read.vertices[tri[0]].z() + read.vertices[tri[1]].z() +
                      read.vertices[tri[2]].z()) / 3.0;
    area_by_band[std::lround(std::floor(z / kFloorBandM))] += 0.5 * area2;
  }
  if (area_by_band.empty()) return Status::error(path + ": the mesh has no horizontal face: no floor");
  double most_area = 0.0;
  for (const auto& [band, area] : area_by_band) most_area = std::max(most_area, area);
  // z down: the lowest band is the one with the largest z.
  long floor_band = 0;
  for (auto it = area_by_band.rbegin(); it != area_by_band.rend(); ++it) {
    if (it->second >= kFloorAreaShare * most_area) {
      floor_band = it->first;
      break;
    }
  }
  // Its height: the horizontal faces' within the tolerance of that band, weighted by area.
  const double band_mid = (static_cast<double>(floor_band) + 0.5) * kFloorBandM;
  double floor_area = 0.0, floor_weighted_z = 0.0;
  for (size_t t = 0; t < read.triangles.size(); ++t) {
    const Eigen::Vector3i& tri = read.triangles[t];
    const float area2 = face_normals[t].norm();
    const double z = (read.vertices[tri[0]].z() + read.vertices[tri[1]].z() +
                      read.vertices[tri[2]].z()) / 3.0;
    if (area2 > 0.0f && std::abs(face_normals[t].z()) >= kHorizontalCos * area2 &&
        std::abs(z - band_mid) <= kFloorToleranceM) {
      floor_area += area2;
      floor_weighted_z += area2 * z;
    }
  }
  scene.floor_z_m = floor_weighted_z / floor_area;

  // The floor's faces first (Scene::floor_triangles): every face within the tolerance of it, the
  // slopes of its bumps too. Each vertex's normal is the area-weighted mean of its faces' as the
  // file winds them.
  std::vector<Eigen::Vector3i> floor_faces, other_faces;
  read.normals.assign(read.vertices.size(), Eigen::Vector3f::Zero());
  for (size_t t = 0; t < read.triangles.size(); ++t) {
    const Eigen::Vector3i& tri = read.triangles[t];
    bool floor = true;
    for (int k = 0; k < 3; ++k) {
      read.normals[tri[k]] += face_normals[t];
      floor = floor && std::abs(read.vertices[tri[k]].z() - scene.floor_z_m) <= kFloorToleranceM;
    }
    (floor ? floor_faces : other_faces).push_back(tri);
  }
  for (Eigen::Vector3f& n : read.normals) {
    n = n.squaredNorm() > 0.0f ? Eigen::Vector3f(n.normalized()) : Eigen::Vector3f(-Eigen::Vector3f::UnitZ());
  }
  scene.mesh.vertices = std::move(read.vertices);
  scene.mesh.normals = std::move(read.normals);
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

const std::vector<std::string>& sceneNames() {
  static const std::vector<std::string> names = {"room", "corridor"};
  return names;
}

StatusOr<Scene> makeScene(const std::string& name) {
  if (name == "room") return furnishedRoom();
  if (name == "corridor") return corridor();
  return Status::error("scene '" + name + "' is unknown (known: room, corridor)");
}

}  // namespace kinfly::sim
