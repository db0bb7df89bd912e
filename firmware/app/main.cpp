// kinfly-fw: the drone's program. Three threads that never wait on each other:
//   capture   source -> (paced to the recording, or as fast as possible) -> capture queue
//   odometry  capture queue -> engine at QVGA in a dense volume that follows the drone ->
//             odometry pose, keyframe selection -> keyframe queue
//   link      keyframe queue -> compression -> LCM; signed corrections in; status at 10 Hz
// Both queues are bounded and drop their oldest item when full (counted): a slow ground station
// costs keyframes, never odometry.
#include <CLI/CLI.hpp>
#include <lcm/lcm-cpp.hpp>
#include <omp.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <memory>
#include <mutex>
#include <optional>
#include <thread>
#include <vector>

#include "config.h"
#include "depth_source.h"
#include "kinfly/depth_codec.h"
#include "kinfly/fusion_pipeline.h"
#include "kinfly/fw/bounded_queue.h"
#include "kinfly/fw/correction_anchor.h"
#include "kinfly/fw/keyframe_selector.h"
#include "kinfly/link/channels.h"
#include "kinfly/link/conversions.h"
#include "kinfly/link/uplink.h"
#include "kinfly/odometry_t.hpp"
#include "kinfly/status_t.hpp"
#include "kinfly/tum_dataset.h"

namespace {

using namespace kinfly;
using namespace kinfly::fw;
using Clock = std::chrono::steady_clock;
using namespace std::chrono_literals;

constexpr const char* kVersion = "0.1.0";
constexpr auto kPollPeriod = 50ms;  // longest any thread sleeps before looking at the stop flag

std::atomic<bool> g_stop{false};
void onSignal(int) { g_stop = true; }

int8_t trackingCode(TrackingStatus status) {
  switch (status) {
    case TrackingStatus::kFirstFrame: return odometry_t::TRACKING_FIRST;
    case TrackingStatus::kOk: return odometry_t::TRACKING_OK;
    case TrackingStatus::kLost: return odometry_t::TRACKING_LOST;
    case TrackingStatus::kGivenPose: return odometry_t::TRACKING_GIVEN;
  }
  return odometry_t::TRACKING_NONE;
}

// Counters shared by the threads; each is written by one thread and read by the link's status.
struct Counters {
  std::atomic<int64_t> frames_captured{0}, frames_skipped{0}, frames_processed{0},
      frames_lost{0}, keyframes_sent{0}, keyframes_dropped{0},
      corrections_unknown{0};
  std::atomic<int8_t> tracking{odometry_t::TRACKING_NONE};
  std::atomic<bool> capture_done{false};
};

struct KeyframeJob {
  Image<uint16_t> depth;  // raw, full resolution: the ground fuses at full resolution
  int64_t utime = 0, frame_id = 0, keyframe_id = 0;
  Pose T_world_cam = Pose::Identity();
  int8_t tracking = odometry_t::TRACKING_NONE;
};

// The re-anchoring shared by the odometry (remembers keyframes, publishes anchored poses) and
// the link (applies corrections).
struct SharedAnchor {
  std::mutex mutex;
  CorrectionAnchor anchor;
  explicit SharedAnchor(const CorrectionAnchor::Params& p) : anchor(p) {}
};

std::unique_ptr<DepthSource> openSource(const FirmwareConfig& config, std::string* why) {
  if (config.source_kind == "dataset") {
    DatasetSourceParams p;
    p.tum_dir = config.source_path;
    p.intrinsics = config.source_intrinsics;
    p.depth_units_per_m = config.source_depth_units_per_m;
    return openDatasetSource(p, why);
  }
  LogSourceParams p;
  p.path = config.source_path;
  p.vehicle_id = config.vehicle_id;
  return openLogSource(p, why);
}

// ---- capture thread -------------------------------------------------------------------------

void captureLoop(const FirmwareConfig& config, DepthSource* source,
                 BoundedQueue<DepthCapture>* queue, Counters* counters) {
  DepthCapture capture;
  std::optional<std::pair<int64_t, Clock::time_point>> start;  // first utime, its wall time
  std::string why;
  while (!g_stop) {
    if (config.source_max_frames > 0 && counters->frames_captured >= config.source_max_frames)
      break;
    const SourceStatus status = source->next(&capture, &why);
    if (status == SourceStatus::kEnd) break;
    if (status == SourceStatus::kSkipped) {
      ++counters->frames_skipped;
      spdlog::warn("capture: frame skipped: {}", why);
      continue;
    }
    if (config.source_realtime) {
      if (!start || capture.utime < start->first) start.emplace(capture.utime, Clock::now());
      const auto due = start->second + std::chrono::microseconds(capture.utime - start->first);
      while (!g_stop && Clock::now() < due)
        std::this_thread::sleep_for(std::min<Clock::duration>(kPollPeriod, due - Clock::now()));
    }
    capture.frame_id = counters->frames_captured++;
    if (!queue->push(capture)) spdlog::debug("capture: queue full, oldest frame dropped");
    // Without pacing the odometry sets the rate: wait for room rather than drop what a
    // replay can simply deliver later.
    while (!config.source_realtime && !g_stop && queue->size() >= queue->capacity())
      std::this_thread::sleep_for(1ms);
  }
  counters->capture_done = true;
  queue->close();
}

// ---- link thread ----------------------------------------------------------------------------

class Link {
 public:
  Link(const FirmwareConfig& config, lcm::LCM* lcm, std::optional<link::Key> key,
       SharedAnchor* anchor, Counters* counters, BoundedQueue<KeyframeJob>* keyframes,
       BoundedQueue<DepthCapture>* capture_queue, const PinholeCamera& camera,
       double depth_scale_m)
      : config_(config), lcm_(lcm), anchor_(anchor), counters_(counters),
        keyframes_(keyframes), capture_queue_(capture_queue), camera_(camera),
        depth_scale_m_(depth_scale_m), codec_(DepthCodec::Params()) {
    if (key) {
      link::VerifierParams verifier;
      verifier.window_s = config.signing_window_s;
      corrections_.emplace(*key, config.vehicle_id, verifier, link::DecodeBounds());
    }
    lcm_->subscribe(link::vehicleChannelsRegex(config.vehicle_id), &Link::onMessage, this);
  }

