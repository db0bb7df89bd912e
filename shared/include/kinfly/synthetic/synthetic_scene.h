// Analytic scenes (planes, spheres, boxes) rendered as depth images with the seed's Kinect noise
// model, for tests against exact ground truth.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <random>
#include <vector>

#include "kinfly/core/camera.h"
#include "kinfly/core/image.h"
#include "kinfly/core/noise_model.h"
#include "kinfly/core/se3.h"

namespace kinfly {

class SyntheticScene {
 public:
  // A room corner in front of a camera at the origin looking along +z (y down): floor, back wall
  // and left wall, with a box standing on the floor and a sphere in front. Three non-parallel
  // planes fix translation; box and sphere add structure for rotation.
  static SyntheticScene cornerRoom();
  // A narrow corridor along +z, without end: floor, ceiling and two walls. Nothing fixes the
  // motion along it (ICP's degenerate case); it is narrow so that a 45 degree vertical field of
  // view sees floor and ceiling from close by, which fixes everything else.
  static SyntheticScene corridor();

  // Plane {p : n.p = offset}; the side n points to is free space.
  void addPlane(const Eigen::Vector3f& normal, float offset_m);
  void addSphere(const Eigen::Vector3f& centre_m, float radius_m);
  // Axis-aligned box in the world frame.
  void addBox(const Eigen::Vector3f& centre_m, const Eigen::Vector3f& half_extent_m);

  // Exact distance along the ray p = origin + t * dir (dir need not be unit) to the first
  // surface, in units of t; +inf if none.
  float intersect(const Eigen::Vector3f& origin, const Eigen::Vector3f& dir) const;

  // Noise-free metric depth (z in the camera frame), 0 where a ray hits nothing within
  // max_depth_m.
  void renderDepth(const PinholeCamera& camera, const Pose& T_world_cam, float max_depth_m,
                   ImageView<float> depth_m) const;

  // Raw sensor depth: z plus Gaussian noise of sigma kinectNoiseSigmaM(z), quantised with
  // `depth_scale_m` (metres per unit), 0 where nothing is hit. Deterministic for a given rng.
  void renderRawDepth(const PinholeCamera& camera, const Pose& T_world_cam, float max_depth_m,
                      double depth_scale_m, std::mt19937* rng, ImageView<uint16_t> raw) const;

 private:
  struct Plane { Eigen::Vector3f n; float d; };
  struct Sphere { Eigen::Vector3f c; float r; };
  struct Box { Eigen::Vector3f lo, hi; };
  std::vector<Plane> planes_;
  std::vector<Sphere> spheres_;
  std::vector<Box> boxes_;
};

// Camera at `eye` looking at `target`, image y as close to world +y (down) as possible.
Pose lookAtPose(const Eigen::Vector3d& eye, const Eigen::Vector3d& target);

}  // namespace kinfly
