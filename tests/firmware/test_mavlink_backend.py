"""kinfly-fw's mavlink backend, the real binary, against a stand-in PX4 autopilot made with
pymavlink (tests/tools/autopilot_peer.py) in a network namespace: the autopilot's IMU clocks the
control task, kinfly's vision pose goes to the autopilot as ODOMETRY, an arm command from the
ground starts the offboard handshake (setpoints streamed first, then offboard, then arming), a
take-off streams body-rate and thrust setpoints at 100 Hz or more, a pilot's mode switch hands
over for good (offboard is never asked for again), every frame is signed with the MAVLink key, a
wrongly signed autopilot is never heard nor answered, an autopilot that disappears is a
failsafe, and one on a serial port that is pulled out is opened again."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from conftest import REPO_ROOT, built
from demo import Watched
from firmware_run import control_summary, firmware, mavlink_summary

VEHICLE = 9
PEER = REPO_ROOT / "tests" / "tools" / "autopilot_peer.py"
SERIAL_BRIDGE = REPO_ROOT / "tests" / "tools" / "serial_bridge.py"
GROUND = Path(sys.executable).parent / "kinfly-ground"
PORT = 14540
IMU_RATE_HZ = 250.0
# The longest any step may take on a loaded machine (each waits on what it needs, never on time).
STEP_TIMEOUT_S = 60.0
# The estimator starts after a still second of IMU and a pose; arming is refused until then and
# is asked again (take-off too, for a pose fresh enough), at most this many times, each after the
# drone's answer.
ARM_ATTEMPTS = 30
# The stand-in runs at real-time priority, as the autopilot it stands for (a microcontroller) is
# never descheduled: beside two busy loops a plain Python process paused its IMU for longer than
# kinfly's IMU-lost failsafe allows (the tests run as root, as the network namespace needs).
AUTOPILOT_PRIORITY = ["chrt", "-f", "5"]
# MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD; MAV_ESTIMATOR_TYPE_VISION; ATTITUDE_IGNORE
ODOMETRY_FRAMES = [20, 12]
ESTIMATOR_TYPE_VISION = 2
ATTITUDE_IGNORE = 128
# The floor for the setpoint stream; kinfly-fw sends up to flight.mavlink_setpoint_hz (200).
MIN_SETPOINT_RATE_HZ = 100.0
# kinfly-fw's prestream before asking for offboard (AutopilotParams::prestream_s), less the
# scheduling slack of two processes on a busy machine.
MIN_PRESTREAM_S = 0.4
# At rest: the drone's vision pose stays at the origin within the synthetic depth's noise.
MAX_POSE_DISTANCE_M = 0.05
# The estimate's tilt against the autopilot's own, both of a body at rest and level.
MAX_TILT_DEG = 1.0


def keygen(path: Path) -> Path:
    subprocess.run([built("bin/kinfly-keygen"), "--out", path], check=True, capture_output=True)
    return path


def drone_command(netns: list[str], key: Path, url: str = f"udpin:127.0.0.1:{PORT}") -> list[str]:
    """kinfly-fw with the mavlink backend at real-time priority, on the synthetic camera at rest
    at QVGA and 15 Hz: the synthetic source stamps its frames on its schedule, so when it renders
    slower than that it drops frames, as a camera on a late host does; and the odometry takes
    the newest frame (capture_queue 1), as a drone that flies on its poses should: beside two
    busy loops a queue of 4 held the poses 0.27 s behind, older than arming allows (vision_fresh_s, 0.2 s). With
    VGA, 30 Hz or the longer queue, arming was refused throughout in some of those runs."""
    return [*netns, *firmware("--vehicle.id", VEHICLE, "--source.kind", "synthetic",
                              "--source.motion", "still", "--source.width", 320,
                              "--source.height", 240, "--source.rate_hz", 15,
                              "--odometry.capture_queue", 1,
                              "--flight.backend", "mavlink",
                              "--flight.imu", "mavlink", "--flight.rate_hz", IMU_RATE_HZ,
                              "--flight.mavlink_url", url,
                              "--flight.mavlink_key", key, "--flight.rt_priority", 10,
                              key_file=str(key), lcm_url=None)]


def ground_command(netns: list[str], key: Path, *args: object) -> subprocess.CompletedProcess:
    """`kinfly-ground command`, which waits for the drone's answer (exit 0: accepted)."""
    return subprocess.run([*netns, str(GROUND), "command", *map(str, args), "--vehicle",
                           str(VEHICLE), "--key", str(key), "--wait", str(STEP_TIMEOUT_S)],
                          capture_output=True, text=True, timeout=2 * STEP_TIMEOUT_S)


