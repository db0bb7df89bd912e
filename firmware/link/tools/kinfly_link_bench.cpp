// kinfly-link-bench: both ends of the link over real LCM, for the delivery benchmark
// (tests/bench/bench_link.py) and the two-process tests in a network namespace. Keyframes travel
// as kinfly-fw sends them: in FEC-coded chunks (docs/wire.md, "Keyframes in chunks").
//
//   kinfly-link-bench drone  --tum DIR --rate HZ --seconds S [--key FILE] [--mtu B]
//                            [--loss P --loss-run L] [--spread-ms T] [--rate-kbit R] [--repair]
//       encodes TUM frames at HZ and sends each as chunks (m recovery chunks per group for the
//       loss P in runs of L, recoveryChunks()), spread evenly over T ms and at most R kbit/s (a
//       token bucket); a frame due while the last one is still going out is skipped. A
//       drone_status_t at 10 Hz, the last one marked final. With --repair it answers
//       chunk_request_t; with --key it verifies every message on its correction channel,
//       counting each rejection and timing each accepted correction (receive time minus
//       signing time, one host's CLOCK_REALTIME); either way it stays listening 1.5 s after
//       its final status. Prints one JSON summary.
//   kinfly-link-bench ground --seconds S [--expect N] [--tum DIR] [--repair] [--key FILE]
//                            [--correction-copies N] [--copy-interval-ms MS]
//       assembles chunks, decodes keyframes within bounds, measures latency (receive time minus
//       the keyframe's utime, stamped after encoding) and loss (of keyframes: those the drone's
//       final status says it sent; of chunks: sequence gaps); with --tum checks every keyframe
//       bit for bit; with --repair asks for incomplete groups as the ground station does
//       (link::RepairScheduler: a keyframe's once the next one starts, again while incomplete)
//       and at the end; with --key signs a correction of each keyframe. Ends after the drone's
//       final status (or 1 s without its status) and a last repair round. Prints one JSON
//       summary.
#include <CLI/CLI.hpp>
#include <lcm/lcm-cpp.hpp>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <deque>
#include <iostream>
#include <optional>
#include <set>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include "kinfly/codec/depth_codec.h"
#include "kinfly/fw/send_budget.h"
#include "kinfly/io/png_io.h"
#include "kinfly/io/tum_dataset.h"
#include "kinfly/link/channels.h"
#include "kinfly/link/chunking.h"
#include "kinfly/link/conversions.h"
#include "kinfly/link/counters.h"
#include "kinfly/link/decode.h"
#include "kinfly/link/repair.h"
#include "kinfly/link/signing.h"
#include "kinfly/link/uplink.h"
#include "percentile.h"

