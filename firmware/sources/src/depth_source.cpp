#include "kinfly/sources/depth_source.h"

#include "kinfly/core/range_check.h"

namespace kinfly::fw {

StatusOr<PinholeCamera> sourceCamera(float fx_at_640_px, int width_px, int height_px,
                                     const std::string& intrinsics) {
  PinholeCamera camera;
  camera.fx = camera.fy = fx_at_640_px * static_cast<float>(width_px) / 640.f;
  camera.cx = 0.5f * static_cast<float>(width_px - 1);
  camera.cy = 0.5f * static_cast<float>(height_px - 1);
  if (!intrinsics.empty())
    if (Status parsed = parseIntrinsics(intrinsics, &camera); !parsed.ok()) return parsed;
  camera.width = width_px;
  camera.height = height_px;
  if (Status valid = camera.validate(); !valid.ok()) return valid;
  return camera;
}

Status checkSourceSize(int width_px, int height_px) {
  return firstError(outOfRange("source.width", width_px, 16, 4096),
                      outOfRange("source.height", height_px, 16, 4096));
}

}  // namespace kinfly::fw
