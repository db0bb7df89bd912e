// An LCM event log (kinfly-tum-to-log, lcm-logger) replayed as a depth source: one vehicle's
// KINFLY_<vid>_DEPTH frames, with its KINFLY_<vid>_GROUND_TRUTH poses where the log has them.
#pragma once

#include <memory>
#include <string>

#include "kinfly/sources/depth_source.h"

namespace kinfly::fw {

struct LogSourceParams {
  std::string path;    // source.path: the LCM event log
  int vehicle_id = 1;  // vehicle.id: whose channels to replay
};

// An error when the log cannot be opened or holds no decodable frame.
StatusOr<std::unique_ptr<DepthSource>> openLogSource(const LogSourceParams& params);

}  // namespace kinfly::fw
