"""`kinfly-ground command`'s pieces: the mission file's reading, with errors that name the file
and line; the flight_command_t it builds; and the command line's refusals (exit 2, naming the
value). The signed path through the real drone: tests/firmware/test_control_task.py."""
from __future__ import annotations

from pathlib import Path

import pytest

from kinfly import flight_command_t
from kinfly_ground.cli import main
from kinfly_ground.command import CommandError, build, read_waypoints


def test_a_mission_file_reads_its_waypoints(tmp_path: Path) -> None:
    path = tmp_path / "square.txt"
    path.write_text("# a square 1 m up\n0 0 -1\n1 0 -1  # east\n\n1 1 -1\n")
    assert read_waypoints(path) == [(0.0, 0.0, -1.0), (1.0, 0.0, -1.0), (1.0, 1.0, -1.0)]


@pytest.mark.parametrize("text,message", [
    ("0 0 -1\n1 0\n", "square.txt:2: want three numbers x y z, got '1 0'"),
    ("0 0 -1\nup 0 -1\n", "square.txt:2: want three numbers x y z, got 'up 0 -1'"),
    ("0 0 -1\n", "a mission needs 2 to 100 waypoints (got 1)"),
])
def test_a_bad_mission_file_is_named(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "square.txt"
    path.write_text(text)
    with pytest.raises(CommandError, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_waypoints(path)


def test_the_command_carries_what_was_asked() -> None:
    m = build(5, "mission", 17, waypoints=[(0, 0, -1), (2, 0, -1)], max_speed_m_s=0.5)
    decoded = flight_command_t.decode(m.encode())
    assert (decoded.vehicle_id, decoded.command_id, decoded.kind) == (5, 17,
                                                                      flight_command_t.MISSION)
    assert decoded.waypoint_count == 2
    assert list(decoded.waypoints_world_m[1]) == [2.0, 0.0, -1.0]
    assert decoded.max_speed_m_s == 0.5
    goto = flight_command_t.decode(build(5, "goto", 18, target=(1.0, 2.0, -3.0)).encode())
    assert list(goto.target_world_m) == [1.0, 2.0, -3.0] and goto.waypoint_count == 0
    assert not goto.has_yaw  # the drone keeps its heading
    turn = flight_command_t.decode(build(5, "goto", 19, target=(1.0, 2.0, -3.0),
                                         yaw_rad=-1.5).encode())
    assert turn.has_yaw and turn.yaw_rad == -1.5


@pytest.mark.parametrize("action,options,message", [
    (["takeoff"], [], "takeoff takes 1 value(s) (got 0)"),
    (["goto", "1", "2", "x"], [], "goto: not a number in 1 2 x"),
    (["arm"], ["--copies", "0"], "--copies 0 outside [1, 100]"),
    (["arm"], ["--vehicle", "70000"], "--vehicle 70000 outside [0, 65535]"),
    (["goto", "1", "2", "-1"], ["--yaw", "400"], "--yaw 400: for goto only, in [-360, 360]"),
    (["land"], ["--yaw", "90"], "--yaw 90: for goto only, in [-360, 360]"),
])
def test_a_wrong_command_line_exits_2_naming_it(action: list[str], options: list[str],
                                                message: str,
                                                capsys: pytest.CaptureFixture[str],
                                                tmp_path: Path) -> None:
    key = tmp_path / "v.key"
    key.write_bytes(bytes(32))
    key.chmod(0o600)
    assert main(["command", *action, "--vehicle", "1", "--key", str(key), *options]) == 2
    assert message in capsys.readouterr().err
