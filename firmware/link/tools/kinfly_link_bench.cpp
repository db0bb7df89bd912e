// kinfly-link-bench: both ends of the link over real LCM, for the delivery benchmark
// (tests/bench/bench_link.py) and the two-process tests in a network namespace.
//
//   kinfly-link-bench drone  --tum DIR --rate HZ --seconds S [--key FILE]
//       publishes depth keyframes (TUM frames, encoded as they are sent) at HZ and a drone_status_t at
//       10 Hz, and with --key verifies every message on its correction channel, counting each
//       rejection; prints one JSON summary.
//   kinfly-link-bench ground --seconds S [--expect N] [--tum DIR]
//       receives keyframes, decodes them within bounds, measures latency (receive time minus the
//       message's utime, both CLOCK_REALTIME of one host) and loss (frame id gaps); with --tum,
//       checks every decoded frame bit for bit against the folder; prints one JSON summary.
#include <CLI/CLI.hpp>
#include <lcm/lcm-cpp.hpp>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <iostream>
#include <optional>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include "kinfly/codec/depth_codec.h"
#include "kinfly/link/channels.h"
#include "kinfly/link/conversions.h"
#include "kinfly/link/counters.h"
#include "kinfly/link/decode.h"
#include "kinfly/link/signing.h"
#include "kinfly/link/uplink.h"
#include "kinfly/io/png_io.h"
#include "kinfly/io/tum_dataset.h"
#include "percentile.h"

namespace {

using namespace kinfly;
using Clock = std::chrono::steady_clock;

constexpr double kTumDepthUnitsPerMetre = 5000.0;
constexpr auto kStatusPeriod = std::chrono::milliseconds(100);  // drone_status_t at 10 Hz

std::atomic<bool> g_stop{false};
void onSignal(int) { g_stop = true; }

int fail(const std::string& message) {
  std::cerr << "kinfly-link-bench: error: " << message << "\n";
  return 1;
}

Status loadFrames(const std::string& dir, int max_frames, std::vector<Image<uint16_t>>* out) {
  std::vector<TumDepthEntry> entries;
  if (Status read = readTumDepthList(dir, &entries); !read.ok()) return read;
  if (max_frames > 0 && static_cast<size_t>(max_frames) < entries.size())
    entries.resize(static_cast<size_t>(max_frames));
  if (entries.empty()) return Status::error(dir + "/depth.txt lists no frames");
  out->resize(entries.size());
  for (size_t i = 0; i < entries.size(); ++i)
    if (Status loaded = loadDepthPng(entries[i].path, &(*out)[i]); !loaded.ok()) return loaded;
  return {};
}

std::string countersJson(const link::RejectCounters& r) {
  std::ostringstream out;
  out << "{\"unsigned\": " << r.unsigned_messages << ", \"wrong_key\": " << r.wrong_key
      << ", \"bad_mac\": " << r.bad_mac << ", \"stale\": " << r.stale
      << ", \"replayed\": " << r.replayed << ", \"malformed\": " << r.malformed
      << ", \"unknown_channel\": " << r.unknown_channel
      << ", \"wrong_vehicle\": " << r.wrong_vehicle << "}";
  return out.str();
}

int waitMs(Clock::time_point until) {
  const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(until - Clock::now());
  return static_cast<int>(std::max<int64_t>(0, left.count()));
}

struct Options {
  std::string role;
  int vehicle_id = 1;
  std::string lcm_url;  // empty: LCM's default (LCM_DEFAULT_URL, else udpm://239.255.76.67:7667)
  std::string tum_dir;
  int max_frames = 0;
  double seconds = 10.0;
  // drone
  double rate_hz = 10.0;
  std::string key_path;
  std::string encoding = "palette_rvl_zstd";
  double window_s = link::VerifierParams().window_s;
  // ground
  int64_t expect = 0;
};

// ---- drone end ------------------------------------------------------------------------------

class DroneEnd {
 public:
  explicit DroneEnd(std::optional<link::CorrectionReceiver> corrections)
      : corrections_(std::move(corrections)) {}

