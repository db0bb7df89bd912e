#include "kinfly/mesh/mesh.h"

#include <Eigen/Geometry>
#include <cerrno>
#include <cstdint>
#include <cstring>
#include <fstream>

namespace kinfly {

double TriangleMesh::surfaceAreaM2() const {
  double area = 0.0;
  for (const Eigen::Vector3i& t : triangles) {
    const Eigen::Vector3d a = vertices[t[0]].cast<double>();
    area += 0.5 * (vertices[t[1]].cast<double>() - a).cross(vertices[t[2]].cast<double>() - a).norm();
  }
  return area;
}

Status writePly(const TriangleMesh& mesh, const std::string& path) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  if (!out) return Status::error("cannot write " + path + ": " + std::strerror(errno));
  out << "ply\nformat binary_little_endian 1.0\ncomment kinfly TSDF mesh, metres, world frame\n"
      << "element vertex " << mesh.vertices.size() << "\n"
      << "property float x\nproperty float y\nproperty float z\n"
      << "property float nx\nproperty float ny\nproperty float nz\n"
      << "element face " << mesh.triangles.size() << "\n"
      << "property list uchar int vertex_indices\nend_header\n";
  static_assert(sizeof(float) == 4 && sizeof(int) == 4, "PLY float/int are 32-bit");
  // x86-64 and aarch64 are little-endian, so fields are written as they lie in memory.
  for (size_t i = 0; i < mesh.vertices.size(); ++i) {
    const Eigen::Vector3f n = i < mesh.normals.size() ? mesh.normals[i] : Eigen::Vector3f::Zero();
    out.write(reinterpret_cast<const char*>(mesh.vertices[i].data()), 3 * sizeof(float));
    out.write(reinterpret_cast<const char*>(n.data()), 3 * sizeof(float));
  }
  for (const Eigen::Vector3i& t : mesh.triangles) {
    const uint8_t count = 3;
    out.write(reinterpret_cast<const char*>(&count), 1);
    out.write(reinterpret_cast<const char*>(t.data()), 3 * sizeof(int));
  }
  out.close();
  if (!out) return Status::error("failed writing " + path + " (disk full?)");
  return {};
}

}  // namespace kinfly
