// A Scene's mesh in Embree (Debian's libembree, a kept ray tracer), for the depth camera and the
// collision check; never kinfly's own TSDF raycaster, which would test the map against itself.
// Built once, on one thread (Embree's own threads would make the simulator's core count and
// timing depend on the machine), read by any number of casts.
#pragma once

#include <Eigen/Core>
#include <memory>

#include "kinfly/core/status.h"
#include "kinfly/sim/scene.h"

namespace kinfly::sim {

struct RayHit {
  bool hit = false;
  float distance = 0.0f;             // along the ray, in units of its direction's length
  int triangle = -1;                 // the hit triangle's index in the Scene's mesh
  bool floor = false;                // it is the Scene's floor
};

class RayScene {
 public:
  // Fails only when Embree cannot make a device or build the scene (a broken installation).
  static StatusOr<std::unique_ptr<RayScene>> create(const Scene& scene);
  ~RayScene();
  RayScene(const RayScene&) = delete;
  RayScene& operator=(const RayScene&) = delete;

  // The nearest hit of origin + t direction for t in [0, max_distance].
  RayHit cast(const Eigen::Vector3f& origin, const Eigen::Vector3f& direction,
              float max_distance) const;
  // Eight rays from one origin at once (Embree's ray packets): distances[i] = 0 where ray i hits
  // nothing within max_distance; cos_incidence[i] = |cos| of the angle between ray i and the
  // face it hits. Rays with active[i] false are not cast.
  void cast8(const Eigen::Vector3f& origin, const Eigen::Vector3f directions[8],
             const bool active[8], float max_distance, float distances[8],
             float cos_incidence[8]) const;
  // Whether a face other than the floor's lies within `radius` of `p` (the body's sphere against
  // the scene: a collision, or no room to stand), probed along the 26 directions of a cube's
  // faces, edges and corners. No direction is more than 27.6° from a probe, so a plane is found
  // once it is within cos 27.6° = 0.886 of `radius` along its normal, whichever way it faces.
  bool touches(const Eigen::Vector3d& p, double radius) const;

 private:
  struct Embree;
  explicit RayScene(int floor_triangles);
  std::unique_ptr<Embree> embree_;
  int floor_triangles_;
};

}  // namespace kinfly::sim
