// Where kinfly-fw's depth comes from: one interface, chosen by configuration. Sources only read;
// pacing (real time or as fast as possible) is the capture thread's, and so is deciding that a
// sensor has gone quiet (SensorWatch).
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include "kinfly/core/camera.h"
#include "kinfly/core/image.h"
#include "kinfly/core/se3.h"

namespace kinfly::fw {

struct DepthCapture {
  Image<uint16_t> depth;  // raw sensor units
  int64_t utime = 0;      // [us] capture time
  int64_t frame_id = 0;   // capture counter since start (set by the capture thread)
  // Where the camera really was, from sources that know (synthetic): T_world_cam in the frame
  // of the first capture's camera, the odometry's own world frame.
  bool has_ground_truth = false;
  Pose T_world_cam_truth = Pose::Identity();
};

enum class SourceStatus {
  kFrame,    // *out holds a new frame
  kSkipped,  // a frame was unreadable; *why says why; the next call goes on with the next one
  kWaiting,  // no frame for now (no device, reconnecting, or none within the source's read
             // timeout); *why says why; call again
  kEnd,      // no more frames (end of a log, dataset or recording)
};

class DepthSource {
 public:
  virtual ~DepthSource() = default;
  // Intrinsics and raw size of every frame the source will deliver (a device that cannot give
  // them is refused): the engine's buffers are allocated for them once.
  virtual const PinholeCamera& camera() const = 0;
  virtual double depthScaleM() const = 0;  // [m per raw unit]
  virtual std::string describe() const = 0;
  // Reads the next frame into *out (its buffer is reused when the size matches). Returns within
  // about 100 ms, so the capture thread sees a stop request in time.
  virtual SourceStatus next(DepthCapture* out, std::string* why) = 0;
  // Times a sensor was opened: 1 for files, more after a device was lost and found again.
  virtual int64_t connects() const { return 1; }
  // True while a device source has no device (absent, or lost and not yet back).
  virtual bool waiting() const { return false; }
};

// The camera of a source that knows its image size but maybe not its lens: focal length
// `fx_at_640_px` scaled to the width, principal point at the centre, unless `intrinsics`
// ("fx,fy,cx,cy") says otherwise. False and *why when the result is not a valid camera.
bool sourceCamera(float fx_at_640_px, int width_px, int height_px, const std::string& intrinsics,
                  PinholeCamera* camera, std::string* why);

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

struct SyntheticSourceParams {
  std::string intrinsics;      // "fx,fy,cx,cy"; empty: a Kinect's at this size
  int width_px = 640, height_px = 480;
  double rate_hz = 30.0;       // frame times are 1 / rate_hz apart
  uint32_t seed = 1;           // the noise; the same seed gives the same frames
  int64_t first_utime = 0;     // [us] capture time of frame 0
};
// The corner room of shared/ (SyntheticScene::cornerRoom) seen from a drone orbiting in it,
// rendered with the Kinect noise model; never ends (source.max_frames stops it).
std::unique_ptr<DepthSource> openSyntheticSource(const SyntheticSourceParams& params,
                                                 std::string* why);

struct OpenniSourceParams {
  // A device URI, "" for the first depth sensor OpenNI2 finds, or the path of an .oni recording
  // (replayed through OpenNI2's own file driver).
  std::string uri;
  std::string intrinsics;      // "fx,fy,cx,cy"; empty: a PrimeSense sensor's 58 x 45 deg view
  int width_px = 640, height_px = 480;  // the depth mode asked of the sensor
  double reconnect_min_s = 0.5;  // [s] first retry after losing the sensor; doubles ...
  double reconnect_max_s = 8.0;  // [s] ... up to this
};
// A depth sensor through OpenNI2 (Kinect, Xtion, Orbbec), or a recording of one. With no sensor
// present it still opens: next() reports kWaiting and keeps retrying, so a drone can boot before
// its sensor is plugged in. nullptr and *why only when OpenNI2 itself cannot start, or a
// recording cannot be opened.
std::unique_ptr<DepthSource> openOpenniSource(const OpenniSourceParams& params,
                                              std::string* why);

}  // namespace kinfly::fw
