// The link thread: keyframes out (compressed, in erasure-coded chunks, paced by a budget that
// follows the link: docs/wire.md), signed corrections and chunk requests in, the drone's status
// at 10 Hz, and the sensor watch. A slow or absent ground station, a narrow link, or no network
// at all costs keyframes here (counted), never odometry. The small messages go first: a keyframe
// is sent a few chunks at a time between them, never as one burst that they would queue behind.
#pragma once

#include <optional>

#include "config.h"
#include "kinfly/codec/depth_codec.h"
#include "kinfly/fw/bounded_queue.h"
#include "kinfly/fw/latest_value.h"
#include "kinfly/fw/log_throttle.h"
#include "kinfly/fw/send_budget.h"
#include "kinfly/fw/sensor_watch.h"
#include "kinfly/link/chunking.h"
#include "kinfly/link/counters.h"
#include "kinfly/link/signing.h"
#include "kinfly/link/uplink.h"
#include "kinfly/drone_status_t.hpp"
#include "kinfly/flight_status_t.hpp"
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
           double depth_scale_m, LatestValue<CommandMail>* commands,
           LatestValue<flight_status_t>* flight_status, const StopToken* stop);

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

  // Of corrections and commands together, as the status reports them.
  link::RejectCounters rejects() const;
  int64_t accepted() const { return corrections_ ? corrections_->accepted() : 0; }
  // Commands authenticated and passed to the control task; those that could not be (no control
  // task, a mission that makes no trajectory).
  int64_t commandsPassed() const { return commands_passed_; }
  int64_t commandsDropped() const { return commands_dropped_; }
  // Commands sent again by a sender that heard no answer: already taken, not passed again.
  int64_t commandsRepeated() const { return recent_commands_.repeats(); }
  int64_t sensorStalls() const { return watch_.stalls(); }

 private:
  // LCM's C callback: the C++ wrapper would copy every channel name into a std::string, an
  // allocation per message, and the drone hears each of its own messages looped back.
  static void onMessage(const lcm_recv_buf_t* rbuf, const char* channel, void* self);
  void handle(const lcm_recv_buf_t* rbuf, const char* channel);
  void onGroundStatus(const lcm_recv_buf_t* rbuf);
  void onCommand(const lcm_recv_buf_t* rbuf);
  // A signed message through its receiver (none without a key: counted unsigned), each
  // rejection logged (throttled); the inner message when it is authentic.
  template <class Inner>
  std::optional<Inner> receiveSigned(std::optional<link::SignedReceiver<Inner>>& receiver,
                                     const lcm_recv_buf_t* rbuf, const char* what, double now_s);
  // One turn of the loop: messages in (or a wait for a keyframe while the network is down),
  // queued keyframes out, the status when due.
  void serve(Clock::time_point* next_status);
  // Takes the newest queued keyframe (the older ones are skipped: the budget could not send
  // them in time) and cuts it into chunks; false when none is queued.
  bool takeKeyframe();
  void startKeyframe(const KeyframeJob& job);
  // Sends the current keyframe's chunks while the budget allows.
  void sendChunks();
  bool sending() const { return next_chunk_ < pending_.size(); }
  // Publishes one chunk stamped with its send time and sequence number.
  bool publishChunk(const keyframe_chunk_t& chunk);
  void onChunkRequest(const lcm_recv_buf_t* rbuf);
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
  Image<uint16_t> scaled_;  // the keyframe at 1/2 (or, in its first quarter, 1/4) of the size
  link::ChunkEncoder chunks_;
  link::ChunkSpan pending_;  // the keyframe being sent
  size_t next_chunk_ = 0;
  int64_t pending_keyframe_id_ = -1;
  keyframe_chunk_t out_;     // the chunk going out: copied to stamp it, its block's capacity kept
  chunk_request_t request_;
  int64_t next_sequence_ = 0;
  TokenBucket bucket_;
  LinkRate rate_;
  bool limited_ = false;     // had chunks to send but no budget, since the last ground report
  // What went before the keyframes (Counters::priority_bytes): bytes since the window began,
  // and the rate over the last whole window.
  int64_t priority_window_bytes_ = 0;
  Clock::time_point priority_window_start_ = Clock::now();
  double priority_bps_ = 0.0;
  int scale_ = 1;
  KeyframeScale::Costs wire_costs_{};  // [bytes] the last keyframe's chunks at each scale
  float redundancy_ = 0.f;
  int64_t chunks_sent_ = 0, chunks_resent_ = 0, keyframes_skipped_ = 0;
  drone_status_t status_{};  // its vehicle_id set once; link::fillDroneStatus the rest
  std::optional<link::CorrectionReceiver> corrections_;
  std::optional<link::CommandReceiver> command_receiver_;
  LatestValue<CommandMail>* commands_ = nullptr;  // to the control task; nullptr without one
  // From the control task, sent with each status; nullptr without one.
  LatestValue<flight_status_t>* flight_status_ = nullptr;
  link::RecentCommands recent_commands_;
  int64_t commands_passed_ = 0, commands_dropped_ = 0;
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
  // Last: it may start LCM at once, and its start subscribes this task's handler.
  Publisher publisher_;
};

}  // namespace kinfly::fw