namespace {

using namespace kinfly;
using Clock = std::chrono::steady_clock;

constexpr double kTumDepthUnitsPerMetre = 5000.0;
constexpr double kStatusPeriodS = 0.1;  // drone_status_t at 10 Hz
// The drone's final status goes out this many times, 10 ms apart: all are lost once in 10^10 runs
// at 10 % independent loss, and once in 150 in bursts of mean 5 at 5 % (0.05 * 0.8^9), when the
// ground ends after its quiet time instead.
constexpr int kFinalStatusCopies = 10;
// [s] the drone keeps answering chunk requests and taking corrections after its final status.
constexpr double kDroneLingerS = 1.5;
// [s] without a drone status, and nothing left to handle, the ground takes the drone to have
// stopped (its final statuses lost); within the drone's linger, so the last repairs are answered.
constexpr double kDroneQuietS = 1.0;
// [s] the ground's last repair rounds (asks again included) and their answers.
constexpr double kLastRepairWaitS = 0.5;
// Messages LCM queues for a subscription before it drops the newest (its default is 30): a
// keyframe is ~45 chunks, which arrive within the spread while the handler may wait for a core
// on a loaded machine. 4096 chunks (~6 MB) hold some 90 keyframes.
constexpr int kChunkQueueMessages = 4096;
// The drone's subscription: corrections and chunk requests, a few per keyframe.
constexpr int kUplinkQueueMessages = 256;

std::atomic<bool> g_stop{false};
void onSignal(int) { g_stop = true; }

int fail(const std::string& message) {
  std::cerr << "kinfly-link-bench: error: " << message << "\n";
  return 1;
}

double secondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
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

// {"median": .., "p99": .., "max": ..} of milliseconds, null when there are none.
std::string latencyJson(const std::vector<double>& ms) {
  if (ms.empty()) return "null";
  char text[128];
  std::snprintf(text, sizeof text, "{\"median\": %.3f, \"p99\": %.3f, \"max\": %.3f}",
                tools::percentile(ms, 0.5), tools::percentile(ms, 0.99),
                *std::max_element(ms.begin(), ms.end()));
  return text;
}

// Rounded up, so that a wait shorter than a millisecond sleeps rather than spins.
int waitMs(double seconds) {
  return static_cast<int>(std::clamp(std::ceil(seconds * 1e3), 0.0, 100.0));
}

struct Options {
  std::string role;
  int vehicle_id = 1;
  std::string lcm_url;  // empty: LCM's default (LCM_DEFAULT_URL, else udpm://239.255.76.67:7667)
  std::string tum_dir;
  int max_frames = 0;
  double seconds = 10.0;
  std::string key_path;
  bool repair = false;
  // drone
  double rate_hz = 10.0;
  std::string encoding = "palette_rvl_zstd";
  double window_s = link::VerifierParams().window_s;
  int mtu_bytes = link::ChunkEncoder::Params().mtu_bytes;
  double loss = 0.0;      // the loss the link is expected to have, for the redundancy
  double loss_run = 1.0;  // [chunks] its mean run
  double spread_ms = 20.0;
  double rate_kbit = 0.0;  // 0: no cap
  // ground
  int64_t expect = 0;
  // Each correction goes out this many times, copy_interval_ms apart (as the ground station
  // sends them), so a loss run rarely takes them all, and all before the next keyframe's.
  int correction_copies = 4;
  double copy_interval_ms = 30.0;
};

// ---- drone end ------------------------------------------------------------------------------

class DroneEnd {
 public:
  DroneEnd(const Options& options, lcm::LCM* lcm,
           std::optional<link::CorrectionReceiver> corrections)
      : options_(options), lcm_(lcm), corrections_(std::move(corrections)),
        encoder_(encoderParams(options)),
        chunk_channel_(link::channelName(link::Channel::kKeyframeChunk, options.vehicle_id)) {
    // A burst of two chunks, as kinfly-fw: the cap's pace holds from the first keyframe on.
    if (options.rate_kbit > 0)
      bucket_.emplace(options.rate_kbit * 1e3 / 8.0, 2.0 * options.mtu_bytes);
  }

  static link::ChunkEncoder::Params encoderParams(const Options& options) {
    link::ChunkEncoder::Params params;
    params.mtu_bytes = options.mtu_bytes;
    return params;
  }

  void onMessage(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    const auto parsed = link::parseChannel(channel);
    if (!parsed) {
      ++rejects_.unknown_channel;
    } else if (parsed->channel == link::Channel::kCorrection) {
      onCorrection(rbuf);
    } else if (parsed->channel == link::Channel::kChunkRequest && options_.repair) {
      onChunkRequest(rbuf);
    }
    // Everything else on our channels is our own traffic looping back.
  }

  // Cuts the keyframe into chunks, which go out from now on as the pacing allows.
  Status start(const depth_keyframe_t& keyframe) {
    const int originals = encoder_.originalsPerGroup(keyframe.getEncodedSize());
    const int recovery = link::recoveryChunks(
        originals, {options_.loss, options_.loss_run}, link::RedundancyParams());
    const StatusOr<link::ChunkSpan> chunks = encoder_.encode(keyframe, recovery);
    if (!chunks.ok()) return chunks.status();
    pending_ = *chunks;
    next_chunk_ = 0;
    started_s_ = now();
    for (const keyframe_chunk_t& c : pending_)
      (c.index < c.originals ? originals_sent_ : recovery_sent_) += 1;
    return {};
  }
  bool sending() const { return next_chunk_ < pending_.size(); }

  // Sends what is due; the seconds until the next chunk is (large when none is pending).
  double sendDue() {
    while (sending()) {
      const keyframe_chunk_t& chunk = pending_.first[next_chunk_];
      // Spread evenly: chunk i of n leaves spread * i / n after the keyframe's first.
      const double due_s = started_s_ + options_.spread_ms * 1e-3 *
                                            static_cast<double>(next_chunk_) /
                                            static_cast<double>(pending_.size());
      const double now_s = now();
      double wait_s = due_s - now_s;
      if (bucket_ && wait_s <= 0) wait_s = bucket_->waitS(chunk.getEncodedSize(), now_s);
      if (wait_s > 0) return wait_s;
      if (bucket_) bucket_->take(chunk.getEncodedSize(), now_s);
      publish(chunk);
      ++next_chunk_;
    }
    return 1.0;
  }

