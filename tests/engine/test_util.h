// Shared helpers for the unit tests: synthetic scenes, poses, image conversions and pose errors.
// Every random number comes from a std::mt19937 with a fixed seed.
#pragma once

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>

#include "kinfly/core/camera.h"
#include "kinfly/preprocessing/depth_preprocessor.h"
#include "kinfly/tracking/icp_tracker.h"
#include "kinfly/core/image.h"
#include "kinfly/core/se3.h"
#include "kinfly/synthetic/synthetic_scene.h"
#include "kinfly/volume/tsdf_volume.h"

namespace kinfly::test {

constexpr double kTumDepthScale = 1.0 / 5000.0;  // [m per unit] TUM PNGs
constexpr float kRenderMaxDepthM = 5.f;          // [m] beyond every wall of the test scenes
constexpr double kPi = 3.14159265358979323846;

inline double degToRad(double deg) { return deg * kPi / 180.0; }
inline double radToDeg(double rad) { return rad * 180.0 / kPi; }

// The TUM freiburg3 camera of PinholeCamera's defaults, 640x480.
inline PinholeCamera tumCamera() { return PinholeCamera(); }

// Pose from a rotation vector (axis * angle, radians) and a translation.
inline Pose makePose(const Eigen::Vector3d& rotation_vector, const Eigen::Vector3d& t) {
  Pose T = Pose::Identity();
  const double angle = rotation_vector.norm();
  if (angle > 0.0) T.linear() = Eigen::AngleAxisd(angle, rotation_vector / angle).matrix();
  T.translation() = t;
  return T;
}

// A random rigid motion with exactly the given translation length and rotation angle.
inline Pose randomOffset(std::mt19937* rng, double translation_m, double rotation_rad) {
  std::normal_distribution<double> n01(0.0, 1.0);
  Eigen::Vector3d axis(n01(*rng), n01(*rng), n01(*rng));
  Eigen::Vector3d dir(n01(*rng), n01(*rng), n01(*rng));
  return makePose(axis.normalized() * rotation_rad, dir.normalized() * translation_m);
}

inline double translationErrorM(const Pose& a, const Pose& b) {
  return (a.translation() - b.translation()).norm();
}
// Angle of a^-1 b from the skew and symmetric parts (atan2 stays accurate at small angles,
// where acos of the trace loses precision and clamps a slightly non-orthonormal matrix to 0).
inline double rotationErrorRad(const Pose& a, const Pose& b) {
  const Eigen::Matrix3d R = a.linear().transpose() * b.linear();
  const Eigen::Vector3d skew(R(2, 1) - R(1, 2), R(0, 2) - R(2, 0), R(1, 0) - R(0, 1));
  return std::atan2(0.5 * skew.norm(), 0.5 * (R.trace() - 1.0));
}
// Frobenius norm of R^T R - I: how far a pose's rotation is from a rotation.
inline double orthonormalityError(const Pose& T) {
  return (T.linear().transpose() * T.linear() - Eigen::Matrix3d::Identity()).norm();
}
// Products of a few hundred exact rotations drift by ~1e-14; anything near 1e-9 is growing.
constexpr double kOrthonormalityTol = 1e-9;

// Noise-free sensor image: metric depth quantised to TUM units (0.2 mm), 0 stays 0.
inline void metresToRaw(ImageView<const float> depth_m, ImageView<uint16_t> raw) {
  for (int i = 0; i < raw.numPixels(); ++i)
    raw.data()[i] = static_cast<uint16_t>(std::lround(depth_m.data()[i] / kTumDepthScale));
}

// Raw uint16 -> metres, 0 stays 0 (the conversion the engine does, without range limits).
inline void rawToMetres(ImageView<const uint16_t> raw, double depth_scale_m,
                        ImageView<float> depth_m) {
  for (int y = 0; y < raw.height(); ++y) {
    for (int x = 0; x < raw.width(); ++x) {
      depth_m(x, y) = static_cast<float>(raw(x, y) * depth_scale_m);
    }
  }
}

// One noisy sensor frame in metres: Kinect-noise depth of `scene` drawn with its own seed and
// quantised to TUM units. `raw` is scratch space of the same size.
inline void renderNoisyMetres(const SyntheticScene& scene, const PinholeCamera& camera,
                              const Pose& T_world_cam, uint32_t seed, ImageView<uint16_t> raw,
                              ImageView<float> depth_m) {
  std::mt19937 rng(seed);
  scene.renderRawDepth(camera, T_world_cam, kRenderMaxDepthM, kTumDepthScale, &rng, raw);
  rawToMetres(raw, kTumDepthScale, depth_m);
}

// Model maps as a perfect raycast would give them: level 0 from exact depth, then the pyramid.
inline void fillModelFromDepth(ImageView<const float> depth_m, const PinholeCamera& camera,
                               ModelMaps* model) {
  computeVertexMap(depth_m, camera, model->vertex_ref[0]);
  computeNormalMap(model->vertex_ref[0], model->normal_ref[0]);
  model->buildPyramid();
}

// Global voxel index -> voxel, nullptr where its block is not allocated.
inline const Voxel* voxelAt(const TsdfVolume& volume, const Eigen::Vector3i& g) {
  const BlockIndex b(static_cast<int>(std::floor(g.x() / static_cast<double>(kBlockSide))),
                     static_cast<int>(std::floor(g.y() / static_cast<double>(kBlockSide))),
                     static_cast<int>(std::floor(g.z() / static_cast<double>(kBlockSide))));
  const VoxelBlock* block = volume.findBlock(b);
  if (block == nullptr) return nullptr;
  const Eigen::Vector3i l = g - b * kBlockSide;
  return &block->voxels[VoxelBlock::linear(l.x(), l.y(), l.z())];
}

// Angle between two vectors in degrees.
inline double angleDeg(const Eigen::Vector3f& a, const Eigen::Vector3f& b) {
  const double c = a.normalized().dot(b.normalized());
  return radToDeg(std::acos(std::clamp(c, -1.0, 1.0)));
}

}  // namespace kinfly::test
