#include "kinfly/sim/mission.h"

#include <toml++/toml.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>
#include <optional>
#include <set>
#include <sstream>

namespace kinfly::sim {
namespace {

constexpr int kMaxWaypoints = 100;  // what a flight_command_t carries
constexpr double kMaxTimeS = 86400.0;

// Errors carry "source:line: ".
class Reader {
 public:
  explicit Reader(std::string source) : source_(std::move(source)) {}

  Status error(const toml::node& node, const std::string& what) const {
    return Status::error(source_ + ":" + std::to_string(node.source().begin.line) + ": " + what);
  }
  Status error(const std::string& what) const { return Status::error(source_ + ": " + what); }

  // Every key of `table` must be one of `known`.
  Status onlyKnown(const toml::table& table, const std::set<std::string>& known,
                   const std::string& where) const {
    for (const auto& [key, value] : table) {
      if (known.count(std::string(key.str())) == 0) {
        std::string list;
        for (const std::string& k : known) list += (list.empty() ? "" : ", ") + k;
        return error(value, "unknown key '" + std::string(key.str()) + "' in " + where +
                                " (known: " + list + ")");
      }
    }
    return {};
  }

  StatusOr<double> number(const toml::table& table, const std::string& key, double lo,
                          double hi, std::optional<double> fallback = std::nullopt) const {
    const toml::node* node = table.get(key);
    if (node == nullptr) {
      if (fallback) return *fallback;
      return error(table, "'" + key + "' is required here");
    }
    const std::optional<double> value = node->value<double>();
    if (!value || !std::isfinite(*value) || *value < lo || *value > hi) {
      std::ostringstream range;
      range << "[" << lo << ", " << hi << "]";
      return error(*node, "'" + key + "' must be a number in " + range.str());
    }
    return *value;
  }

  StatusOr<Eigen::Vector3d> vector3(const toml::node& node, const std::string& key,
                                    double limit) const {
    const toml::array* array = node.as_array();
    Eigen::Vector3d v;
    if (array == nullptr || array->size() != 3) {
      return error(node, "'" + key + "' must be three numbers [x, y, z]");
    }
    for (int i = 0; i < 3; ++i) {
      const std::optional<double> value = (*array)[static_cast<size_t>(i)].value<double>();
      if (!value || !std::isfinite(*value) || std::abs(*value) > limit) {
        std::ostringstream bound;
        bound << limit;
        return error(node, "'" + key + "' must be three numbers within +-" + bound.str());
      }
      v[i] = *value;
    }
    return v;
  }

  StatusOr<Eigen::Vector3d> vector3(const toml::table& table, const std::string& key,
                                    double limit) const {
    const toml::node* node = table.get(key);
    if (node == nullptr) return error(table, "'" + key + "' is required here");
    return vector3(*node, key, limit);
  }

