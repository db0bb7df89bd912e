// kinfly-sim: the simulated world kinfly-fw flies in, over LCM, in lockstep (docs/sim.md).
//
// Simulation time is the only clock. Each IMU period the simulator steps the vehicle (RK4, one
// step per IMU sample), publishes the sample, and waits for kinfly-fw's control task to answer it
// with the rotor commands of that sample (motor_command_t, same utime) before it goes on. Depth
// frames are rendered at capture time and published after the camera's latency; the simulator
// waits for the odometry's pose of that frame (odometry_t, same utime) before it sends the IMU
// sample at which the pose is due (--pose-age-ms after the capture; 0: at once), and kinfly-fw's
// control task fuses the pose at that sample (flight.lockstep_pose_age_s, the same age): the
// odometry runs beside the simulation, and the flight is the same on any machine. The mission (a
// TOML file, or the built-in take off, hold, land) is sent as signed commands, as `kinfly-ground
// command` would, and its scripted faults act on the world at their times.
#include <CLI/CLI.hpp>
#include <lcm/lcm-cpp.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <deque>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <sstream>
#include <optional>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "kinfly/codec/depth_codec.h"
#include "kinfly/core/json.h"
#include "kinfly/core/range_check.h"
#include "kinfly/core/se3.h"
#include "kinfly/link/channels.h"
#include "kinfly/link/conversions.h"
#include "kinfly/link/decode.h"
#include "kinfly/link/signing.h"
#include "kinfly/mesh/mesh.h"
#include "kinfly/sim/depth_camera.h"
#include "kinfly/sim/barometer.h"
#include "kinfly/sim/imu_model.h"
#include "kinfly/sim/mission.h"
#include "kinfly/sim/multirotor.h"
#include "kinfly/sim/ray_scene.h"
#include "kinfly/sim/scene.h"
#include "kinfly/sim/wind.h"
#include "kinfly/flight_status_t.hpp"
#include "kinfly/sim_state_t.hpp"

namespace kinfly::sim {
namespace {

using Clock = std::chrono::steady_clock;

constexpr int64_t kStartUtime = 1'000'000;  // [us] a start after 0 keeps every stamp positive
constexpr int kStateEverySteps = 10;        // sim_state_t at a tenth of the IMU rate
// After an orchestrated event's line: the orchestrator writes a line to standard input once it
// has acted (scripts/sim.py looks for this text).
constexpr const char* kAwaitingOrchestrator = ": waiting for the orchestrator";

struct Options {
  std::string scene = "room";
  uint64_t seed = 1;
  int vehicle_id = 1;
  std::string lcm_url;
  std::string truth_lcm_url;  // also ground_truth_t there (empty: only on lcm_url)
  std::string key_file;
  std::string mission_file;
  bool realtime = false;
  bool orchestrated = false;
  double max_seconds = 0.0;
  double wait_s = 10.0;
  double takeoff_height_m = 1.0;
  double hover_s = 10.0;
  double crash_speed_m_s = 1.5;
  double pose_age_ms = 0.0;
  int camera_downsample = 1;
  std::string summary;
  std::string scene_mesh;
  std::vector<double> scene_start;  // X Y HEADING_DEG; a built-in scene's own where empty
  // Errors of the simulated vehicle against the nominal one (what kinfly-fw's flight stack
  // believes by default): fractions, +0.05 = 5 % more.
  double mass_error = 0.0;
  double inertia_error = 0.0;
  double thrust_error = 0.0;
  std::vector<double> wind_m_s{0.0, 0.0, 0.0};
  double turbulence_w20_m_s = 0.0;
  MultirotorParams vehicle;
  ImuParams imu;
  BarometerParams baro;
  DepthCameraParams camera;
};

Status validate(const Options& o) {
  if (o.wind_m_s.size() != 3) return Status::error("--wind needs three values: x y z [m/s]");
  return firstError(
      outOfRange("--max-seconds", o.max_seconds, 0.0, 86400.0),
      outOfRange("--wait-s", o.wait_s, 0.1, 600.0),
      outOfRange("--takeoff-height-m", o.takeoff_height_m, 0.2, 2.5),
      outOfRange("--hover-s", o.hover_s, 0.0, 3600.0),
      outOfRange("--crash-speed-m-s", o.crash_speed_m_s, 0.1, 20.0, Bound::kOpen),
      outOfRange("--mass-error", o.mass_error, -0.5, 0.5),
      outOfRange("--inertia-error", o.inertia_error, -0.5, 0.5),
      outOfRange("--thrust-error", o.thrust_error, -0.5, 0.5),
      outOfRange("--camera-downsample", o.camera_downsample, 1, 4));
}

// --pose-age-ms against the clocks: a pose is due after its frame's delivery (the IMU sample at
// or after the latency, which has ticked before the frame is sent), and at the latest when the
// next frame is delivered, so that kinfly-fw has fused it before the odometry can publish the
// next (its control task holds one pose). Captures fall on the IMU's steps, the next at least the
// frame period rounded down to them after the last. Rates and latency valid.
Status checkPoseAge(const Options& o, const ImuParams& imu, const DepthCameraParams& camera) {
  if (o.pose_age_ms == 0.0) return {};
  const int64_t step_us = std::llround(1e6 / imu.rate_hz);
  const int64_t frame_us = std::llround(1e6 / camera.rate_hz);
  const int64_t latency_us = std::llround(camera.latency_s * 1e6);
  const int64_t delivered_us = (latency_us + step_us - 1) / step_us * step_us;
  const int64_t latest_us = delivered_us + frame_us / step_us * step_us;
  const int64_t age_us = std::llround(o.pose_age_ms * 1e3);
  if (age_us > delivered_us && age_us <= latest_us) return {};
  char why[320];
  std::snprintf(why, sizeof why,
                "--pose-age-ms %g: a pose is due after its frame's delivery (%g ms: the camera's "
                "latency on the IMU's %g ms steps) and at the latest at the next frame's (%g ms: "
                "%g ms more between captures)",
                o.pose_age_ms, static_cast<double>(delivered_us) * 1e-3,
                static_cast<double>(step_us) * 1e-3, static_cast<double>(latest_us) * 1e-3,
                static_cast<double>(latest_us - delivered_us) * 1e-3);
  return Status::error(why);
}

// The simulated vehicle: the nominal one with the stated errors.
MultirotorParams simulatedVehicle(const Options& o) {
  MultirotorParams p = o.vehicle;
  p.mass_kg *= 1.0 + o.mass_error;
  p.inertia_xx_kg_m2 *= 1.0 + o.inertia_error;
  p.inertia_yy_kg_m2 *= 1.0 + o.inertia_error;
  p.inertia_zz_kg_m2 *= 1.0 + o.inertia_error;
  p.thrust_coeff_n_s2_rad2 *= 1.0 + o.thrust_error;
  return p;
}

// The scene by --scene: a built-in one by name (at its own start, or at --scene-start in its own
// frame: z down, as --scene-mesh writes it), else a mesh file standing at --scene-start.
StatusOr<Scene> chosenScene(const Options& o) {
  const std::vector<std::string>& names = sceneNames();
  if (std::find(names.begin(), names.end(), o.scene) != names.end()) {
    StatusOr<Scene> scene = makeScene(o.scene);
    if (scene.ok() && o.scene_start.size() == 3) {
      scene.value().start_xy_m = {o.scene_start[0], o.scene_start[1]};
      scene.value().start_yaw_rad = o.scene_start[2] * M_PI / 180.0;
    }
    return scene;
  }
  if (!std::filesystem::is_regular_file(o.scene)) {
    std::string known;
    for (const std::string& name : names) known += (known.empty() ? "" : ", ") + name;
    return Status::error("--scene: '" + o.scene + "' is neither a scene (" + known +
                         ") nor a mesh file");
  }
  if (o.scene_start.size() != 3) {
    return Status::error("--scene-start: a scene from a mesh file (" + o.scene + ") needs where "
                         "the drone stands: X Y HEADING_DEG in the mesh's frame");
  }
  StatusOr<Scene> loaded = loadMeshScene(o.scene, {o.scene_start[0], o.scene_start[1]},
                                         o.scene_start[2] * M_PI / 180.0);
  if (!loaded.ok()) return Status::error("--scene: " + loaded.status().message());
  return loaded;
}

// What kinfly-fw sends back, as the LCM handlers see it.
struct Answers {
  int64_t motor_utime = -1;
  motor_command_t motor;
  bool motor_heard = false;
  std::set<int64_t> odometry;        // utimes of odometry poses heard (erased when taken)
  int64_t commands_passed = 0;       // the drone's status: commands handed to its flight stack
  int64_t rejected = 0;
};

class Link {
 public:
  Link(const Options& o, lcm::LCM* lcm) : o_(o), lcm_(lcm) {
    lcm_->subscribeFunction(link::channelName(link::Channel::kMotorCommand, o.vehicle_id),
                            &Link::onMotor, this);
    lcm_->subscribeFunction(link::channelName(link::Channel::kOdometry, o.vehicle_id),
                            &Link::onOdometry, this);
    lcm_->subscribeFunction(link::channelName(link::Channel::kStatus, o.vehicle_id),
                            &Link::onStatus, this);
  }
  Answers& answers() { return answers_; }

