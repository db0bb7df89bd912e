#include "kinfly/sim/ray_scene.h"

#include <embree3/rtcore.h>

#include <cmath>
#include <cstring>
#include <limits>
#include <string>

namespace kinfly::sim {

struct RayScene::Embree {
  RTCDevice device = nullptr;
  RTCScene scene = nullptr;
  ~Embree() {
    if (scene != nullptr) rtcReleaseScene(scene);
    if (device != nullptr) rtcReleaseDevice(device);
  }
};

RayScene::RayScene(int floor_triangles)
    : embree_(std::make_unique<Embree>()), floor_triangles_(floor_triangles) {}

StatusOr<std::unique_ptr<RayScene>> RayScene::create(const Scene& scene) {
  std::unique_ptr<RayScene> made(new RayScene(scene.floor_triangles));
  Embree& embree = *made->embree_;
  // threads=1: the scene is built once on this thread; set_affinity=0 leaves the process's
  // placement alone; verbose=0: quiet.
  embree.device = rtcNewDevice("threads=1,set_affinity=0,verbose=0");
  if (embree.device == nullptr) {
    return Status::error("Embree: no device (rtcNewDevice failed: a broken installation?)");
  }
  embree.scene = rtcNewScene(embree.device);
  rtcSetSceneFlags(embree.scene, RTC_SCENE_FLAG_ROBUST);
  rtcSetSceneBuildQuality(embree.scene, RTC_BUILD_QUALITY_HIGH);
  RTCGeometry geometry = rtcNewGeometry(embree.device, RTC_GEOMETRY_TYPE_TRIANGLE);
  const TriangleMesh& mesh = scene.mesh;
  auto* vertices = static_cast<float*>(
      rtcSetNewGeometryBuffer(geometry, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                              3 * sizeof(float), mesh.vertices.size()));
  for (size_t i = 0; i < mesh.vertices.size(); ++i) {
    std::memcpy(vertices + 3 * i, mesh.vertices[i].data(), 3 * sizeof(float));
  }
  auto* indices = static_cast<unsigned*>(
      rtcSetNewGeometryBuffer(geometry, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                              3 * sizeof(unsigned), mesh.triangles.size()));
  for (size_t i = 0; i < mesh.triangles.size(); ++i) {
    for (int k = 0; k < 3; ++k) indices[3 * i + k] = static_cast<unsigned>(mesh.triangles[i][k]);
  }
  rtcCommitGeometry(geometry);
  rtcAttachGeometry(embree.scene, geometry);
  rtcReleaseGeometry(geometry);
  rtcCommitScene(embree.scene);
  const RTCError error = rtcGetDeviceError(embree.device);
  if (error != RTC_ERROR_NONE) {
    return Status::error("Embree: building scene '" + scene.name + "' failed (error " +
                         std::to_string(static_cast<int>(error)) + ")");
  }
  return made;
}

RayScene::~RayScene() = default;

RayHit RayScene::cast(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction,
                      float max_distance) const {
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  RTCRayHit ray{};
  ray.ray.org_x = origin.x();
  ray.ray.org_y = origin.y();
  ray.ray.org_z = origin.z();
  ray.ray.dir_x = direction.x();
  ray.ray.dir_y = direction.y();
  ray.ray.dir_z = direction.z();
  ray.ray.tnear = 0.0f;
  ray.ray.tfar = max_distance;
  ray.ray.mask = std::numeric_limits<unsigned>::max();
  ray.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  rtcIntersect1(embree_->scene, &context, &ray);
  RayHit hit;
  if (ray.hit.geomID == RTC_INVALID_GEOMETRY_ID) return hit;
  hit.hit = true;
  hit.distance = ray.ray.tfar;
  hit.triangle = static_cast<int>(ray.hit.primID);
  hit.floor = hit.triangle < floor_triangles_;
  return hit;
}

void RayScene::cast8(const Eigen::Vector3f& origin, const Eigen::Vector3f directions[8],
                     const bool active[8], float max_distance, float distances[8],
                     float cos_incidence[8]) const {
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  context.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;  // the rays of neighbouring pixels
  alignas(32) int valid[8];
  // Only what Embree reads is set: zeroing the whole packet (640 bytes) cost as much as the rest.
  alignas(32) RTCRayHit8 rays;
  for (int i = 0; i < 8; ++i) {
    valid[i] = active[i] ? -1 : 0;
    rays.ray.org_x[i] = origin.x();
    rays.ray.org_y[i] = origin.y();
    rays.ray.org_z[i] = origin.z();
    rays.ray.dir_x[i] = directions[i].x();
    rays.ray.dir_y[i] = directions[i].y();
    rays.ray.dir_z[i] = directions[i].z();
    rays.ray.tnear[i] = 0.0f;
    rays.ray.tfar[i] = max_distance;
    rays.ray.time[i] = 0.0f;
    rays.ray.mask[i] = std::numeric_limits<unsigned>::max();
    rays.ray.id[i] = 0;
    rays.ray.flags[i] = 0;
    rays.hit.geomID[i] = RTC_INVALID_GEOMETRY_ID;
    rays.hit.instID[0][i] = RTC_INVALID_GEOMETRY_ID;
  }
  rtcIntersect8(valid, embree_->scene, &context, &rays);
  for (int i = 0; i < 8; ++i) {
    if (!active[i] || rays.hit.geomID[i] == RTC_INVALID_GEOMETRY_ID) {
      distances[i] = 0.0f;
      cos_incidence[i] = 0.0f;
      continue;
    }
    distances[i] = rays.ray.tfar[i];
    const Eigen::Vector3f normal(rays.hit.Ng_x[i], rays.hit.Ng_y[i], rays.hit.Ng_z[i]);
    cos_incidence[i] = std::abs(normal.dot(directions[i])) /
                       std::sqrt(normal.squaredNorm() * directions[i].squaredNorm());
  }
}

bool RayScene::touches(const Eigen::Vector3d& p, double radius) const {
  for (int x = -1; x <= 1; ++x) {
    for (int y = -1; y <= 1; ++y) {
      for (int z = -1; z <= 1; ++z) {
        if (x == 0 && y == 0 && z == 0) continue;
        const Eigen::Vector3f direction = Eigen::Vector3f(static_cast<float>(x), static_cast<float>(y),
                                                          static_cast<float>(z)).normalized();
        const RayHit hit = cast(p.cast<float>(), direction, static_cast<float>(radius));
        if (hit.hit && !hit.floor) return true;
      }
    }
  }
  return false;
}

}  // namespace kinfly::sim
