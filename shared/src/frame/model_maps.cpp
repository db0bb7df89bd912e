#include "kinfly/frame/model_maps.h"

#include "parallel.h"

namespace kinfly {

ModelMaps::ModelMaps(const PinholeCamera& level0_camera) {
  for (int l = 0; l < kPyramidLevels; ++l) {
    camera[l] = level0_camera.scaled(1 << l);
    vertex_ref[l] = Image<Eigen::Vector3f>(camera[l].width, camera[l].height, invalidVector());
    normal_ref[l] = Image<Eigen::Vector3f>(camera[l].width, camera[l].height, invalidVector());
  }
}

void ModelMaps::buildPyramid() {
  for (int l = 1; l < kPyramidLevels; ++l) {
    const int w = camera[l].width, h = camera[l].height;
    forEachStatic(h, [&](int y) {
      for (int x = 0; x < w; ++x) {
        vertex_ref[l](x, y) = vertex_ref[l - 1](2 * x, 2 * y);
        normal_ref[l](x, y) = normal_ref[l - 1](2 * x, 2 * y);
      }
    });
  }
}

}  // namespace kinfly
