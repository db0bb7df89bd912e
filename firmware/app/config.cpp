#include "config.h"

#include <sstream>

#include "kinfly/link/channels.h"

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

}  // namespace

void addConfigOptions(CLI::App* app, FirmwareConfig* c) {
  app->config_formatter(std::make_shared<SectionedConfig>());
  // A misspelt key would otherwise leave its default in force unnoticed.
  app->allow_config_extras(CLI::config_extras_mode::error);
  app->add_option("--vehicle.id", c->vehicle_id, "vehicle id [0, 65535]")->capture_default_str();
  app->add_option("--vehicle.key_file", c->key_file, "signing key (kinfly-keygen), mode 0600")
      ->capture_default_str();
  app->add_option("--source.kind", c->source_kind, "log | dataset | openni | synthetic")
      ->capture_default_str();
  app->add_option("--source.path", c->source_path,
                  "LCM log (log), TUM folder (dataset), device URI or .oni file (openni; empty: "
                  "the first sensor found)");
  app->add_option("--source.realtime", c->source_realtime,
                  "replay at the recorded rate (false: as fast as possible)")
      ->capture_default_str();
  app->add_option("--source.speed", c->source_speed, "replay rate factor when realtime")
      ->capture_default_str();
  app->add_option("--source.intrinsics", c->source_intrinsics,
                  "fx,fy,cx,cy (empty: the source's own)");
  app->add_option("--source.depth_units_per_m", c->source_depth_units_per_m,
                  "dataset: raw depth units per metre")
      ->capture_default_str();
  app->add_option("--source.width", c->source_width_px, "openni, synthetic: image width [px]")
      ->capture_default_str();
  app->add_option("--source.height", c->source_height_px, "openni, synthetic: image height [px]")
      ->capture_default_str();
  app->add_option("--source.rate_hz", c->source_rate_hz, "synthetic: frame rate [Hz]")
      ->capture_default_str();
  app->add_option("--source.seed", c->source_seed, "synthetic: noise seed")->capture_default_str();
  app->add_option("--source.max_frames", c->source_max_frames, "stop after N frames (0: never)")
      ->capture_default_str();
  app->add_option("--source.reconnect_min_s", c->source_reconnect_min_s,
                  "openni: first retry after losing the sensor [s]; doubles up to the max")
      ->capture_default_str();
  app->add_option("--source.reconnect_max_s", c->source_reconnect_max_s,
                  "openni: longest interval between retries [s]")
      ->capture_default_str();
  app->add_option("--source.stall_timeout_s", c->sensor.stall_timeout_s,
                  "no frame this long: the sensor counts as stalled [s]")
      ->capture_default_str();
  app->add_option("--odometry.downsample", c->odometry_downsample, "1, 2 or 4")
      ->capture_default_str();
  app->add_option("--odometry.volume_vox", c->odometry_volume_vox, "dense volume edge in voxels")
      ->capture_default_str();
  app->add_option("--odometry.voxel_m", c->odometry_voxel_m, "voxel size [m]")
      ->capture_default_str();
  app->add_option("--odometry.lookahead_m", c->odometry_lookahead_m,
                  "the volume follows the drone, centred this far ahead of the camera [m]")
      ->capture_default_str();
  app->add_option("--odometry.shift_blocks", c->odometry_shift_blocks,
                  "it shifts when its wanted centre has moved this many 8-voxel blocks")
      ->capture_default_str();
  app->add_option("--odometry.threads", c->odometry_threads,
                  "engine threads (1: no OpenMP region at all, no allocation per frame)")
      ->capture_default_str();
  app->add_option("--odometry.capture_queue", c->capture_queue, "frames queued before odometry")
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
  app->add_option("--link.lcm_url", c->lcm_url, "LCM URL (empty: LCM_DEFAULT_URL or default)");
  app->add_option("--link.signing_window_s", c->signing_window_s,
                  "accepted age of a signed correction [s]; both clocks must agree this well")
      ->capture_default_str();
  app->add_option("--link.keyframe_queue", c->keyframe_queue,
                  "keyframes waiting for the link (oldest dropped when full)")
      ->capture_default_str();
  app->add_option("--link.status_rate_hz", c->status_rate_hz, "drone_status_t rate [Hz]")
      ->capture_default_str();
  app->add_option("--link.timeout_s", c->link_timeout_s,
                  "ground station unheard this long: link stale [s]")
      ->capture_default_str();
  app->add_option("--link.final_wait_s", c->final_wait_s,
                  "when the source ends: the longest wait for the ground's last corrections [s]")
      ->capture_default_str();
  app->add_option("--corrections.history_keyframes", c->corrections.history_keyframes,
                  "keyframes whose onboard pose is kept for corrections")
      ->capture_default_str();
  app->add_option("--output.trajectory", c->trajectory_out, "TUM trajectory written at exit");
  app->add_option("--output.ground_truth", c->ground_truth_out,
                  "TUM file of the source's true poses, written at exit (synthetic)");
  app->add_option("--output.log_level", c->log_level, "trace | debug | info | warn | error")
      ->capture_default_str();
}

