// Triangle meshes and binary PLY output.
#pragma once

#include <Eigen/Core>
#include <string>
#include <vector>

#include "kinfly/core/status.h"

namespace kinfly {

struct TriangleMesh {
  std::vector<Eigen::Vector3f> vertices;   // [m] world frame
  std::vector<Eigen::Vector3f> normals;    // unit, per vertex, pointing into free space
  std::vector<Eigen::Vector3i> triangles;  // counter-clockwise seen from free space
  double surfaceAreaM2() const;
};

// Binary little-endian PLY with vertex normals. An error names the file.
Status writePly(const TriangleMesh& mesh, const std::string& path);

}  // namespace kinfly