def until_accepted(netns: list[str], key: Path, drone: Watched, *command: object) -> str:
    """Asks until the drone's answer is yes, and returns the answer. The estimator needs its
    still start before arming, and a pose fused within vision_fresh_s (0.2 s) for arming and
    take-off, which a loaded machine's odometry misses now and then: the refusal says so, and
    the command is asked again, as a pilot would."""
    for _ in range(ARM_ATTEMPTS):
        answered = ground_command(netns, key, *command)
        if answered.returncode == 0:
            return answered.stderr
        assert f"({command[0]}) refused: " in answered.stderr, answered.stderr + drone.output()
    # Stopped, it prints its summaries: what became of the poses says why. They come first, as
    # a long log is cut in the middle where it is shown.
    output = stop(drone)
    summaries = [line for line in output.splitlines() if line.startswith("kinfly-fw: ")]
    raise AssertionError(f"{command[0]} refused {ARM_ATTEMPTS} times; " + "\n".join(summaries)
                         + f"\nthe whole log:\n{output}")


@contextmanager
def drone_and_autopilot(netns: list[str], key: Path,
                        autopilot_key: Path) -> Iterator[tuple[Watched, Watched]]:
    """kinfly-fw signing with KEY and, once its autopilot link is open, the stand-in autopilot
    signing with AUTOPILOT_KEY; both are killed afterwards, whatever happened."""
    drone = Watched(drone_command(netns, key))
    peer = None
    try:
        assert drone.wait_for("control: autopilot link on", 1, STEP_TIMEOUT_S), drone.output()
        peer = Watched([*netns, *AUTOPILOT_PRIORITY, sys.executable, str(PEER), "--url",
                        f"udpout:127.0.0.1:{PORT}", "--key", str(autopilot_key)])
        yield drone, peer
    finally:
        drone.process.kill()
        if peer is not None:
            peer.process.kill()


def stop(process: Watched) -> str:
    """SIGTERM, and its output once it exited 0."""
    process.process.terminate()
    assert process.finish(STEP_TIMEOUT_S) == 0, process.output()
    return process.output()


def report(peer_output: str) -> dict:
    """The stand-in's JSON report, its last line."""
    return json.loads(peer_output.strip().splitlines()[-1])


