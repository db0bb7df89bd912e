// kinfly-fw: the drone's program. Three threads that never wait on each other:
//   capture   source -> (paced to the recording, or as fast as possible) -> capture queue
//   odometry  capture queue -> engine at QVGA in a dense volume that follows the drone ->
//             odometry pose, keyframe selection -> keyframe queue
//   link      keyframe queue -> compression -> LCM; signed corrections in; status at 10 Hz
//   control   (flight.backend other than none) IMU samples -> the flight stack, one tick each,
//             with the odometry's newest pose -> rotor commands
// Both queues are bounded and drop their oldest item when full (counted): a slow ground station
// costs keyframes, never odometry; the control task takes the odometry's newest pose and never
// waits for it. docs/firmware.md has the whole picture.
#include <CLI/CLI.hpp>
#include <pthread.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <csignal>
#include <cstdio>
#include <memory>
#include <optional>
#include <thread>
#include <utility>

#include "capture.h"
#include "config.h"
#include "control_task.h"
#include "kinfly/core/range_check.h"
#include "kinfly/link/chunking.h"
#include "kinfly/link/signing.h"
#include "link_task.h"
#include "odometry_task.h"
#include "publisher.h"
#include "runtime.h"
#include "kinfly/sources/dataset_source.h"
#include "kinfly/sources/log_source.h"
#include "kinfly/sources/openni_source.h"
#include "kinfly/sources/lcm_source.h"
#include "kinfly/sources/synthetic_source.h"

