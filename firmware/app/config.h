// kinfly-fw's configuration: one section per stage, each the stage's own Params where it has one
// (the sources', the dense volume's, the keyframe selector's, the signature check's ...), so a
// value's unit, default and range are written once, at its field, and checked by that Params'
// validate(). Read from a config file (INI/TOML sections, CLI11) with command-line overrides of
// the same names (`[source] path = ...` is `--source.path ...`); defaults ship in
// firmware/config/kinfly-fw.toml. validate() names the first wrong value's key and its range.
#pragma once

#include <CLI/CLI.hpp>

#include <optional>
#include <string>

#include "kinfly/core/status.h"
#include "kinfly/actuators/autopilot.h"
#include "kinfly/flight/flight_stack.h"
#include "kinfly/fw/correction_anchor.h"
#include "kinfly/fw/keyframe_selector.h"
#include "kinfly/fw/send_budget.h"
#include "kinfly/fw/sensor_watch.h"
#include "kinfly/link/chunking.h"
#include "kinfly/link/peer.h"
#include "kinfly/link/signing.h"
#include "kinfly/sources/dataset_source.h"
#include "kinfly/sources/lcm_source.h"
#include "kinfly/sources/log_source.h"
#include "kinfly/sources/openni_source.h"
#include "kinfly/sources/synthetic_source.h"
#include "kinfly/volume/tsdf_volume.h"