def test_offboard_handshake_setpoints_and_the_autopilot_lost(netns: list[str],
                                                             tmp_path: Path) -> None:
    key = keygen(tmp_path / "vehicle.key")  # the uplink's and the MAVLink link's, for brevity
    with drone_and_autopilot(netns, key, key) as (drone, peer):
        assert drone.wait_for("mavlink: heard PX4", 1, STEP_TIMEOUT_S), drone.output()
        assert "(arm) accepted" in until_accepted(netns, key, drone, "arm")
        # Armed, kinfly streams idle setpoints; the autopilot goes offboard, then arms.
        assert peer.wait_for("peer: armed", 1, STEP_TIMEOUT_S), peer.output() + drone.output()
        assert drone.wait_for("mavlink: autopilot armed", 1, STEP_TIMEOUT_S), drone.output()
        take_off = until_accepted(netns, key, drone, "takeoff", 1.0)
        assert "(takeoff) accepted; vehicle 9 is in take off" in take_off, take_off
        # The stand-in does not fly: the climb's thrust grows while its IMU stays at rest.
        assert peer.wait_for("peer: climb thrust", 3, STEP_TIMEOUT_S), peer.output()
        # The pilot switches to position mode: kinfly hands over and never asks for offboard
        # or arming again (its heartbeat goes on).
        peer.process.send_signal(signal.SIGUSR1)
        assert drone.wait_for("the autopilot took over: take-off -> handed over", 1,
                              STEP_TIMEOUT_S), drone.output()
        assert peer.wait_for("peer: companion heartbeat after the takeover", 1, STEP_TIMEOUT_S), \
            peer.output()
        # The autopilot disappears: its IMU stops at once, its heartbeat too.
        got = report(stop(peer))
        assert drone.wait_for("failsafe: autopilot lost", 1, STEP_TIMEOUT_S), drone.output()
        output = stop(drone)
    control = control_summary(output)
    link = mavlink_summary(output)
    print(next(line for line in output.splitlines() if line.startswith("kinfly-fw: mavlink:")))
    print(f"setpoints at the stand-in: {got['setpoints']} at {got['setpoint_rate_hz']:.0f} Hz, "
          f"{got['climb_setpoints']} of the climb at {got['climb_rate_hz']:.0f} Hz, offboard "
          f"{got['offboard_at_s'] - got['first_setpoint_at_s']:.2f} s after the first")

    # Signed both ways with the key: nothing unsigned or wrongly signed on either side.
    assert got["signing"]["good"] > 0 and got["signing"]["bad"] == 0
    assert got["signing"]["unsigned"] == 0 and got["signing"]["rejected"] == 0
    assert link["bad_signature"] == 0 and link["heartbeats"] > 0
    # kinfly asked for the IMU at its control rate and the attitude; the IMU clocked its ticks.
    assert got["stream_requests"]["105"] == pytest.approx(1e6 / IMU_RATE_HZ)
    assert "31" in got["stream_requests"]
    assert control["imu_samples"] == link["imu_samples"] > 0 and control["imu_rejected"] == 0
    # The pressure altitude the IMU messages carried reached the estimator and was fused.
    assert control["baro_fused"] > 0 and control["baro_rejected"] == 0, control
    assert link["max_tilt_deg"] <= MAX_TILT_DEG
    # The handshake in PX4's order: setpoints streamed, then offboard, then arming.
    assert got["offboard_at_s"] - got["first_setpoint_at_s"] >= MIN_PRESTREAM_S, got
    assert got["setpoints_before_offboard"] > 0 and got["armed_at_s"] >= got["offboard_at_s"]
    assert link["mode_requests"] >= 1 and link["arm_requests"] >= 1
    assert link["accepted"] >= 2  # the mode and the arming (and the stream requests)
    # Body rates and thrust to the autopilot's ids, at the rate or more.
    assert got["type_masks"] == [ATTITUDE_IGNORE] and got["setpoint_targets"] == [[1, 1]]
    assert got["setpoint_rate_hz"] >= MIN_SETPOINT_RATE_HZ, got["setpoint_rate_hz"]
    assert got["climb_setpoints"] > 0 and got["climb_rate_hz"] >= MIN_SETPOINT_RATE_HZ, got
    assert got["mode_requests_after_takeover"] == 0 and got["arm_requests_after_takeover"] == 0
    assert got["max_thrust"] > 0.0
    # Sent is what arrived, and the few sent after the stand-in stopped reading.
    assert got["setpoints"] <= link["setpoints"]
    # The vision pose went to the autopilot's EKF in local FRD, at rest near the origin.
    assert got["odometry"] > 0 and got["odometry_frames"] == [ODOMETRY_FRAMES]
    assert got["odometry_estimator_types"] == [ESTIMATOR_TYPE_VISION]
    assert got["odometry_max_distance_m"] <= MAX_POSE_DISTANCE_M
    assert got["reset_counters"] == [0]
    # Handed over by the pilot, then gone: its loss is counted.
    assert link["lost"] == 1 and control["mode"] == "handed over"
    assert control["commands_accepted"] == 2  # arm, take-off


