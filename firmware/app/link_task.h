// The link thread: keyframes out (compressed, docs/wire.md), signed corrections in, the drone's
// status at 10 Hz, and the sensor watch. A slow or absent ground station, or no network at all,
// costs keyframes here (counted), never odometry.
#pragma once

#include <optional>

#include "config.h"
#include "kinfly/codec/depth_codec.h"
#include "kinfly/fw/bounded_queue.h"
#include "kinfly/fw/log_throttle.h"
#include "kinfly/fw/sensor_watch.h"
#include "kinfly/link/counters.h"
#include "kinfly/link/signing.h"
#include "kinfly/link/uplink.h"
#include "kinfly/drone_status_t.hpp"
#include "kinfly/ground_status_t.hpp"
#include "kinfly/sources/depth_source.h"
#include "publisher.h"
#include "runtime.h"

namespace kinfly::fw {

class LinkTask {
 public:
  LinkTask(const FirmwareConfig& config, std::optional<link::Key> key, SharedAnchor* anchor,
           Counters* counters, BoundedQueue<KeyframeJob>* keyframes,
           const BoundedQueue<DepthCapture>* capture_queue, const PinholeCamera& camera,
           double depth_scale_m, const StopToken* stop);

  // Until stop(); then sends what is still queued, waits for the ground's last corrections when
  // asked to, and sends a last status (drone_status_t.RUN_FINAL).
  void run();
  // Called once the odometry has handed over its last keyframe. `await_corrections`: the source
  // ended (a replayed flight), so the corrections of the last keyframes are worth waiting for,
  // up to link.final_wait_s; not when the drone is told to stop.
  void stop(bool await_corrections) {
    await_corrections_ = await_corrections;
    stop_ = true;
  }

  link::RejectCounters rejects() const;
  int64_t accepted() const { return corrections_ ? corrections_->accepted() : 0; }
  int64_t sensorStalls() const { return watch_.stalls(); }

 private:
  // LCM's C callback: the C++ wrapper would copy every channel name into a std::string, an
  // allocation per message, and the drone hears each of its own messages looped back.
  static void onMessage(const lcm_recv_buf_t* rbuf, const char* channel, void* self);
  void handle(const lcm_recv_buf_t* rbuf, const char* channel);
  void onGroundStatus(const lcm_recv_buf_t* rbuf);
  // One turn of the loop: messages in (or a wait for a keyframe while the network is down),
  // queued keyframes out, the status when due.
  void serve(Clock::time_point* next_status);
  void send(const KeyframeJob& job);
  // Whether the ground station's status was heard within link.timeout_s.
  bool groundHeard() const;
  // Until the ground reports being done with the last keyframe sent: it sends that report after
  // the keyframe's correction, so every correction it will send has come by then.
  void awaitCorrections();
  void watchSensor();
  // is_final: the last status before kinfly-fw exits (drone_status_t.RUN_FINAL).
  void publishStatus(bool is_final = false);

  const FirmwareConfig& config_;
  SharedAnchor* anchor_;
  Counters* counters_;
  BoundedQueue<KeyframeJob>* keyframes_;
  const BoundedQueue<DepthCapture>* capture_queue_;
  const StopToken* stop_token_;  // its interruption cuts the final wait short
  PinholeCamera camera_;
  double depth_scale_m_;
  DepthCodec codec_;
  KeyframeJob job_;  // swapped with the queue's slots: its image circulates, never reallocated
  depth_keyframe_t message_{};
  drone_status_t status_{};  // its vehicle_id set once; link::fillDroneStatus the rest
  std::optional<link::CorrectionReceiver> corrections_;
  link::RejectCounters rejects_;
  SensorWatch watch_;
  std::atomic<bool> stop_{false}, await_corrections_{false};
  Clock::time_point began_ = Clock::now();
  Clock::time_point last_ground_heard_{};
  int64_t last_keyframe_sent_ = -1;
  ground_status_t ground_status_{};  // the last one heard
  bool ground_status_heard_ = false;
  LogThrottle reject_log_, send_log_;
  Clock::time_point rate_window_start_ = Clock::now();
  int64_t captured_at_window_ = 0, processed_at_window_ = 0, sent_at_window_ = 0;
  float depth_rate_hz_ = 0.f, odometry_rate_hz_ = 0.f, keyframe_rate_hz_ = 0.f;
  // Last: it may start LCM at once, and its start subscribes this task's handler. LCM reports
  // send errors only for single-datagram messages: a fragmented one (a keyframe) returns success
  // even when its datagrams could not be sent (lcm_udpm.c), so keyframes are sent only while the
  // status messages go out.
  Publisher publisher_;
};

}  // namespace kinfly::fw
