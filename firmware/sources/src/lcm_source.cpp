#include "kinfly/sources/lcm_source.h"

#include <lcm/lcm-cpp.hpp>

#include <array>
#include <chrono>
#include <cmath>
#include <optional>
#include <vector>

#include "kinfly/codec/depth_codec.h"
#include "kinfly/link/channels.h"
#include "kinfly/link/conversions.h"
#include "kinfly/link/decode.h"

namespace kinfly::fw {
namespace {

// What one next() waits for a message before it says kPaused or kWaiting (the interface's
// ~100 ms).
constexpr int kWaitMs = 100;
// A sender quiet for less than this has paused (kinfly-sim waits on the ground at every
// keyframe, and renders slower than real time): only a longer silence is reported.
constexpr auto kPause = std::chrono::seconds(1);
// Messages held between next() calls: LCM hands them over as they come, the odometry takes them
// one by one; a sender far ahead loses its oldest (counted as skipped).
constexpr size_t kHeld = 8;
// Intrinsics of two cameras that differ by less than this are the same lens (float rounding of
// the message's fields).
constexpr float kSameLensPx = 1e-3f;

class LcmSource : public DepthSource {
 public:
  LcmSource(const LcmSourceParams& params, const PinholeCamera& camera)
      : url_(params.lcm_url),
        channel_(link::channelName(link::Channel::kDepth, params.vehicle_id)),
        vehicle_id_(params.vehicle_id),
        camera_(camera),
        depth_scale_m_(LcmSourceParams::kDepthScaleM),
        lcm_(params.lcm_url),
        codec_(DepthCodec::Params()) {}

  bool good() { return lcm_.good(); }
  void subscribe() { lcm_.subscribeFunction(channel_, &LcmSource::onMessage, this); }

  const PinholeCamera& camera() const override { return camera_; }
  double depthScaleM() const override { return depth_scale_m_; }
  std::string describe() const override {
    return "LCM " + channel_ + (url_.empty() ? std::string() : " on " + url_);
  }

  SourceStatus next(DepthCapture* out, std::string* why) override {
    if (count_ == 0) lcm_.handleTimeout(kWaitMs);
    if (count_ == 0) {
      if (last_heard_ && std::chrono::steady_clock::now() - *last_heard_ < kPause) {
        return SourceStatus::kPaused;
      }
      *why = "no depth frame on " + describe() +
             (last_heard_ ? " for over " + std::to_string(kPause.count()) + " s" : " yet");
      return SourceStatus::kWaiting;
    }
    // Frames the sender overwrote are reported first, as skipped; the held ones stay for the
    // next calls.
    if (overwritten_ > 0) {
      *why = std::to_string(overwritten_) + " frame(s) arrived faster than they were taken";
      overwritten_ = 0;
      return SourceStatus::kSkipped;
    }
    std::vector<uint8_t>& bytes = held_[first_];
    first_ = (first_ + 1) % kHeld;
    --count_;
    return decode(bytes, out, why);
  }

 private:
  static void onMessage(const lcm::ReceiveBuffer* buffer, const std::string&, LcmSource* self) {
    self->hold(buffer);
  }

  void hold(const lcm::ReceiveBuffer* buffer) {
    if (count_ == kHeld) {  // the oldest goes
      first_ = (first_ + 1) % kHeld;
      --count_;
      ++overwritten_;
    }
    std::vector<uint8_t>& slot = held_[(first_ + count_) % kHeld];
    const auto* data = static_cast<const uint8_t*>(buffer->data);
    slot.assign(data, data + buffer->data_size);  // keeps its capacity: no allocation once warm
    ++count_;
    last_heard_ = std::chrono::steady_clock::now();
  }

  SourceStatus decode(const std::vector<uint8_t>& bytes, DepthCapture* out, std::string* why) {
    const link::DecodeResult decoded =
        link::decodeMessage(bytes.data(), bytes.size(), link::DecodeBounds(), &message_);
    if (!decoded.ok()) {
      *why = channel_ + ": " + toString(decoded.status) + " (" + decoded.detail + ")";
      return SourceStatus::kSkipped;
    }
    if (message_.vehicle_id != vehicle_id_) {
      *why = channel_ + ": a frame of vehicle " + std::to_string(message_.vehicle_id);
      return SourceStatus::kSkipped;
    }
    const PinholeCamera camera = link::cameraOf(message_);
    if (camera.width != camera_.width || camera.height != camera_.height ||
        std::abs(camera.fx - camera_.fx) > kSameLensPx ||
        std::abs(camera.fy - camera_.fy) > kSameLensPx ||
        std::abs(camera.cx - camera_.cx) > kSameLensPx ||
        std::abs(camera.cy - camera_.cy) > kSameLensPx ||
        message_.depth_scale_m != depth_scale_m_) {
      *why = channel_ + ": a frame's camera (" + std::to_string(camera.width) + "x" +
             std::to_string(camera.height) + ", fx " + std::to_string(camera.fx) +
             ", depth scale " + std::to_string(message_.depth_scale_m) +
             ") is not the configured one (source.width, source.height, source.intrinsics; "
             "depth in mm)";
      return SourceStatus::kSkipped;
    }
    const CodecResult r = link::decodeDepth(codec_, message_, &out->depth);
    if (!r.ok()) {
      *why = channel_ + ": depth does not decode: " + toString(r.status);
      return SourceStatus::kSkipped;
    }
    out->utime = message_.utime;
    out->has_ground_truth = false;
    return SourceStatus::kFrame;
  }

  std::string url_;
  std::string channel_;
  int vehicle_id_;
  PinholeCamera camera_;
  double depth_scale_m_;
  lcm::LCM lcm_;
  DepthCodec codec_;
  depth_keyframe_t message_;
  std::array<std::vector<uint8_t>, kHeld> held_;
  size_t first_ = 0;
  size_t count_ = 0;
  int64_t overwritten_ = 0;
  std::optional<std::chrono::steady_clock::time_point> last_heard_;  // the last frame's arrival
};

}  // namespace

Status LcmSourceParams::validate() const {
  return checkSourceSize(width_px, height_px);
}

StatusOr<std::unique_ptr<DepthSource>> openLcmSource(const LcmSourceParams& params) {
  // A Kinect's focal length, 525 px at 640 wide, as the OpenNI source assumes.
  StatusOr<PinholeCamera> camera =
      sourceCamera(525.0f, params.width_px, params.height_px, params.intrinsics);
  if (!camera.ok()) return camera.status();
  auto source = std::make_unique<LcmSource>(params, camera.value());
  if (!source->good())
    return Status::error("source.kind = lcm: cannot start LCM on '" + params.lcm_url + "'");
  source->subscribe();
  return std::unique_ptr<DepthSource>(std::move(source));
}

}  // namespace kinfly::fw