  void publishStatus(int64_t keyframes_sent, int64_t skipped, bool is_final) {
    link::DroneHealth health;
    health.utime = link::wallClockUtime();
    health.is_final = is_final;
    health.keyframe_rate_hz = static_cast<float>(options_.rate_hz);
    health.keyframes_sent = keyframes_sent;
    health.last_keyframe_id = keyframes_sent - 1;
    health.keyframes_skipped = skipped;
    health.chunks_sent = next_sequence_;
    health.chunks_resent = resent_;
    health.send_budget_bps = static_cast<float>(options_.rate_kbit * 1e3);
    health.tracking = TrackingStatus::kGivenPose;
    health.rejects = rejects();
    health.corrections_accepted = accepted();
    drone_status_t status{};
    status.vehicle_id = options_.vehicle_id;
    link::fillDroneStatus(health, &status);
    lcm_->publish(link::channelName(link::Channel::kStatus, options_.vehicle_id), &status);
  }

  link::RejectCounters rejects() const {
    link::RejectCounters all = rejects_;
    if (corrections_) all += corrections_->rejects();
    return all;
  }
  int64_t accepted() const { return corrections_ ? corrections_->accepted() : 0; }
  int64_t duplicates() const { return corrections_ ? corrections_->duplicates() : 0; }
  int64_t chunksSent() const { return next_sequence_; }
  int64_t originalsSent() const { return originals_sent_; }
  int64_t recoverySent() const { return recovery_sent_; }
  int64_t resent() const { return resent_; }
  const std::vector<double>& correctionLatencyMs() const { return correction_latency_ms_; }

 private:
  double now() const { return secondsSince(began_); }

  void onCorrection(const lcm::ReceiveBuffer* rbuf) {
    if (!corrections_) {
      ++rejects_.unsigned_messages;  // without a key nothing can be authenticated
      return;
    }
    const int64_t now_utime = link::wallClockUtime();
    if (!corrections_->receive(rbuf->data, rbuf->data_size, now_utime)) return;
    // Accepted, so the envelope decodes: its signing time is the ground's send time.
    if (link::decodeMessage(rbuf->data, rbuf->data_size, link::DecodeBounds(), &envelope_).ok())
      correction_latency_ms_.push_back(static_cast<double>(now_utime - envelope_.utime) * 1e-3);
  }

  void onChunkRequest(const lcm::ReceiveBuffer* rbuf) {
    const link::DecodeResult r =
        link::decodeMessage(rbuf->data, rbuf->data_size, link::DecodeBounds(), &request_);
    if (!r.ok()) {
      rejects_.count(r.status);
      return;
    }
    if (request_.vehicle_id != options_.vehicle_id) {
      ++rejects_.wrong_vehicle;
      return;
    }
    // Answered at once, ahead of the keyframe being sent, and paid from the same budget.
    for (int i = 0; i < request_.index_count; ++i) {
      const keyframe_chunk_t* chunk = encoder_.resend(request_, i);
      if (!chunk) break;  // no longer kept, or its repair budget spent
      if (bucket_) bucket_->charge(chunk->getEncodedSize(), now());
      publish(*chunk);
      ++resent_;
    }
  }

  void publish(const keyframe_chunk_t& chunk) {
    out_ = chunk;
    // Numbered in the order they leave, resends included, as kinfly-fw: the ground's loss count
    // from the gaps then sees only the network's reordering.
    out_.sequence = next_sequence_++;
    out_.sent_utime = link::wallClockUtime();
    lcm_->publish(chunk_channel_, &out_);
  }