  // Handles messages until done() or wait_s of wall time; false on the timeout. again() is
  // called every kAgainPeriod of the wait: what was sent and is not yet answered is sent again
  // (a datagram lost to a socket buffer full on a busy machine is never retransmitted).
  template <class Done, class Again>
  bool waitFor(Done done, Again again) {
    constexpr auto kAgainPeriod = std::chrono::milliseconds(500);
    const Clock::time_point start = Clock::now();
    const Clock::time_point deadline =
        start + std::chrono::duration_cast<Clock::duration>(
                    std::chrono::duration<double>(o_.wait_s));
    Clock::time_point next_again = start + kAgainPeriod;
    while (!done()) {
      const Clock::time_point now = Clock::now();
      const auto left =
          std::chrono::duration_cast<std::chrono::milliseconds>(deadline - now).count();
      if (left <= 0) return false;
      if (now >= next_again) {
        again();
        next_again = now + kAgainPeriod;
      }
      lcm_->handleTimeout(static_cast<int>(std::min<int64_t>(left, 100)));
    }
    return true;
  }
  template <class Done>
  bool waitFor(Done done) {
    return waitFor(done, [] {});
  }

 private:
  // Decodes what LCM delivered within bounds, for this vehicle only; else counts it rejected.
  template <class Message>
  bool accept(const lcm::ReceiveBuffer* buffer, Message* m) {
    if (link::decodeMessage(buffer->data, buffer->data_size, link::DecodeBounds(), m).ok() &&
        m->vehicle_id == o_.vehicle_id) {
      return true;
    }
    ++answers_.rejected;
    return false;
  }
  static void onMotor(const lcm::ReceiveBuffer* buffer, const std::string&, Link* self) {
    motor_command_t m;
    if (!self->accept(buffer, &m)) return;
    self->answers_.motor = m;
    self->answers_.motor_utime = m.utime;
    self->answers_.motor_heard = true;
  }
  static void onStatus(const lcm::ReceiveBuffer* buffer, const std::string&, Link* self) {
    drone_status_t m;
    if (!self->accept(buffer, &m)) return;
    self->answers_.commands_passed = std::max(self->answers_.commands_passed, m.commands_passed);
  }
  static void onOdometry(const lcm::ReceiveBuffer* buffer, const std::string&, Link* self) {
    odometry_t m;
    if (self->accept(buffer, &m)) self->answers_.odometry.insert(m.utime);
  }