def test_a_wrongly_signed_autopilot_is_never_heard(netns: list[str], tmp_path: Path) -> None:
    key = keygen(tmp_path / "vehicle.key")
    with drone_and_autopilot(netns, key, keygen(tmp_path / "other.key")) as (drone, peer):
        assert drone.wait_for("mavlink: dropped a frame unsigned or signed with another key", 1,
                              STEP_TIMEOUT_S), drone.output()
        refused = ground_command(netns, key, "arm")
        assert refused.returncode == 1, refused.stderr
        assert "(arm) refused: no autopilot" in refused.stderr, refused.stderr
        got = report(stop(peer))
        output = stop(drone)
    link = mavlink_summary(output)
    assert link["bad_signature"] > 0 and link["heartbeats"] == 0 and link["imu_samples"] == 0
    assert "mavlink: heard" not in output
    # Nor does kinfly answer it: a sender it has not verified never becomes its peer.
    assert got["companion_heartbeats"] == 0 and got["signing"]["good"] == 0


def test_a_serial_autopilot_unplugged_and_plugged_back_is_heard_again(netns: list[str],
                                                                      tmp_path: Path) -> None:
    """The autopilot on a serial port (a pseudo-terminal bridged to the stand-in), named by a
    fixed path as udev names a USB adapter: pulled out, kinfly-fw's reads fail, it counts the
    error, the autopilot is lost (the failsafe), and the port is opened again by its path until
    the adapter is back; then the autopilot is heard again."""
    key = keygen(tmp_path / "vehicle.key")
    link = tmp_path / "ttyAutopilot"
    bridge = Watched([*netns, sys.executable, str(SERIAL_BRIDGE), "--link", str(link), "--udp",
                      f"127.0.0.1:{PORT}"])
    peer = drone = None
    try:
        assert bridge.wait_for("bridge: plugged", 1, STEP_TIMEOUT_S), bridge.output()
        peer = Watched([*netns, *AUTOPILOT_PRIORITY, sys.executable, str(PEER), "--url",
                        f"udpin:127.0.0.1:{PORT}", "--key", str(key)])
        drone = Watched(drone_command(netns, key, url=str(link)))
        assert drone.wait_for("mavlink: PX4 alive", 1, STEP_TIMEOUT_S), drone.output()
        bridge.process.send_signal(signal.SIGUSR1)
        assert drone.wait_for("the autopilot link is down", 1, STEP_TIMEOUT_S), drone.output()
        assert drone.wait_for("failsafe: autopilot lost", 1, STEP_TIMEOUT_S), drone.output()
        bridge.process.send_signal(signal.SIGUSR2)
        assert bridge.wait_for("bridge: plugged", 2, STEP_TIMEOUT_S), bridge.output()
        assert drone.wait_for(f"mavlink: {link} open", 2, STEP_TIMEOUT_S), drone.output()
        assert drone.wait_for("mavlink: PX4 alive", 2, STEP_TIMEOUT_S), drone.output()
        output = stop(drone)
    finally:
        for process in (drone, peer, bridge):
            if process is not None:
                process.process.kill()
    link_summary = mavlink_summary(output)
    assert link_summary["port_errors"] == 1 and link_summary["lost"] == 1
    assert link_summary["bad_signature"] == 0 and link_summary["imu_samples"] > 0


@pytest.mark.parametrize("args,message", [
    (["--flight.backend", "mavlink"],
     'flight.imu = mavlink goes with flight.backend = mavlink (got imu "lcm", backend "mavlink")'),
    (["--flight.backend", "mavlink", "--flight.imu", "mavlink", "--flight.mavlink_url",
      "tcp:1.2.3.4:5760"], 'flight.mavlink_url: MAVLink URL "tcp:1.2.3.4:5760": unknown form'),
    (["--flight.backend", "mavlink", "--flight.imu", "mavlink", "--flight.mavlink_url",
      "udpin:0.0.0.0:99999"], "port must be 1 to 65535"),
    (["--flight.backend", "mavlink", "--flight.imu", "mavlink", "--flight.mavlink_setpoint_hz",
      "50"], "flight.mavlink_setpoint_hz must be in [100"),
    (["--flight.backend", "mavlink", "--flight.imu", "mavlink", "--flight.mavlink_key",
      "/nonexistent.key"], "/nonexistent.key"),
])
def test_a_wrong_mavlink_setting_refuses_to_start(args: list[str], message: str) -> None:
    run = subprocess.run(firmware("--source.kind", "synthetic", *args), capture_output=True,
                         text=True, timeout=60)
    assert run.returncode == 2, run.stderr
    assert message in run.stderr, run.stderr
