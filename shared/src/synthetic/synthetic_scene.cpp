// Analytic scenes for tests: exact ray casting against planes, spheres and axis-aligned boxes,
// plus the seed's Kinect noise model for raw sensor images.
#include "kinfly/synthetic/synthetic_scene.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace kinfly {
namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();
// Hits nearer than this (in units of t) are ignored, so a ray starting on a surface does not
// report that surface at t = 0.
constexpr float kMinHitT = 1e-6f;

float intersectPlane(const Eigen::Vector3f& n, float offset, const Eigen::Vector3f& origin,
                     const Eigen::Vector3f& dir) {
  const float denom = n.dot(dir);
  if (denom == 0.f) return kInf;  // parallel: never hits
  const float t = (offset - n.dot(origin)) / denom;
  return t > kMinHitT ? t : kInf;
}

float intersectSphere(const Eigen::Vector3f& centre, float radius, const Eigen::Vector3f& origin,
                      const Eigen::Vector3f& dir) {
  // |o + t d - c|^2 = r^2  ->  a t^2 + 2 h t + k = 0
  const Eigen::Vector3f oc = origin - centre;
  const float a = dir.squaredNorm();
  const float h = oc.dot(dir);
  const float k = oc.squaredNorm() - radius * radius;
  const float disc = h * h - a * k;
  if (disc < 0.f || a == 0.f) return kInf;
  const float s = std::sqrt(disc);
  const float t_near = (-h - s) / a;
  if (t_near > kMinHitT) return t_near;
  const float t_far = (-h + s) / a;  // origin inside the sphere
  return t_far > kMinHitT ? t_far : kInf;
}

// Slab method: the ray is inside the box where it is inside all three slabs.
float intersectBox(const Eigen::Vector3f& lo, const Eigen::Vector3f& hi,
                   const Eigen::Vector3f& origin, const Eigen::Vector3f& dir) {
  float t_enter = -kInf;
  float t_exit = kInf;
  for (int i = 0; i < 3; ++i) {
    if (dir[i] == 0.f) {
      if (origin[i] < lo[i] || origin[i] > hi[i]) return kInf;  // parallel, outside the slab
      continue;
    }
    const float inv = 1.f / dir[i];
    float t0 = (lo[i] - origin[i]) * inv;
    float t1 = (hi[i] - origin[i]) * inv;
    if (t0 > t1) std::swap(t0, t1);
    t_enter = std::max(t_enter, t0);
    t_exit = std::min(t_exit, t1);
  }
  if (t_enter > t_exit) return kInf;
  if (t_enter > kMinHitT) return t_enter;
  return t_exit > kMinHitT ? t_exit : kInf;  // origin inside the box
}

}  // namespace

SyntheticScene SyntheticScene::cornerRoom() {
  SyntheticScene scene;
  scene.addPlane(Eigen::Vector3f(0.f, -1.f, 0.f), -0.9f);  // floor y = 0.9 (free side: y < 0.9)
  scene.addPlane(Eigen::Vector3f(0.f, 0.f, -1.f), -3.0f);  // back wall z = 3.0
  scene.addPlane(Eigen::Vector3f(1.f, 0.f, 0.f), -1.4f);   // left wall x = -1.4
  scene.addBox(Eigen::Vector3f(0.45f, 0.55f, 2.1f), Eigen::Vector3f(0.25f, 0.35f, 0.25f));
  scene.addSphere(Eigen::Vector3f(-0.45f, 0.25f, 1.9f), 0.3f);
  return scene;
}

SyntheticScene SyntheticScene::corridor() {
  SyntheticScene scene;
  scene.addPlane(Eigen::Vector3f(0.f, -1.f, 0.f), -0.5f);  // floor y = 0.5
  scene.addPlane(Eigen::Vector3f(0.f, 1.f, 0.f), -0.6f);   // ceiling y = -0.6
  scene.addPlane(Eigen::Vector3f(1.f, 0.f, 0.f), -0.6f);   // left wall x = -0.6
  scene.addPlane(Eigen::Vector3f(-1.f, 0.f, 0.f), -0.7f);  // right wall x = 0.7
  return scene;
}

