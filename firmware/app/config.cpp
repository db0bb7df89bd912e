#include "config.h"

#include <algorithm>
#include <cstdlib>
#include <initializer_list>
#include <string_view>
#include <utility>
#include <vector>

#include "kinfly/core/range_check.h"
#include "kinfly/frame/depth_frame.h"
#include "kinfly/link/channels.h"
#include "publisher.h"

namespace kinfly::fw {
namespace {

// CLI11 (2.1) reads `[source] max_frames = 5` as option max_frames of a subcommand "source" and,
// finding no such subcommand, drops it without a word. kinfly-fw's options are flat, named
// section.key (--source.max_frames), so every item is flattened back to that name.
class SectionedConfig : public CLI::ConfigTOML {
 public:
  std::vector<CLI::ConfigItem> from_config(std::istream& input) const override {
    std::vector<CLI::ConfigItem> flat;
    for (CLI::ConfigItem& item : CLI::ConfigTOML::from_config(input)) {
      if (item.name == "++" || item.name == "--") continue;  // section open and close marks
      std::string name;
      for (const std::string& parent : item.parents) name += parent + ".";
      item.name = name + item.name;
      item.parents.clear();
      flat.push_back(std::move(item));
    }
    return flat;
  }
};

// A key that several sources read (source.path, ...): each value given sets it in all their
// Params. Its default is theirs (the same in each).
template <class T>
CLI::Option* addSharedOption(CLI::App* app, const std::string& name, std::vector<T*> fields,
                             const std::string& help) {
  const T first = *fields.front();
  CLI::Option* option = app->add_option_function<T>(
      name, [fields](const T& value) { for (T* field : fields) *field = value; }, help);
  if constexpr (std::is_same_v<T, std::string>) {
    option->run_callback_for_default();  // --print-config writes an empty default as ""
    option->default_str(first);
  } else {
    option->default_str(std::to_string(first));
  }
  return option;
}

// The engine's and the link's Params name their fields as those libraries do; kinfly-fw's keys
// for some of them are older (and users' config files have them): a message that starts with
// such a field's name is given the key instead.
Status namingKeys(Status status,
                  std::initializer_list<std::pair<std::string_view, std::string_view>> keys) {
  const std::string& why = status.message();
  for (const auto& [field, key] : keys)
    if (why.size() > field.size() && why.compare(0, field.size(), field) == 0 &&
        why[field.size()] == ' ')
      return Status::error(std::string(key) + why.substr(field.size()));
  return status;
}

// [s] the IMU-alive check and the IMU-lost failsafe with the mavlink backend (the library's are
// for a 1 kHz IMU in the same computer).
constexpr double kMavlinkImuTimeoutS = 0.05;
constexpr double kMavlinkImuLostS = 0.25;

bool oneOf(const std::string& value, std::initializer_list<const char*> allowed) {
  for (const char* a : allowed)
    if (value == a) return true;
  return false;
}

}  // namespace

void addConfigOptions(CLI::App* app, FirmwareConfig* c) {
  app->config_formatter(std::make_shared<SectionedConfig>());
  // A misspelt key would otherwise leave its default in force unnoticed.
  app->allow_config_extras(CLI::config_extras_mode::error);
  app->add_option("--vehicle.id", c->vehicle.id, "vehicle id [0, 65535]")->capture_default_str();
  app->add_option("--vehicle.key_file", c->vehicle.key_file,
                  "signing key (kinfly-keygen), mode 0600")
      ->capture_default_str();
  SourceConfig& s = c->source;
  app->add_option("--source.kind", s.kind,
                  "log | dataset | openni | synthetic | lcm (frames over LCM: kinfly-sim)")
      ->capture_default_str();
  addSharedOption<std::string>(app, "--source.path", {&s.log.path, &s.dataset.tum_dir, &s.openni.uri},
                               "LCM log (log), TUM folder (dataset), device URI or .oni file "
                               "(openni; empty: the first sensor found)");
  app->add_option("--source.realtime", s.realtime,
                  "replay at the recorded rate (false: as fast as possible)")
      ->capture_default_str();
  app->add_option("--source.speed", s.speed, "replay rate factor when realtime")
      ->capture_default_str();
  app->add_option("--source.lockstep", s.lockstep,
                  "realtime = false only: each keyframe's correction applied before the next "
                  "frame (waits up to link.final_wait_s for the ground)")
      ->capture_default_str();
  app->add_option("--source.loop", s.log.loop,
                  "log: none (play once) | bounce (forward, backward, forward ...: soak runs)")
      ->capture_default_str();
  app->add_option("--source.laps", s.log.laps,
                  "log with loop = bounce: passes over the flight (0: until stopped)")
      ->capture_default_str();
  addSharedOption<std::string>(app, "--source.intrinsics",
                               {&s.dataset.intrinsics, &s.openni.intrinsics,
                                &s.synthetic.intrinsics, &s.lcm.intrinsics},
                               "fx,fy,cx,cy (empty: the source's own)");
  // Before its replacement, so that the new key wins when a file or command line has both.
  app->add_option_function<double>(
         "--source.depth_units_per_m",
         [&s](double units_per_m) {
           s.deprecated_depth_units_per_m = units_per_m;
           if (units_per_m > 0.0) s.dataset.depth_scale_m = 1.0 / units_per_m;
         },
         "deprecated: raw depth units per metre; use source.depth_scale_m = 1 / this")
      ->group("Deprecated");
  app->add_option("--source.depth_scale_m", s.dataset.depth_scale_m,
                  "dataset: metres per raw depth unit (TUM 0.0002)")
      ->capture_default_str();
  app->add_option("--source.lcm_url", s.lcm.lcm_url,
                  "lcm: where the frames come (empty: link.lcm_url's)")
      ->capture_default_str();
  addSharedOption<int>(app, "--source.width",
                       {&s.openni.width_px, &s.synthetic.width_px, &s.lcm.width_px},
                       "openni, synthetic, lcm: image width [px]");
  addSharedOption<int>(app, "--source.height",
                       {&s.openni.height_px, &s.synthetic.height_px, &s.lcm.height_px},
                       "openni, synthetic, lcm: image height [px]");
  app->add_option("--source.rate_hz", s.synthetic.rate_hz, "synthetic: frame rate [Hz]")
      ->capture_default_str();
  app->add_option("--source.seed", s.synthetic.seed, "synthetic: noise seed")
      ->capture_default_str();
  app->add_option("--source.motion", s.synthetic.motion,
                  "synthetic: swing (a hovering drone) | still (at rest, for bench tests)")
      ->capture_default_str();
  app->add_option("--source.max_frames", s.max_frames, "stop after N frames (0: never)")
      ->capture_default_str();
  app->add_option("--source.reconnect_min_s", s.openni.reconnect_min_s,
                  "openni: first retry after losing the sensor [s]; doubles up to the max")
      ->capture_default_str();
  app->add_option("--source.reconnect_max_s", s.openni.reconnect_max_s,
                  "openni: longest interval between retries [s]")
      ->capture_default_str();
  app->add_option("--source.stall_timeout_s", s.watch.stall_timeout_s,
                  "no frame this long: the sensor counts as stalled [s]")
      ->capture_default_str();
  OdometryConfig& o = c->odometry;
  app->add_option("--odometry.downsample", o.downsample, "1, 2 or 4")->capture_default_str();
  app->add_option("--odometry.volume_vox", o.volume.resolution_vox,
                  "dense volume edge in voxels")
      ->capture_default_str();
  app->add_option("--odometry.voxel_m", o.volume.voxel_size_m, "voxel size [m]")
      ->capture_default_str();
  app->add_option("--odometry.lookahead_m", o.volume.lookahead_m,
                  "the volume follows the drone, centred this far ahead of the camera [m]")
      ->capture_default_str();
  app->add_option("--odometry.max_lookahead_m", o.volume.max_lookahead_m,
                  "the volume goes out to where the camera sees its scene (the frame's median "
                  "depth), up to this far ahead; at or below lookahead_m it stays there [m]")
      ->capture_default_str();
  app->add_option("--odometry.shift_blocks", o.volume.shift_threshold_blocks,
                  "it shifts when its wanted centre has moved this many 8-voxel blocks")
      ->capture_default_str();
  app->add_option("--odometry.threads", o.threads,
                  "engine threads (1: no OpenMP region at all, no allocation per frame)")
      ->capture_default_str();
  app->add_option("--odometry.icp_fine_iterations", o.icp_fine_iterations,
                  "ICP iterations at the finest level (the engine's default: 4)")
      ->capture_default_str();
  app->add_option("--odometry.model_level", o.model_level,
                  "raycast the model for tracking at this pyramid level's resolution (0: every "
                  "pixel; 1: half, a quarter of the rays)")
      ->capture_default_str();
  app->add_option("--odometry.capture_queue", o.capture_queue, "frames queued before odometry")
      ->capture_default_str();
  KeyframeSelector::Params& k = c->keyframe;
  app->add_option("--keyframe.min_translation_m", k.min_translation_m,
                  "a keyframe after this much travel [m]")
      ->capture_default_str();
  app->add_option("--keyframe.min_rotation_rad", k.min_rotation_rad,
                  "... or this much rotation [rad]")
      ->capture_default_str();
  app->add_option("--keyframe.max_interval_s", k.max_interval_s,
                  "... or at least this often, moving or not [s]")
      ->capture_default_str();
  app->add_option("--keyframe.min_interval_s", k.min_interval_s, "never more often [s]")
      ->capture_default_str();
  app->add_option("--keyframe.min_inlier_fraction", k.min_inlier_fraction,
                  "only from frames tracked at least this well (ICP inlier fraction)")
      ->capture_default_str();
  app->add_option("--keyframe.max_gap_rotation_rad", k.max_gap_rotation_rad,
                  "... or from any frame tracked, once it turned this far from the last [rad]")
      ->capture_default_str();
  app->add_option("--keyframe.max_gap_translation_m", k.max_gap_translation_m,
                  "... or moved this far from it [m]")
      ->capture_default_str();
  app->add_option("--keyframe.min_covisibility", k.min_covisibility,
                  "... or once less than this share of what it sees was seen by the last keyframe "
                  "(0: off)")
      ->capture_default_str();
  LinkConfig& l = c->link;
  app->add_option("--link.lcm_url", l.lcm_url,
                  "LCM URL (empty: LCM_DEFAULT_URL or default; memq:// with link.peers)");
  app->add_option("--link.peers", l.peers,
                  "ADDRESS:PORT[,ADDRESS:PORT]: ground stations' IPv4 addresses to send to by UDP "
                  "unicast as well "
                  "(on Wi-Fi, docs/wire.md); empty: LCM multicast only");
  app->add_option("--link.peer_port", l.peer_port,
                  "UDP port the ground stations' unicast comes to")
      ->capture_default_str();
  app->add_option("--link.signing_window_s", l.signing.window_s,
                  "accepted age of a signed correction [s]; both clocks must agree this well")
      ->capture_default_str();
  app->add_option("--link.keyframe_queue", l.keyframe_queue,
                  "keyframes waiting for the link (oldest dropped when full)")
      ->capture_default_str();
  app->add_option("--link.status_rate_hz", l.status_rate_hz, "drone_status_t rate [Hz]")
      ->capture_default_str();
  app->add_option("--link.timeout_s", l.timeout_s,
                  "ground station unheard this long: link stale [s]")
      ->capture_default_str();
  app->add_option("--link.final_wait_s", l.final_wait_s,
                  "when the source ends: the longest wait for the ground's last corrections; "
                  "with source.lockstep, for each keyframe's [s]")
      ->capture_default_str();
  app->add_option("--link.mtu_bytes", l.chunks.mtu_bytes,
                  "IP MTU of the link [bytes]: no keyframe chunk is larger, so IP never "
                  "fragments one")
      ->capture_default_str();
  app->add_option("--link.fec_group_chunks", l.chunks.max_originals_per_group,
                  "original chunks per erasure-coding group at most [1, 255]")
      ->capture_default_str();
  app->add_option("--link.fec_target_failure", l.redundancy.target_failure,
                  "probability a keyframe group may be lost at the measured loss (0, 0.1]")
      ->capture_default_str();
  app->add_option("--link.fec_min_loss", l.redundancy.min_loss_fraction,
                  "loss fraction assumed at least when choosing the redundancy [0, 0.5]")
      ->capture_default_str();
  app->add_option("--link.repair_keyframes", l.chunks.repair_keyframes,
                  "last keyframes whose chunks are kept to answer the ground's requests")
      ->capture_default_str();
  app->add_option("--link.repair_chunks", l.chunks.repair_chunks_per_keyframe,
                  "chunks resent per keyframe at most")
      ->capture_default_str();
  app->add_option("--link.start_rate_bps", l.rate.start_bps,
                  "keyframes' send budget before the ground reports [bit/s]")
      ->capture_default_str();
  app->add_option("--link.min_rate_bps", l.rate.min_bps, "the budget never goes below [bit/s]")
      ->capture_default_str();
  app->add_option("--link.max_rate_bps", l.rate.max_bps, "the budget never goes above [bit/s]")
      ->capture_default_str();
  app->add_option("--link.queue_low_ms", l.rate.queue_low_ms,
                  "chunks' queueing delay below which the budget may grow [ms]")
      ->capture_default_str();
  app->add_option("--link.queue_high_ms", l.rate.queue_high_ms,
                  "chunks' queueing delay above which the budget shrinks [ms]")
      ->capture_default_str();
  app->add_option("--link.min_keyframe_rate_hz", l.scale.min_rate_hz,
                  "keyframe rate below which keyframe images shrink [Hz]")
      ->capture_default_str();
  app->add_option("--link.max_scale", l.scale.max_scale,
                  "smallest keyframe image: 1/max_scale of the width and height {1, 2, 4}")
      ->capture_default_str();
  app->add_option("--corrections.history_keyframes", c->corrections.history_keyframes,
                  "keyframes whose onboard pose is kept for corrections")
      ->capture_default_str();
  FlightConfig& f = c->flight;
  flight::FlightStackParams& st = f.stack;
  app->add_option("--flight.backend", f.backend,
                  "none (mapping only) | motors (motor_command_t over LCM: the simulator) | "
                  "mavlink (a PX4 or ArduPilot autopilot)")
      ->capture_default_str();
  app->add_option("--flight.imu", f.imu,
                  "lcm (imu_t on KINFLY_<vid>_IMU: the simulator) | mavlink (the autopilot's)")
      ->capture_default_str();
  app->add_option("--flight.mavlink_url", f.mavlink_url,
                  "the autopilot: udpin:HOST:PORT, udpout:HOST:PORT or a serial port's path")
      ->capture_default_str();
  app->add_option("--flight.mavlink_baud", f.mavlink_baud, "serial port baud rate")
      ->capture_default_str();
  app->add_option("--flight.mavlink_key", f.mavlink_key,
                  "MAVLink 2 signing key file (32 bytes, mode 0600); empty: unsigned");
  app->add_option("--flight.mavlink_system_id", f.mavlink.system_id,
                  "our MAVLink system id (a companion shares its vehicle's)")
      ->capture_default_str();
  app->add_option("--flight.mavlink_component_id", f.mavlink.component_id,
                  "our MAVLink component id (191: onboard computer)")
      ->capture_default_str();
  app->add_option("--flight.mavlink_timeout_s", f.mavlink.heartbeat_timeout_s,
                  "no heartbeat this long: the autopilot is lost (a failsafe) [s]")
      ->capture_default_str();
  app->add_option("--flight.mavlink_setpoint_hz", f.mavlink.setpoint_rate_hz,
                  "body-rate and thrust setpoints at most this often [Hz]")
      ->capture_default_str();
  app->add_option("--flight.mavlink_hover_thrust", f.mavlink.hover_thrust,
                  "the autopilot's normalised hover thrust (PX4: MPC_THR_HOVER)")
      ->capture_default_str();
  app->add_option("--flight.lcm_url", f.lcm_url,
                  "the control task's LCM (IMU in, rotor commands out); empty: link.lcm_url's");
  app->add_option("--flight.rt_priority", f.rt_priority,
                  "SCHED_FIFO priority of the control thread [1, 99]; 0: the default policy")
      ->capture_default_str();
  app->add_option("--flight.cpu", f.cpu, "pin the control thread to this core; -1: none")
      ->capture_default_str();
  app->add_option("--flight.rate_hz", st.rate_hz,
                  "the IMU's sample rate [Hz]: one control tick per sample")
      ->capture_default_str();
  app->add_option("--flight.position_rate_hz", st.position.rate_hz,
                  "position loop rate [Hz], at most flight.rate_hz")
      ->capture_default_str();
  app->add_option("--flight.attitude_law", f.attitude_law, "geometric | lqr")
      ->capture_default_str();
  app->add_option("--flight.lockstep", f.lockstep,
                  "the IMU's stamps are the only clock (a lockstep simulator): no ticks of the "
                  "task's own while it is silent")
      ->capture_default_str();
  app->add_option("--flight.lockstep_pose_age_s", f.lockstep_pose_age_s,
                  "with flight.lockstep: each odometry pose reaches the estimator this long after "
                  "its frame's capture, as kinfly-sim --pose-age-ms waits for it [s]; 0: when "
                  "published")
      ->capture_default_str();
  app->add_option("--flight.mass_kg", st.vehicle.mass_kg, "vehicle mass [kg]")
      ->capture_default_str();
  app->add_option("--flight.arm_length_m", st.vehicle.arm_length_m,
                  "centre of mass to each rotor axis [m]")
      ->capture_default_str();
  app->add_option("--flight.max_speed_m_s", st.trajectory.max_speed_m_s,
                  "peak speed of go-to, take-off and missions [m/s]")
      ->capture_default_str();
  app->add_option("--flight.max_accel_m_s2", st.trajectory.max_accel_m_s2,
                  "peak acceleration of the same [m/s^2]")
      ->capture_default_str();
  app->add_option("--flight.max_jerk_m_s3", st.trajectory.max_jerk_m_s3,
                  "peak jerk of the same: how fast the tilt asked for turns, about jerk / g "
                  "[m/s^3]")
      ->capture_default_str();
  app->add_option("--flight.max_yaw_rate_rad_s", st.trajectory.max_yaw_rate_rad_s,
                  "peak yaw rate of a go-to's turn to its heading [rad/s]")
      ->capture_default_str();
  app->add_option("--flight.land_speed_m_s", st.modes.land_speed_m_s, "landing descent [m/s]")
      ->capture_default_str();
  app->add_option("--flight.vision_lost_s", st.modes.vision_lost_s,
                  "no pose fused this long: level and descend to land [s]")
      ->capture_default_str();
  app->add_option("--output.trajectory", c->output.trajectory, "TUM trajectory written at exit");
  app->add_option("--output.ground_truth", c->output.ground_truth,
                  "TUM file of the source's true poses, written at exit (synthetic)");
  app->add_option("--output.log_level", c->output.log_level,
                  "trace | debug | info | warn | error")
      ->capture_default_str();
}

Status VehicleConfig::validate() const {
  return outOfRange("vehicle.id", id, 0, link::kMaxVehicleId);
}

Status SourceConfig::validate() const {
  if (!oneOf(kind, {"log", "dataset", "openni", "synthetic", "lcm"}))
    return Status::error("source.kind must be log, dataset, openni, synthetic or lcm (got \"" + kind +
                         "\")");
  if ((kind == "log" && log.path.empty()) || (kind == "dataset" && dataset.tum_dir.empty()))
    return Status::error("source.path is required for source.kind = " + kind);
  if (lockstep && realtime)
    return Status::error("source.lockstep needs source.realtime = false: frames paced to their "
                         "capture times cannot wait for the ground station");
  Status deprecated;
  if (deprecated_depth_units_per_m)
    deprecated = outOfRange("source.depth_units_per_m", *deprecated_depth_units_per_m, 0, 1e6,
                            Bound::kOpen);
  return firstError(outOfRange("source.speed", speed, 0, 100, Bound::kOpen),
                      std::move(deprecated), log.validate(), dataset.validate(),
                      synthetic.validate(), lcm.validate(),
                      outOfRange("source.max_frames", max_frames, 0, 1e9),
                      openni.validate(), watch.validate());
}

Status OdometryConfig::validate() const {
  if (!(downsample == 1 || downsample == 2 || downsample == 4))
    return Status::error("odometry.downsample must be 1, 2 or 4 (got " +
                         std::to_string(downsample) + ")");
  return firstError(namingKeys(volume.validate(), {{"resolution_vox", "odometry.volume_vox"},
                                                     {"voxel_size_m", "odometry.voxel_m"},
                                                     {"max_lookahead_m",
                                                      "odometry.max_lookahead_m"},
                                                     {"lookahead_m", "odometry.lookahead_m"},
                                                     {"shift_threshold_blocks",
                                                      "odometry.shift_blocks"}}),
                      outOfRange("odometry.threads", threads, 1, 64),
                      outOfRange("odometry.icp_fine_iterations", icp_fine_iterations, 1, 20),
                      outOfRange("odometry.model_level", model_level, 0, kPyramidLevels - 2),
                      outOfRange("odometry.capture_queue", capture_queue, 1, 64));
}

Status LinkConfig::validate() const {
  std::vector<link::PeerAddress> addresses;
  const Status parsed = link::parsePeers(peers, &addresses);
  return firstError(parsed.ok() ? parsed : Status::error("link.peers: " + parsed.message()),
                      outOfRange("link.peer_port", peer_port, 1, 65535),
                      namingKeys(signing.validate(), {{"window_s", "link.signing_window_s"}}),
                      outOfRange("link.keyframe_queue", keyframe_queue, 1, 64),
                      outOfRange("link.status_rate_hz", status_rate_hz, 1, 100),
                      outOfRange("link.timeout_s", timeout_s, 0, 60, Bound::kOpen),
                      outOfRange("link.final_wait_s", final_wait_s, 0, 60),
                      namingKeys(chunks.validate(),
                                 {{"mtu_bytes", "link.mtu_bytes"},
                                  {"max_originals_per_group", "link.fec_group_chunks"},
                                  {"repair_keyframes", "link.repair_keyframes"},
                                  {"repair_chunks_per_keyframe", "link.repair_chunks"}}),
                      namingKeys(redundancy.validate(),
                                 {{"target_failure", "link.fec_target_failure"},
                                  {"min_loss_fraction", "link.fec_min_loss"}}),
                      rate.validate(), scale.validate());
}

std::string LinkConfig::effectiveLcmUrl() const {
  if (!lcm_url.empty() || peers.empty()) return lcm_url;
  const char* env = std::getenv("LCM_DEFAULT_URL");
  return env != nullptr && *env != '\0' ? env : "memq://";
}

Status FlightConfig::validate() const {
  if (!oneOf(backend, {"none", "motors", "mavlink"}))
    return Status::error("flight.backend must be none, motors or mavlink (got \"" + backend +
                         "\")");
  if (!oneOf(imu, {"lcm", "mavlink"}))
    return Status::error("flight.imu must be lcm or mavlink (got \"" + imu + "\")");
  // The autopilot's IMU is read by the mavlink backend's link, and that link needs it: the
  // setpoints go out on its clock.
  if ((imu == "mavlink") != (backend == "mavlink"))
    return Status::error("flight.imu = mavlink goes with flight.backend = mavlink (got imu \"" +
                         imu + "\", backend \"" + backend + "\")");
  if (backend == "mavlink") {
    if (Status url = actuators::MavlinkPort::checkUrl(mavlink_url); !url.ok())
      return Status::error("flight.mavlink_url: " + url.message());
    if (Status ap = namingKeys(autopilotParams().validate(),
                               {{"mavlink.system_id", "flight.mavlink_system_id"},
                                {"mavlink.component_id", "flight.mavlink_component_id"},
                                {"mavlink.heartbeat_timeout_s", "flight.mavlink_timeout_s"},
                                {"mavlink.setpoint_rate_hz", "flight.mavlink_setpoint_hz"},
                                {"mavlink.imu_rate_hz", "flight.rate_hz (with mavlink)"},
                                {"mavlink.hover_thrust", "flight.mavlink_hover_thrust"}});
        !ap.ok())
      return ap;
  }
  if (!oneOf(attitude_law, {"geometric", "lqr"}))
    return Status::error("flight.attitude_law must be geometric or lqr (got \"" +
                         attitude_law + "\")");
  if (Status url = lcm_url.empty() ? Status() : Publisher::checkUrl(lcm_url); !url.ok())
    return Status::error("flight.lcm_url: " + url.message());
  if (lockstep_pose_age_s != 0.0 && !lockstep)
    return Status::error("flight.lockstep_pose_age_s needs flight.lockstep = true: a real IMU's "
                         "poses are fused when they come");
  // Half of what the stack counts as a fresh pose (or of the estimator's history, if shorter),
  // so that the pose after the last fused one comes before the last grows stale.
  const flight::FlightStackParams params = stackParams();
  const double max_age_s = 0.5 * std::min({params.estimator.history_s,
                                           params.estimator.vision_timeout_s,
                                           params.modes.vision_fresh_s});
  return firstError(outOfRange("flight.rt_priority", rt_priority, 0, 99),
                    outOfRange("flight.cpu", cpu, -1, 1023),
                    outOfRange("flight.lockstep_pose_age_s", lockstep_pose_age_s, 0.0, max_age_s),
                    namingKeys(stackParams().validate(),
                               {{"position.rate_hz", "flight.position_rate_hz"},
                                {"vehicle.mass_kg", "flight.mass_kg"},
                                {"vehicle.arm_length_m", "flight.arm_length_m"},
                                {"trajectory.max_speed_m_s", "flight.max_speed_m_s"},
                                {"trajectory.max_accel_m_s2", "flight.max_accel_m_s2"},
                                {"trajectory.max_jerk_m_s3", "flight.max_jerk_m_s3"},
                                {"trajectory.max_yaw_rate_rad_s", "flight.max_yaw_rate_rad_s"},
                                {"modes.land_speed_m_s", "flight.land_speed_m_s"},
                                {"modes.vision_lost_s", "flight.vision_lost_s"}}));
}

flight::FlightStackParams FlightConfig::stackParams() const {
  flight::FlightStackParams params = stack;
  params.attitude.law =
      attitude_law == "lqr" ? flight::AttitudeLaw::kLqr : flight::AttitudeLaw::kGeometric;
  // The simulator's motors can be stopped; a real autopilot (the mavlink backend) takes over.
  params.modes.attitude_limit_action = backend == "mavlink"
                                           ? flight::AttitudeLimitAction::kHandOver
                                           : flight::AttitudeLimitAction::kCutMotors;
  if (backend == "mavlink") {
    // The autopilot's IMU comes over a UART or UDP in bursts, and its own rate loop holds the
    // attitude meanwhile: a gap of a few samples is the link's, not a failure.
    params.modes.imu_timeout_s = kMavlinkImuTimeoutS;
    params.modes.imu_lost_s = kMavlinkImuLostS;
  }
  return params;
}

actuators::AutopilotParams FlightConfig::autopilotParams() const {
  actuators::AutopilotParams params = mavlink;
  params.imu_rate_hz = stack.rate_hz;
  return params;
}

Status OutputConfig::validate() const {
  if (!oneOf(log_level, {"trace", "debug", "info", "warn", "error"}))
    return Status::error("output.log_level must be trace, debug, info, warn or error (got \"" +
                         log_level + "\")");
  return {};
}

Status FirmwareConfig::validate() const {
  return firstError(vehicle.validate(), source.validate(), odometry.validate(),
                      link.validate(), keyframe.validate(), corrections.validate(),
                      flight.validate(), output.validate());
}

}  // namespace kinfly::fw
