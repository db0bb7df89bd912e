#include <lcm/lcm-cpp.hpp>

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <memory>
#include <optional>
#include <vector>

#include "kinfly/sources/log_source.h"
#include "kinfly/codec/depth_codec.h"
#include "kinfly/core/range_check.h"
#include "kinfly/link/channels.h"
#include "kinfly/link/conversions.h"
#include "kinfly/link/decode.h"

namespace kinfly::fw {
namespace {

constexpr int kMaxLaps = 1'000'000;

class LogSource : public DepthSource {
 public:
  LogSource(const LogSourceParams& params, std::unique_ptr<lcm::LogFile> log)
      : path_(params.path),
        channel_(link::channelName(link::Channel::kDepth, params.vehicle_id)),
        truth_channel_(link::channelName(link::Channel::kGroundTruth, params.vehicle_id)),
        bounce_(params.loop == "bounce"),
        laps_(params.laps),
        log_(std::move(log)),
        codec_(DepthCodec::Params()) {}

  // Bouncing, first finds every frame in the log (index_); then reads up to the first decodable
  // frame to learn the camera, and starts over.
  Status open() {
    if (bounce_) {
      indexFrames();
      if (index_.size() < 2)
        return Status::error("source.loop = bounce needs at least 2 frames on " + channel_ +
                             " in " + path_ + " (found " + std::to_string(index_.size()) + ")");
      if (Status rewound = restart(); !rewound.ok()) return rewound;
    }
    DepthCapture probe;
    std::string why;
    for (;;) {
      const SourceStatus status = next(&probe, &why);
      if (status == SourceStatus::kFrame) break;
      if (status == SourceStatus::kEnd)
        return Status::error(path_ + " holds no decodable frame on " + channel_ +
                             (why.empty() ? "" : " (last problem: " + why + ")"));
    }
    return restart();
  }

  const PinholeCamera& camera() const override { return camera_; }
  double depthScaleM() const override { return depth_scale_m_; }
  std::string describe() const override {
    std::string what = "LCM log " + path_ + " (" + channel_ + ")";
    if (!bounce_) return what;
    return what + ", bouncing forward and backward " +
           (laps_ == 0 ? std::string("until stopped") : "for " + std::to_string(laps_) + " laps");
  }

  SourceStatus next(DepthCapture* out, std::string* why) override {
    return bounce_ ? nextBounced(out, why) : nextInOrder(out, why);
  }

 private:
  // Ground truth in a converted dataset's log (kinfly-tum-to-log) is motion capture at its own
  // rate, in the capture system's frame. A frame gets the latest pose before it when that is close
  // enough to stand for it, re-expressed from the first such pose on, so that it is in the
  // odometry's world frame like a synthetic source's truth.
  static constexpr int64_t kMaxTruthGapUs = 20'000;  // TUM's own association tolerance

  // A frame of a bounced log: where its event starts, and what the in-order reading gave it.
  struct IndexedFrame {
    long long offset = 0;             // [bytes] the event's start in the log
    std::optional<int64_t> utime;     // [us] its recorded capture time (none: not decodable)
    bool has_ground_truth = false;
    Pose T_world_cam_truth = Pose::Identity();
  };

  // The log as recorded, each event once.
  SourceStatus nextInOrder(DepthCapture* out, std::string* why) {
    for (const lcm::LogEvent* event = log_->readNextEvent(); event != nullptr;
         event = log_->readNextEvent()) {
      if (event->channel == truth_channel_) {
        readTruth(*event);
        continue;
      }
      if (event->channel != channel_) continue;
      const SourceStatus status = decodeFrame(*event, out, why);
      if (status == SourceStatus::kFrame)
        out->has_ground_truth = truthAt(out->utime, &out->T_world_cam_truth);
      return status;
    }
    return SourceStatus::kEnd;
  }

