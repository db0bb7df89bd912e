// Whether the depth sensor is delivering: the link thread asks at every status tick, from the
// time of the last frame and what the source says of itself, so a sensor that stops (cable out,
// driver hung, a gap in a replayed flight) shows in the status and the log, whatever the source.
#pragma once

#include <cstdint>
#include <string>

#include "kinfly/core/status.h"

namespace kinfly::fw {

class SensorWatch {
 public:
  struct Params {
    double stall_timeout_s = 1.0;  // [s] (0, 60]: no frame this long while connected: stalled
    Status validate() const;
  };

  enum class State {
    kStreaming,  // frames arrive
    kWaiting,    // no sensor yet, or reconnecting after losing it (the source says so)
    kStalled,    // the source is connected but no frame came within stall_timeout_s
    kEnded,      // a replay reached its end
  };

  // What update() saw change, for the caller to log.
  enum class Change { kNone, kStalled, kResumed, kWaiting, kEnded };

  explicit SensorWatch(const Params& params) : params_(params) {}

  // now_s and last_frame_s on one monotonic clock; last_frame_s < 0 before the first frame (the
  // watch then counts from the first update()).
  Change update(double now_s, double last_frame_s, bool source_waiting, bool ended);

  State state() const { return state_; }
  int64_t stalls() const { return stalls_; }
  // [s] how long the last stall lasted (valid after Change::kResumed).
  double lastStallS() const { return last_stall_s_; }

 private:
  Params params_;
  State state_ = State::kStreaming;
  double started_s_ = -1.0;
  double stall_began_s_ = 0.0;
  double last_stall_s_ = 0.0;
  int64_t stalls_ = 0;
};

const char* toString(SensorWatch::State state);

}  // namespace kinfly::fw
