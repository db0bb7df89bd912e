// Triangle meshes from files (PLY, OBJ, OFF, STL), read by CGAL in a library of its own so that
// CGAL's compile flags (-frounding-math) stay off the simulator's other sources.
#pragma once

#include <string>

#include "kinfly/core/status.h"
#include "kinfly/mesh/mesh.h"

namespace kinfly::sim {

// The file's vertices and faces as it has them (no normals), each polygon as a fan of triangles
// (a scan's are triangles; others are taken to be convex). An error names the file: missing,
// unreadable, malformed or cut short, a face naming a vertex it does not have, no triangle.
StatusOr<TriangleMesh> readMeshFile(const std::string& path);

}  // namespace kinfly::sim