std::string FirmwareConfig::validate() const {
  std::ostringstream why;
  const auto range = [&](const char* name, double value, double lo, double hi, bool lo_open) {
    if (why.tellp() > 0) return;
    if (!(lo_open ? value > lo : value >= lo) || !(value <= hi))
      why << name << " must be in " << (lo_open ? "(" : "[") << lo << ", " << hi << "] (got "
          << value << ")";
  };
  range("vehicle.id", vehicle_id, 0, link::kMaxVehicleId, false);
  if (why.tellp() == 0 && source_kind != "log" && source_kind != "dataset" &&
      source_kind != "openni" && source_kind != "synthetic")
    why << "source.kind must be log, dataset, openni or synthetic (got \"" << source_kind
        << "\")";
  if (why.tellp() == 0 && source_path.empty() &&
      (source_kind == "log" || source_kind == "dataset"))
    why << "source.path is required for source.kind = " << source_kind;
  range("source.speed", source_speed, 0, 100, true);
  range("source.depth_units_per_m", source_depth_units_per_m, 0, 1e6, true);
  range("source.width", source_width_px, 16, 4096, false);
  range("source.height", source_height_px, 16, 4096, false);
  range("source.rate_hz", source_rate_hz, 0, 1000, true);
  range("source.seed", source_seed, 0, 2147483647, false);
  range("source.max_frames", source_max_frames, 0, 1e9, false);
  range("source.reconnect_min_s", source_reconnect_min_s, 0.01, 60, false);
  range("source.reconnect_max_s", source_reconnect_max_s, source_reconnect_min_s, 600, false);
  if (why.tellp() == 0) {
    if (std::string w = sensor.validate(); !w.empty()) why << w;
  }
  if (why.tellp() == 0 && odometry_downsample != 1 && odometry_downsample != 2 &&
      odometry_downsample != 4)
    why << "odometry.downsample must be 1, 2 or 4 (got " << odometry_downsample << ")";
  if (why.tellp() == 0 && (odometry_volume_vox % 8 != 0))
    why << "odometry.volume_vox must be a multiple of 8 (got " << odometry_volume_vox << ")";
  range("odometry.volume_vox", odometry_volume_vox, 16, 512, false);
  range("odometry.voxel_m", odometry_voxel_m, 0, 0.2, true);
  range("odometry.lookahead_m", odometry_lookahead_m, 0, 10, false);
  range("odometry.shift_blocks", odometry_shift_blocks, 1, 64, false);
  range("odometry.threads", odometry_threads, 1, 64, false);
  range("odometry.capture_queue", capture_queue, 1, 64, false);
  range("link.signing_window_s", signing_window_s, 0, 3600, true);
  range("link.keyframe_queue", keyframe_queue, 1, 64, false);
  range("link.status_rate_hz", status_rate_hz, 1, 100, false);
  range("link.timeout_s", link_timeout_s, 0, 60, true);
  range("link.final_wait_s", final_wait_s, 0, 60, false);
  if (why.tellp() == 0) {
    if (std::string k = keyframe.validate(); !k.empty()) why << k;
  }
  if (why.tellp() == 0) {
    if (std::string h = corrections.validate(); !h.empty()) why << h;
  }
  if (why.tellp() == 0 && log_level != "trace" && log_level != "debug" && log_level != "info" &&
      log_level != "warn" && log_level != "error")
    why << "output.log_level must be trace, debug, info, warn or error (got \"" << log_level
        << "\")";
  return why.str();
}

}  // namespace kinfly::fw
