// The capture thread: reads the source, paces replays to their capture times (or waits for room
// when replaying as fast as possible), and hands frames to the odometry through the drop-oldest
// queue.
#pragma once

#include "config.h"
#include "kinfly/fw/bounded_queue.h"
#include "kinfly/sources/depth_source.h"
#include "runtime.h"

namespace kinfly::fw {

// Runs until the source ends, source.max_frames is reached or a stop is requested; then closes
// the queue.
void runCapture(const SourceConfig& config, DepthSource* source,
                BoundedQueue<DepthCapture>* queue, Counters* counters, const StopToken* stop);

}  // namespace kinfly::fw
