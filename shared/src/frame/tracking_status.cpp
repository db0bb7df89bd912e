#include "kinfly/frame/tracking_status.h"

namespace kinfly {

const char* toString(TrackingStatus status) {
  switch (status) {
    case TrackingStatus::kFirstFrame: return "first";
    case TrackingStatus::kOk: return "ok";
    case TrackingStatus::kLost: return "lost";
    case TrackingStatus::kGivenPose: return "given";
  }
  return "unknown";
}

}  // namespace kinfly