  const Options& options_;
  lcm::LCM* lcm_;
  std::optional<link::CorrectionReceiver> corrections_;
  link::ChunkEncoder encoder_;
  std::optional<fw::TokenBucket> bucket_;
  std::string chunk_channel_;
  Clock::time_point began_ = Clock::now();
  link::ChunkSpan pending_;
  size_t next_chunk_ = 0;
  double started_s_ = 0.0;
  keyframe_chunk_t out_;
  chunk_request_t request_;
  signed_t envelope_;
  int64_t next_sequence_ = 0, originals_sent_ = 0, recovery_sent_ = 0, resent_ = 0;
  std::vector<double> correction_latency_ms_;
  link::RejectCounters rejects_;
};

int runDrone(const Options& options) {
  DepthCodec::Params codec_params;
  if (!parseDepthEncoding(options.encoding, &codec_params.encoding))
    return fail("--encoding: unknown encoding \"" + options.encoding + "\"");
  if (const Status valid = DroneEnd::encoderParams(options).validate(); !valid.ok())
    return fail("--mtu: " + valid.message());
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
  DroneEnd end(options, &lcm, std::move(corrections));
  // Every channel of this vehicle but its own chunks, which multicast loops back (LCM's patterns
  // are GLib regular expressions), as kinfly-fw subscribes.
  const std::string channels =
      "(?!" + link::channelName(link::Channel::kKeyframeChunk, options.vehicle_id) + "$)" +
      link::vehicleChannelsRegex(options.vehicle_id);
  lcm.subscribe(channels, &DroneEnd::onMessage, &end)->setQueueCapacity(kUplinkQueueMessages);

  DepthCodec codec(codec_params);
  PinholeCamera camera;
  depth_keyframe_t keyframe;
  keyframe.vehicle_id = options.vehicle_id;
  std::vector<double> payload_bytes;
  const Clock::time_point start = Clock::now();
  const double frame_period_s = 1.0 / options.rate_hz;
  double next_frame_s = 0.0, next_status_s = 0.0;
  int64_t ticks = 0, sent = 0, skipped = 0;
  // Frames are taken until --seconds; the keyframe going out then still goes out whole.
  while (!g_stop && (secondsSince(start) < options.seconds || end.sending())) {
    const double now_s = secondsSince(start);
    if (now_s >= next_frame_s && now_s < options.seconds) {
      if (end.sending()) {
        ++skipped;  // the link is still busy with the last one: as kinfly-fw, the newest waits
      } else {
        const Image<uint16_t>& raw = frames[static_cast<size_t>(ticks) % frames.size()];
        camera.width = raw.width();
        camera.height = raw.height();
        link::fillKeyframe({0, ticks, sent, Pose::Identity(), TrackingStatus::kGivenPose},
                           &keyframe);
        const CodecResult r =
            link::encodeDepth(codec, raw, camera, 1.0 / kTumDepthUnitsPerMetre, &keyframe);
        if (!r.ok()) return fail(std::string("cannot encode frame: ") + toString(r.status));
        // Stamped after encoding: the latency measured is the link's alone (pacing included).
        keyframe.utime = link::wallClockUtime();
        if (const Status started = end.start(keyframe); !started.ok())
          return fail("cannot cut keyframe into chunks: " + started.message());
        payload_bytes.push_back(static_cast<double>(keyframe.payload_size));
        ++sent;
      }
      ++ticks;
      next_frame_s += frame_period_s;
    }
    const double chunk_wait_s = end.sendDue();
    if (secondsSince(start) >= next_status_s) {
      end.publishStatus(sent, skipped, /*is_final=*/false);
      next_status_s += kStatusPeriodS;
    }
    const double now_after_s = secondsSince(start);
    lcm.handleTimeout(waitMs(std::min({chunk_wait_s, next_frame_s - now_after_s,
                                       next_status_s - now_after_s})));
  }
  for (int i = 0; i < kFinalStatusCopies && !g_stop; ++i) {
    end.publishStatus(sent, skipped, /*is_final=*/true);
    lcm.handleTimeout(10);
  }
  if (options.repair || !options.key_path.empty()) {
    const Clock::time_point linger = Clock::now();
    while (!g_stop && secondsSince(linger) < kDroneLingerS) lcm.handleTimeout(50);
  }
  const int64_t originals = end.originalsSent();
  std::printf(
      "{\"role\": \"drone\", \"sent\": %lld, \"skipped\": %lld, \"rate_hz\": %g, "
      "\"payload_bytes_median\": %.0f, \"chunks_sent\": %lld, \"originals\": %lld, "
      "\"recovery\": %lld, \"resent\": %lld, \"overhead\": %.4f, \"overhead_with_resent\": %.4f, "
      "\"corrections_accepted\": %lld, \"corrections_duplicate\": %lld, "
      "\"correction_latency_ms\": %s, \"rejected\": %s}\n",
      static_cast<long long>(sent), static_cast<long long>(skipped), options.rate_hz,
      tools::percentile(payload_bytes, 0.5), static_cast<long long>(end.chunksSent()),
      static_cast<long long>(originals), static_cast<long long>(end.recoverySent()),
      static_cast<long long>(end.resent()),
      originals ? static_cast<double>(end.recoverySent()) / static_cast<double>(originals) : 0.0,
      originals ? static_cast<double>(end.recoverySent() + end.resent()) /
                      static_cast<double>(originals)
                : 0.0,
      static_cast<long long>(end.accepted()), static_cast<long long>(end.duplicates()),
      latencyJson(end.correctionLatencyMs()).c_str(),
      countersJson(end.rejects()).c_str());
  return 0;
}

// ---- ground end -----------------------------------------------------------------------------

class GroundEnd {
 public:
  GroundEnd(const Options& options, lcm::LCM* lcm, std::vector<Image<uint16_t>> reference,
            std::optional<link::Key> key)
      : options_(options), lcm_(lcm), codec_(DepthCodec::Params()),
        reference_(std::move(reference)),
        assembler_(options.vehicle_id, link::ChunkAssembler::Params()),
        request_channel_(link::channelName(link::Channel::kChunkRequest, options.vehicle_id)),
        correction_channel_(link::channelName(link::Channel::kCorrection, options.vehicle_id)) {
    if (key) signer_.emplace(*key, options.vehicle_id, link::wallClockUtime());
  }