  // The indexed frames in bounce order, capture times rescheduled.
  SourceStatus nextBounced(DepthCapture* out, std::string* why) {
    if (!advance()) return SourceStatus::kEnd;
    const IndexedFrame& frame = index_[position_];
    std::FILE* file = log_->getFilePtr();
    const lcm::LogEvent* event = nullptr;
    if (fseeko(file, static_cast<off_t>(frame.offset), SEEK_SET) == 0)
      event = log_->readNextEvent();
    if (event == nullptr) {
      *why = "the frame at byte " + std::to_string(frame.offset) + " cannot be read again";
      return SourceStatus::kSkipped;
    }
    const SourceStatus status = decodeFrame(*event, out, why);
    if (status != SourceStatus::kFrame) return status;
    out->utime = scheduledUtime(*frame.utime);  // decoded now, so it decoded when indexed
    out->has_ground_truth = frame.has_ground_truth;
    out->T_world_cam_truth = frame.T_world_cam_truth;
    return SourceStatus::kFrame;
  }

  // The next index position of the bounce, 0, 1, ..., N-1, N-2, ..., 0, 1, ...: the frame at a
  // turn is played once. False when the laps are done.
  bool advance() {
    if (!started_) {
      started_ = true;
      position_ = 0;
      return true;
    }
    const long long last = static_cast<long long>(index_.size()) - 1;
    if (position_ + direction_ < 0 || position_ + direction_ > last) {
      ++lap_;
      if (laps_ > 0 && lap_ >= laps_) return false;
      direction_ = -direction_;
    }
    position_ += direction_;
    return true;
  }

  // The first frame keeps its recorded time; every later one comes the recorded spacing between
  // it and the frame before it in the bounce after that one (at least 1 us, so that time strictly
  // increases even over repeated timestamps).
  int64_t scheduledUtime(int64_t recorded_utime) {
    if (last_recorded_utime_)
      scheduled_utime_ += std::max<int64_t>(1, std::abs(recorded_utime - *last_recorded_utime_));
    else
      scheduled_utime_ = recorded_utime;
    last_recorded_utime_ = recorded_utime;
    return scheduled_utime_;
  }

  // Every event on the depth channel, in order, with what reading it in order gives it: its
  // capture time and its ground truth.
  void indexFrames() {
    std::FILE* file = log_->getFilePtr();
    for (long long offset = ftello(file); const lcm::LogEvent* event = log_->readNextEvent();
         offset = ftello(file)) {
      if (event->channel == truth_channel_) {
        readTruth(*event);
        continue;
      }
      if (event->channel != channel_) continue;
      IndexedFrame frame;
      frame.offset = offset;
      if (link::decodeMessage(event->data, static_cast<size_t>(event->datalen),
                              link::DecodeBounds(), &message_)
              .ok()) {
        frame.utime = message_.utime;
        frame.has_ground_truth = truthAt(message_.utime, &frame.T_world_cam_truth);
      }
      index_.push_back(frame);
    }
  }

  // One depth event: the message, the camera (the first frame's; later ones must keep its size)
  // and the depth; its recorded capture time.
  SourceStatus decodeFrame(const lcm::LogEvent& event, DepthCapture* out, std::string* why) {
    const link::DecodeResult decoded = link::decodeMessage(
        event.data, static_cast<size_t>(event.datalen), link::DecodeBounds(), &message_);
    if (!decoded.ok()) {
      *why = "event " + std::to_string(event.eventnum) + ": " + toString(decoded.status) + " (" +
             decoded.detail + ")";
      return SourceStatus::kSkipped;
    }
    const PinholeCamera camera = link::cameraOf(message_);
    if (frames_ == 0) {
      camera_ = camera;
      depth_scale_m_ = message_.depth_scale_m;
    } else if (camera.width != camera_.width || camera.height != camera_.height) {
      *why = "event " + std::to_string(event.eventnum) + ": image size changed";
      return SourceStatus::kSkipped;
    }
    const CodecResult r = link::decodeDepth(codec_, message_, &out->depth);
    if (!r.ok()) {
      *why = "event " + std::to_string(event.eventnum) + ": depth does not decode: " +
             toString(r.status);
      return SourceStatus::kSkipped;
    }
    out->utime = message_.utime;
    ++frames_;
    return SourceStatus::kFrame;
  }

