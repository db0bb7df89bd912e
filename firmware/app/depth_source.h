// Where kinfly-fw's depth comes from: one interface, chosen by configuration. Sources only read;
// pacing (real time or as fast as possible) is the capture thread's.
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include "kinfly/camera.h"
#include "kinfly/image.h"

namespace kinfly::fw {

struct DepthCapture {
  Image<uint16_t> depth;  // raw sensor units
  int64_t utime = 0;      // [us] capture time
  int64_t frame_id = 0;   // capture counter since start (set by the capture thread)
};

enum class SourceStatus {
  kFrame,    // *out holds a new frame
  kSkipped,  // a frame was unreadable; *why says why; the next call goes on with the next one
  kEnd,      // no more frames (end of a log or dataset)
};

class DepthSource {
 public:
  virtual ~DepthSource() = default;
  // Intrinsics and raw size of the frames; valid after open().
  virtual const PinholeCamera& camera() const = 0;
  virtual double depthScaleM() const = 0;  // [m per raw unit]
  virtual std::string describe() const = 0;
  // Reads the next frame into *out (its buffer is reused when the size matches).
  virtual SourceStatus next(DepthCapture* out, std::string* why) = 0;
};

struct DatasetSourceParams {
  std::string tum_dir;
  std::string intrinsics;            // "fx,fy,cx,cy"; empty: TUM freiburg3
  double depth_units_per_m = 5000.0; // TUM PNGs
};
// A TUM RGB-D folder. nullptr and *why when it cannot be opened.
std::unique_ptr<DepthSource> openDatasetSource(const DatasetSourceParams& params,
                                               std::string* why);

struct LogSourceParams {
  std::string path;     // LCM event log (kinfly-tum-to-log or lcm-logger)
  int vehicle_id = 1;   // whose KINFLY_<vid>_DEPTH channel to replay
};
// An LCM event log's depth frames. nullptr and *why when it cannot be opened or holds none.
std::unique_ptr<DepthSource> openLogSource(const LogSourceParams& params, std::string* why);

}  // namespace kinfly::fw
