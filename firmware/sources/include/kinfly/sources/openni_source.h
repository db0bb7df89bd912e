// A depth sensor through OpenNI2 (Kinect-class PrimeSense, Xtion, Orbbec through the PS1080
// driver), or a recording of one (.oni). With no sensor present it still opens: next() reports
// kWaiting and keeps retrying with backoff, so a drone can boot before its sensor is plugged in.
#pragma once

#include <memory>
#include <string>

#include "kinfly/core/status.h"
#include "kinfly/sources/depth_source.h"

namespace kinfly::fw {

struct OpenniSourceParams {
  // source.path: a device URI, "" for the first depth sensor OpenNI2 finds, or the path of an
  // .oni recording (replayed through OpenNI2's own file driver).
  std::string uri;
  std::string intrinsics;        // source.intrinsics: "fx,fy,cx,cy"; empty: a PrimeSense
                                 // sensor's 58 x 45 deg view
  int width_px = 640;            // source.width [px] [16, 4096]: the depth mode asked of the
  int height_px = 480;           // source.height [px] [16, 4096]   sensor
  double reconnect_min_s = 0.5;  // source.reconnect_min_s [s] [0.01, 60]: first retry after
                                 // losing the sensor; doubles ...
  double reconnect_max_s = 8.0;  // source.reconnect_max_s [s] [reconnect_min_s, 600]: ... up
                                 // to this
  Status validate() const;  // an error names the key, its range and the value
};

// An error only when the parameters are invalid, OpenNI2 itself cannot start, or a recording
// cannot be opened.
StatusOr<std::unique_ptr<DepthSource>> openOpenniSource(const OpenniSourceParams& params);

}  // namespace kinfly::fw