  void onMessage(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    const auto parsed = link::parseChannel(channel);
    if (!parsed) {
      ++rejects_.unknown_channel;
    } else if (parsed->channel == link::Channel::kKeyframeChunk) {
      onChunk(rbuf);
    } else if (parsed->channel == link::Channel::kStatus) {
      onDroneStatus(rbuf);
    }
    // Everything else on our channels is our own traffic looping back.
  }

  // The requests due now (the older keyframes' only, unless include_newest).
  void askRepairs(bool include_newest) {
    const int64_t now_us =
        std::chrono::duration_cast<std::chrono::microseconds>(Clock::now().time_since_epoch()).count();
    const int n = repair_.due(assembler_, include_newest, now_us, &requests_);
    for (int i = 0; i < n; ++i) lcm_->publish(request_channel_, &requests_[static_cast<size_t>(i)]);
  }

  int64_t received() const { return static_cast<int64_t>(keyframe_ids_.size()); }
  bool droneDone() const { return drone_final_; }
  // [s] since the drone's last status; negative before the first.
  double sinceDroneStatus() const {
    return status_heard_ ? secondsSince(last_status_) : -1.0;
  }

  void print(bool checked) const {
    // With the drone's final count, every keyframe it sent and that did not arrive; without it,
    // those between the first and the last received (frames lost before the first or after the
    // last cannot be told from frames never sent).
    const int64_t first = keyframe_ids_.empty() ? -1 : *keyframe_ids_.begin();
    const int64_t last = keyframe_ids_.empty() ? -1 : *keyframe_ids_.rbegin();
    const int64_t sent = drone_final_ ? std::max(drone_sent_, last + 1)
                                      : (keyframe_ids_.empty() ? 0 : last - first + 1);
    const int64_t lost = sent - received();
    const link::ChunkCounters& c = assembler_.counters();
    const link::LossStats loss = assembler_.loss();
    std::printf(
        "{\"role\": \"ground\", \"received\": %lld, \"lost\": %lld, \"loss_fraction\": %.6f, "
        "\"drone_sent\": %s, \"first_keyframe_id\": %lld, \"last_keyframe_id\": %lld, "
        "\"latency_ms\": %s, \"message_bytes_median\": %.0f, \"bit_exact\": %s, "
        "\"keyframes\": {\"recovered_by_fec\": %lld, \"repaired\": %lld, \"evicted\": %lld, "
        "\"incomplete_at_end\": %lld}, "
        "\"chunks\": {\"received\": %lld, \"stored\": %lld, \"duplicate\": %lld, "
        "\"surplus\": %lld, \"stale\": %lld, \"mismatch\": %lld, \"malformed\": %lld, "
        "\"digest_mismatch\": %lld}, "
        "\"link_loss\": {\"fraction\": %.6f, \"mean_run\": %.3f, \"expected\": %lld, "
        "\"received\": %lld}, \"repair_requests\": %lld, \"corrections_sent\": %lld, "
        "\"rejected\": %s}\n",
        static_cast<long long>(received()), static_cast<long long>(lost),
        sent > 0 ? static_cast<double>(lost) / static_cast<double>(sent) : 0.0,
        drone_final_ ? std::to_string(drone_sent_).c_str() : "null",
        static_cast<long long>(first), static_cast<long long>(last),
        latencyJson(latency_ms_).c_str(), tools::percentile(bytes_, 0.5),
        !checked ? "null" : (mismatches_ == 0 && received() > 0 ? "true" : "false"),
        static_cast<long long>(fec_recovered_), static_cast<long long>(repaired_),
        static_cast<long long>(c.keyframes_evicted),
        static_cast<long long>(incompleteKeyframes()),
        static_cast<long long>(c.chunks), static_cast<long long>(c.stored),
        static_cast<long long>(c.duplicate), static_cast<long long>(c.surplus),
        static_cast<long long>(c.stale), static_cast<long long>(c.mismatch),
        static_cast<long long>(c.malformed), static_cast<long long>(c.digest_mismatch),
        loss.lossFraction(), loss.meanLossRun(), static_cast<long long>(loss.expected),
        static_cast<long long>(loss.received), static_cast<long long>(repair_.requests()),
        static_cast<long long>(corrections_sent_), countersJson(rejects_).c_str());
  }

