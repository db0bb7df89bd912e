#include "capture.h"

#include <spdlog/spdlog.h>

#include <optional>
#include <thread>
#include <utility>

#include "kinfly/fw/log_throttle.h"

namespace kinfly::fw {

void runCapture(const SourceConfig& config, DepthSource* source,
                BoundedQueue<DepthCapture>* queue, Counters* counters, const StopToken* stop) {
  using namespace std::chrono_literals;
  DepthCapture capture = withDepthImage<DepthCapture>(source->camera());
  // Pacing: the first frame's capture time and the wall time it was due, re-anchored whenever
  // the recording's clock goes backwards or the sensor comes back after a loss.
  std::optional<std::pair<int64_t, Clock::time_point>> start;
  const Clock::time_point began = Clock::now();
  LogThrottle skipped_log, dropped_log;
  std::string why, last_waiting_why;
  bool waiting = false;
  while (!stop->stopRequested()) {
    if (config.max_frames > 0 && counters->frames_captured >= config.max_frames)
      break;
    const SourceStatus status = source->next(&capture, &why);
    counters->sensor_connects = source->connects();
    counters->sensor_waiting = source->waiting();
    if (status == SourceStatus::kEnd) {
      spdlog::info("capture: {} ended after {} frames", source->describe(),
                   counters->frames_captured.load());
      break;
    }
    if (status == SourceStatus::kPaused) {
      start.reset();
      continue;
    }
    if (status == SourceStatus::kWaiting) {
      if (!waiting || why != last_waiting_why) spdlog::warn("capture: {}", why);
      waiting = true;
      last_waiting_why = why;
      start.reset();
      continue;
    }
    if (waiting) spdlog::info("capture: {} delivering again", source->describe());
    waiting = false;
    last_waiting_why.clear();
    if (status == SourceStatus::kSkipped) {
      ++counters->frames_skipped;
      if (skipped_log.allow(secondsSince(began)))
        spdlog::warn("capture: frame skipped: {} ({} more since the last report)", why,
                     skipped_log.suppressed());
      continue;
    }
    if (config.realtime) {
      if (!start || capture.utime < start->first) start.emplace(capture.utime, Clock::now());
      const auto due = start->second + std::chrono::microseconds(static_cast<int64_t>(
                                           static_cast<double>(capture.utime - start->first) /
                                           config.speed));
      while (!stop->stopRequested() && Clock::now() < due)
        std::this_thread::sleep_for(std::min<Clock::duration>(kPollPeriod, due - Clock::now()));
    }
    capture.frame_id = counters->frames_captured;
    counters->last_frame_ns =
        std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch())
            .count();
    ++counters->frames_captured;
    if (!queue->push(capture) && dropped_log.allow(secondsSince(began)))
      spdlog::warn("capture: odometry behind, oldest frame dropped ({} dropped in all)",
                   queue->dropped());
    // Without pacing the odometry sets the rate: wait for room rather than drop what a
    // replay can simply deliver later.
    while (!config.realtime && !stop->stopRequested() && queue->size() >= queue->capacity())
      std::this_thread::sleep_for(1ms);
  }
  counters->capture_done = true;
  queue->close();
}

}  // namespace kinfly::fw
