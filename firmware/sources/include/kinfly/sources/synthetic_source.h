// A flight without hardware: the corner room of shared/ (SyntheticScene::cornerRoom) seen from a
// drone swinging around the objects in it, rendered with the Kinect noise model; each frame
// comes with its true pose. It never ends (source.max_frames stops it).
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>

#include "kinfly/core/status.h"
#include "kinfly/sources/depth_source.h"

namespace kinfly::fw {

struct SyntheticSourceParams {
  std::string intrinsics;      // source.intrinsics: "fx,fy,cx,cy"; empty: a Kinect's at this size
  int width_px = 640;          // source.width [px] [16, 4096]
  int height_px = 480;         // source.height [px] [16, 4096]
  double rate_hz = 30.0;       // source.rate_hz [Hz] (0, 1000]: frame times 1 / rate_hz apart
  int seed = 1;                // source.seed [0, 2^31): the same seed gives the same frames
  // source.motion: swing (the hovering drone's swing and bob) | still (at rest where the swing
  // starts: a drone on the floor, for bench tests with an IMU at rest)
  std::string motion = "swing";
  // [us] Read once frame 0 is rendered, it is that frame's capture time (kinfly-fw: the wall
  // clock); none: 0. Read then, not at the opening, so that however long the program takes to
  // start, a frame paced to its stamp is delivered on it.
  std::function<int64_t()> clock;
  // With a clock: a frame whose successor is already due by it is dropped (kSkipped), as a
  // camera's would be on a host that is late (kinfly-fw: when paced at the rate of its stamps).
  bool drop_late = false;
  Status validate() const;  // an error names the key, its range and the value
};

// An error when the parameters do not make a camera.
StatusOr<std::unique_ptr<DepthSource>> openSyntheticSource(const SyntheticSourceParams& params);

}  // namespace kinfly::fw