Pose lookAtPose(const Eigen::Vector3d& eye, const Eigen::Vector3d& target) {
  const Eigen::Vector3d z = (target - eye).normalized();
  const Eigen::Vector3d x = Eigen::Vector3d::UnitY().cross(z).normalized();
  const Eigen::Vector3d y = z.cross(x);
  Pose T = Pose::Identity();
  T.linear().col(0) = x;
  T.linear().col(1) = y;
  T.linear().col(2) = z;
  T.translation() = eye;
  return T;
}

void SyntheticScene::addPlane(const Eigen::Vector3f& normal, float offset_m) {
  const float norm = normal.norm();
  planes_.push_back({normal / norm, offset_m / norm});
}

void SyntheticScene::addSphere(const Eigen::Vector3f& centre_m, float radius_m) {
  spheres_.push_back({centre_m, radius_m});
}

void SyntheticScene::addBox(const Eigen::Vector3f& centre_m, const Eigen::Vector3f& half_extent_m) {
  boxes_.push_back({centre_m - half_extent_m, centre_m + half_extent_m});
}

float SyntheticScene::intersect(const Eigen::Vector3f& origin, const Eigen::Vector3f& dir) const {
  float t_best = kInf;
  for (const Plane& p : planes_) t_best = std::min(t_best, intersectPlane(p.n, p.d, origin, dir));
  for (const Sphere& s : spheres_) {
    t_best = std::min(t_best, intersectSphere(s.c, s.r, origin, dir));
  }
  for (const Box& b : boxes_) t_best = std::min(t_best, intersectBox(b.lo, b.hi, origin, dir));
  return t_best;
}

void SyntheticScene::renderDepth(const PinholeCamera& camera, const Pose& T_world_cam,
                                 float max_depth_m, ImageView<float> depth_m) const {
  const Eigen::Matrix3f R_world_cam = T_world_cam.linear().cast<float>();
  const Eigen::Vector3f origin_world = T_world_cam.translation().cast<float>();
  for (int v = 0; v < depth_m.height(); ++v) {
    for (int u = 0; u < depth_m.width(); ++u) {
      // The camera-frame ray has z = 1, so the hit parameter t is the depth z itself.
      const Eigen::Vector3f dir_cam((static_cast<float>(u) - camera.cx) / camera.fx,
                                    (static_cast<float>(v) - camera.cy) / camera.fy, 1.f);
      const float z = intersect(origin_world, R_world_cam * dir_cam);
      depth_m(u, v) = z <= max_depth_m ? z : 0.f;
    }
  }
}

void SyntheticScene::renderRawDepth(const PinholeCamera& camera, const Pose& T_world_cam,
                                    float max_depth_m, double depth_scale_m, std::mt19937* rng,
                                    ImageView<uint16_t> raw) const {
  const Eigen::Matrix3f R_world_cam = T_world_cam.linear().cast<float>();
  const Eigen::Vector3f origin_world = T_world_cam.translation().cast<float>();
  std::normal_distribution<float> standard_normal(0.f, 1.f);
  constexpr double kMaxRaw = std::numeric_limits<uint16_t>::max();
  for (int v = 0; v < raw.height(); ++v) {
    for (int u = 0; u < raw.width(); ++u) {
      const Eigen::Vector3f dir_cam((static_cast<float>(u) - camera.cx) / camera.fx,
                                    (static_cast<float>(v) - camera.cy) / camera.fy, 1.f);
      const float z = intersect(origin_world, R_world_cam * dir_cam);
      if (!(z <= max_depth_m)) {
        raw(u, v) = 0;
        continue;
      }
      const float z_noisy = z + kinectNoiseSigmaM(z) * standard_normal(*rng);
      const double units = std::round(static_cast<double>(z_noisy) / depth_scale_m);
      // A reading that rounds to 0 (or below) would read as "no depth"; the sensor saturates.
      raw(u, v) = static_cast<uint16_t>(std::clamp(units, 1.0, kMaxRaw));
    }
  }
}

}  // namespace kinfly
