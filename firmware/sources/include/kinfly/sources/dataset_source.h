// A TUM RGB-D folder (depth.txt and its 16-bit PNGs) replayed as a depth source.
#pragma once

#include <memory>
#include <string>

#include "kinfly/core/status.h"
#include "kinfly/sources/depth_source.h"

namespace kinfly::fw {

struct DatasetSourceParams {
  std::string tum_dir;             // source.path: the folder holding depth.txt
  std::string intrinsics;          // source.intrinsics: "fx,fy,cx,cy"; empty: TUM freiburg3
  double depth_scale_m = 0.0002;   // source.depth_scale_m [m per raw unit] [1e-6, 1]: TUM 1/5000
  Status validate() const;  // an error names the key, its range and the value
};

// An error when the folder cannot be opened or its first frame read.
StatusOr<std::unique_ptr<DepthSource>> openDatasetSource(const DatasetSourceParams& params);

}  // namespace kinfly::fw