  const Options& o_;
  lcm::LCM* lcm_;
  Answers answers_;
};

// The command a mission's step sends.
flight_command_t commandOf(const MissionCommand& step, int vehicle_id, int64_t command_id) {
  flight_command_t c{};
  c.utime = link::wallClockUtime();
  c.vehicle_id = vehicle_id;
  c.command_id = command_id;
  c.height_m = step.height_m;
  for (int i = 0; i < 3; ++i) c.target_world_m[i] = step.target_world_m[i];
  c.has_yaw = !std::isnan(step.yaw_rad);
  c.yaw_rad = c.has_yaw ? step.yaw_rad : 0.0;
  c.max_speed_m_s = step.max_speed_m_s;
  c.waypoint_count = 0;
  switch (step.kind) {
    case MissionCommand::Kind::kArm: c.kind = flight_command_t::ARM; break;
    case MissionCommand::Kind::kDisarm: c.kind = flight_command_t::DISARM; break;
    case MissionCommand::Kind::kTakeOff: c.kind = flight_command_t::TAKE_OFF; break;
    case MissionCommand::Kind::kHold: c.kind = flight_command_t::HOLD; break;
    case MissionCommand::Kind::kGoTo: c.kind = flight_command_t::GO_TO; break;
    case MissionCommand::Kind::kLand: c.kind = flight_command_t::LAND; break;
    case MissionCommand::Kind::kWaypoints:
      c.kind = flight_command_t::MISSION;
      c.waypoint_count = static_cast<int32_t>(step.waypoints_world_m.size());
      for (const Eigen::Vector3d& w : step.waypoints_world_m) {
        c.waypoints_world_m.push_back({w.x(), w.y(), w.z()});
      }
      break;
  }
  return c;
}

// flight_status_t's names of the flight modes motor_command_t carries.
const char* modeName(int mode) {
  static const char* const names[] = {"disarmed", "armed", "take_off", "hold", "go_to",
                                      "mission", "land", "descend", "motors_cut", "handed_over"};
  return mode >= 0 && mode < 10 ? names[mode] : "unknown";
}

bool failsafeMode(int mode) {
  return mode == flight_status_t::MODE_DESCEND || mode == flight_status_t::MODE_MOTORS_CUT ||
         mode == flight_status_t::MODE_HANDED_OVER;
}

struct Flight {
  int64_t steps = 0;
  int64_t frames = 0;
  int64_t odometry_missed = 0;
  int64_t motor_missed = 0;
  bool collided = false;
  Eigen::Vector3d collision_world_m = Eigen::Vector3d::Zero();
  double collision_speed_m_s = 0.0;
  bool crashed_on_floor = false;
  double last_touchdown_m_s = 0.0;
  double max_height_m = 0.0;
  double hover_sq_sum_m2 = 0.0;
  int64_t hover_samples = 0;
  bool landed = false;
  std::vector<std::pair<double, int>> modes;   // (time, mode) at each change
  int failsafes = 0;                           // changes into a failsafe mode
  std::vector<std::pair<double, std::string>> events;  // the faults applied
  double sim_s = 0.0;
  double wall_s = 0.0;
};

int run(const Options& o) {
  StatusOr<Scene> scene = chosenScene(o);
  if (!scene.ok()) {
    std::fprintf(stderr, "kinfly-sim: %s\n", scene.status().message().c_str());
    return 2;
  }
  if (!o.scene_mesh.empty()) {
    if (Status written = writePly(scene->mesh, o.scene_mesh); !written.ok()) {
      std::fprintf(stderr, "kinfly-sim: --scene-mesh: %s\n", written.message().c_str());
      return 2;
    }
  }
  const MultirotorParams vehicle_params = simulatedVehicle(o);
  DepthCameraParams camera_params = o.camera;
  {
    // A Kinect at the smaller size: the focal length scaled, the principal point at the centre
    // (what kinfly-fw's lcm source assumes without source.intrinsics).
    PinholeCamera& c = camera_params.camera;
    const float n = static_cast<float>(o.camera_downsample);
    c.fx /= n;
    c.fy /= n;
    c.width /= o.camera_downsample;
    c.height /= o.camera_downsample;
    c.cx = 0.5f * static_cast<float>(c.width - 1);
    c.cy = 0.5f * static_cast<float>(c.height - 1);
  }
  camera_params.seed = o.seed * 3 + 1;
  ImuParams imu_params = o.imu;
  imu_params.seed = o.seed * 3 + 2;
  BarometerParams baro_params = o.baro;
  baro_params.seed = o.seed * 7919 + 4;  // a stream of its own, apart from the seeds' 3 above
  WindParams wind_params;
  wind_params.mean_world_m_s = Eigen::Vector3d(o.wind_m_s[0], o.wind_m_s[1], o.wind_m_s[2]);
  wind_params.turbulence_w20_m_s = o.turbulence_w20_m_s;
  wind_params.seed = o.seed * 3 + 3;
  for (const Status& status : {validate(o), vehicle_params.validate(), camera_params.validate(),
                               imu_params.validate(), baro_params.validate(),
                               wind_params.validate()}) {
    if (!status.ok()) {
      std::fprintf(stderr, "kinfly-sim: %s\n", status.message().c_str());
      return 2;
    }
  }
  if (const Status age = checkPoseAge(o, imu_params, camera_params); !age.ok()) {
    std::fprintf(stderr, "kinfly-sim: %s\n", age.message().c_str());
    return 2;
  }
  StatusOr<Mission> loaded = o.mission_file.empty()
                                ? StatusOr<Mission>(defaultMission(o.takeoff_height_m, o.hover_s))
                                : loadMission(o.mission_file);
  if (!loaded.ok()) {
    std::fprintf(stderr, "kinfly-sim: --mission: %s\n", loaded.status().message().c_str());
    return 2;
  }
  const Mission& mission = loaded.value();
  for (const MissionEvent& e : mission.events) {
    if (e.orchestrated() && !o.orchestrated) {
      std::fprintf(stderr,
                   "kinfly-sim: --mission: the %s at %.1f s needs the program that runs the "
                   "ground station and the network to act on it: fly this mission with "
                   "scripts/sim.py (which passes --orchestrated)\n",
                   e.kind == MissionEvent::Kind::kGroundKilled ? "ground_restart" : "link_loss",
                   e.at_s);
      return 2;
    }
  }
  StatusOr<link::Key> key = link::loadKeyFile(o.key_file);
  if (!key.ok()) {
    std::fprintf(stderr, "kinfly-sim: --key-file: %s\n", key.status().message().c_str());
    return 2;
  }
  StatusOr<std::unique_ptr<RayScene>> rays = RayScene::create(scene.value());
  if (!rays.ok()) {
    std::fprintf(stderr, "kinfly-sim: %s\n", rays.status().message().c_str());
    return 1;
  }
  lcm::LCM lcm(o.lcm_url);
  if (!lcm.good()) {
    std::fprintf(stderr, "kinfly-sim: cannot start LCM on '%s'\n", o.lcm_url.c_str());
    return 1;
  }
  Link link_io(o, &lcm);
  Answers& answers = link_io.answers();
  // Beside the drone's bus, as a motion-capture system sends the truth to the ground station.
  std::optional<lcm::LCM> truth_lcm;
  if (!o.truth_lcm_url.empty() && !truth_lcm.emplace(o.truth_lcm_url).good()) {
    std::fprintf(stderr, "kinfly-sim: --truth-lcm-url: cannot start LCM on '%s'\n",
                 o.truth_lcm_url.c_str());
    return 1;
  }

  Multirotor drone(vehicle_params);
  drone.placeOnFloor(scene.value().start_xy_m, scene.value().start_yaw_rad,
                     scene.value().floor_z_m);
  {
    // A start off the floor (on a table, outside the room, over a hole in a scan), under
    // something (a table, inside a box) or against the scene would end the flight at once: say so
    // before flying. Below, the floor within the floor's own tolerance of the gear; above, room to
    // climb to the mission's first take-off height.
    constexpr double kBelowGearM = 0.05;
    const Eigen::Vector3d& p = drone.state().p_world_m;
    const RayHit below = rays.value()->cast(p.cast<float>(), Eigen::Vector3f::UnitZ(),
                                            static_cast<float>(vehicle_params.gear_height_m + kBelowGearM));
    double climb_m = o.takeoff_height_m;
    for (const MissionCommand& c : mission.commands) {
      if (c.kind == MissionCommand::Kind::kTakeOff) {
        climb_m = c.height_m;
        break;
      }
    }
    const RayHit above = rays.value()->cast(p.cast<float>(), -Eigen::Vector3f::UnitZ(),
                                            static_cast<float>(climb_m + vehicle_params.body_radius_m));
    const char* problem = !below.hit || !below.floor ? "is not over the scene's floor"
                          : above.hit ? "has no room to take off above it"
                          : rays.value()->touches(p, vehicle_params.body_radius_m)
                              ? "is within the body's radius of the scene"
                              : nullptr;
    if (problem != nullptr && !o.scene_start.empty()) {
      // + 0.0: a floor at the mesh's zero prints as 0.000, not -0.000.
      std::fprintf(stderr, "kinfly-sim: --scene-start %g %g %g: the drone standing there %s "
                   "(its floor is at %.3f m in the scene's frame)\n", o.scene_start[0],
                   o.scene_start[1], o.scene_start[2], problem, -scene.value().floor_z_m + 0.0);
      return 2;
    }
    if (problem != nullptr) {
      std::fprintf(stderr, "kinfly-sim: scene %s: its start %s\n", scene.value().name.c_str(),
                   problem);
      return 2;
    }
  }
  Wind wind(wind_params);
  ImuModel imu(imu_params);
  Barometer baro(baro_params);
  DepthCamera camera(*rays.value(), camera_params);
  DepthCodec codec{DepthCodec::Params()};
  const Pose T_body_cam = forwardBodyCam();
  link::Signer signer(key.value(), o.vehicle_id, link::wallClockUtime());

  const std::string imu_channel = link::channelName(link::Channel::kImu, o.vehicle_id);
  const std::string depth_channel = link::channelName(link::Channel::kDepth, o.vehicle_id);
  const std::string truth_channel = link::channelName(link::Channel::kGroundTruth, o.vehicle_id);
  const std::string state_channel = link::channelName(link::Channel::kSimState, o.vehicle_id);
  const std::string command_channel = link::channelName(link::Channel::kCommand, o.vehicle_id);

  const PinholeCamera& cam = camera_params.camera;
  std::printf("kinfly-sim: scene %s, seed %llu, IMU %.0f Hz, depth %dx%d (fx %g, fy %g, cx %g, "
              "cy %g) at %.0f Hz (latency %.0f ms); waiting for kinfly-fw's control task on %s\n",
              o.scene.c_str(), static_cast<unsigned long long>(o.seed), imu_params.rate_hz,
              cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, camera_params.rate_hz,
              camera_params.latency_s * 1e3,
              link::channelName(link::Channel::kMotorCommand, o.vehicle_id).c_str());
  std::fflush(stdout);
  // Ready: the control task ticks on the wall clock until the first IMU sample, and answers.
  if (!link_io.waitFor([&] { return answers.motor_heard; })) {
    std::fprintf(stderr, "kinfly-sim: kinfly-fw's control task never answered within %.0f s "
                         "(is it running with flight.backend = motors and this LCM URL?)\n",
                 o.wait_s);
    return 1;
  }

  size_t next_command = 0;
  size_t next_event = 0;
  int64_t command_id = 0;
  double dropout_until_s = -1.0;  // a vision dropout: no frames captured before then

  const double dt_s = 1.0 / imu_params.rate_hz;
  const int64_t period_us = static_cast<int64_t>(std::llround(1e6 / imu_params.rate_hz));
  const int64_t frame_period_us = static_cast<int64_t>(std::llround(1e6 / camera_params.rate_hz));
  const int64_t latency_us = static_cast<int64_t>(std::llround(camera_params.latency_s * 1e6));
  struct Pending {
    int64_t due_us;
    depth_keyframe_t message;
  };
  std::vector<Pending> pending;
  Image<uint16_t> raw(camera_params.camera.width, camera_params.camera.height);
  int64_t next_frame_us = kStartUtime;
  Vector4d command = Vector4d::Zero();
  Flight flight;
  const int64_t pose_age_us = std::llround(o.pose_age_ms * 1e3);
  // Capture times of the frames delivered whose poses are due later (--pose-age-ms), oldest first.
  std::deque<int64_t> awaited;
  // False when kinfly-fw's odometry did not answer the frame captured at `captured` (counted).
  const auto awaitPose = [&](int64_t captured) {
    if (!link_io.waitFor([&] { return answers.odometry.count(captured) > 0; })) {
      ++flight.odometry_missed;
      std::fprintf(stderr, "kinfly-sim: kinfly-fw's odometry did not answer the frame captured "
                           "at t=%.3f s within %.0f s (its log says why: is source.kind = lcm, "
                           "its camera this one?)\n",
                   static_cast<double>(captured - kStartUtime) * 1e-6, o.wait_s);
      return false;
    }
    answers.odometry.erase(answers.odometry.begin(), answers.odometry.upper_bound(captured));
    return true;
  };
  // Heights are the body's above where it stood (as kinfly-fw's take-off counts them).
  const double stand_z_m = scene.value().floor_z_m - vehicle_params.gear_height_m;
  // Holding after a take-off: from the climb's end (at ~0.5 m/s, with room) to the next command.
  bool holding_after_take_off = false;
  double hover_from_s = 0.0;
  double hover_to_s = 0.0;
  Eigen::Vector3d hover_target = Eigen::Vector3d::Zero();
  const Clock::time_point wall_start = Clock::now();
  int64_t utime = kStartUtime;
  bool airborne = false;
  int64_t disarmed_on_floor_steps = 0;
  const double max_s = o.max_seconds > 0.0 ? o.max_seconds : mission.max_s;
  const int64_t end_utime = kStartUtime + static_cast<int64_t>(max_s * 1e6);
  sim_state_t state_msg{};
  state_msg.vehicle_id = o.vehicle_id;
  imu_t imu_msg{};
  imu_msg.vehicle_id = o.vehicle_id;
  imu_msg.temperature_c = NAN;
  // The barometer's readings go with the IMU sample at or after each of its periods.
  const int64_t baro_period_us =
      baro_params.rate_hz > 0.0 ? std::llround(1e6 / baro_params.rate_hz) : 0;
  int64_t next_baro_us = kStartUtime;
  ground_truth_t truth_msg{};
  truth_msg.vehicle_id = o.vehicle_id;
  double next_progress_s = 5.0;

  while (utime < end_utime) {
    const double t_s = static_cast<double>(utime - kStartUtime) * 1e-6;
    // The mission's commands, signed as the ground signs them.
    while (next_command < mission.commands.size() && t_s >= mission.commands[next_command].at_s) {
      const MissionCommand& step = mission.commands[next_command++];
      const flight_command_t c = commandOf(step, o.vehicle_id, ++command_id);
      std::vector<uint8_t> inner(static_cast<size_t>(c.getEncodedSize()));
      c.encode(inner.data(), 0, static_cast<int>(inner.size()));
      // Signed anew each time it is sent: the drone's Verifier takes only sequence numbers above
      // the last and signing times within its window; its link acts on a command_id once.
      const auto send_command = [&] {
        signed_t envelope;
        signer.sign(inner.data(), inner.size(), link::wallClockUtime(), &envelope);
        lcm.publish(command_channel, &envelope);
      };
      send_command();
      std::printf("kinfly-sim: t=%.2f s: %s\n", t_s, step.name.c_str());
      std::fflush(stdout);
      // Held until the drone says the command is its flight stack's, so that the next sample's
      // tick takes it, on any machine (the link hands it over on its own thread).
      if (!link_io.waitFor([&] { return answers.commands_passed >= command_id; },
                           send_command)) {
        std::fprintf(stderr, "kinfly-sim: kinfly-fw did not take the %s command within %.0f s "
                             "(its log says why: the key, the clock window, a mission it cannot "
                             "fly)\n",
                     step.name.c_str(), o.wait_s);
        return 1;
      }
      holding_after_take_off = step.kind == MissionCommand::Kind::kTakeOff;
      if (holding_after_take_off) {
        hover_from_s = step.at_s + 2.0 + 2.0 * step.height_m;
        hover_to_s = next_command < mission.commands.size() ? mission.commands[next_command].at_s
                                                             : max_s;
        hover_target << scene.value().start_xy_m, stand_z_m - step.height_m;
      }
    }
    // The faults, on the world.
    while (next_event < mission.events.size() && t_s >= mission.events[next_event].at_s) {
      const MissionEvent& e = mission.events[next_event++];
      switch (e.kind) {
        case MissionEvent::Kind::kWindStep: wind.setMean(e.vector); break;
        case MissionEvent::Kind::kGust: wind.addGust({e.at_s, e.duration_s, e.vector}); break;
        case MissionEvent::Kind::kVisionDropout: dropout_until_s = e.at_s + e.duration_s; break;
        case MissionEvent::Kind::kImuBiasStep: imu.stepBias(e.vector, e.accel_m_s2); break;
        case MissionEvent::Kind::kMotorLoss: drone.setRotorEfficiency(e.rotor - 1, e.fraction); break;
        case MissionEvent::Kind::kGroundKilled:
        case MissionEvent::Kind::kGroundRestarted:
        case MissionEvent::Kind::kLinkLossStarted:
        case MissionEvent::Kind::kLinkLossEnded: break;  // the orchestrator's, below
      }
      flight.events.emplace_back(t_s, e.name);
      // The loss's shape in words scripts/sim.py reads, "loss=0.2 run=4", every digit kept (its
      // LinkShape checks the run against the fraction as the loader did).
      char shape[96] = "";
      if (e.kind == MissionEvent::Kind::kLinkLossStarted) {
        std::snprintf(shape, sizeof(shape), " loss=%.17g run=%.17g", e.fraction,
                      e.loss_run_packets);
      }
      std::printf("kinfly-sim: t=%.2f s: %s%s%s\n", t_s, e.name.c_str(), shape,
                  e.orchestrated() ? kAwaitingOrchestrator : "");
      std::fflush(stdout);
      // Simulation time stands still while the orchestrator acts, so the ground is down for
      // exactly duration_s of it, however long a restart takes on this machine.
      if (e.orchestrated()) {
        std::string done;
        if (!std::getline(std::cin, done)) {
          std::fprintf(stderr, "kinfly-sim: the orchestrator closed standard input before it "
                               "acted on %s\n", e.name.c_str());
          return 1;
        }
      }
    }

    // Depth frames captured now, delivered after the latency.
    if (utime >= next_frame_us && t_s < dropout_until_s) {
      next_frame_us += frame_period_us;  // the camera covered: nothing captured
    } else if (utime >= next_frame_us) {
      const Pose T_world_body = [&] {
        Pose T = Pose::Identity();
        T.linear() = drone.state().q_world_body.toRotationMatrix();
        T.translation() = drone.state().p_world_m;
        return T;
      }();
      const Pose T_world_cam = T_world_body * T_body_cam;
      camera.render(T_world_cam, raw);
      Pending p{utime + latency_us, depth_keyframe_t{}};
      link::KeyframeHeader header;
      header.utime = utime;
      header.frame_id = flight.frames;
      header.keyframe_id = -1;
      header.T_world_cam = Pose::Identity();  // a raw capture: no pose
      link::fillKeyframe(header, &p.message);
      p.message.vehicle_id = o.vehicle_id;
      if (!link::encodeDepth(codec, raw, camera_params.camera, camera_params.depth_scale_m,
                             &p.message).ok()) {
        std::fprintf(stderr, "kinfly-sim: a rendered frame does not encode\n");
        return 1;
      }
      pending.push_back(std::move(p));
      link::fillGroundTruth(utime, T_world_cam, &truth_msg);
      lcm.publish(truth_channel, &truth_msg);
      if (truth_lcm) truth_lcm->publish(truth_channel, &truth_msg);
      ++flight.frames;
      next_frame_us += frame_period_us;
    }
    while (!pending.empty() && pending.front().due_us <= utime) {
      const int64_t captured = pending.front().message.utime;
      lcm.publish(depth_channel, &pending.front().message);
      pending.erase(pending.begin());
      if (pose_age_us > 0) {
        awaited.push_back(captured);
      } else if (!awaitPose(captured)) {
        break;
      }
    }
    if (flight.odometry_missed > 0) break;

    // The physics over one IMU period with the last answer's commands.
    const Eigen::Vector3d air = wind.step(t_s + dt_s, dt_s, scene.value().floor_z_m -
                                          drone.state().p_world_m.z(), drone.state().v_world_m_s);
    const double touchdown = drone.step(command, air, dt_s);
    utime += period_us;
    ++flight.steps;
    const MultirotorState& s = drone.state();
    flight.max_height_m = std::max(flight.max_height_m, stand_z_m - s.p_world_m.z());
    if (touchdown > 0.0) {
      flight.last_touchdown_m_s = touchdown;
      if (touchdown > o.crash_speed_m_s) flight.crashed_on_floor = true;
    }
    if (!drone.onFloor()) airborne = true;
    // The scene: a face within the body's radius, the floor aside, ends the flight.
    if (rays.value()->touches(s.p_world_m, vehicle_params.body_radius_m)) {
      flight.collided = true;
      flight.collision_world_m = s.p_world_m;
      flight.collision_speed_m_s = s.v_world_m_s.norm();
    }
    const double now_s = t_s + dt_s;
    if (holding_after_take_off && now_s >= hover_from_s && now_s < hover_to_s) {
      flight.hover_sq_sum_m2 += (s.p_world_m - hover_target).squaredNorm();
      ++flight.hover_samples;
    }

    const ImuReading reading = imu.sample(s.omega_body_rad_s, drone.specificForceBodyMS2());
    imu_msg.utime = utime;
    for (int i = 0; i < 3; ++i) {
      imu_msg.angular_velocity_rad_s[i] = reading.angular_velocity_rad_s[i];
      imu_msg.linear_acceleration_m_s2[i] = reading.specific_force_m_s2[i];
    }
    imu_msg.has_pressure_altitude = baro_period_us > 0 && utime >= next_baro_us;
    if (imu_msg.has_pressure_altitude) {
      imu_msg.pressure_altitude_m = static_cast<float>(baro.read(-s.p_world_m.z()));
      next_baro_us += baro_period_us;
    }
    if (flight.steps % kStateEverySteps == 0 || flight.collided) {
      state_msg.utime = utime;
      for (int i = 0; i < 3; ++i) {
        state_msg.p_world_m[i] = s.p_world_m[i];
        state_msg.v_world_m_s[i] = s.v_world_m_s[i];
        state_msg.omega_body_rad_s[i] = s.omega_body_rad_s[i];
        state_msg.wind_world_m_s[i] = static_cast<float>(air[i]);
      }
      const Eigen::Vector4d q = s.q_world_body.coeffs();
      for (int i = 0; i < 4; ++i) {
        state_msg.q_world_body[i] = q[i];
        state_msg.rotor_speed_rad_s[i] = static_cast<float>(s.rotor_speed_rad_s[i]);
      }
      state_msg.on_floor = drone.onFloor();
      state_msg.collided = flight.collided;
      lcm.publish(state_channel, &state_msg);
    }
    if (flight.collided) break;
    // The poses due at this sample, before it: the control task fuses them there.
    while (!awaited.empty() && awaited.front() + pose_age_us <= utime && awaitPose(awaited.front()))
      awaited.pop_front();
    if (flight.odometry_missed > 0) break;
    lcm.publish(imu_channel, &imu_msg);
    if (!link_io.waitFor([&] { return answers.motor_utime == utime; })) {
      ++flight.motor_missed;
      std::fprintf(stderr, "kinfly-sim: t=%.3f s: no rotor command for this IMU sample within "
                           "%.0f s: kinfly-fw is gone\n", now_s, o.wait_s);
      break;
    }
    const motor_command_t& m = answers.motor;
    if (flight.modes.empty() || flight.modes.back().second != m.flight_mode) {
      flight.modes.emplace_back(now_s, m.flight_mode);
      if (failsafeMode(m.flight_mode)) ++flight.failsafes;
    }
    for (int i = 0; i < 4; ++i) {
      command[i] = m.state == motor_command_t::STOPPED ? 0.0 : m.rotor_speed_rad_s[i];
    }
    // Landed: back on the floor, rotors stopped, a second after the land command.
    if (airborne && drone.onFloor() && m.state == motor_command_t::STOPPED) {
      if (static_cast<double>(++disarmed_on_floor_steps) * dt_s >= 1.0) {
        flight.landed = true;
        break;
      }
    } else {
      disarmed_on_floor_steps = 0;
    }
    if (o.realtime) {
      std::this_thread::sleep_until(wall_start + std::chrono::microseconds(utime - kStartUtime));
    }
    if (now_s >= next_progress_s) {
      std::printf("kinfly-sim: t=%.0f s, height %.2f m, %.1fx real time\n", now_s,
                  stand_z_m - s.p_world_m.z(),
                  now_s / std::chrono::duration<double>(Clock::now() - wall_start).count());
      std::fflush(stdout);
      next_progress_s += 5.0;
    }
  }
  // The poses of the frames delivered, as at a frame's delivery with --pose-age-ms 0: every
  // frame sent is answered before the flight's outputs are, whatever kinfly-fw was still doing.
  if (flight.motor_missed == 0 && flight.odometry_missed == 0) {
    while (!awaited.empty() && awaitPose(awaited.front())) awaited.pop_front();
  }
  flight.sim_s = static_cast<double>(utime - kStartUtime) * 1e-6;
  flight.wall_s = std::chrono::duration<double>(Clock::now() - wall_start).count();

  const double hover_rms_m = flight.hover_samples > 0
                                 ? std::sqrt(flight.hover_sq_sum_m2 /
                                             static_cast<double>(flight.hover_samples))
                                 : NAN;
  const bool ok = flight.landed && !flight.collided && !flight.crashed_on_floor &&
                  flight.motor_missed == 0 && flight.odometry_missed == 0;
  std::ostringstream json;
  json << std::fixed << std::setprecision(4);
  json << "{\n  \"scene\": \"" << jsonEscape(o.scene) << "\",\n  \"mission\": \""
       << jsonEscape(mission.name)
       << "\",\n  \"seed\": " << o.seed << ",\n  \"sim_s\": " << flight.sim_s
       << ",\n  \"wall_s\": " << flight.wall_s
       << ",\n  \"real_time_factor\": " << flight.sim_s / std::max(flight.wall_s, 1e-9)
       << ",\n  \"imu_samples\": " << flight.steps << ",\n  \"depth_frames\": " << flight.frames
       << ",\n  \"odometry_missed\": " << flight.odometry_missed
       << ",\n  \"motor_missed\": " << flight.motor_missed
       << ",\n  \"max_height_m\": " << flight.max_height_m << ",\n  \"hover_rms_m\": ";
  if (std::isfinite(hover_rms_m)) {
    json << std::setprecision(5) << hover_rms_m << std::setprecision(4);
  } else {
    json << "null";
  }
  json << ",\n  \"touchdown_m_s\": " << flight.last_touchdown_m_s
       << ",\n  \"landed\": " << (flight.landed ? "true" : "false")
       << ",\n  \"collided\": " << (flight.collided ? "true" : "false")
       << ",\n  \"collision_world_m\": [" << flight.collision_world_m.x() << ", "
       << flight.collision_world_m.y() << ", " << flight.collision_world_m.z() << "]"
       << ",\n  \"collision_speed_m_s\": " << flight.collision_speed_m_s
       << ",\n  \"crashed_on_floor\": " << (flight.crashed_on_floor ? "true" : "false")
       << ",\n  \"failsafes\": " << flight.failsafes << ",\n  \"modes\": [";
  for (size_t i = 0; i < flight.modes.size(); ++i) {
    json << (i ? ", " : "") << "[" << std::setprecision(3) << flight.modes[i].first << ", \""
         << modeName(flight.modes[i].second) << "\"]";
  }
  json << "],\n  \"events\": [";
  for (size_t i = 0; i < flight.events.size(); ++i) {
    json << (i ? ", " : "") << "[" << std::setprecision(3) << flight.events[i].first << ", \""
         << flight.events[i].second << "\"]";
  }
  json << "],\n  \"ok\": " << (ok ? "true" : "false") << "\n}\n";
  std::fputs(json.str().c_str(), stdout);
  if (!o.summary.empty()) {
    std::ofstream out(o.summary);
    out << json.str();
    if (!out) {
      std::fprintf(stderr, "kinfly-sim: cannot write --summary %s\n", o.summary.c_str());
      return 1;
    }
  }
  if (flight.collided) {
    std::fprintf(stderr, "kinfly-sim: the drone hit the scene at (%.2f, %.2f, %.2f) m, %.2f m/s\n",
                 flight.collision_world_m.x(), flight.collision_world_m.y(),
                 flight.collision_world_m.z(), flight.collision_speed_m_s);
  } else if (flight.crashed_on_floor) {
    std::fprintf(stderr, "kinfly-sim: the drone hit the floor at %.2f m/s\n",
                 flight.last_touchdown_m_s);
  } else if (!flight.landed && flight.motor_missed == 0 && flight.odometry_missed == 0) {
    std::fprintf(stderr, "kinfly-sim: the mission did not end landed within %.0f s\n", max_s);
  }
  return ok ? 0 : 1;
}

}  // namespace
}  // namespace kinfly::sim

