// Mission files: what they say reaches the mission as said, and every mistake is named with its
// file and line; the default mission and the figure eight's waypoints.
#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "kinfly/sim/mission.h"

namespace kinfly::sim {
namespace {

constexpr const char* kTour = R"(# a comment
[mission]
name = "tour"
max_s = 60

[[command]]
at_s = 2.0
kind = "arm"

[[command]]
at_s = 3
kind = "take_off"
height_m = 1.5

[[command]]
at_s = 9
kind = "go_to"
target_m = [1.0, -0.5, -1.5]

[[command]]
at_s = 12
kind = "go_to"
target_m = [1.0, 0.5, -1.5]
yaw_deg = -90

[[command]]
at_s = 15
kind = "figure_eight"
centre_m = [0.0, 0.0, -1.0]
size_m = [2.0, 1.0]
max_speed_m_s = 1.0

[[command]]
at_s = 30
kind = "land"

[[event]]
at_s = 20
kind = "motor_loss"
rotor = 2
fraction = 0.8

[[event]]
at_s = 12
kind = "gust"
amplitude_m_s = [0.0, 1.0, 0.0]
duration_s = 0.5
)";

TEST(Mission, AFileSaysWhatItsMissionDoes) {
  StatusOr<Mission> parsed = parseMission(kTour, "tour.toml");
  ASSERT_TRUE(parsed.ok()) << parsed.status().message();
  const Mission& m = parsed.value();
  EXPECT_EQ(m.name, "tour");
  EXPECT_EQ(m.max_s, 60.0);
  ASSERT_EQ(m.commands.size(), 6u);
  EXPECT_EQ(m.commands[1].kind, MissionCommand::Kind::kTakeOff);
  EXPECT_EQ(m.commands[1].height_m, 1.5);
  EXPECT_EQ(m.commands[2].target_world_m, Eigen::Vector3d(1.0, -0.5, -1.5));
  EXPECT_TRUE(std::isnan(m.commands[2].yaw_rad));  // no heading given: the drone keeps its own
  EXPECT_DOUBLE_EQ(m.commands[3].yaw_rad, -M_PI / 2.0);
  EXPECT_EQ(m.commands[4].kind, MissionCommand::Kind::kWaypoints);
  EXPECT_EQ(m.commands[4].waypoints_world_m.size(), 17u);
  EXPECT_EQ(m.commands[4].max_speed_m_s, 1.0);
  // Events in time order, whatever the file's.
  ASSERT_EQ(m.events.size(), 2u);
  EXPECT_EQ(m.events[0].kind, MissionEvent::Kind::kGust);
  EXPECT_EQ(m.events[1].kind, MissionEvent::Kind::kMotorLoss);
  EXPECT_EQ(m.events[1].rotor, 2);
  EXPECT_EQ(m.events[1].fraction, 0.8);
}

TEST(Mission, AGroundRestartIsAKillAndARestartForTheOrchestrator) {
  StatusOr<Mission> parsed = parseMission(
      "[[command]]\nat_s = 1\nkind = \"arm\"\n"
      "[[event]]\nat_s = 10\nkind = \"ground_restart\"\nduration_s = 4\n"
      "[[event]]\nat_s = 12\nkind = \"gust\"\namplitude_m_s = [1, 0, 0]\nduration_s = 0.5\n"
      "[[event]]\nat_s = 14\nkind = \"ground_restart\"\nduration_s = 0.5\n",
      "m.toml");
  ASSERT_TRUE(parsed.ok()) << parsed.status().message();
  const std::vector<MissionEvent>& e = parsed.value().events;
  ASSERT_EQ(e.size(), 5u);
  EXPECT_EQ(e[0].kind, MissionEvent::Kind::kGroundKilled);
  EXPECT_EQ(e[0].name, "ground_killed");
  EXPECT_EQ(e[0].at_s, 10.0);
  EXPECT_EQ(e[1].kind, MissionEvent::Kind::kGust);
  EXPECT_FALSE(e[1].orchestrated());
  EXPECT_EQ(e[2].kind, MissionEvent::Kind::kGroundRestarted);
  EXPECT_EQ(e[2].name, "ground_restarted");
  EXPECT_EQ(e[2].at_s, 14.0);
  // Killed again as it restarts: the restart first, so the two follow each other.
  EXPECT_EQ(e[3].kind, MissionEvent::Kind::kGroundKilled);
  EXPECT_EQ(e[3].at_s, 14.0);
  EXPECT_EQ(e[4].kind, MissionEvent::Kind::kGroundRestarted);
  EXPECT_EQ(e[4].at_s, 14.5);
  EXPECT_TRUE(e[0].orchestrated() && e[2].orchestrated());
  EXPECT_EQ(parseMission("[[command]]\nat_s = 1\nkind = \"arm\"\n[[event]]\nat_s = 2\n"
                         "kind = \"ground_restart\"\n",
                         "m.toml")
                .status()
                .message(),
            "m.toml:4: 'duration_s' is required here");
  // One station: no kill while it is down, no restart after the mission's end.
  EXPECT_EQ(parseMission("[[command]]\nat_s = 1\nkind = \"arm\"\n"
                         "[[event]]\nat_s = 8\nkind = \"ground_restart\"\nduration_s = 3\n"
                         "[[event]]\nat_s = 9\nkind = \"ground_restart\"\nduration_s = 0.5\n",
                         "m.toml")
                .status()
                .message(),
            "m.toml: the ground_restart at 9 s begins while the station killed at 8 s is still "
            "down");
  EXPECT_EQ(parseMission("[mission]\nmax_s = 20\n[[command]]\nat_s = 1\nkind = \"arm\"\n"
                         "[[event]]\nat_s = 15\nkind = \"ground_restart\"\nduration_s = 5\n",
                         "m.toml")
                .status()
                .message(),
            "m.toml:6: the ground_restart at 15 s would end after the mission's max_s (20 s)");
}

TEST(Mission, ALinkLossStartsAndEndsForTheOrchestrator) {
  StatusOr<Mission> parsed = parseMission(
      "[[command]]\nat_s = 1\nkind = \"arm\"\n"
      "[[event]]\nat_s = 10\nkind = \"link_loss\"\nduration_s = 5\nfraction = 0.2\n"
      "loss_run_packets = 4\n",
      "m.toml");
  ASSERT_TRUE(parsed.ok()) << parsed.status().message();
  const std::vector<MissionEvent>& e = parsed.value().events;
  ASSERT_EQ(e.size(), 2u);
  EXPECT_EQ(e[0].kind, MissionEvent::Kind::kLinkLossStarted);
  EXPECT_EQ(e[0].name, "link_loss_started");
  EXPECT_EQ(e[0].fraction, 0.2);
  EXPECT_EQ(e[0].loss_run_packets, 4.0);
  EXPECT_EQ(e[1].kind, MissionEvent::Kind::kLinkLossEnded);
  EXPECT_EQ(e[1].at_s, 15.0);
  EXPECT_TRUE(e[0].orchestrated() && e[1].orchestrated());
  const auto message = [](const std::string& events) {
    return parseMission("[[command]]\nat_s = 1\nkind = \"arm\"\n" + events, "m.toml")
        .status()
        .message();
  };
  EXPECT_EQ(message("[[event]]\nat_s = 2\nkind = \"link_loss\"\nduration_s = 1\nfraction = 1\n"),
            "m.toml:8: 'fraction' must be a number in [1e-06, 0.9]");
  EXPECT_EQ(message("[[event]]\nat_s = 2\nkind = \"link_loss\"\nduration_s = 5\nfraction = 0.1\n"
                    "[[event]]\nat_s = 4\nkind = \"link_loss\"\nduration_s = 1\nfraction = 0.5\n"),
            "m.toml: the link_loss at 4 s begins while the one from 2 s goes on");
  // Back to back, in either order in the file.
  EXPECT_EQ(message("[[event]]\nat_s = 4\nkind = \"link_loss\"\nduration_s = 1\nfraction = 0.5\n"
                    "[[event]]\nat_s = 2\nkind = \"link_loss\"\nduration_s = 2\nfraction = 0.1\n"),
            "");
  // Runs shorter than independent losses' own (1 / (1 - 0.3)) would make losses avoid each other.
  EXPECT_EQ(message("[[event]]\nat_s = 2\nkind = \"link_loss\"\nduration_s = 1\nfraction = 0.3\n"
                    "loss_run_packets = 1.2\n"),
            "m.toml:9: 'loss_run_packets' must be 1 (independent losses) or at least "
            "1.4285714285714286 (1 / (1 - fraction))");
  EXPECT_EQ(message("[[event]]\nat_s = 2\nkind = \"link_loss\"\nduration_s = 0\nfraction = 0.3\n"),
            "m.toml:7: 'duration_s' must be a number in [0.01, 3600]");
}

TEST(Mission, MistakesAreNamedWithTheirLine) {
  const auto message = [](const std::string& text) {
    return parseMission(text, "m.toml").status().message();
  };
  EXPECT_EQ(message("[[command]]\nat_s = 1\nkind = \"jump\"\n"),
            "m.toml:1: unknown command kind 'jump' (known: arm, disarm, take_off, hold, go_to, "
            "waypoints, figure_eight, land)");
  EXPECT_EQ(message("[[command]]\nat_s = 1\nkind = \"arm\"\nheight_m = 2\n"),
            "m.toml:4: unknown key 'height_m' in arm (known: at_s, kind)");
  EXPECT_EQ(message("[[command]]\nat_s = 1\nkind = \"go_to\"\ntarget_m = [1, 2]\n"),
            "m.toml:4: 'target_m' must be three numbers [x, y, z]");
  EXPECT_EQ(message("[[command]]\nat_s = 1\nkind = \"go_to\"\ntarget_m = [1, 2, 3]\nyaw_deg = 400\n"),
            "m.toml:5: 'yaw_deg' must be a number in [-360, 360]");
  EXPECT_EQ(message("[[command]]\nat_s = -1\nkind = \"arm\"\n"),
            "m.toml:2: 'at_s' must be a number in [0, 86400]");
  EXPECT_EQ(message("[[command]]\nat_s = 5\nkind = \"arm\"\n[[command]]\nat_s = 1\nkind = \"land\"\n"),
            "m.toml:4: commands must be in time order (at_s 1.000000 after 5.000000)");
  EXPECT_EQ(message("[[command]]\nat_s = 1\nkind = \"arm\"\n[[event]]\nat_s = 2\nkind = "
                    "\"motor_loss\"\nrotor = 5\nfraction = 0.5\n"),
            "m.toml:7: 'rotor' must be a number in [1, 4]");
  EXPECT_EQ(message("[mission]\nname = \"x\"\n"), "m.toml: a mission needs at least one [[command]]");
  EXPECT_EQ(message("[[command]\n").rfind("m.toml:1: ", 0), 0u);  // TOML syntax, toml++'s words
  EXPECT_EQ(loadMission("/nonexistent/tour.toml").status().message(),
            "/nonexistent/tour.toml: cannot be read");
}

TEST(Mission, TheDefaultTakesOffHoldsAndLands) {
  const Mission m = defaultMission(1.0, 10.0);
  ASSERT_EQ(m.commands.size(), 3u);
  EXPECT_EQ(m.commands[0].kind, MissionCommand::Kind::kArm);
  EXPECT_EQ(m.commands[1].kind, MissionCommand::Kind::kTakeOff);
  EXPECT_EQ(m.commands[2].kind, MissionCommand::Kind::kLand);
  EXPECT_GT(m.commands[2].at_s, m.commands[1].at_s + 10.0);  // the climb, then the hold
  EXPECT_GT(m.max_s, m.commands[2].at_s);
}

TEST(Mission, AFigureEightSpansItsSizeAndClosesAtItsCentre) {
  const Eigen::Vector3d centre(0.5, -0.5, -1.0);
  const auto points = figureEightWaypoints(centre, {2.0, 1.0});
  EXPECT_LT((points.front() - centre).norm(), 1e-12);
  EXPECT_LT((points.back() - centre).norm(), 1e-12);
  double x_min = 1e9, x_max = -1e9, y_min = 1e9, y_max = -1e9;
  for (const Eigen::Vector3d& p : points) {
    x_min = std::min(x_min, p.x() - centre.x());
    x_max = std::max(x_max, p.x() - centre.x());
    y_min = std::min(y_min, p.y() - centre.y());
    y_max = std::max(y_max, p.y() - centre.y());
    EXPECT_EQ(p.z(), centre.z());
  }
  EXPECT_NEAR(x_max - x_min, 2.0, 1e-12);
  // sin(2t) peaks between the sampled eighths: the waypoints reach 1 m across in y.
  EXPECT_NEAR(y_max - y_min, 1.0, 1e-12);
}

}  // namespace
}  // namespace kinfly::sim
