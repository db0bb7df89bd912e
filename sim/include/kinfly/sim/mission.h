// A simulated flight's script (docs/sim.md, "Missions"): the commands a pilot would send, at
// simulation times, and the faults the world throws at the drone. Read from a TOML file; an error
// names the file, the line and what is wrong. Positions are in the drone's world: gravity-aligned,
// z down, its origin where the drone stood at the start, x its heading then (the flight stack's
// world, so a mission reads as the commands the drone gets).
#pragma once

#include <Eigen/Core>
#include <limits>
#include <string>
#include <string_view>
#include <vector>

#include "kinfly/core/status.h"

namespace kinfly::sim {

struct MissionCommand {
  enum class Kind { kArm, kDisarm, kTakeOff, kHold, kGoTo, kWaypoints, kLand };
  double at_s = 0.0;                                    // [s] simulation time, from the start
  Kind kind = Kind::kHold;
  double height_m = 1.0;                                // take-off: above where it stands
  Eigen::Vector3d target_world_m = Eigen::Vector3d::Zero();  // go-to
  // go-to: the heading to turn to on the way [rad], about world z from world x towards world y
  // (the file's yaw_deg); NaN: keep the drone's
  double yaw_rad = std::numeric_limits<double>::quiet_NaN();
  std::vector<Eigen::Vector3d> waypoints_world_m;       // waypoints (and a figure eight's)
  double max_speed_m_s = 0.0;                           // waypoints: peak speed; 0: the drone's
  std::string name;                                     // as written: arm, figure_eight ...
};

struct MissionEvent {
  // kGroundKilled and kGroundRestarted come in pairs from one ground_restart in the file,
  // kLinkLossStarted and kLinkLossEnded from one link_loss: the orchestrator that runs the
  // ground station and the network acts on them (MissionEvent::orchestrated).
  enum class Kind {
    kWindStep, kGust, kVisionDropout, kImuBiasStep, kMotorLoss, kGroundKilled, kGroundRestarted,
    kLinkLossStarted, kLinkLossEnded
  };
  double at_s = 0.0;                                    // [s] simulation time
  Kind kind = Kind::kWindStep;
  Eigen::Vector3d vector = Eigen::Vector3d::Zero();     // wind [m/s], gust amplitude [m/s],
                                                        // gyro bias step [rad/s]
  Eigen::Vector3d accel_m_s2 = Eigen::Vector3d::Zero(); // accelerometer bias step
  double duration_s = 0.0;                              // gust rise, dropout length, ground
                                                        // down, link loss length
  int rotor = 1;                                        // motor loss: 1..4 (PX4's order)
  double fraction = 1.0;                                // motor loss: what is left of its
                                                        // thrust; link loss: packets lost
  double loss_run_packets = 1.0;                        // link loss: mean run of losses
  std::string name;

  // Not the world's to act on: scripts/sim.py kills and restarts the ground station, and
  // shapes the link.
  bool orchestrated() const {
    return kind == Kind::kGroundKilled || kind == Kind::kGroundRestarted ||
           kind == Kind::kLinkLossStarted || kind == Kind::kLinkLossEnded;
  }
};

struct Mission {
  std::string name = "default";
  double max_s = 120.0;  // [s] simulated time at most; a flight still in the air then failed
  std::vector<MissionCommand> commands;  // in time order
  std::vector<MissionEvent> events;      // in time order
};

// The default: arm at 2 s, take off to takeoff_height_m at 3 s, hold hover_s, land.
Mission defaultMission(double takeoff_height_m, double hover_s);

// A figure eight (Gerono's lemniscate) of size_m (x by y) around centre_world_m, as 17
// waypoints for a minimum-snap mission: x = a sin(t), y = b sin(2t) / 2 ... once round.
std::vector<Eigen::Vector3d> figureEightWaypoints(const Eigen::Vector3d& centre_world_m,
                                                  const Eigen::Vector2d& size_m);

// Parses a mission; `source` names it in errors ("tour.toml:12: ...").
StatusOr<Mission> parseMission(std::string_view text, const std::string& source);
StatusOr<Mission> loadMission(const std::string& path);

}  // namespace kinfly::sim
