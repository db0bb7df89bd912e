// Where kinfly-fw's depth comes from: one interface, chosen by configuration; each source has its
// own header with its Params (defaults, units and ranges at the fields, validate()). Sources only
// read; pacing (real time or as fast as possible) is the capture thread's, and so is deciding that
// a sensor has gone quiet (SensorWatch).
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include "kinfly/core/camera.h"
#include "kinfly/core/image.h"
#include "kinfly/core/se3.h"
#include "kinfly/core/status.h"

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

// What next() did: a per-frame outcome that the capture thread counts and acts on, not an error
// (kinfly/core/status.h). Its *why is the text a Status message would be, for the log.
enum class SourceStatus {
  kFrame,    // *out holds a new frame
  kSkipped,  // a frame was unreadable; *why says why; the next call goes on with the next one
  kWaiting,  // no frame for now (no device, reconnecting, or none within the source's read
             // timeout); *why says why; call again
  kPaused,   // no frame within the read timeout from a sender that pauses between frames (a
             // simulator in lockstep, waiting on the ground): no news; call again
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
// ("fx,fy,cx,cy") says otherwise. An error when the result is not a valid camera.
StatusOr<PinholeCamera> sourceCamera(float fx_at_640_px, int width_px, int height_px,
                                     const std::string& intrinsics);

// The range of the image size asked of a source that makes or requests its frames
// (source.width, source.height: [16, 4096] px).
Status checkSourceSize(int width_px, int height_px);

}  // namespace kinfly::fw
