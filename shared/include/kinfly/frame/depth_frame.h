// One depth image as the engine holds it: filtered depth per pyramid level and the packed points
// the tracker reads. Data only: DepthPreprocessor fills it, the tracker and the integrator read it.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cmath>
#include <limits>
#include <vector>

#include "kinfly/core/camera.h"
#include "kinfly/core/image.h"
#include "kinfly/core/lanes.h"

namespace kinfly {

constexpr int kPyramidLevels = 3;

// Invalid vertices and normals are NaN vectors, so a single isValid() test covers both.
inline Eigen::Vector3f invalidVector() {
  return Eigen::Vector3f::Constant(std::numeric_limits<float>::quiet_NaN());
}
inline bool isValid(const Eigen::Vector3f& v) { return !std::isnan(v.x()); }

// The points of one level that the tracker can use (vertex and normal both valid), one image per
// coordinate with each row's points packed to its front: the tracker reads them contiguously,
// skips nothing, and its per-point loops vectorise.
struct PackedPoints {
  // Rows hold a multiple of this many points, so that the tracker's 4-wide loads past a row's
  // last point stay inside the row.
  static constexpr int kRowPadding = lanes::kWidth;
  PackedPoints() = default;
  PackedPoints(int width, int height);
  Image<float> vx, vy, vz;  // [m] camera frame
  Image<float> nx, ny, nz;  // unit, facing the camera
  std::vector<int> row_count;  // points packed into each row
};

// Everything the tracker and integrator need from one depth image. Level 0 is the finest.
struct DepthFrame {
  explicit DepthFrame(const PinholeCamera& level0_camera);

  std::array<PinholeCamera, kPyramidLevels> camera;
  Image<float> raw_depth_m;                               // level 0, unfiltered: integrated into the TSDF
  std::array<Image<float>, kPyramidLevels> depth_m;       // bilateral-filtered, then pyramid
  // The pixels of depth_m with a vertex and a normal (computeVertexMap, computeNormalMap), packed;
  // no per-pixel maps are kept, since nothing reads them.
  std::array<PackedPoints, kPyramidLevels> points;
};

}  // namespace kinfly