 private:
  // Keyframes still being assembled.
  int64_t incompleteKeyframes() const {
    std::set<int64_t> ids;
    const int n = assembler_.repairRequests(true, &requests_);
    for (int i = 0; i < n; ++i) ids.insert(requests_[static_cast<size_t>(i)].keyframe_id);
    return static_cast<int64_t>(ids.size());
  }

  void onDroneStatus(const lcm::ReceiveBuffer* rbuf) {
    drone_status_t status;
    const link::DecodeResult r =
        link::decodeMessage(rbuf->data, rbuf->data_size, link::DecodeBounds(), &status);
    if (!r.ok()) {
      rejects_.count(r.status);
      return;
    }
    if (status.vehicle_id != options_.vehicle_id) {
      ++rejects_.wrong_vehicle;
      return;
    }
    status_heard_ = true;
    last_status_ = Clock::now();
    drone_sent_ = status.keyframes_sent;
    drone_final_ = drone_final_ || status.run_state == drone_status_t::RUN_FINAL;
  }

  void onChunk(const lcm::ReceiveBuffer* rbuf) {
    const int64_t now = link::wallClockUtime();
    const link::DecodeResult decoded =
        link::decodeMessage(rbuf->data, rbuf->data_size, link::DecodeBounds(), &chunk_);
    if (!decoded.ok()) {
      rejects_.count(decoded.status);
      return;
    }
    const int64_t recovered_before = assembler_.counters().keyframes_recovered;
    const link::ChunkStatus status = assembler_.add(chunk_);
    const bool kept =
        status == link::ChunkStatus::kStored || status == link::ChunkStatus::kCompleted;
    if (status == link::ChunkStatus::kCompleted) {
      const bool repaired = repair_.asked(chunk_.utime, chunk_.keyframe_id);
      repaired_ += repaired;
      fec_recovered_ +=
          !repaired && assembler_.counters().keyframes_recovered > recovered_before;
      onKeyframe(now);
    }
    // The keyframes before the newest have had all their chunks sent.
    if (kept && options_.repair) askRepairs(/*include_newest=*/false);
  }

  void onKeyframe(int64_t now) {
    const std::vector<uint8_t>& message = assembler_.message();
    const link::DecodeResult decoded =
        link::decodeMessage(message.data(), message.size(), link::DecodeBounds(), &keyframe_);
    if (!decoded.ok()) {
      rejects_.count(decoded.status);
      return;
    }
    if (keyframe_.vehicle_id != options_.vehicle_id) {
      ++rejects_.wrong_vehicle;
      return;
    }
    if (!link::decodeDepth(codec_, keyframe_, &depth_).ok()) {
      ++rejects_.malformed;
      return;
    }
    latency_ms_.push_back(static_cast<double>(now - keyframe_.utime) * 1e-3);
    keyframe_ids_.insert(keyframe_.keyframe_id);
    bytes_.push_back(static_cast<double>(message.size()));
    if (!reference_.empty()) {
      const Image<uint16_t>& want =
          reference_[static_cast<size_t>(keyframe_.frame_id) % reference_.size()];
      const bool same = want.width() == depth_.width() && want.height() == depth_.height() &&
                        std::memcmp(want.data(), depth_.data(),
                                    want.numPixels() * sizeof(uint16_t)) == 0;
      if (!same) ++mismatches_;
    }
    if (signer_) sendCorrection();
  }

