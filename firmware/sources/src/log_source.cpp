#include <lcm/lcm-cpp.hpp>

#include <cstdlib>
#include <filesystem>
#include <memory>

#include "kinfly/sources/log_source.h"
#include "kinfly/codec/depth_codec.h"
#include "kinfly/link/channels.h"
#include "kinfly/link/conversions.h"
#include "kinfly/link/decode.h"

namespace kinfly::fw {
namespace {

class LogSource : public DepthSource {
 public:
  LogSource(const LogSourceParams& params, std::unique_ptr<lcm::LogFile> log)
      : path_(params.path),
        channel_(link::channelName(link::Channel::kDepth, params.vehicle_id)),
        truth_channel_(link::channelName(link::Channel::kGroundTruth, params.vehicle_id)),
        log_(std::move(log)),
        codec_(DepthCodec::Params()) {}

  // Reads up to the first decodable frame to learn the camera, then starts over.
  Status open() {
    DepthCapture probe;
    std::string why;
    for (;;) {
      const SourceStatus status = next(&probe, &why);
      if (status == SourceStatus::kFrame) break;
      if (status == SourceStatus::kEnd)
        return Status::error(path_ + " holds no decodable frame on " + channel_ +
                             (why.empty() ? "" : " (last problem: " + why + ")"));
    }
    frames_ = 0;
    has_truth_ = has_truth_origin_ = false;
    return rewind();
  }

  const PinholeCamera& camera() const override { return camera_; }
  double depthScaleM() const override { return depth_scale_m_; }
  std::string describe() const override { return "LCM log " + path_ + " (" + channel_ + ")"; }

  SourceStatus next(DepthCapture* out, std::string* why) override {
    for (const lcm::LogEvent* event = log_->readNextEvent(); event != nullptr;
         event = log_->readNextEvent()) {
      if (event->channel == truth_channel_) {
        readTruth(*event);
        continue;
      }
      if (event->channel != channel_) continue;
      const link::DecodeResult decoded = link::decodeMessage(
          event->data, static_cast<size_t>(event->datalen), link::DecodeBounds(), &message_);
      if (!decoded.ok()) {
        *why = "event " + std::to_string(event->eventnum) + ": " + toString(decoded.status) +
               " (" + decoded.detail + ")";
        return SourceStatus::kSkipped;
      }
      const PinholeCamera camera = link::cameraOf(message_);
      if (frames_ == 0) {
        camera_ = camera;
        depth_scale_m_ = message_.depth_scale_m;
      } else if (camera.width != camera_.width || camera.height != camera_.height) {
        *why = "event " + std::to_string(event->eventnum) + ": image size changed";
        return SourceStatus::kSkipped;
      }
      const CodecResult r = link::decodeDepth(codec_, message_, &out->depth);
      if (!r.ok()) {
        *why = "event " + std::to_string(event->eventnum) + ": depth does not decode: " +
               toString(r.status);
        return SourceStatus::kSkipped;
      }
      out->utime = message_.utime;
      attachTruth(out);
      ++frames_;
      return SourceStatus::kFrame;
    }
    return SourceStatus::kEnd;
  }

 private:
  // Ground truth in a converted dataset's log (kinfly-tum-to-log) is motion capture at its own
  // rate, in the capture system's frame. A frame gets the latest pose before it when that is close
  // enough to stand for it, re-expressed from the first such pose on, so that it is in the
  // odometry's world frame like a synthetic source's truth.
  static constexpr int64_t kMaxTruthGapUs = 20'000;  // TUM's own association tolerance

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

  void attachTruth(DepthCapture* out) {
    out->has_ground_truth = has_truth_ && std::abs(out->utime - truth_utime_) <= kMaxTruthGapUs;
    if (!out->has_ground_truth) return;
    if (!has_truth_origin_) {
      T_cam0_mocap_ = T_mocap_cam_.inverse();
      has_truth_origin_ = true;
    }
    out->T_world_cam_truth = orthonormalized(T_cam0_mocap_ * T_mocap_cam_);
  }

  Status rewind() {
    log_ = std::make_unique<lcm::LogFile>(path_, "r");
    if (!log_->good()) return Status::error("cannot reopen " + path_);
    return {};
  }

  std::string path_, channel_, truth_channel_;
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
};

}  // namespace

StatusOr<std::unique_ptr<DepthSource>> openLogSource(const LogSourceParams& params) {
  if (!std::filesystem::is_regular_file(params.path))
    return Status::error("source.path: " + params.path + " is not a file");
  auto log = std::make_unique<lcm::LogFile>(params.path, "r");
  if (!log->good()) return Status::error("cannot open LCM log " + params.path);
  auto source = std::make_unique<LogSource>(params, std::move(log));
  if (Status opened = source->open(); !opened.ok()) return opened;
  return source;
}

}  // namespace kinfly::fw