namespace kinfly::fw {

struct VehicleConfig {                           // [vehicle]
  int id = 1;                                    // id [0, 65535], in every channel name
  std::string key_file = "/etc/kinfly/vehicle.key";  // key_file: kinfly-keygen; mode 0600
  Status validate() const;
};

struct SourceConfig {                            // [source]
  std::string kind = "log";                      // kind: log | dataset | openni | synthetic | lcm
  bool realtime = true;          // realtime: replay at capture rate; false: as fast as possible
  double speed = 1.0;            // speed (0, 100]: replay rate factor when realtime
  // lockstep: only with realtime = false: after each keyframe, the next frame waits until the
  // ground station reports that keyframe done (its correction applied), at most
  // link.final_wait_s; a replay then gives the same trajectory on any machine, however fast.
  bool lockstep = false;
  int max_frames = 0;            // max_frames [0, 1e9]: stop after this many frames (0: never)
  // Each source's own Params, whatever the kind: every value is checked, so a config file
  // stays valid when its kind changes. Keys that several sources read (path, intrinsics, width,
  // height) set the field in each of them.
  LogSourceParams log;
  DatasetSourceParams dataset;
  OpenniSourceParams openni;
  SyntheticSourceParams synthetic;
  LcmSourceParams lcm;
  SensorWatch::Params watch;     // stall_timeout_s
  // Given only by the deprecated key source.depth_units_per_m (raw units per metre), which sets
  // dataset.depth_scale_m to its inverse; main warns when it is there.
  std::optional<double> deprecated_depth_units_per_m;
  Status validate() const;
};

struct OdometryConfig {                          // [odometry]
  int downsample = 2;            // downsample {1, 2, 4}: 640x480 sensors run at 320x240
  // volume_vox (resolution_vox), voxel_m (voxel_size_m), lookahead_m, max_lookahead_m, shift_blocks
  // (shift_threshold_blocks): the volume that follows the drone.
  DenseVolume::Params volume;
  int threads = 1;               // threads [1, 64]: the engine's OpenMP threads
  // icp_fine_iterations [1, 20]: ICP iterations at the finest level. The engine's 4 (docs/engine.md
  // item 2) cost 4 M instructions each at 320x240; after the coarser levels 2 track as well.
  int icp_fine_iterations = 2;
  // model_level [0, 1]: the model is raycast for tracking at this pyramid level's resolution
  // (FusionPipeline::Params::model_level): 1, 160x120, cut the frame from 6.5 to 4.8 ms on the
  // TUM teddy sequence and moved its ATE from 1.559 to 1.580 cm (docs/engine.md item 4).
  int model_level = 1;
  int capture_queue = 4;         // capture_queue [1, 64]: frames between capture and odometry
  Status validate() const;
};

struct LinkConfig {                              // [link]
  std::string lcm_url;           // lcm_url; empty: LCM_DEFAULT_URL, else LCM's default (memq://
                                 // with peers)
  // peers: "ADDRESS:PORT[,ADDRESS:PORT]", ground stations' IPv4 addresses sent to by UDP unicast (docs/wire.md,
  // "Unicast on Wi-Fi"); empty: LCM multicast only
  std::string peers;
  int peer_port = link::PeerLink::kDefaultPort;  // peer_port [1, 65535]: where peers send to
  link::VerifierParams signing;  // signing_window_s (window_s): accepted age of a correction
  int keyframe_queue = 4;        // keyframe_queue [1, 64]: keyframes waiting for the link
  double status_rate_hz = 10.0;  // status_rate_hz [Hz] [1, 100]
  double timeout_s = 2.0;        // timeout_s [s] (0, 60]: ground unheard this long: link stale
  // final_wait_s [s] [0, 60]: when the source ends (a replayed flight), how long at most to
  // wait for the ground's corrections of the last keyframes before exiting; with
  // source.lockstep, how long each keyframe waits for its own
  double final_wait_s = 5.0;
  // Keyframes in chunks (docs/wire.md): mtu_bytes, fec_group_chunks (max_originals_per_group),
  // repair_keyframes, repair_chunks (repair_chunks_per_keyframe).
  link::ChunkEncoder::Params chunks;
  // fec_target_failure (target_failure), fec_min_loss (min_loss_fraction): the recovery chunks
  // per group, from the loss the ground reports.
  link::RedundancyParams redundancy;
  // start_rate_bps, min_rate_bps, max_rate_bps, queue_low_ms, queue_high_ms: the keyframes'
  // send budget, which follows what the link carries.
  LinkRate::Params rate;
  // min_keyframe_rate_hz, max_scale: smaller keyframe images when the budget is short.
  KeyframeScale::Params scale;
  Status validate() const;
  // The URL the tasks use: lcm_url; with peers and no lcm_url, LCM_DEFAULT_URL if set, else
  // memq:// (nothing multicast, no route needed).
  std::string effectiveLcmUrl() const;
};

struct FlightConfig {                            // [flight] docs/flight.md, "The control task"
  // backend: none (mapping only: no control task) | motors (rotor speeds as motor_command_t over
  // LCM: the simulator, or ESCs behind a bridge) | mavlink (body rates and thrust to a PX4 or
  // ArduPilot autopilot, which is then the IMU too)
  std::string backend = "none";
  // imu: lcm (imu_t on KINFLY_<vid>_IMU: the simulator) | mavlink (the autopilot's)
  std::string imu = "lcm";
  // lcm_url: the control task's own LCM (IMU in, rotor commands out); empty: link.lcm_url's.
  // A simulator on this machine: udpm://239.255.76.67:7669?ttl=0, so 1 kHz never reaches Wi-Fi.
  std::string lcm_url;
  int rt_priority = 0;           // rt_priority [0, 99]: SCHED_FIFO priority; 0: the default policy
  int cpu = -1;                  // cpu [-1, 1023]: pin the control thread to this core; -1: none
  std::string attitude_law = "geometric";  // attitude_law: geometric | lqr
  // lockstep: the IMU's stamps are the only clock, as with a lockstep simulator (kinfly-sim,
  // docs/sim.md) that pauses while it renders or waits: no ticks of the task's own while the IMU
  // is silent after its first sample (so no IMU-lost failsafe either). false: a real IMU, whose
  // silence is a failure the stack must see on the wall clock.
  bool lockstep = false;
  // lockstep_pose_age_s: with lockstep, each odometry pose reaches the estimator at the first IMU
  // sample this long after its frame's capture, and the simulator (kinfly-sim --pose-age-ms, the
  // same age) waits for the pose only then: the odometry runs beside the simulation and the
  // flight stays the same on any machine. A pose fetched after that sample is counted
  // (ControlSummary::poses_late). [0, 0.1]; 0: each pose at the first sample after it is
  // published, as on a drone (kinfly-sim --pose-age-ms 0 waits for it at its frame's delivery).
  double lockstep_pose_age_s = 0.0;
  // rate_hz (the IMU's sample rate: one tick per sample), position_rate_hz, the vehicle's mass_kg
  // and arm_length_m, max_speed_m_s, max_accel_m_s2, max_jerk_m_s3, land_speed_m_s,
  // vision_lost_s: the flight
  // stack's parameters; the rest keep the library's defaults.
  flight::FlightStackParams stack;
  // The mavlink backend: mavlink_url (udpin:HOST:PORT, udpout:HOST:PORT or a /dev/ serial port),
  // mavlink_baud (serial), mavlink_key (a 32-byte key file for MAVLink 2 signing; empty:
  // unsigned), mavlink_system_id, mavlink_component_id, mavlink_timeout_s, mavlink_setpoint_hz,
  // mavlink_hover_thrust (docs/flight.md, "The mavlink backend").
  std::string mavlink_url = "udpin:0.0.0.0:14540";
  int mavlink_baud = 921600;
  std::string mavlink_key;
  actuators::AutopilotParams mavlink;
  Status validate() const;
  // The autopilot's parameters, with the IMU rate asked of it.
  actuators::AutopilotParams autopilotParams() const;
  // The stack's parameters with the attitude law and the failsafe action for the backend.
  flight::FlightStackParams stackParams() const;
  bool enabled() const { return backend != "none"; }
};

struct OutputConfig {                            // [output]
  std::string trajectory;        // trajectory: TUM file of the published poses, written at exit
  std::string ground_truth;      // ground_truth: TUM file of the source's true poses
  std::string log_level = "info";  // log_level: trace | debug | info | warn | error
  Status validate() const;
};

struct FirmwareConfig {
  VehicleConfig vehicle;
  SourceConfig source;
  OdometryConfig odometry;
  KeyframeSelector::Params keyframe;             // [keyframe]
  LinkConfig link;
  CorrectionAnchor::Params corrections;          // [corrections]
  FlightConfig flight;
  OutputConfig output;

  // An error names the first wrong value, its key in the config, and the allowed range.
  Status validate() const;
};

// Registers every field as an option (and config key) of `app`, and makes `app` read config
// files section by section into those options, refusing keys it does not know.
void addConfigOptions(CLI::App* app, FirmwareConfig* config);

}  // namespace kinfly::fw