  void readTruth(const lcm::LogEvent& event) {
    ground_truth_t truth;
    if (!link::decodeMessage(event.data, static_cast<size_t>(event.datalen), link::DecodeBounds(),
                             &truth)
             .ok())
      return;  // ground truth is for evaluation only; a bad sample is simply not used
    truth_utime_ = truth.utime;
    T_mocap_cam_ = link::readPose(truth.T_world_cam);
    has_truth_ = true;
  }

  // The truth for a frame captured at UTIME, from the truth read so far; false when there is
  // none close enough.
  bool truthAt(int64_t utime, Pose* T_world_cam) {
    if (!has_truth_ || std::abs(utime - truth_utime_) > kMaxTruthGapUs) return false;
    if (!has_truth_origin_) {
      T_cam0_mocap_ = T_mocap_cam_.inverse();
      has_truth_origin_ = true;
    }
    *T_world_cam = orthonormalized(T_cam0_mocap_ * T_mocap_cam_);
    return true;
  }

  // Back to the log's start and the first frame, as if nothing had been read (the index stays).
  Status restart() {
    frames_ = 0;
    has_truth_ = has_truth_origin_ = false;
    started_ = false;
    position_ = 0;
    direction_ = 1;
    lap_ = 0;
    last_recorded_utime_.reset();
    scheduled_utime_ = 0;
    log_ = std::make_unique<lcm::LogFile>(path_, "r");
    if (!log_->good()) return Status::error("cannot reopen " + path_);
    return {};
  }

  std::string path_, channel_, truth_channel_;
  bool bounce_ = false;
  int laps_ = 0;
  std::unique_ptr<lcm::LogFile> log_;
  DepthCodec codec_;
  depth_keyframe_t message_;
  PinholeCamera camera_;
  double depth_scale_m_ = 0.0;
  int64_t frames_ = 0;
  bool has_truth_ = false, has_truth_origin_ = false;
  int64_t truth_utime_ = 0;
  Pose T_mocap_cam_ = Pose::Identity();
  Pose T_cam0_mocap_ = Pose::Identity();
  // Bouncing: the frames, where the bounce is, and the capture-time schedule.
  std::vector<IndexedFrame> index_;
  bool started_ = false;
  long long position_ = 0;
  int direction_ = 1;
  int lap_ = 0;
  std::optional<int64_t> last_recorded_utime_;
  int64_t scheduled_utime_ = 0;
};

}  // namespace

Status LogSourceParams::validate() const {
  if (loop != "none" && loop != "bounce")
    return Status::error("source.loop must be none or bounce (got \"" + loop + "\")");
  if (Status range = outOfRange("source.laps", laps, 0, kMaxLaps); !range.ok()) return range;
  if (loop == "none" && laps != 0)
    return Status::error("source.laps needs source.loop = bounce (got laps = " +
                         std::to_string(laps) + " with loop = none)");
  return {};
}

StatusOr<std::unique_ptr<DepthSource>> openLogSource(const LogSourceParams& params) {
  if (Status valid = params.validate(); !valid.ok()) return valid;
  if (!std::filesystem::is_regular_file(params.path))
    return Status::error("source.path: " + params.path + " is not a file");
  auto log = std::make_unique<lcm::LogFile>(params.path, "r");
  if (!log->good()) return Status::error("cannot open LCM log " + params.path);
  auto source = std::make_unique<LogSource>(params, std::move(log));
  if (Status opened = source->open(); !opened.ok()) return opened;
  return source;
}

}  // namespace kinfly::fw
