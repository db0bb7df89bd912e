// Stage 8: marching cubes over every allocated block of a TSDF volume.
#pragma once

#include <string>

#include "kinfly/core/status.h"
#include "kinfly/mesh/mesh.h"
#include "kinfly/volume/tsdf_volume.h"

namespace kinfly {

class MarchingCubes {
 public:
  struct Params {
    // Cubes with any corner observed less than this are skipped, so single noisy
    // observations do not become surface.
    float min_weight = 1.f;  // > 0
    Status validate() const;
  };
  explicit MarchingCubes(const Params& params);

  // Vertices on shared cube edges are merged, so a closed surface gives a watertight mesh;
  // where a zero crossing steps by more than the truncation band (a depth discontinuity,
  // docs/engine.md item 13) its triangles are left out, and the mesh has a hole there.
  TriangleMesh extract(const TsdfVolume& volume) const;

 private:
  Params params_;
};

}  // namespace kinfly
