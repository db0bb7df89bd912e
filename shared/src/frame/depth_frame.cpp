#include "kinfly/frame/depth_frame.h"

namespace kinfly {

namespace {
int paddedWidth(int width) {
  constexpr int kPad = PackedPoints::kRowPadding;
  return (width + kPad - 1) / kPad * kPad;
}
}  // namespace

PackedPoints::PackedPoints(int width, int height)
    : vx(paddedWidth(width), height),
      vy(paddedWidth(width), height),
      vz(paddedWidth(width), height),
      nx(paddedWidth(width), height),
      ny(paddedWidth(width), height),
      nz(paddedWidth(width), height),
      row_count(static_cast<size_t>(height), 0) {}

DepthFrame::DepthFrame(const PinholeCamera& level0_camera)
    : raw_depth_m(level0_camera.width, level0_camera.height, 0.f) {
  for (int l = 0; l < kPyramidLevels; ++l) {
    camera[l] = level0_camera.scaled(1 << l);
    depth_m[l] = Image<float>(camera[l].width, camera[l].height, 0.f);
    points[l] = PackedPoints(camera[l].width, camera[l].height);
  }
}

}  // namespace kinfly
