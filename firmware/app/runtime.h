// What kinfly-fw's threads share: counters (each written by one thread, read by the link for the
// status), the keyframe hand-over, the re-anchoring, and the stop token.
#pragma once

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <mutex>
#include <optional>
#include <type_traits>

#include "kinfly/fw/correction_anchor.h"
#include "kinfly/core/camera.h"
#include "kinfly/frame/tracking_status.h"
#include "kinfly/core/image.h"
#include "kinfly/core/se3.h"
#include "kinfly/flight/anchored_vision.h"
#include "kinfly/flight/flight_modes.h"
#include "kinfly/flight/pose_history.h"
#include "kinfly/flight/trajectory.h"

namespace kinfly::fw {

using Clock = std::chrono::steady_clock;
// The longest any thread waits before looking at the stop flag again.
constexpr std::chrono::milliseconds kPollPeriod{50};

// The odometry's last verdict, for the status: the engine's TrackingStatus kept in an atomic of
// its underlying value; nullopt before the first frame.
class AtomicTracking {
 public:
  void store(TrackingStatus status) { value_ = static_cast<Value>(status); }
  std::optional<TrackingStatus> load() const {
    const Value value = value_;
    if (value == kNone) return std::nullopt;
    return static_cast<TrackingStatus>(value);
  }

 private:
  using Value = std::underlying_type_t<TrackingStatus>;
  static constexpr Value kNone = -1;
  std::atomic<Value> value_{kNone};
};

struct Counters {
  // capture thread
  std::atomic<int64_t> frames_captured{0}, frames_skipped{0}, sensor_connects{0};
  std::atomic<bool> sensor_waiting{false}, capture_done{false};
  std::atomic<int64_t> last_frame_ns{-1};  // [ns] Clock time of the last frame, -1 before one
  // odometry thread
  std::atomic<int64_t> frames_processed{0}, frames_lost{0};
  std::atomic<int64_t> frames_weak{0};  // tracked with weak directions (degenerate geometry)
  // Tracking back after lost frames (by relocalisation against a keyframe or otherwise), and
  // the most frames lost before one of those.
  std::atomic<int64_t> recoveries{0}, relocalisations{0}, new_maps{0}, longest_loss_frames{0};
  AtomicTracking tracking;
  // link thread
  std::atomic<int64_t> keyframes_sent{0}, keyframes_failed{0}, corrections_unknown{0};
  // The last keyframe id the ground station reported done (ground_status_t.last_keyframe_id,
  // sent after that keyframe's correction), -1 before one: source.lockstep waits for it.
  std::atomic<int64_t> ground_done_keyframe{-1};
  // Ground statuses heard for this vehicle: a lockstep wait that ran out waits again from the
  // next one (a station back, or a new one).
  std::atomic<int64_t> ground_statuses{0};
  // any thread that sends: bytes of everything but keyframe chunks put on the link since the link
  // thread last took them; they went first, and the keyframes' budget pays for them
  std::atomic<int64_t> priority_bytes{0};
};

// The odometry's pose of a tracked frame for the control task: the capture time, the engine's own
// pose and the ground's anchor with its reset counter as they were when the pose was made
// (flight::AnchoredVision turns a jump of the anchor into the estimator's reset).
using OdometryPose = flight::AnchoredPose;

// A command from the ground for the control task, authenticated by the link, which also builds a
// mission's trajectory (a minimum-snap solve allocates; the control tick must not).
struct CommandMail {
  int64_t command_id = -1;
  flight::FlightCommand command;
  std::optional<flight::Trajectory> mission;
};

// The estimator's camera poses, written by the control task at every IMU sample (when the lock is
// free: it never waits, but in a lockstep flight), read by the odometry for its motion prior
// across at most kSpanS (flight::PoseHistory). The ring also holds kLeadS, how far the control
// task may be ahead of the frame the odometry looks up: a drone's latency and processing, or a
// lockstep flight's pose age (flight.lockstep_pose_age_s, at most 0.1 s), so that a lookup's
// answer does not depend on how far the control task ran meanwhile.
struct SharedPoseHistory {
  static constexpr double kSpanS = 1.0;   // [s] the longest loss of tracking the prior bridges
  static constexpr double kLeadS = 0.25;  // [s]
  explicit SharedPoseHistory(double imu_rate_hz)
      : history(static_cast<int>(std::ceil((kSpanS + kLeadS) * imu_rate_hz)) + 1,
                static_cast<int64_t>(kSpanS * 1e6)) {}
  std::mutex mutex;
  flight::PoseHistory history;
};

struct KeyframeJob {
  Image<uint16_t> depth;  // raw, full resolution: the ground fuses at full resolution
  int64_t utime = 0, frame_id = 0, keyframe_id = 0;
  Pose T_world_cam = Pose::Identity();
  TrackingStatus tracking = TrackingStatus::kLost;
};

// The re-anchoring shared by the odometry (remembers keyframes, publishes anchored poses) and
// the link (applies corrections).
struct SharedAnchor {
  std::mutex mutex;
  CorrectionAnchor anchor;
  explicit SharedAnchor(const CorrectionAnchor::Params& p) : anchor(p) {}
};

// A queue item (DepthCapture, KeyframeJob) with its depth image allocated for `camera`: every
// image the threads pass around is made at start, and swapping items never reallocates.
template <class Item>
Item withDepthImage(const PinholeCamera& camera) {
  Item item;
  item.depth = Image<uint16_t>(camera.width, camera.height);
  return item;
}

// Asks the tasks to finish. main owns it and hands it to each task; every loop checks it at
// least every kPollPeriod. Why they stop matters at the end: a flight whose source ended waits
// for the ground's last corrections, one the drone was told to end (SIGINT, SIGTERM) does not.
class StopToken {
 public:
  // The source ended, or main is done: finish what is under way.
  void requestStop() { stop_ = true; }
  // The drone was told to stop: finish, and wait for nothing.
  void interrupt() {
    interrupted_ = true;
    stop_ = true;
  }
  bool stopRequested() const { return stop_; }
  bool interrupted() const { return interrupted_; }

 private:
  std::atomic<bool> stop_{false}, interrupted_{false};
};

inline double secondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

}  // namespace kinfly::fw