  // A signed correction of the keyframe just received (to its own pose), as the ground station
  // sends one per keyframe; signed now, so the drone times the uplink from the envelope's utime.
  void sendCorrection() {
    link::KeyframeHeader header;
    header.utime = keyframe_.utime;
    header.keyframe_id = keyframe_.keyframe_id;
    pose_correction_t correction;
    link::fillCorrection(options_.vehicle_id, header, Pose::Identity(), 0, &correction);
    inner_.resize(static_cast<size_t>(correction.getEncodedSize()));
    correction.encode(inner_.data(), 0, static_cast<int>(inner_.size()));
    signer_->sign(inner_.data(), inner_.size(), link::wallClockUtime(), &envelope_);
    lcm_->publish(correction_channel_, &envelope_);
    ++corrections_sent_;
    if (options_.correction_copies > 1)
      copies_.push_back({envelope_, Clock::now() + copyInterval(), options_.correction_copies - 1});
  }

 public:
  // [s] until the next copy of a correction is due (`limit_s` when none is).
  double nextCopyS(double limit_s) const {
    if (copies_.empty()) return limit_s;
    return std::min(limit_s, std::chrono::duration<double>(copies_.front().due - Clock::now()).count());
  }
  // Sends the copies that are due; the envelope is the same, so the drone counts a duplicate.
  void sendDueCopies() {
    while (!copies_.empty() && copies_.front().due <= Clock::now()) {
      Copy copy = copies_.front();
      copies_.pop_front();
      lcm_->publish(correction_channel_, &copy.envelope);
      if (--copy.left > 0) {
        copy.due += copyInterval();
        copies_.push_back(copy);
      }
    }
  }

 private:
  struct Copy {
    signed_t envelope;
    Clock::time_point due;
    int left;
  };
  Clock::duration copyInterval() const {
    return std::chrono::duration_cast<Clock::duration>(
        std::chrono::duration<double, std::milli>(options_.copy_interval_ms));
  }
  std::deque<Copy> copies_;