namespace kinfly::fw {
namespace {

constexpr const char* kVersion = "0.1.0";

// Set by SIGINT/SIGTERM, the one thing a handler may safely do; main's thread passes it on to
// the tasks' StopToken while it waits for them.
volatile std::sig_atomic_t g_signal_received = 0;

void onSignal(int) { g_signal_received = 1; }

// The key in PATH into *key (none for an empty path); false, said with WHAT (the config key and
// what an empty one means), when the file cannot be used.
bool loadKey(const std::string& path, const char* what, std::optional<link::Key>* key) {
  if (path.empty()) return true;
  StatusOr<link::Key> loaded = link::loadKeyFile(path);
  if (!loaded.ok()) {
    spdlog::critical("{} ({})", loaded.status().message(), what);
    return false;
  }
  *key = *loaded;
  return true;
}

// Waits for a task's thread to end (`finished` set as its last act), meanwhile passing a signal
// on to the tasks.
void awaitTask(std::thread* thread, const std::atomic<bool>& finished, StopToken* stop) {
  while (!finished) {
    if (g_signal_received && !stop->interrupted()) stop->interrupt();
    std::this_thread::sleep_for(kPollPeriod);
  }
  thread->join();
  if (g_signal_received) stop->interrupt();
}

StatusOr<std::unique_ptr<DepthSource>> openSource(const FirmwareConfig& config) {
  const SourceConfig& source = config.source;
  if (source.kind == "dataset") return openDatasetSource(source.dataset);
  if (source.kind == "synthetic") {
    SyntheticSourceParams p = source.synthetic;
    p.clock = link::wallClockUtime;
    // Paced as its stamps say, it is a live camera; unpaced or faster, a replay of itself.
    p.drop_late = source.realtime && source.speed == 1.0;
    return openSyntheticSource(p);
  }
  if (source.kind == "openni") return openOpenniSource(source.openni);
  if (source.kind == "lcm") {
    LcmSourceParams p = source.lcm;
    p.vehicle_id = config.vehicle.id;
    if (p.lcm_url.empty()) p.lcm_url = config.link.effectiveLcmUrl();
    return openLcmSource(p);
  }
  LogSourceParams p = source.log;
  p.vehicle_id = config.vehicle.id;
  return openLogSource(p);
}

// Thread names show in top, gdb and the journal; the allocation test tells threads apart by them.
void nameThisThread(const char* name) { pthread_setname_np(pthread_self(), name); }

// Writes a trajectory the configuration asked for; false (and a log line) if it cannot.
bool writeIfAsked(const std::string& path, const std::vector<StampedPose>& poses,
                  const char* key) {
  if (path.empty()) return true;
  if (const Status written = writeTumTrajectory(path, poses); !written.ok()) {
    spdlog::error("{}: {}", key, written.message());
    return false;
  }
  return true;
}

// CLI11 exits with a code of its own for each kind of error (109 an unknown option, 110 an
// unknown key in the file) and words some of them for its parser ("INI was not able to parse").
// Every refused command line or file is a configuration error: exit 2, naming what was wrong.
std::optional<int> parseArguments(CLI::App* app, int argc, char** argv) {
  try {
    app->parse(argc, argv);
    return std::nullopt;
  } catch (const CLI::Success& done) {  // --help, --version
    return app->exit(done);
  } catch (const CLI::ParseError& error) {
    std::string why = error.what();
    const std::string file = app->get_config_ptr()->as<std::string>();
    const std::string extras_prefix = "INI was not able to parse ";
    if (dynamic_cast<const CLI::ConfigError*>(&error) != nullptr &&
        why.rfind(extras_prefix, 0) == 0)
      why = "unknown key \"" + why.substr(extras_prefix.size()) + "\" in " + file;
    else if (dynamic_cast<const CLI::ExtrasError*>(&error) != nullptr)
      why = "unknown option or stray argument: " + why.substr(why.find(':') + 2);
    std::fprintf(stderr,
                 "kinfly-fw: invalid configuration: %s (kinfly-fw --help lists the options, "
                 "--print-config the keys and their values)\n",
                 why.c_str());
    return 2;
  }
}

int run(int argc, char** argv) {
  link::restoreIeeeFloatingPoint();  // before any thread: chunking.h says why
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
  if (std::optional<int> exit_code = parseArguments(&app, argc, argv)) return *exit_code;
  if (print_config) {
    std::fputs(app.config_to_str(true, false).c_str(), stdout);
    return 0;
  }
  // Logs go to stderr; stdout carries only the summary line (and --print-config).
  spdlog::set_default_logger(spdlog::stderr_color_mt("kinfly-fw"));
  if (const Status valid = config.validate(); !valid.ok()) {
    spdlog::critical("invalid configuration: {}", valid.message());
    return 2;
  }
  spdlog::set_level(spdlog::level::from_str(config.output.log_level));
  if (config.source.deprecated_depth_units_per_m)
    spdlog::warn("source.depth_units_per_m is deprecated and will go: write source.depth_scale_m "
                 "= {} (metres per raw unit) instead of source.depth_units_per_m = {}",
                 config.source.dataset.depth_scale_m, *config.source.deprecated_depth_units_per_m);
  // A URL LCM cannot use is a configuration error; a network that is not up yet is not.
  const std::string lcm_url = config.link.effectiveLcmUrl();
  if (Status url = firstError(Publisher::checkUrl(lcm_url), config.link.peers.empty()
                                                               ? Status()
                                                               : Publisher::checkPeerUrl(lcm_url));
      !url.ok()) {
    spdlog::critical("invalid configuration: {}", url.message());
    return 2;
  }

  std::optional<link::Key> key;
  if (!loadKey(config.vehicle.key_file, "vehicle.key_file; empty to run without corrections",
               &key))
    return 2;
  if (!key) spdlog::warn("no vehicle.key_file: every correction will be rejected as unsigned");
  StatusOr<std::unique_ptr<DepthSource>> opened = openSource(config);
  if (!opened.ok()) {
    spdlog::critical("source: {}", opened.status().message());
    return 2;
  }
  const std::unique_ptr<DepthSource> source = *std::move(opened);
  const PinholeCamera camera = source->camera();
  DenseVolume::Params volume_params;
  FusionPipeline::Params pipeline_params;
  if (const Status valid = OdometryTask::engineParams(config, camera, source->depthScaleM(),
                                                      &volume_params, &pipeline_params);
      !valid.ok()) {
    spdlog::critical("odometry: {}", valid.message());
    return 2;
  }
  std::unique_ptr<flight::FlightStack> stack;
  if (config.flight.enabled()) {
    auto made = flight::FlightStack::create(config.flight.stackParams());
    if (!made.ok()) {
      spdlog::critical("invalid configuration: {}", made.status().message());
      return 2;
    }
    stack = *std::move(made);
  }
  std::optional<link::Key> mavlink_key;
  if (config.flight.backend == "mavlink" &&
      !loadKey(config.flight.mavlink_key, "flight.mavlink_key; empty for an unsigned MAVLink link",
               &mavlink_key))
    return 2;
  std::signal(SIGINT, onSignal);
  std::signal(SIGTERM, onSignal);
  spdlog::info("kinfly-fw {} vehicle {}: {}, {}x{} -> {}x{} odometry", kVersion,
               config.vehicle.id, source->describe(), camera.width, camera.height,
               camera.width / config.odometry.downsample,
               camera.height / config.odometry.downsample);

  SharedAnchor anchor(config.corrections);
  Counters counters;
  // What the source says of itself before its first read: the first status must not claim a
  // sensor that is not there.
  counters.sensor_waiting = source->waiting();
  counters.sensor_connects = source->connects();
  BoundedQueue<DepthCapture> capture_queue(static_cast<size_t>(config.odometry.capture_queue),
                                           [&] { return withDepthImage<DepthCapture>(camera); });
  BoundedQueue<KeyframeJob> keyframe_queue(static_cast<size_t>(config.link.keyframe_queue),
                                           [&] { return withDepthImage<KeyframeJob>(camera); });
  // Each task owns its LCM instance (publisher.h says why); neither needs the network to start.
  StopToken stop;
  LatestValue<OdometryPose> poses;
  LatestValue<CommandMail> commands;
  LatestValue<flight_status_t> flight_status;
  // The fastest of the IMU's rate as configured and the estimator's own limit.
  const flight::FlightStackParams stack_params = config.flight.stackParams();
  SharedPoseHistory pose_history(
      std::max(stack_params.rate_hz, stack_params.estimator.imu_rate_max_hz));
  OdometryTask odometry(config, camera, volume_params, pipeline_params, &anchor, &counters,
                        &capture_queue, &keyframe_queue, stack ? &poses : nullptr,
                        stack ? &pose_history : nullptr, &stop);
  std::optional<ControlTask> control;
  if (stack) {
    control.emplace(config, std::move(stack), mavlink_key, &poses, &commands, &flight_status,
                    &pose_history, &stop);
  }
  LinkTask link(config, key, &anchor, &counters, &keyframe_queue, &capture_queue, camera,
                source->depthScaleM(), control ? &commands : nullptr,
                control ? &flight_status : nullptr, &stop);

  std::thread capture_thread([&] {
    nameThisThread("kfw-capture");
    runCapture(config.source, source.get(), &capture_queue, &counters, &stop);
  });
  std::atomic<bool> link_finished{false}, odometry_finished{false};
  std::thread link_thread([&] {
    nameThisThread("kfw-link");
    link.run();
    link_finished = true;
  });
  std::thread odometry_thread([&] {
    nameThisThread("kfw-odometry");
    odometry.run();
    odometry_finished = true;
  });
  std::thread control_thread;
  if (control) {
    control_thread = std::thread([&] {
      nameThisThread("kfw-control");
      control->run();
    });
  }
  awaitTask(&odometry_thread, odometry_finished, &stop);
  stop.requestStop();
  const bool interrupted = stop.interrupted();
  capture_queue.close();
  capture_thread.join();
  link.stop(/*await_corrections=*/!interrupted);
  awaitTask(&link_thread, link_finished, &stop);
  if (control_thread.joinable()) control_thread.join();

  const bool written =
      writeIfAsked(config.output.trajectory, odometry.trajectory(), "output.trajectory") &&
      writeIfAsked(config.output.ground_truth, odometry.groundTruth(), "output.ground_truth");
  const link::RejectCounters rejects = link.rejects();
  const auto n = [](int64_t v) { return static_cast<long long>(v); };
  std::printf(
      "kinfly-fw: %s: %lld frames captured, %lld processed (%lld lost, %lld in degenerate "
      "geometry; tracking back %lld times (%lld relocalised, %lld in a new map), after %lld lost "
      "frames at most), "
      "%lld dropped by the queue, %lld skipped; sensor opened %lld times, stalled %lld times; "
      "%lld keyframes sent, "
      "%lld dropped; %lld corrections applied, %lld rejected, %lld for unknown keyframes\n",
      interrupted ? "stopped" : "source ended", n(counters.frames_captured),
      n(counters.frames_processed), n(counters.frames_lost), n(counters.frames_weak),
      n(counters.recoveries), n(counters.relocalisations), n(counters.new_maps),
      n(counters.longest_loss_frames),
      n(capture_queue.dropped()),
      n(counters.frames_skipped), n(counters.sensor_connects), n(link.sensorStalls()),
      n(counters.keyframes_sent), n(counters.keyframes_failed + keyframe_queue.dropped()),
      n(link.accepted() - counters.corrections_unknown), n(rejects.total()),
      n(counters.corrections_unknown));
  if (control) {
    const ControlSummary& c = control->summary();
    const flight::FlightCounters& f = c.modes;
    std::printf(
        "kinfly-fw: control: %lld IMU samples (%lld rejected), %lld ticks (%lld without a new "
        "sample); %lld poses fused (%lld after their lockstep age), %lld rejected, %lld resets "
        "to a pose, %lld resets (%lld before the start); %lld barometer readings fused (%lld "
        "gated); estimator %s; mode %s, %lld mode changes, %lld commands accepted, %lld refused; "
        "failsafes: %lld vision lost, %lld estimator diverged, %lld attitude limit, %lld IMU "
        "lost, %lld geofence; %lld rotor commands sent, %lld not; %lld signed commands passed "
        "by the link, %lld dropped, %lld repeats ignored\n",
        n(c.imu_samples), n(c.imu_rejected), n(c.ticks), n(c.silent_ticks), n(c.poses_fused),
        n(c.poses_late), n(c.poses_rejected), n(c.pose_resets), n(c.resets), n(c.resets_rejected),
        n(c.baro_fused), n(c.baro_rejected), c.estimator_started ? "started" : "not started",
        flight::toString(c.mode), n(f.mode_changes), n(f.commands_accepted),
        n(f.commands_refused), n(f.vision_lost), n(f.estimator_diverged), n(f.attitude_limit),
        n(f.imu_lost), n(f.geofence), n(c.commands_sent), n(c.commands_unsent),
        n(link.commandsPassed()), n(link.commandsDropped()), n(link.commandsRepeated()));
    if (const auto& a = c.autopilot) {
      std::printf(
          "kinfly-fw: mavlink: %lld heartbeats, %lld IMU samples (%lld rejected), %lld "
          "attitudes (tilt against the estimate at most %.2f deg); %lld setpoints and %lld "
          "poses sent, %lld not; %lld mode, %lld arm and %lld disarm requests, %lld accepted, "
          "%lld refused; %lld bad signatures, %lld bad CRC, %lld from other sources; lost %lld "
          "times; %lld port errors\n",
          n(a->heartbeats), n(a->imu_samples), n(a->imu_rejected), n(a->attitudes),
          c.max_tilt_vs_autopilot_rad * 180.0 / 3.14159265358979323846, n(a->setpoints_sent),
          n(a->odometry_sent), n(a->send_failures), n(a->mode_requests), n(a->arm_requests),
          n(a->disarm_requests), n(a->commands_accepted), n(a->commands_refused),
          n(a->bad_signature), n(a->bad_crc), n(a->other_source), n(a->lost),
          n(a->port_errors));
    }
  }
  if (!interrupted && counters.frames_captured == 0) {
    spdlog::error("source: {} ended without delivering a frame", source->describe());
    return 1;
  }
  return written ? 0 : 1;
}

}  // namespace
}  // namespace kinfly::fw

int main(int argc, char** argv) { return kinfly::fw::run(argc, argv); }
