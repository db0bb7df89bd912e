// kinfly-fw's configuration: one struct, read from a config file (INI/TOML sections, CLI11) with
// command-line overrides of the same names (`[source] path = ...` is `--source.path ...`).
// Defaults ship in firmware/config/kinfly-fw.toml; validate() names any wrong value and its range.
#pragma once

#include <CLI/CLI.hpp>

#include <string>

#include "kinfly/fw/correction_anchor.h"
#include "kinfly/fw/keyframe_selector.h"
#include "kinfly/fw/sensor_watch.h"

namespace kinfly::fw {

struct FirmwareConfig {
  // [vehicle]
  int vehicle_id = 1;                              // [0, 65535], in every channel name
  std::string key_file = "/etc/kinfly/vehicle.key";  // kinfly-keygen; mode 0600
  // [source]
  std::string source_kind = "log";      // log | dataset | openni | synthetic
  // log: LCM log; dataset: TUM folder (both required); openni: a device URI or an .oni
  // recording ("": the first sensor found); synthetic: unused
  std::string source_path;
  bool source_realtime = true;          // replay at capture rate; false: as fast as possible
  double source_speed = 1.0;            // (0, 100] replay rate factor when realtime
  std::string source_intrinsics;        // "fx,fy,cx,cy" (empty: the source's own)
  double source_depth_units_per_m = 5000.0;  // dataset: raw units per metre (TUM 5000)
  int source_width_px = 640;            // openni, synthetic: [16, 4096] image size the
  int source_height_px = 480;           //   engine is built for
  double source_rate_hz = 30.0;         // synthetic: (0, 1000] frame rate
  int source_seed = 1;                  // synthetic: [0, 2^31) noise seed
  int source_max_frames = 0;            // stop after this many frames (0: never)
  double source_reconnect_min_s = 0.5;  // openni: [0.01, 60] first retry after a loss; doubles
  double source_reconnect_max_s = 8.0;  // openni: [reconnect_min_s, 600] longest retry interval
  SensorWatch::Params sensor;           // stall_timeout_s
  // [odometry]
  int odometry_downsample = 2;          // {1, 2, 4}: 640x480 sensors run at 320x240
  int odometry_volume_vox = 128;        // dense volume edge [16, 512], multiple of 8
  double odometry_voxel_m = 0.03;       // [m] (0, 0.2]
  double odometry_lookahead_m = 1.5;    // [m] [0, 10] volume centred this far ahead of the camera
  int odometry_shift_blocks = 2;        // [1, 64] re-centre when the centre moved this many blocks
  int odometry_threads = 1;             // [1, 64]
  int capture_queue = 4;                // [1, 64] frames between capture and odometry
  // [keyframe]
  KeyframeSelector::Params keyframe;
  // [link]
  std::string lcm_url;                  // empty: LCM_DEFAULT_URL or LCM's default
  double signing_window_s = 2.0;        // [s] (0, 3600] accepted age of a signed correction
  int keyframe_queue = 4;               // [1, 64] keyframes waiting for the link
  double status_rate_hz = 10.0;         // [Hz] [1, 100]
  double link_timeout_s = 2.0;          // [s] (0, 60] ground unheard this long: link stale
  // [s] [0, 60] when the source ends (a replayed flight), how long at most to wait for the
  // ground's corrections of the last keyframes before exiting
  double final_wait_s = 5.0;
  CorrectionAnchor::Params corrections;
  // [output]
  std::string trajectory_out;           // TUM file of the published poses, written at exit
  std::string ground_truth_out;         // TUM file of the source's true poses (synthetic)
  std::string log_level = "info";       // trace | debug | info | warn | error

  // Empty when valid, else the first wrong value, its name in the config, and the allowed range.
  std::string validate() const;
};

// Registers every field as an option (and config key) of `app`, and makes `app` read config
// files section by section into those options, refusing keys it does not know.
void addConfigOptions(CLI::App* app, FirmwareConfig* config);

}  // namespace kinfly::fw