  void publishOdometry(const odometry_t& message) {
    std::lock_guard<std::mutex> lock(publish_mutex_);
    lcm_->publish(link::channelName(link::Channel::kOdometry, config_.vehicle_id), &message);
  }

  void run() {
    const auto status_period = std::chrono::duration_cast<Clock::duration>(
        std::chrono::duration<double>(1.0 / config_.status_rate_hz));
    Clock::time_point next_status = Clock::now();
    KeyframeJob job;
    while (!stop_) {
      lcm_->handleTimeout(10);
      while (keyframes_->pop(&job, 0ms)) send(job);
      if (Clock::now() >= next_status) {
        publishStatus();
        next_status += status_period;
      }
    }
    // What the odometry selected before it stopped still goes out (at most a queue's worth).
    while (keyframes_->pop(&job, 0ms)) send(job);
    publishStatus();
  }

  // Ends run() after it has sent the keyframes still queued; called by the odometry thread.
  void stop() { stop_ = true; }

  link::RejectCounters rejects() const {
    link::RejectCounters all = rejects_;
    if (corrections_) all += corrections_->rejects();
    return all;
  }
  int64_t accepted() const { return corrections_ ? corrections_->accepted() : 0; }

 private:
  void onMessage(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    const auto parsed = link::parseChannel(channel);
    if (!parsed) {
      ++rejects_.unknown_channel;
      spdlog::warn("link: message on unknown channel {}", channel);
      return;
    }
    if (parsed->channel == link::Channel::kGroundStatus) {
      last_ground_heard_ = Clock::now();
      return;
    }
    if (parsed->channel != link::Channel::kCorrection) return;  // our own traffic, looped back
    last_ground_heard_ = Clock::now();
    if (!corrections_) {
      ++rejects_.unsigned_messages;
      spdlog::warn("link: correction ignored: no key loaded (vehicle.key_file)");
      return;
    }
    const auto correction =
        corrections_->receive(rbuf->data, rbuf->data_size, link::wallClockUtime());
    if (!correction) {  // every refusal is counted by the receiver
      spdlog::warn("link: correction rejected (rejections so far: {})",
                   corrections_->rejects().total());
      return;
    }
    std::lock_guard<std::mutex> lock(anchor_->mutex);
    const Pose corrected = link::readPose(correction->position_m, correction->orientation_xyzw);
    const auto outcome =
        anchor_->anchor.apply(correction->keyframe_id, corrected, correction->reset_counter);
    if (outcome != CorrectionAnchor::Outcome::kApplied) {
      ++counters_->corrections_unknown;
      spdlog::warn("link: correction of keyframe {} not applied: {}", correction->keyframe_id,
                   outcome == CorrectionAnchor::Outcome::kUnknownKeyframe
                       ? "unknown keyframe"
                       : "older than one already applied");
    }
  }

