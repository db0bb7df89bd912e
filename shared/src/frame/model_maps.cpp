#include "kinfly/frame/model_maps.h"

#include <algorithm>

#include "parallel.h"

namespace kinfly {

ModelMaps::ModelMaps(const PinholeCamera& level0_camera, int first_level_in)
    : first_level(first_level_in) {
  for (int l = 0; l < kPyramidLevels; ++l) {
    camera[l] = level0_camera.scaled(1 << std::max(l, first_level));
    vertex_ref[l] = Image<Eigen::Vector3f>(camera[l].width, camera[l].height, invalidVector());
    normal_ref[l] = Image<Eigen::Vector3f>(camera[l].width, camera[l].height, invalidVector());
  }
}

void ModelMaps::buildPyramid() {
  for (int l = 1; l < kPyramidLevels; ++l) {
    const int w = camera[l].width, h = camera[l].height;
    const int step = l <= first_level ? 1 : 2;
    forEachStatic(h, [&](int y) {
      for (int x = 0; x < w; ++x) {
        vertex_ref[l](x, y) = vertex_ref[l - 1](step * x, step * y);
        normal_ref[l](x, y) = normal_ref[l - 1](step * x, step * y);
      }
    });
  }
}

}  // namespace kinfly
