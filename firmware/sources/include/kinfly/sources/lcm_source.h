// Depth frames that arrive over LCM as they are captured: KINFLY_<vid>_DEPTH depth_keyframe_t
// messages from another process, such as kinfly-sim's depth camera (docs/sim.md) or a sensor
// driver on another board. The camera is configured, as a sensor's would be, so the engine's
// buffers are sized at start, and depth comes in OpenNI's units (1 mm), as a sensor's does; a
// frame of another size, lens or depth scale is skipped and said.
#pragma once

#include <memory>
#include <string>

#include "kinfly/core/status.h"
#include "kinfly/sources/depth_source.h"

namespace kinfly::fw {

struct LcmSourceParams {
  static constexpr double kDepthScaleM = 0.001;  // [m] per raw unit: OpenNI's millimetres
  std::string lcm_url;          // source.lcm_url; empty: link.lcm_url's (set by kinfly-fw)
  int vehicle_id = 1;           // vehicle.id: whose KINFLY_<vid>_DEPTH
  std::string intrinsics;       // source.intrinsics "fx,fy,cx,cy"; empty: a Kinect's at this size
  int width_px = 640;           // source.width [px] [16, 4096]
  int height_px = 480;          // source.height [px] [16, 4096]
  Status validate() const;      // an error names the key, its range and the value
};

// An error when the camera is not valid or LCM cannot start on the URL.
StatusOr<std::unique_ptr<DepthSource>> openLcmSource(const LcmSourceParams& params);

}  // namespace kinfly::fw
