#include "kinfly/sim/mesh_file.h"

#include <CGAL/IO/polygon_soup_io.h>
#include <CGAL/Simple_cartesian.h>

#include <exception>
#include <filesystem>
#include <vector>

namespace kinfly::sim {

StatusOr<TriangleMesh> readMeshFile(const std::string& path) {
  if (!std::filesystem::is_regular_file(path)) return Status::error(path + ": no such file");
  std::vector<CGAL::Simple_cartesian<double>::Point_3> points;
  std::vector<std::vector<std::size_t>> polygons;
  // CGAL's reader, not Assimp's: Debian 12's Assimp (5.2.5) hangs on a PLY cut short in its
  // header and crashes on one cut short in its faces, where CGAL's says no. A header that
  // claims more than memory holds makes it throw instead.
  bool read = false;
  try {
    read = CGAL::IO::read_polygon_soup(path, points, polygons, CGAL::parameters::verbose(false));
  } catch (const std::exception& error) {
    return Status::error(path + ": cannot read a mesh from it (" + error.what() + ")");
  }
  if (!read) {
    return Status::error(path + ": cannot read a mesh from it (PLY, OBJ, OFF or STL): malformed, "
                         "cut short, or of another format");
  }
  TriangleMesh mesh;
  mesh.vertices.reserve(points.size());
  for (const auto& p : points) {
    mesh.vertices.emplace_back(static_cast<float>(p.x()), static_cast<float>(p.y()),
                               static_cast<float>(p.z()));
  }
  for (size_t f = 0; f < polygons.size(); ++f) {
    const std::vector<std::size_t>& polygon = polygons[f];
    for (const std::size_t index : polygon) {
      // A PLY's negative index arrives wrapped around: say what is wrong, not its value.
      if (index >= points.size()) {
        return Status::error(path + ": face " + std::to_string(f) + " names a vertex beyond its " +
                             std::to_string(points.size()));
      }
    }
    for (size_t i = 1; i + 1 < polygon.size(); ++i) {
      mesh.triangles.emplace_back(static_cast<int>(polygon[0]), static_cast<int>(polygon[i]),
                                  static_cast<int>(polygon[i + 1]));
    }
  }
  if (mesh.triangles.empty()) return Status::error(path + ": the mesh has no triangles");
  return mesh;
}

}  // namespace kinfly::sim
