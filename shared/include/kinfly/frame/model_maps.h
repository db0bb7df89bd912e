// Data only: the Raycaster fills level 0 (and buildPyramid the rest), the tracker reads every
// level.
#pragma once

#include <Eigen/Core>
#include <array>

#include "kinfly/core/camera.h"
#include "kinfly/core/image.h"
#include "kinfly/frame/depth_frame.h"

namespace kinfly {

// The model prediction: raycast vertex and normal maps in the reference camera frame
// (the camera that was raycast), one per pyramid level. From `first_level` > 0 the raycast is
// that level's resolution, and the finer levels hold it too: ICP at the frame's finest level
// then pairs 2^first_level x 2^first_level of its points with each model pixel (the model's
// camera, camera[level], is what it projects with).
struct ModelMaps {
  explicit ModelMaps(const PinholeCamera& level0_camera, int first_level = 0);
  std::array<PinholeCamera, kPyramidLevels> camera;
  std::array<Image<Eigen::Vector3f>, kPyramidLevels> vertex_ref;  // [m]
  std::array<Image<Eigen::Vector3f>, kPyramidLevels> normal_ref;  // unit, facing the camera
  // The spacing the normals were differenced over (the volume's voxel; 0: unknown): the sensor's
  // noise over it tells how far a normal may lie off the surface's (IcpTracker's angle gate).
  float normal_spacing_m = 0.f;  // [m]
  int first_level = 0;           // the level raycast; the finer ones hold the same image
  // Fills levels 1.. from level 0 by taking every second pixel, matching the depth pyramid's
  // pixel-centre convention (a copy where a level has its finer one's size).
  void buildPyramid();
};

}  // namespace kinfly
