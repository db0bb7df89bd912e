// Pinhole camera model, optical frame: x right, y down, z forward.
#pragma once

#include <Eigen/Core>
#include <string>

#include "kinfly/core/status.h"

namespace kinfly {

struct PinholeCamera {
  float fx = 535.4f;   // [px] > 0, TUM freiburg3 default
  float fy = 539.2f;   // [px] > 0
  float cx = 320.1f;   // [px] principal point, inside the image
  float cy = 247.6f;   // [px]
  int width = 640;     // [px] > 0
  int height = 480;    // [px] > 0

  // An error names the field and what is wrong with it.
  Status validate() const;

  // Intrinsics for an image downsampled by `factor`, where coarse pixel x samples (or is centred
  // on) fine pixel factor * x, as the pyramid and --downsample do.
  PinholeCamera scaled(int factor) const;

  Eigen::Vector3f backProject(float u_px, float v_px, float depth_m) const {
    return {(u_px - cx) * depth_m / fx, (v_px - cy) * depth_m / fy, depth_m};
  }
  // Projects a point in the camera frame; z must be > 0.
  Eigen::Vector2f project(const Eigen::Vector3f& p_cam) const {
    return {fx * p_cam.x() / p_cam.z() + cx, fy * p_cam.y() / p_cam.z() + cy};
  }
};

// Parses "fx,fy,cx,cy" (the --intrinsics option of the tools) into camera's intrinsics; leaves
// *camera alone when the text does not parse.
Status parseIntrinsics(const std::string& text, PinholeCamera* camera);

}  // namespace kinfly
