#include "kinfly/fw/sensor_watch.h"

#include <sstream>

namespace kinfly::fw {

Status SensorWatch::Params::validate() const {
  if (stall_timeout_s > 0.0 && stall_timeout_s <= 60.0) return {};
  std::ostringstream why;
  why << "source.stall_timeout_s must be in (0, 60] (got " << stall_timeout_s << ")";
  return Status::error(why.str());
}

SensorWatch::Change SensorWatch::update(double now_s, double last_frame_s, bool source_waiting,
                                        bool ended) {
  if (started_s_ < 0.0) started_s_ = now_s;
  if (ended) {
    if (state_ == State::kEnded) return Change::kNone;
    state_ = State::kEnded;
    return Change::kEnded;
  }
  const State before = state_;
  if (source_waiting) {
    state_ = State::kWaiting;
    return before == State::kWaiting ? Change::kNone : Change::kWaiting;
  }
  const double since_s = now_s - (last_frame_s < 0.0 ? started_s_ : last_frame_s);
  if (since_s > params_.stall_timeout_s) {
    if (before == State::kStalled) return Change::kNone;
    state_ = State::kStalled;
    stall_began_s_ = now_s - since_s;
    ++stalls_;
    return Change::kStalled;
  }
  state_ = State::kStreaming;
  if (before == State::kStalled) {
    last_stall_s_ = (last_frame_s < 0.0 ? now_s : last_frame_s) - stall_began_s_;
    return Change::kResumed;
  }
  return Change::kNone;
}

const char* toString(SensorWatch::State state) {
  switch (state) {
    case SensorWatch::State::kStreaming: return "streaming";
    case SensorWatch::State::kWaiting: return "waiting for the sensor";
    case SensorWatch::State::kStalled: return "stalled";
    case SensorWatch::State::kEnded: return "ended";
  }
  return "?";
}

}  // namespace kinfly::fw
