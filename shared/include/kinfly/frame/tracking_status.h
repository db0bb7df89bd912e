// What became of a frame's pose: the tracker's verdict, carried by the pipeline's results and the
// firmware's status messages.
#pragma once

namespace kinfly {

enum class TrackingStatus { kFirstFrame, kOk, kLost, kGivenPose };
const char* toString(TrackingStatus status);  // "first", "ok", "lost", "given"

}  // namespace kinfly
