#include "config.h"

#include <sstream>

#include "kinfly/link/channels.h"

namespace kinfly::fw {

void addConfigOptions(CLI::App* app, FirmwareConfig* c) {
  app->add_option("--vehicle.id", c->vehicle_id, "vehicle id [0, 65535]")->capture_default_str();
  app->add_option("--vehicle.key_file", c->key_file, "signing key (kinfly-keygen), mode 0600")
      ->capture_default_str();
  app->add_option("--source.kind", c->source_kind, "log | dataset")->capture_default_str();
  app->add_option("--source.path", c->source_path, "LCM log (log) or TUM folder (dataset)");
  app->add_option("--source.realtime", c->source_realtime,
                  "replay at the recorded rate (false: as fast as possible)")
      ->capture_default_str();
  app->add_option("--source.intrinsics", c->source_intrinsics, "dataset: fx,fy,cx,cy");
  app->add_option("--source.depth_units_per_m", c->source_depth_units_per_m,
                  "dataset: raw depth units per metre")
      ->capture_default_str();
  app->add_option("--source.max_frames", c->source_max_frames, "stop after N frames (0: never)")
      ->capture_default_str();
  app->add_option("--odometry.downsample", c->odometry_downsample, "1, 2 or 4")
      ->capture_default_str();
  app->add_option("--odometry.volume_vox", c->odometry_volume_vox, "dense volume edge in voxels")
      ->capture_default_str();
  app->add_option("--odometry.voxel_m", c->odometry_voxel_m, "voxel size [m]")
      ->capture_default_str();
  app->add_option("--odometry.threads", c->odometry_threads, "OpenMP threads")
      ->capture_default_str();
  app->add_option("--odometry.capture_queue", c->capture_queue, "frames queued before odometry")
      ->capture_default_str();
  KeyframeSelector::Params& k = c->keyframe;
  app->add_option("--keyframe.min_translation_m", k.min_translation_m)->capture_default_str();
  app->add_option("--keyframe.min_rotation_rad", k.min_rotation_rad)->capture_default_str();
  app->add_option("--keyframe.max_interval_s", k.max_interval_s)->capture_default_str();
  app->add_option("--keyframe.min_interval_s", k.min_interval_s)->capture_default_str();
  app->add_option("--keyframe.min_inlier_fraction", k.min_inlier_fraction)->capture_default_str();
  app->add_option("--link.lcm_url", c->lcm_url, "LCM URL (empty: LCM_DEFAULT_URL or default)");
  app->add_option("--link.signing_window_s", c->signing_window_s)->capture_default_str();
  app->add_option("--link.keyframe_queue", c->keyframe_queue)->capture_default_str();
  app->add_option("--link.status_rate_hz", c->status_rate_hz)->capture_default_str();
  app->add_option("--link.timeout_s", c->link_timeout_s)->capture_default_str();
  app->add_option("--corrections.history_keyframes", c->corrections.history_keyframes,
                  "keyframes whose onboard pose is kept for corrections")
      ->capture_default_str();
  app->add_option("--output.trajectory", c->trajectory_out, "TUM trajectory written at exit");
  app->add_option("--output.log_level", c->log_level)->capture_default_str();
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
  if (why.tellp() == 0 && source_kind != "log" && source_kind != "dataset")
    why << "source.kind must be log or dataset (got \"" << source_kind << "\")";
  if (why.tellp() == 0 && source_path.empty())
    why << "source.path is required for source.kind = " << source_kind;
  range("source.depth_units_per_m", source_depth_units_per_m, 0, 1e6, true);
  range("source.max_frames", source_max_frames, 0, 1e9, false);
  if (why.tellp() == 0 && odometry_downsample != 1 && odometry_downsample != 2 &&
      odometry_downsample != 4)
    why << "odometry.downsample must be 1, 2 or 4 (got " << odometry_downsample << ")";
  if (why.tellp() == 0 && (odometry_volume_vox % 8 != 0))
    why << "odometry.volume_vox must be a multiple of 8 (got " << odometry_volume_vox << ")";
  range("odometry.volume_vox", odometry_volume_vox, 16, 512, false);
  range("odometry.voxel_m", odometry_voxel_m, 0, 0.2, true);
  range("odometry.threads", odometry_threads, 1, 64, false);
  range("odometry.capture_queue", capture_queue, 1, 64, false);
  range("link.signing_window_s", signing_window_s, 0, 3600, true);
  range("link.keyframe_queue", keyframe_queue, 1, 64, false);
  range("link.status_rate_hz", status_rate_hz, 1, 100, false);
  range("link.timeout_s", link_timeout_s, 0, 60, true);
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