  void send(const KeyframeJob& job) {
    depth_keyframe_t& m = message_;
    m.utime = job.utime;
    m.vehicle_id = config_.vehicle_id;
    m.frame_id = job.frame_id;
    m.keyframe_id = job.keyframe_id;
    link::writePose(job.T_world_cam, m.position_m, m.orientation_xyzw);
    m.tracking_status = job.tracking;
    if (const CodecResult r = link::encodeDepth(codec_, job.depth, camera_, depth_scale_m_, &m);
        !r.ok()) {
      ++counters_->keyframes_dropped;
      spdlog::error("link: keyframe {} not encoded: {}", job.keyframe_id, toString(r.status));
      return;
    }
    std::lock_guard<std::mutex> lock(publish_mutex_);
    lcm_->publish(link::channelName(link::Channel::kKeyframe, config_.vehicle_id), &m);
    ++counters_->keyframes_sent;
  }

  void publishStatus() {
    status_t s;
    s.utime = link::wallClockUtime();
    s.vehicle_id = config_.vehicle_id;
    s.source = status_t::SOURCE_DRONE;
    const double elapsed_s =
        std::chrono::duration<double>(Clock::now() - rate_window_start_).count();
    if (elapsed_s >= 1.0) {
      const auto rate = [elapsed_s](int64_t now, int64_t before) {
        return static_cast<float>(static_cast<double>(now - before) / elapsed_s);
      };
      depth_rate_hz_ = rate(counters_->frames_captured, captured_at_window_);
      odometry_rate_hz_ = rate(counters_->frames_processed, processed_at_window_);
      keyframe_rate_hz_ = rate(counters_->keyframes_sent, sent_at_window_);
      captured_at_window_ = counters_->frames_captured;
      processed_at_window_ = counters_->frames_processed;
      sent_at_window_ = counters_->keyframes_sent;
      rate_window_start_ = Clock::now();
    }
    s.depth_rate_hz = depth_rate_hz_;
    s.odometry_rate_hz = odometry_rate_hz_;
    s.keyframe_rate_hz = keyframe_rate_hz_;
    s.frames_captured = counters_->frames_captured;
    s.queue_drops = capture_queue_->dropped();
    s.keyframes_sent = counters_->keyframes_sent;
    s.keyframes_dropped = counters_->keyframes_dropped + keyframes_->dropped();
    s.tracking_state = counters_->tracking;
    const auto since = Clock::now() - last_ground_heard_;
    s.link_state = last_ground_heard_ == Clock::time_point()
                       ? status_t::LINK_UNKNOWN
                       : (since <= std::chrono::duration<double>(config_.link_timeout_s)
                              ? status_t::LINK_UP
                              : status_t::LINK_STALE);
    rejects().writeTo(&s);
    s.corrections_accepted = accepted() - counters_->corrections_unknown;
    s.corrections_unknown_keyframe = counters_->corrections_unknown;
    std::lock_guard<std::mutex> lock(publish_mutex_);
    lcm_->publish(link::channelName(link::Channel::kStatus, config_.vehicle_id), &s);
  }