  void onMessage(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    const auto parsed = link::parseChannel(channel);
    if (!parsed) {
      ++rejects_.unknown_channel;
    } else if (parsed->channel == link::Channel::kCorrection) {
      if (corrections_)
        corrections_->receive(rbuf->data, rbuf->data_size, link::wallClockUtime());
      else ++rejects_.unsigned_messages;  // without a key nothing can be authenticated
    }
    // Everything else on our channels is our own traffic looping back, or the ground's status.
  }

  link::RejectCounters rejects() const {
    link::RejectCounters all = rejects_;
    if (corrections_) all += corrections_->rejects();
    return all;
  }
  int64_t accepted() const { return corrections_ ? corrections_->accepted() : 0; }

 private:
  std::optional<link::CorrectionReceiver> corrections_;
  link::RejectCounters rejects_;
};

int runDrone(const Options& options) {
  DepthCodec::Params codec_params;
  if (!parseDepthEncoding(options.encoding, &codec_params.encoding))
    return fail("--encoding: unknown encoding \"" + options.encoding + "\"");
  std::optional<link::CorrectionReceiver> corrections;
  if (!options.key_path.empty()) {
    const StatusOr<link::Key> key = link::loadKeyFile(options.key_path);
    if (!key.ok()) return fail(key.status().message());
    link::VerifierParams verifier;
    verifier.window_s = options.window_s;
    if (const Status valid = verifier.validate(); !valid.ok())
      return fail("--window: " + valid.message());
    corrections.emplace(*key, options.vehicle_id, verifier, link::DecodeBounds());
  }
  if (options.tum_dir.empty()) return fail("drone: --tum is required");
  std::vector<Image<uint16_t>> frames;
  if (const Status loaded = loadFrames(options.tum_dir, options.max_frames, &frames); !loaded.ok())
    return fail(loaded.message());

  lcm::LCM lcm(options.lcm_url);
  if (!lcm.good()) return fail("cannot start LCM on \"" + options.lcm_url + "\"");
  DroneEnd end(std::move(corrections));
  lcm.subscribe(link::vehicleChannelsRegex(options.vehicle_id), &DroneEnd::onMessage, &end);

  DepthCodec codec(codec_params);
  PinholeCamera camera;
  depth_keyframe_t keyframe;
  std::vector<double> payload_bytes;
  const std::string keyframe_channel =
      link::channelName(link::Channel::kKeyframe, options.vehicle_id);
  const std::string status_channel = link::channelName(link::Channel::kStatus, options.vehicle_id);
  const auto frame_period = std::chrono::duration_cast<Clock::duration>(
      std::chrono::duration<double>(1.0 / options.rate_hz));
  const Clock::time_point start = Clock::now();
  const Clock::time_point stop = start + std::chrono::duration_cast<Clock::duration>(
                                             std::chrono::duration<double>(options.seconds));
  Clock::time_point next_frame = start, next_status = start;
  int64_t sent = 0;
  while (!g_stop && Clock::now() < stop) {
    if (Clock::now() >= next_frame) {
      const Image<uint16_t>& raw = frames[static_cast<size_t>(sent) % frames.size()];
      camera.width = raw.width();
      camera.height = raw.height();
      keyframe.vehicle_id = options.vehicle_id;
      link::fillKeyframe({0, sent, sent, Pose::Identity(), TrackingStatus::kGivenPose}, &keyframe);
      const CodecResult r =
          link::encodeDepth(codec, raw, camera, 1.0 / kTumDepthUnitsPerMetre, &keyframe);
      if (!r.ok()) return fail(std::string("cannot encode frame: ") + toString(r.status));
      // Stamped after encoding: the latency measured is the link's alone.
      keyframe.utime = link::wallClockUtime();
      lcm.publish(keyframe_channel, &keyframe);
      payload_bytes.push_back(static_cast<double>(keyframe.payload_size));
      ++sent;
      next_frame += frame_period;
    }
    if (Clock::now() >= next_status) {
      link::DroneHealth health;
      health.utime = link::wallClockUtime();
      health.keyframe_rate_hz = static_cast<float>(options.rate_hz);
      health.keyframes_sent = sent;
      health.last_keyframe_id = sent - 1;
      health.tracking = TrackingStatus::kGivenPose;
      health.rejects = end.rejects();
      health.corrections_accepted = end.accepted();
      drone_status_t status{};
      status.vehicle_id = options.vehicle_id;
      link::fillDroneStatus(health, &status);
      lcm.publish(status_channel, &status);
      next_status += kStatusPeriod;
    }
    lcm.handleTimeout(waitMs(std::min(next_frame, next_status)));
  }
  std::printf(
      "{\"role\": \"drone\", \"sent\": %lld, \"rate_hz\": %g, \"payload_bytes_median\": %.0f, "
      "\"corrections_accepted\": %lld, \"rejected\": %s}\n",
      static_cast<long long>(sent), options.rate_hz, tools::percentile(payload_bytes, 0.5),
      static_cast<long long>(end.accepted()), countersJson(end.rejects()).c_str());
  return 0;
}

// ---- ground end -----------------------------------------------------------------------------

class GroundEnd {
 public:
  explicit GroundEnd(std::vector<Image<uint16_t>> reference)
      : codec_(DepthCodec::Params()), reference_(std::move(reference)) {}