int main(int argc, char** argv) {
  using kinfly::sim::Options;
  Options o;
  CLI::App app{
      "kinfly-sim: the simulated world kinfly-fw flies in, over LCM, in lockstep (docs/sim.md). "
      "Start kinfly-fw first with flight.backend = motors, flight.imu = lcm, flight.lockstep = "
      "true, source.kind = lcm, source.realtime = false on the same LCM URL; kinfly-sim then "
      "flies the mission (--mission, or the built-in take off, hold, land) and prints a summary "
      "(docs/sim.md). Exit status: "
      "0 landed, 1 the flight failed (a collision, a hard landing, kinfly-fw gone), 2 bad input."};
  app.add_option("--scene", o.scene,
                 "room | corridor | ring | a mesh file (PLY, OBJ, OFF or STL: metres, z up, as Replica's "
                 "office0_mesh.ply), which needs --scene-start")
      ->capture_default_str();
  app.add_option("--scene-start", o.scene_start,
                 "where the drone stands on the floor: for a mesh file's scene X Y in the mesh's "
                 "frame [m] and its heading counter-clockwise from the mesh's +x seen from above "
                 "[deg]; for a built-in scene (its own start without it) X Y in the scene's "
                 "frame, z down as --scene-mesh writes it, and the heading from +x towards +y")
      ->expected(3);
  app.add_option("--seed", o.seed, "seeds the IMU, the camera's noise and the wind")
      ->capture_default_str();
  app.add_option("--vehicle", o.vehicle_id, "vehicle id, in every channel name")
      ->capture_default_str();
  app.add_option("--lcm-url", o.lcm_url, "LCM URL (empty: LCM's default)")->capture_default_str();
  app.add_option("--key-file", o.key_file, "the vehicle's key (kinfly-keygen): signs the mission")
      ->required();
  app.add_option("--mission", o.mission_file,
                 "a mission file (TOML: commands and scripted faults, docs/sim.md); empty: take "
                 "off, hold --hover-s, land");
  app.add_flag("--realtime", o.realtime, "pace simulation time to the wall clock, for watching");
  app.add_flag("--orchestrated", o.orchestrated,
               "a program that runs the ground station and the network (scripts/sim.py) acts on "
               "the mission's ground_restart and link_loss: at each kill, restart, loss start and "
               "end kinfly-sim prints 'kinfly-sim: t=T s: ground_killed: waiting for the "
               "orchestrator' (ground_restarted, link_loss_started loss=F run=N, link_loss_ended) "
               "and waits for a line on standard input; without it such a mission is refused");
  app.add_option("--truth-lcm-url", o.truth_lcm_url,
                 "also send each frame's true camera pose (ground_truth_t) on this LCM, as a "
                 "motion-capture system would to the ground station (empty: --lcm-url only)");
  app.add_option("--max-seconds", o.max_seconds,
                 "simulated seconds at most [0, 86400]; 0: the mission's max_s")
      ->capture_default_str();
  app.add_option("--wait-s", o.wait_s,
                 "wall seconds to wait for kinfly-fw's answer before declaring it gone")
      ->capture_default_str();
  app.add_option("--takeoff-height-m", o.takeoff_height_m, "built-in mission: take-off height [m]")
      ->capture_default_str();
  app.add_option("--hover-s", o.hover_s, "built-in mission: seconds held at that height")
      ->capture_default_str();
  app.add_option("--crash-speed-m-s", o.crash_speed_m_s,
                 "a touchdown faster than this is a crash [m/s]")
      ->capture_default_str();
  app.add_option("--pose-age-ms", o.pose_age_ms,
                 "each frame's pose is waited for before the IMU sample this long after its "
                 "capture, not at the frame's delivery, so kinfly-fw's odometry runs beside the "
                 "simulation; kinfly-fw's flight.lockstep_pose_age_s must be the same age (it "
                 "fuses the pose at that sample) [ms]; after the frame's delivery, at the latest "
                 "at the next frame's (31 to 63 at the defaults); 0: waited for at delivery")
      ->capture_default_str();
  app.add_option("--camera-downsample", o.camera_downsample,
                 "render a Kinect at 1/N of its 640x480, principal point at the centre [1, 4]")
      ->capture_default_str();
  app.add_option("--camera-rate-hz", o.camera.rate_hz, "depth frames per second")
      ->capture_default_str();
  app.add_option("--camera-latency-s", o.camera.latency_s, "capture to delivery [s]")
      ->capture_default_str();
  // With --pose-age-ms 0 kinfly-fw waits in the lockstep while a frame renders, so its cores are
  // free for the rays; otherwise its odometry shares them.
  o.camera.threads = static_cast<int>(std::clamp(std::thread::hardware_concurrency(), 1u, 4u));
  app.add_option("--camera-threads", o.camera.threads,
                 "threads a frame is rendered over (the frame is the same for any count) [1, 64]; "
                 "default: the cores, at most 4")
      ->capture_default_str();
  app.add_option("--imu-rate-hz", o.imu.rate_hz, "IMU samples (and physics steps) per second")
      ->capture_default_str();
  app.add_option("--baro-rate-hz", o.baro.rate_hz,
                 "barometer readings per second, sent with the IMU samples [0, 1000]; 0: none")
      ->capture_default_str();
  app.add_option("--baro-noise-m", o.baro.noise_m, "the barometer's 1-sigma noise per reading [m]")
      ->capture_default_str();
  app.add_option("--mass-error", o.mass_error, "the simulated mass against the nominal, +0.05: 5 % more")
      ->capture_default_str();
  app.add_option("--inertia-error", o.inertia_error, "the same for the inertia")
      ->capture_default_str();
  app.add_option("--thrust-error", o.thrust_error, "the same for the rotors' thrust coefficient")
      ->capture_default_str();
  app.add_option("--wind", o.wind_m_s, "mean wind x y z in the world (z down) [m/s]")
      ->expected(3);
  app.add_option("--turbulence-w20", o.turbulence_w20_m_s,
                 "Dryden turbulence: the wind at 20 ft that sets its intensity [m/s]; 0: none")
      ->capture_default_str();
  app.add_option("--summary", o.summary, "also write the summary JSON here");
  app.add_option("--scene-mesh", o.scene_mesh,
                 "also write the scene's triangle mesh here (binary PLY, the world frame): the "
                 "ground truth a map is scored against");
  CLI11_PARSE(app, argc, argv);
  return kinfly::sim::run(o);
}