 private:
  std::string source_;
};

#define KINFLY_TRY_ASSIGN(target, expression)      \
  do {                                             \
    auto kinfly_value = (expression);              \
    if (!kinfly_value.ok()) return kinfly_value.status(); \
    target = kinfly_value.value();                 \
  } while (false)

constexpr double kMaxPositionM = 1000.0;
constexpr double kMaxWindMS = 30.0;

StatusOr<MissionCommand> readCommand(const Reader& r, const toml::table& t) {
  MissionCommand c;
  const std::optional<std::string> kind = t["kind"].value<std::string>();
  if (!kind) return r.error(t, "a command needs a kind (arm, disarm, take_off, hold, go_to, "
                               "waypoints, figure_eight, land)");
  c.name = *kind;
  KINFLY_TRY_ASSIGN(c.at_s, r.number(t, "at_s", 0.0, kMaxTimeS));
  static const std::map<std::string, MissionCommand::Kind> simple = {
      {"arm", MissionCommand::Kind::kArm}, {"disarm", MissionCommand::Kind::kDisarm},
      {"hold", MissionCommand::Kind::kHold}, {"land", MissionCommand::Kind::kLand}};
  if (const auto found = simple.find(*kind); found != simple.end()) {
    c.kind = found->second;
    if (Status s = r.onlyKnown(t, {"kind", "at_s"}, *kind); !s.ok()) return s;
  } else if (*kind == "take_off") {
    c.kind = MissionCommand::Kind::kTakeOff;
    if (Status s = r.onlyKnown(t, {"kind", "at_s", "height_m"}, *kind); !s.ok()) return s;
    KINFLY_TRY_ASSIGN(c.height_m, r.number(t, "height_m", 0.2, 50.0));
  } else if (*kind == "go_to") {
    c.kind = MissionCommand::Kind::kGoTo;
    if (Status s = r.onlyKnown(t, {"kind", "at_s", "target_m", "yaw_deg"}, *kind); !s.ok())
      return s;
    KINFLY_TRY_ASSIGN(c.target_world_m, r.vector3(t, "target_m", kMaxPositionM));
    if (t.get("yaw_deg") != nullptr) {
      double yaw_deg = 0.0;
      KINFLY_TRY_ASSIGN(yaw_deg, r.number(t, "yaw_deg", -360.0, 360.0));
      c.yaw_rad = yaw_deg * M_PI / 180.0;
    }
  } else if (*kind == "waypoints") {
    c.kind = MissionCommand::Kind::kWaypoints;
    if (Status s = r.onlyKnown(t, {"kind", "at_s", "waypoints_m", "max_speed_m_s"}, *kind);
        !s.ok())
      return s;
    const toml::array* list = t["waypoints_m"].as_array();
    if (list == nullptr || list->size() < 2 || list->size() > kMaxWaypoints) {
      return r.error(t, "'waypoints_m' must list 2 to " + std::to_string(kMaxWaypoints) +
                            " points [x, y, z]");
    }
    for (const toml::node& point : *list) {
      Eigen::Vector3d p;
      KINFLY_TRY_ASSIGN(p, r.vector3(point, "waypoints_m", kMaxPositionM));
      c.waypoints_world_m.push_back(p);
    }
    KINFLY_TRY_ASSIGN(c.max_speed_m_s, r.number(t, "max_speed_m_s", 0.0, 20.0, 0.0));
  } else if (*kind == "figure_eight") {
    c.kind = MissionCommand::Kind::kWaypoints;
    if (Status s = r.onlyKnown(t, {"kind", "at_s", "centre_m", "size_m", "max_speed_m_s"},
                               *kind);
        !s.ok())
      return s;
    Eigen::Vector3d centre;
    KINFLY_TRY_ASSIGN(centre, r.vector3(t, "centre_m", kMaxPositionM));
    const toml::array* size = t["size_m"].as_array();
    const std::optional<double> sx = size && size->size() == 2 ? (*size)[0].value<double>() : std::nullopt;
    const std::optional<double> sy = size && size->size() == 2 ? (*size)[1].value<double>() : std::nullopt;
    if (!sx || !sy || !(*sx > 0.0 && *sx <= 100.0) || !(*sy > 0.0 && *sy <= 100.0)) {
      return r.error(t.get("size_m") ? *t.get("size_m") : static_cast<const toml::node&>(t),
                     "'size_m' must be [x, y], each in (0, 100] m");
    }
    c.waypoints_world_m = figureEightWaypoints(centre, {*sx, *sy});
    KINFLY_TRY_ASSIGN(c.max_speed_m_s, r.number(t, "max_speed_m_s", 0.0, 20.0, 0.0));
  } else {
    return r.error(t, "unknown command kind '" + *kind + "' (known: arm, disarm, take_off, "
                      "hold, go_to, waypoints, figure_eight, land)");
  }
  return c;
}

// "12.5", not std::to_string's "12.500000".
std::string seconds(double s) {
  std::ostringstream text;
  text << s;
  return text.str();
}

// Every digit a double holds: a bound quoted back is one the reader can type.
std::string exact(double v) {
  char text[32];
  std::snprintf(text, sizeof(text), "%.17g", v);
  return text;
}

StatusOr<MissionEvent> readEvent(const Reader& r, const toml::table& t) {
  MissionEvent e;
  const std::optional<std::string> kind = t["kind"].value<std::string>();
  if (!kind) return r.error(t, "an event needs a kind (wind_step, gust, vision_dropout, "
                               "imu_bias_step, motor_loss, ground_restart, link_loss)");
  e.name = *kind;
  KINFLY_TRY_ASSIGN(e.at_s, r.number(t, "at_s", 0.0, kMaxTimeS));
  if (*kind == "wind_step") {
    e.kind = MissionEvent::Kind::kWindStep;
    if (Status s = r.onlyKnown(t, {"kind", "at_s", "wind_m_s"}, *kind); !s.ok()) return s;
    KINFLY_TRY_ASSIGN(e.vector, r.vector3(t, "wind_m_s", kMaxWindMS));
  } else if (*kind == "gust") {
    e.kind = MissionEvent::Kind::kGust;
    if (Status s = r.onlyKnown(t, {"kind", "at_s", "amplitude_m_s", "duration_s"}, *kind);
        !s.ok())
      return s;
    KINFLY_TRY_ASSIGN(e.vector, r.vector3(t, "amplitude_m_s", kMaxWindMS));
    KINFLY_TRY_ASSIGN(e.duration_s, r.number(t, "duration_s", 0.01, 60.0));
  } else if (*kind == "vision_dropout") {
    e.kind = MissionEvent::Kind::kVisionDropout;
    if (Status s = r.onlyKnown(t, {"kind", "at_s", "duration_s"}, *kind); !s.ok()) return s;
    KINFLY_TRY_ASSIGN(e.duration_s, r.number(t, "duration_s", 0.01, 3600.0));
  } else if (*kind == "imu_bias_step") {
    e.kind = MissionEvent::Kind::kImuBiasStep;
    if (Status s = r.onlyKnown(t, {"kind", "at_s", "gyro_rad_s", "accel_m_s2"}, *kind); !s.ok())
      return s;
    if (t.contains("gyro_rad_s")) KINFLY_TRY_ASSIGN(e.vector, r.vector3(t, "gyro_rad_s", 1.0));
    if (t.contains("accel_m_s2")) KINFLY_TRY_ASSIGN(e.accel_m_s2, r.vector3(t, "accel_m_s2", 5.0));
  } else if (*kind == "motor_loss") {
    e.kind = MissionEvent::Kind::kMotorLoss;
    if (Status s = r.onlyKnown(t, {"kind", "at_s", "rotor", "fraction"}, *kind); !s.ok())
      return s;
    double rotor = 0.0;
    KINFLY_TRY_ASSIGN(rotor, r.number(t, "rotor", 1.0, 4.0));
    if (rotor != std::floor(rotor)) return r.error(*t.get("rotor"), "'rotor' must be 1, 2, 3 or 4");
    e.rotor = static_cast<int>(rotor);
    KINFLY_TRY_ASSIGN(e.fraction, r.number(t, "fraction", 0.0, 1.0));
  } else if (*kind == "ground_restart") {
    // The loader adds the restart, duration_s after this kill.
    e.kind = MissionEvent::Kind::kGroundKilled;
    e.name = "ground_killed";
    if (Status s = r.onlyKnown(t, {"kind", "at_s", "duration_s"}, *kind); !s.ok()) return s;
    KINFLY_TRY_ASSIGN(e.duration_s, r.number(t, "duration_s", 0.01, 3600.0));
  } else if (*kind == "link_loss") {
    // The loader adds its end, duration_s later. The range is scripts/netns.py's LinkShape's.
    e.kind = MissionEvent::Kind::kLinkLossStarted;
    e.name = "link_loss_started";
    if (Status s = r.onlyKnown(t, {"kind", "at_s", "duration_s", "fraction", "loss_run_packets"},
                               *kind);
        !s.ok())
      return s;
    KINFLY_TRY_ASSIGN(e.duration_s, r.number(t, "duration_s", 0.01, 3600.0));
    KINFLY_TRY_ASSIGN(e.fraction, r.number(t, "fraction", 1e-6, 0.9));
    KINFLY_TRY_ASSIGN(e.loss_run_packets,
                      r.number(t, "loss_run_packets", 1.0, 1000.0, 1.0));
    // Independent losses already run 1 / (1 - fraction) on average: shorter would make losses
    // avoid each other (scripts/netns.py, LinkShape).
    const double independent_run = 1.0 / (1.0 - e.fraction);
    if (e.loss_run_packets != 1.0 && e.loss_run_packets < independent_run) {
      return r.error(*t.get("loss_run_packets"),
                     "'loss_run_packets' must be 1 (independent losses) or at least " +
                         exact(independent_run) + " (1 / (1 - fraction))");
    }
  } else {
    return r.error(t, "unknown event kind '" + *kind + "' (known: wind_step, gust, "
                      "vision_dropout, imu_bias_step, motor_loss, ground_restart, "
                      "link_loss)");
  }
  return e;
}

}  // namespace

Mission defaultMission(double takeoff_height_m, double hover_s) {
  // Armed after the estimator's still start (half a second of IMU at rest) and its first poses.
  const double climb_s = 2.0 + 2.0 * takeoff_height_m;  // at ~0.5 m/s, with room
  Mission mission;
  mission.name = "default: take off, hold, land";
  MissionCommand arm;
  arm.at_s = 2.0;
  arm.kind = MissionCommand::Kind::kArm;
  arm.name = "arm";
  MissionCommand take_off;
  take_off.at_s = 3.0;
  take_off.kind = MissionCommand::Kind::kTakeOff;
  take_off.height_m = takeoff_height_m;
  take_off.name = "take_off";
  MissionCommand land;
  land.at_s = take_off.at_s + climb_s + hover_s;
  land.kind = MissionCommand::Kind::kLand;
  land.name = "land";
  mission.commands = {arm, take_off, land};
  mission.max_s = land.at_s + 30.0;
  return mission;
}

std::vector<Eigen::Vector3d> figureEightWaypoints(const Eigen::Vector3d& centre_world_m,
                                                  const Eigen::Vector2d& size_m) {
  constexpr int kPoints = 17;  // 16 segments: a waypoint every eighth of each loop
  std::vector<Eigen::Vector3d> points;
  for (int k = 0; k < kPoints; ++k) {
    const double t = 2.0 * M_PI * k / (kPoints - 1);
    points.push_back(centre_world_m + Eigen::Vector3d(0.5 * size_m.x() * std::sin(t),
                                                      0.5 * size_m.y() * std::sin(2.0 * t), 0.0));
  }
  return points;
}

StatusOr<Mission> parseMission(std::string_view text, const std::string& source) {
  const Reader r(source);
  // Debian builds toml++ with exceptions: a syntax error is thrown, with its place.
  toml::table root;
  try {
    root = toml::parse(text, source);
  } catch (const toml::parse_error& err) {
    return Status::error(source + ":" + std::to_string(err.source().begin.line) + ": " +
                         std::string(err.description()));
  }
  if (Status s = r.onlyKnown(root, {"mission", "command", "event"}, "the file"); !s.ok()) return s;
  Mission mission;
  if (const toml::table* head = root["mission"].as_table()) {
    if (Status s = r.onlyKnown(*head, {"name", "max_s"}, "[mission]"); !s.ok()) return s;
    mission.name = (*head)["name"].value_or(std::string("unnamed"));
    KINFLY_TRY_ASSIGN(mission.max_s, r.number(*head, "max_s", 1.0, kMaxTimeS, 120.0));
  }
  const toml::array* commands = root["command"].as_array();
  if (commands == nullptr || commands->empty()) {
    return r.error("a mission needs at least one [[command]]");
  }
  for (const toml::node& node : *commands) {
    const toml::table* table = node.as_table();
    if (table == nullptr) return r.error(node, "[[command]] must be a table");
    MissionCommand c;
    KINFLY_TRY_ASSIGN(c, readCommand(r, *table));
    if (!mission.commands.empty() && c.at_s < mission.commands.back().at_s) {
      return r.error(node, "commands must be in time order (at_s " + std::to_string(c.at_s) +
                               " after " + std::to_string(mission.commands.back().at_s) + ")");
    }
    mission.commands.push_back(std::move(c));
  }
  if (const toml::array* events = root["event"].as_array()) {
    for (const toml::node& node : *events) {
      const toml::table* table = node.as_table();
      if (table == nullptr) return r.error(node, "[[event]] must be a table");
      MissionEvent e;
      KINFLY_TRY_ASSIGN(e, readEvent(r, *table));
      mission.events.push_back(e);
      const bool restart = e.kind == MissionEvent::Kind::kGroundKilled;
      if (restart || e.kind == MissionEvent::Kind::kLinkLossStarted) {
        const std::string what = restart ? "ground_restart" : "link_loss";
        if (e.at_s + e.duration_s >= mission.max_s) {
          return r.error(node, "the " + what + " at " + seconds(e.at_s) + " s would end after "
                               "the mission's max_s (" + seconds(mission.max_s) + " s)");
        }
        e.kind = restart ? MissionEvent::Kind::kGroundRestarted
                         : MissionEvent::Kind::kLinkLossEnded;
        e.name = restart ? "ground_restarted" : "link_loss_ended";
        e.at_s += e.duration_s;
        mission.events.push_back(std::move(e));
      }
    }
    // At one time, an end before a start, whatever the file's order: a loss from 2 to 4 s and
    // one from 4 s on follow each other (every duration is > 0, so an event's own end is later).
    const auto ends = [](const MissionEvent& e) {
      return e.kind == MissionEvent::Kind::kGroundRestarted ||
             e.kind == MissionEvent::Kind::kLinkLossEnded;
    };
    std::stable_sort(mission.events.begin(), mission.events.end(),
                     [&](const MissionEvent& a, const MissionEvent& b) {
                       if (a.at_s != b.at_s) return a.at_s < b.at_s;
                       return ends(a) && !ends(b);
                     });
    // One station and one link: a kill while it is down would have nothing to kill and its
    // restart would start a second one; two losses at once would be one rule replacing another.
    std::optional<double> down_since_s, lossy_since_s;
    for (const MissionEvent& e : mission.events) {
      using Kind = MissionEvent::Kind;
      if (e.kind == Kind::kGroundKilled && down_since_s) {
        return r.error("the ground_restart at " + seconds(e.at_s) + " s begins while the "
                       "station killed at " + seconds(*down_since_s) + " s is still down");
      }
      if (e.kind == Kind::kLinkLossStarted && lossy_since_s) {
        return r.error("the link_loss at " + seconds(e.at_s) + " s begins while the one from " +
                       seconds(*lossy_since_s) + " s goes on");
      }
      if (e.kind == Kind::kGroundKilled) down_since_s = e.at_s;
      if (e.kind == Kind::kGroundRestarted) down_since_s.reset();
      if (e.kind == Kind::kLinkLossStarted) lossy_since_s = e.at_s;
      if (e.kind == Kind::kLinkLossEnded) lossy_since_s.reset();
    }
  }
  return mission;
}

StatusOr<Mission> loadMission(const std::string& path) {
  std::ifstream in(path);
  if (!in) return Status::error(path + ": cannot be read");
  std::stringstream text;
  text << in.rdbuf();
  return parseMission(text.str(), path);
}

}  // namespace kinfly::sim