  void onMessage(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    const int64_t now = link::wallClockUtime();
    const auto parsed = link::parseChannel(channel);
    if (!parsed) {
      ++rejects_.unknown_channel;
      return;
    }
    if (parsed->channel != link::Channel::kKeyframe) return;
    const link::DecodeResult decoded =
        link::decodeMessage(rbuf->data, rbuf->data_size, link::DecodeBounds(), &keyframe_);
    if (!decoded.ok()) {
      rejects_.count(decoded.status);
      return;
    }
    if (keyframe_.vehicle_id != parsed->vehicle_id) {
      ++rejects_.wrong_vehicle;
      return;
    }
    if (!link::decodeDepth(codec_, keyframe_, &depth_).ok()) {
      ++rejects_.malformed;
      return;
    }
    latency_ms_.push_back(static_cast<double>(now - keyframe_.utime) * 1e-3);
    frame_ids_.insert(keyframe_.frame_id);
    bytes_.push_back(static_cast<double>(rbuf->data_size));
    if (!reference_.empty()) {
      const Image<uint16_t>& want =
          reference_[static_cast<size_t>(keyframe_.frame_id) % reference_.size()];
      const bool same = want.width() == depth_.width() && want.height() == depth_.height() &&
                        std::memcmp(want.data(), depth_.data(),
                                    want.numPixels() * sizeof(uint16_t)) == 0;
      if (!same) ++mismatches_;
    }
  }

  int64_t received() const { return static_cast<int64_t>(frame_ids_.size()); }

  void print(bool checked) const {
    // Frames between the first and the last received that never arrived; frames lost before
    // the first or after the last cannot be told from frames never sent.
    const int64_t span =
        frame_ids_.empty() ? 0 : *frame_ids_.rbegin() - *frame_ids_.begin() + 1;
    const int64_t lost = span - received();
    std::printf(
        "{\"role\": \"ground\", \"received\": %lld, \"lost\": %lld, \"loss_fraction\": %.6f, "
        "\"first_frame_id\": %lld, \"last_frame_id\": %lld, "
        "\"latency_ms\": {\"median\": %.3f, \"p99\": %.3f, \"max\": %.3f}, "
        "\"message_bytes_median\": %.0f, \"bit_exact\": %s, \"rejected\": %s}\n",
        static_cast<long long>(received()), static_cast<long long>(lost),
        span > 0 ? static_cast<double>(lost) / static_cast<double>(span) : 0.0,
        static_cast<long long>(frame_ids_.empty() ? -1 : *frame_ids_.begin()),
        static_cast<long long>(frame_ids_.empty() ? -1 : *frame_ids_.rbegin()),
        tools::percentile(latency_ms_, 0.5), tools::percentile(latency_ms_, 0.99),
        latency_ms_.empty() ? 0.0 : *std::max_element(latency_ms_.begin(), latency_ms_.end()),
        tools::percentile(bytes_, 0.5),
        !checked ? "null" : (mismatches_ == 0 && received() > 0 ? "true" : "false"),
        countersJson(rejects_).c_str());
  }

