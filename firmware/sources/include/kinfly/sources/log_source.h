// An LCM event log (kinfly-tum-to-log, lcm-logger) replayed as a depth source: one vehicle's
// KINFLY_<vid>_DEPTH frames, with its KINFLY_<vid>_GROUND_TRUTH poses where the log has them.
// Played once, or bounced (forward, backward, forward ...) for soak runs (docs/firmware.md).
#pragma once

#include <memory>
#include <string>

#include "kinfly/core/status.h"
#include "kinfly/sources/depth_source.h"

namespace kinfly::fw {

struct LogSourceParams {
  std::string path;    // source.path: the LCM event log
  int vehicle_id = 1;  // vehicle.id: whose channels to replay
  // source.loop: none | bounce. "none" plays the flight once. "bounce" plays it forward, then
  // backward (its frames in reverse order), then forward again ..., so that the camera never
  // jumps back to the start (the odometry would lose it); each frame's capture time is the
  // previous frame's plus the recorded spacing between the two, so time keeps increasing.
  std::string loop = "none";
  // source.laps [0, 1e6]: with loop = bounce, the passes over the flight (forward, backward,
  // forward ...; each as long as the recording); 0: until stopped (or source.max_frames).
  int laps = 0;
  Status validate() const;  // an error names the key, its range and the value
};

// An error when the log cannot be opened, holds no decodable frame, or (bounce) fewer than two.
StatusOr<std::unique_ptr<DepthSource>> openLogSource(const LogSourceParams& params);

}  // namespace kinfly::fw