  const FirmwareConfig& config_;
  lcm::LCM* lcm_;
  SharedAnchor* anchor_;
  Counters* counters_;
  BoundedQueue<KeyframeJob>* keyframes_;
  BoundedQueue<DepthCapture>* capture_queue_;
  PinholeCamera camera_;
  double depth_scale_m_;
  DepthCodec codec_;
  depth_keyframe_t message_;
  std::optional<link::CorrectionReceiver> corrections_;
  link::RejectCounters rejects_;
  std::atomic<bool> stop_{false};
  std::mutex publish_mutex_;  // lcm publish from the odometry and the link threads
  Clock::time_point last_ground_heard_{};
  Clock::time_point rate_window_start_ = Clock::now();
  int64_t captured_at_window_ = 0, processed_at_window_ = 0, sent_at_window_ = 0;
  float depth_rate_hz_ = 0.f, odometry_rate_hz_ = 0.f, keyframe_rate_hz_ = 0.f;
};

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "kinfly-fw: the drone's program. Onboard KinectFusion odometry at QVGA, keyframes to the "
      "ground station over LCM, signed pose corrections back. Every option can also be set in "
      "the config file ([section] key = value)."};
  FirmwareConfig config;
  // A value given twice (config file, then command line, or twice on the command line): the
  // last one wins.
  app.option_defaults()->multi_option_policy(CLI::MultiOptionPolicy::TakeLast);
  app.set_config("--config", "", "config file (TOML/INI; firmware/config/kinfly-fw.toml)");
  addConfigOptions(&app, &config);
  bool print_config = false;
  app.add_flag("--print-config", print_config, "print the effective configuration and exit")
      ->configurable(false);
  app.set_version_flag("--version", std::string("kinfly-fw ") + kVersion);
  CLI11_PARSE(app, argc, argv);
  if (print_config) {
    std::fputs(app.config_to_str(true, false).c_str(), stdout);
    return 0;
  }
  // Logs go to stderr; stdout carries only the summary line (and --print-config).
  spdlog::set_default_logger(spdlog::stderr_color_mt("kinfly-fw"));
  if (std::string why = config.validate(); !why.empty()) {
    spdlog::critical("invalid configuration: {}", why);
    return 2;
  }
  spdlog::set_level(spdlog::level::from_str(config.log_level));

  std::string why;
  std::optional<link::Key> key;
  if (!config.key_file.empty()) {
    key = link::loadKeyFile(config.key_file, &why);
    if (!key) {
      spdlog::critical("{} (vehicle.key_file; empty to run without corrections)", why);
      return 2;
    }
  } else {
    spdlog::warn("no vehicle.key_file: every correction will be rejected as unsigned");
  }
  std::unique_ptr<DepthSource> source = openSource(config, &why);
  if (!source) {
    spdlog::critical("source: {}", why);
    return 2;
  }
  const PinholeCamera camera = source->camera();
  if (camera.width % config.odometry_downsample != 0 ||
      camera.height % config.odometry_downsample != 0) {
    spdlog::critical("odometry.downsample {} does not divide the {}x{} image",
                     config.odometry_downsample, camera.width, camera.height);
    return 2;
  }

  DenseVolume::Params volume_params;
  volume_params.resolution_vox = config.odometry_volume_vox;
  volume_params.voxel_size_m = static_cast<float>(config.odometry_voxel_m);
  FusionPipeline::Params pipeline_params;
  pipeline_params.preprocess.depth_scale_m = source->depthScaleM();
  pipeline_params.preprocess.downsample = config.odometry_downsample;
  pipeline_params.integrate.truncation_m = 4.f * volume_params.voxel_size_m;
  if (std::string problem = volume_params.validate(); !problem.empty()) why = problem;
  else why = pipeline_params.validate(volume_params.voxel_size_m);
  if (!why.empty()) {
    spdlog::critical("odometry: {}", why);
    return 2;
  }
  lcm::LCM lcm(config.lcm_url);
  if (!lcm.good()) {
    spdlog::critical("cannot start LCM on \"{}\" (link.lcm_url)", config.lcm_url);
    return 2;
  }

  std::signal(SIGINT, onSignal);
  std::signal(SIGTERM, onSignal);
  omp_set_num_threads(config.odometry_threads);
  spdlog::info("kinfly-fw {} vehicle {}: {}, {}x{} -> {}x{} odometry", kVersion,
               config.vehicle_id, source->describe(), camera.width, camera.height,
               camera.width / config.odometry_downsample,
               camera.height / config.odometry_downsample);

  DenseVolume volume(volume_params);
  FusionPipeline pipeline(camera, pipeline_params, &volume);
  KeyframeSelector selector(config.keyframe);
  SharedAnchor anchor(config.corrections);
  Counters counters;
  BoundedQueue<DepthCapture> capture_queue(static_cast<size_t>(config.capture_queue));
  BoundedQueue<KeyframeJob> keyframe_queue(static_cast<size_t>(config.keyframe_queue));
  Link link(config, &lcm, key, &anchor, &counters, &keyframe_queue, &capture_queue, camera,
            source->depthScaleM());

  std::thread capture_thread(captureLoop, std::cref(config), source.get(), &capture_queue,
                             &counters);
  std::thread link_thread(&Link::run, &link);

  std::vector<StampedPose> trajectory;
  DepthCapture capture;
  KeyframeJob job;
  int64_t next_keyframe_id = 0;
  while (!g_stop) {
    if (!capture_queue.pop(&capture, kPollPeriod)) {
      if (counters.capture_done && capture_queue.size() == 0) break;
      continue;
    }
    const FrameResult r = pipeline.processFrame(capture.depth.view(), capture.utime);
    const int64_t frame_id = capture.frame_id;
    ++counters.frames_processed;
    counters.tracking = trackingCode(r.status);
    if (r.status == TrackingStatus::kLost) {
      ++counters.frames_lost;
      spdlog::warn("odometry: frame {} lost: {}", frame_id, r.lost_reason);
    }
    Pose T_world_cam;
    int32_t reset_counter = 0;
    const bool keyframe =
        selector.select(r.T_world_cam, r.utime, r.status, r.inlier_fraction);
    {
      std::lock_guard<std::mutex> lock(anchor.mutex);
      if (keyframe) anchor.anchor.rememberKeyframe(next_keyframe_id, r.T_world_cam);
      T_world_cam = anchor.anchor.toWorld(r.T_world_cam);
      reset_counter = anchor.anchor.resetCounter();
    }
    odometry_t odometry;
    odometry.utime = r.utime;
    odometry.vehicle_id = config.vehicle_id;
    odometry.frame_id = frame_id;
    link::writePose(T_world_cam, odometry.position_m, odometry.orientation_xyzw);
    odometry.tracking_status = trackingCode(r.status);
    odometry.inlier_fraction = r.inlier_fraction;
    odometry.residual_m = r.rmse_m;
    odometry.reset_counter = reset_counter;
    link.publishOdometry(odometry);
    // Kept only when asked for (replays and tests): in flight it would grow without bound.
    if (!config.trajectory_out.empty())
      trajectory.push_back({static_cast<double>(r.utime) * 1e-6, T_world_cam});
    if (keyframe) {
      // The job's previous buffer comes back from the queue on the next push: no allocation.
      if (job.depth.width() != capture.depth.width() ||
          job.depth.height() != capture.depth.height())
        job.depth = Image<uint16_t>(capture.depth.width(), capture.depth.height());
      job.depth.copyFrom(capture.depth.view());
      job.utime = r.utime;
      job.frame_id = frame_id;
      job.keyframe_id = next_keyframe_id++;
      job.T_world_cam = T_world_cam;
      job.tracking = trackingCode(r.status);
      if (!keyframe_queue.push(job)) spdlog::warn("link busy: oldest keyframe dropped");
    }
  }
  const bool interrupted = g_stop.exchange(true);
  capture_queue.close();
  capture_thread.join();
  link.stop();
  link_thread.join();

  if (!config.trajectory_out.empty()) {
    if (std::string problem = writeTumTrajectory(config.trajectory_out, trajectory);
        !problem.empty())
      spdlog::error("output.trajectory: {}", problem);
  }
  const link::RejectCounters rejects = link.rejects();
  std::printf(
      "kinfly-fw: %s: %lld frames captured, %lld processed (%lld lost), %lld dropped by the "
      "queue, %lld skipped; %lld keyframes sent, %lld dropped; %lld corrections applied, %lld "
      "rejected, %lld for unknown keyframes\n",
      interrupted ? "stopped" : "source ended",
      static_cast<long long>(counters.frames_captured.load()),
      static_cast<long long>(counters.frames_processed.load()),
      static_cast<long long>(counters.frames_lost.load()),
      static_cast<long long>(capture_queue.dropped()),
      static_cast<long long>(counters.frames_skipped.load()),
      static_cast<long long>(counters.keyframes_sent.load()),
      static_cast<long long>(counters.keyframes_dropped.load() + keyframe_queue.dropped()),
      static_cast<long long>(link.accepted() - counters.corrections_unknown.load()),
      static_cast<long long>(rejects.total()),
      static_cast<long long>(counters.corrections_unknown.load()));
  return 0;
}