 private:
  DepthCodec codec_;
  std::vector<Image<uint16_t>> reference_;
  depth_keyframe_t keyframe_;
  Image<uint16_t> depth_;
  std::set<int64_t> frame_ids_;
  std::vector<double> latency_ms_, bytes_;
  int64_t mismatches_ = 0;
  link::RejectCounters rejects_;
};

int runGround(const Options& options) {
  std::vector<Image<uint16_t>> reference;
  if (!options.tum_dir.empty()) {
    if (const Status loaded = loadFrames(options.tum_dir, options.max_frames, &reference);
        !loaded.ok())
      return fail(loaded.message());
  }
  lcm::LCM lcm(options.lcm_url);
  if (!lcm.good()) return fail("cannot start LCM on \"" + options.lcm_url + "\"");
  GroundEnd end(std::move(reference));
  lcm.subscribe(link::vehicleChannelsRegex(options.vehicle_id), &GroundEnd::onMessage, &end);
  // Ready line for the driving script: it starts the sender only after the subscription exists.
  std::fprintf(stderr, "kinfly-link-bench: ground listening\n");
  const Clock::time_point stop = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                                    std::chrono::duration<double>(options.seconds));
  while (!g_stop && Clock::now() < stop && (options.expect == 0 || end.received() < options.expect))
    lcm.handleTimeout(std::min(waitMs(stop), 100));
  end.print(!options.tum_dir.empty());
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Both ends of kinfly's link over real LCM: keyframe delivery and signed uplink."};
  app.require_subcommand(1);
  Options o;
  const auto addCommon = [&](CLI::App* sub) {
    sub->add_option("--vehicle", o.vehicle_id, "vehicle id")
        ->check(CLI::Range(0, link::kMaxVehicleId))
        ->capture_default_str();
    sub->add_option("--lcm-url", o.lcm_url, "LCM provider URL (default: LCM's own default)");
    sub->add_option("--seconds", o.seconds, "how long to run")
        ->check(CLI::PositiveNumber)
        ->capture_default_str();
    sub->add_option("--max-frames", o.max_frames, "use only the first N frames of --tum");
  };
  CLI::App* drone = app.add_subcommand("drone", "publish keyframes and status, verify corrections");
  addCommon(drone);
  drone->add_option("--tum", o.tum_dir, "TUM folder whose depth frames are sent, cycling")
      ->required()
      ->check(CLI::ExistingDirectory);
  drone->add_option("--rate", o.rate_hz, "keyframes per second")
      ->check(CLI::Range(0.1, 100.0))
      ->capture_default_str();
  drone->add_option("--key", o.key_path, "vehicle key file (kinfly-keygen) to verify corrections");
  drone->add_option("--window", o.window_s, "accepted signing-time window in seconds")
      ->capture_default_str();
  drone->add_option("--encoding", o.encoding, "raw16, rvl, rvl_zstd or palette_rvl_zstd")
      ->capture_default_str();
  CLI::App* ground = app.add_subcommand("ground", "receive keyframes, measure loss and latency");
  addCommon(ground);
  ground->add_option("--tum", o.tum_dir, "TUM folder to check decoded frames against")
      ->check(CLI::ExistingDirectory);
  ground->add_option("--expect", o.expect, "stop after this many keyframes");
  CLI11_PARSE(app, argc, argv);

  std::signal(SIGINT, onSignal);
  std::signal(SIGTERM, onSignal);
  return drone->parsed() ? runDrone(o) : runGround(o);
}
