// The link thread: keyframes out (compressed, docs/wire.md), signed corrections in, the drone's
// status at 10 Hz, and the sensor watch. A slow or absent ground station costs keyframes here
// (counted), never odometry.
#pragma once

#include <optional>

#include "config.h"
#include "depth_source.h"
#include "kinfly/depth_codec.h"
#include "kinfly/fw/bounded_queue.h"
#include "kinfly/fw/log_throttle.h"
#include "kinfly/fw/sensor_watch.h"
#include "kinfly/link/counters.h"
#include "kinfly/link/signing.h"
#include "kinfly/link/uplink.h"
#include "kinfly/status_t.hpp"
#include "publisher.h"
#include "runtime.h"

namespace kinfly::fw {

class LinkTask {
 public:
  LinkTask(const FirmwareConfig& config, Publisher* publisher, std::optional<link::Key> key,
           SharedAnchor* anchor, Counters* counters, BoundedQueue<KeyframeJob>* keyframes,
           const BoundedQueue<DepthCapture>* capture_queue, const PinholeCamera& camera,
           double depth_scale_m);

  // Until stop(); then sends what is still queued and a last status.
  void run();
  // Called by the odometry's thread once it has handed over its last keyframe.
  void stop() { stop_ = true; }

  link::RejectCounters rejects() const;
  int64_t accepted() const { return corrections_ ? corrections_->accepted() : 0; }
  int64_t sensorStalls() const { return watch_.stalls(); }

 private:
  // LCM's C callback: the C++ wrapper would copy every channel name into a std::string, an
  // allocation per message, and the drone hears each of its own messages looped back.
  static void onMessage(const lcm_recv_buf_t* rbuf, const char* channel, void* self);
  void handle(const lcm_recv_buf_t* rbuf, const char* channel);
  void send(const KeyframeJob& job);
  void watchSensor();
  void publishStatus();

  const FirmwareConfig& config_;
  Publisher* publisher_;
  SharedAnchor* anchor_;
  Counters* counters_;
  BoundedQueue<KeyframeJob>* keyframes_;
  const BoundedQueue<DepthCapture>* capture_queue_;
  PinholeCamera camera_;
  double depth_scale_m_;
  DepthCodec codec_;
  KeyframeJob job_;  // swapped with the queue's slots: its image circulates, never reallocated
  depth_keyframe_t message_{};
  status_t status_{};
  std::optional<link::CorrectionReceiver> corrections_;
  link::RejectCounters rejects_;
  SensorWatch watch_;
  std::atomic<bool> stop_{false};
  Clock::time_point began_ = Clock::now();
  Clock::time_point last_ground_heard_{};
  // Whether the last status went out. LCM reports send errors only for single-datagram messages:
  // a fragmented one (a keyframe) returns success even when its datagrams could not be sent
  // (lcm_udpm.c), so a keyframe sent while the status could not be is counted as dropped.
  bool network_up_ = true;
  LogThrottle reject_log_, send_log_;
  Clock::time_point rate_window_start_ = Clock::now();
  int64_t captured_at_window_ = 0, processed_at_window_ = 0, sent_at_window_ = 0;
  float depth_rate_hz_ = 0.f, odometry_rate_hz_ = 0.f, keyframe_rate_hz_ = 0.f;
};

}  // namespace kinfly::fw