  const Options& options_;
  lcm::LCM* lcm_;
  DepthCodec codec_;
  std::vector<Image<uint16_t>> reference_;
  link::ChunkAssembler assembler_;
  std::string request_channel_, correction_channel_;
  std::optional<link::Signer> signer_;
  keyframe_chunk_t chunk_;
  depth_keyframe_t keyframe_;
  Image<uint16_t> depth_;
  mutable std::vector<chunk_request_t> requests_;
  link::RepairScheduler repair_{link::RepairScheduler::Params()};
  std::vector<uint8_t> inner_;
  signed_t envelope_;
  std::set<int64_t> keyframe_ids_;
  std::vector<double> latency_ms_, bytes_;
  int64_t mismatches_ = 0, fec_recovered_ = 0, repaired_ = 0;
  int64_t corrections_sent_ = 0;
  bool status_heard_ = false, drone_final_ = false;
  int64_t drone_sent_ = 0;
  Clock::time_point last_status_;
  link::RejectCounters rejects_;
};

int runGround(const Options& options) {
  std::vector<Image<uint16_t>> reference;
  if (!options.tum_dir.empty()) {
    if (const Status loaded = loadFrames(options.tum_dir, options.max_frames, &reference);
        !loaded.ok())
      return fail(loaded.message());
  }
  std::optional<link::Key> key;
  if (!options.key_path.empty()) {
    StatusOr<link::Key> loaded = link::loadKeyFile(options.key_path);
    if (!loaded.ok()) return fail(loaded.status().message());
    key = *loaded;
  }
  lcm::LCM lcm(options.lcm_url);
  if (!lcm.good()) return fail("cannot start LCM on \"" + options.lcm_url + "\"");
  GroundEnd end(options, &lcm, std::move(reference), key);
  lcm.subscribe(link::vehicleChannelsRegex(options.vehicle_id), &GroundEnd::onMessage, &end)
      ->setQueueCapacity(kChunkQueueMessages);
  // Ready line for the driving script: it starts the sender only after the subscription exists.
  std::fprintf(stderr, "kinfly-link-bench: ground listening\n");
  const Clock::time_point start = Clock::now();
  const auto running = [&] {
    return !g_stop && secondsSince(start) < options.seconds &&
           (options.expect == 0 || end.received() < options.expect);
  };
  while (running() && !end.droneDone()) {
    // Quiet only when nothing is queued: a ground that waited for a core has statuses to read.
    const int handled = lcm.handleTimeout(
        static_cast<int>(1e3 * std::max(0.0, end.nextCopyS(options.seconds - secondsSince(start)))));
    end.sendDueCopies();
    if (handled == 0 && end.sinceDroneStatus() > kDroneQuietS) break;
  }
  // The drone has stopped: last rounds for what is still incomplete, the newest included.
  if (running()) {
    const Clock::time_point last_round = Clock::now();
    while (running() && secondsSince(last_round) < kLastRepairWaitS) {
      if (options.repair) end.askRepairs(/*include_newest=*/true);
      lcm.handleTimeout(static_cast<int>(1e3 * std::max(0.0, end.nextCopyS(0.05))));
      end.sendDueCopies();
    }
  }
  end.print(!options.tum_dir.empty());
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  link::restoreIeeeFloatingPoint();  // before any thread: chunking.h says why
  CLI::App app{"Both ends of kinfly's link over real LCM: keyframes in chunks and signed uplink."};
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
  CLI::App* drone = app.add_subcommand(
      "drone", "publish keyframes in chunks and status, answer chunk requests, verify corrections");
  addCommon(drone);
  drone->add_option("--tum", o.tum_dir, "TUM folder whose depth frames are sent, cycling")
      ->required()
      ->check(CLI::ExistingDirectory);
  drone->add_option("--rate", o.rate_hz, "keyframes per second (one due while the last is still "
                                         "going out is skipped)")
      ->check(CLI::Range(0.1, 100.0))
      ->capture_default_str();
  drone->add_option("--key", o.key_path, "vehicle key file (kinfly-keygen) to verify corrections");
  drone->add_option("--window", o.window_s, "accepted signing-time window in seconds")
      ->capture_default_str();
  drone->add_option("--encoding", o.encoding, "raw16, rvl, rvl_zstd or palette_rvl_zstd")
      ->capture_default_str();
  drone->add_option("--mtu", o.mtu_bytes, "link MTU in bytes: no chunk datagram is larger")
      ->check(CLI::Range(576, 9000))
      ->capture_default_str();
  drone->add_option("--loss", o.loss,
                    "packet loss the link is expected to have, for the recovery chunks "
                    "(floored at 0.5 %)")
      ->check(CLI::Range(0.0, 0.9))
      ->capture_default_str();
  drone->add_option("--loss-run", o.loss_run, "mean run of lost packets (1: independent)")
      ->check(CLI::Range(1.0, 64.0))
      ->capture_default_str();
  drone->add_option("--spread-ms", o.spread_ms,
                    "a keyframe's chunks leave evenly over this many ms (0: at once)")
      ->check(CLI::Range(0.0, 1000.0))
      ->capture_default_str();
  drone->add_option("--rate-kbit", o.rate_kbit,
                    "cap on chunks in kbit/s, a token bucket of two chunks (0: none)")
      ->check(CLI::Range(0.0, 1e6))
      ->capture_default_str();
  drone->add_flag("--repair", o.repair, "answer the ground's chunk requests");
  CLI::App* ground = app.add_subcommand(
      "ground", "assemble keyframes from chunks, measure delivery, loss and latency");
  addCommon(ground);
  ground->add_option("--tum", o.tum_dir, "TUM folder to check decoded frames against")
      ->check(CLI::ExistingDirectory);
  ground->add_option("--expect", o.expect, "stop after this many keyframes");
  ground->add_flag("--repair", o.repair, "ask the drone for the chunks incomplete groups lack");
  ground->add_option("--key", o.key_path,
                     "vehicle key file: send a signed correction of each keyframe received");
  ground->add_option("--correction-copies", o.correction_copies,
                     "times each correction is sent (the drone applies the first, counts the "
                     "rest as duplicates)")
      ->capture_default_str()
      ->check(CLI::Range(1, 10));
  ground->add_option("--copy-interval-ms", o.copy_interval_ms, "between a correction's copies")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 1000.0));
  CLI11_PARSE(app, argc, argv);

  std::signal(SIGINT, onSignal);
  std::signal(SIGTERM, onSignal);
  return drone->parsed() ? runDrone(o) : runGround(o);
}
