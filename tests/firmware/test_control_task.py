"""kinfly-fw's control task, the real binary with flight.backend = motors, against a stand-in
simulator (tests/tools/imu_peer.py) in a network namespace: every IMU sample that arrives is one
tick of the flight stack and one motor_command_t back; the odometry's poses reach the stack; a
disarmed drone commands its rotors stopped; when the IMU falls silent the stack goes on ticking
on the clock (so that the IMU-lost failsafe can act in flight); a wrong flight setting refuses
to start, naming the key."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO_ROOT, built
from demo import Watched
from firmware_run import allocations_by_thread, control_summary, firmware

VEHICLE = 9
IMU_PEER = REPO_ROOT / "tests" / "tools" / "imu_peer.py"
IMU_RATE_HZ = 1000.0
IMU_SECONDS = 3.0
# The longest wait for kinfly-fw to start its control task (a loaded machine is slow, never
# this slow).
STARTUP_TIMEOUT_S = 60.0
# UDP on the namespace's loopback drops a datagram only when a receiver's socket buffer is full
# (a process descheduled for a long while on a loaded machine): most must arrive, all need not.
# kinfly-fw's control task, at real-time priority with its 2 MB buffer, lost none of 3001 beside
# two busy loops; the stand-in, a plain Python process, may.
MIN_LOOPBACK_DELIVERY = 0.9
# SCHED_FIFO for the control task (the tests run as root, as the network namespace needs): the
# drone's configuration on a busy computer. Without it, beside two busy loops, LCM's receive
# thread waited so long for a core that up to a tenth of the samples overflowed the socket.
RT_PRIORITY = 10
# The commands test keeps the IMU running while it sends its three commands and waits for each
# answer in the drone's log (then stops it): longer than that takes on a loaded machine.
COMMAND_IMU_SECONDS = 120.0
GROUND = Path(sys.executable).parent / "kinfly-ground"
# A take-off command without its signed_t envelope, as a forger on the Wi-Fi would send it.
UNSIGNED_COMMAND = """
import sys, lcm
from kinfly import flight_command_t
from kinfly_ground._native import Channel, channel_name
m = flight_command_t()
m.vehicle_id, m.kind, m.height_m = int(sys.argv[1]), flight_command_t.TAKE_OFF, 1.0
m.target_world_m = [0.0, 0.0, 0.0]
lcm.LCM().publish(channel_name(Channel.COMMAND, m.vehicle_id), m.encode())
"""
# One land command (refused: disarmed) sent five times, each signed anew as `kinfly-ground
# command` resends an unanswered one: to the drone's Verifier five new messages, to its link one
# command (five: a loaded machine may lose a datagram or two; more than one still arrives).
RESENT_COMMAND = """
import sys, time, lcm
from pathlib import Path
from kinfly_ground._native import Signer, load_key_file
from kinfly_ground.command import build, send
vehicle = int(sys.argv[1])
signer = Signer(load_key_file(Path(sys.argv[2])), vehicle)
lc = lcm.LCM()
for _ in range(5):
    send(lc, signer, build(vehicle, "land", 4242), 1)
    time.sleep(0.1)
"""


def fly_imu(netns: list[str], seconds: float, env: list[str] | None = None,
            ) -> tuple[dict, dict[str, int | str], str]:
    """kinfly-fw on the synthetic source (its poses for the estimator) with the motors backend
    at real-time priority, as on the drone (ENV: `env` arguments before it), the stand-in
    simulator's IMU for SECONDS, then SIGTERM: what the stand-in sent and received, the control
    summary, and kinfly-fw's output."""
    drone = Watched([*netns, *(["env", *env] if env else []),
                     *firmware("--vehicle.id", VEHICLE, "--source.kind", "synthetic",
                               "--flight.backend", "motors", "--flight.rt_priority",
                               RT_PRIORITY, lcm_url=None)])
    try:
        assert drone.wait_for("control: LCM started", 1, STARTUP_TIMEOUT_S), drone.output()
        peer = subprocess.run([*netns, sys.executable, str(IMU_PEER), "--vehicle", str(VEHICLE),
                               "--seconds", str(seconds), "--rate-hz", str(IMU_RATE_HZ)],
                              capture_output=True, text=True, timeout=60)
        assert peer.returncode == 0, peer.stderr
        # The stand-in listened 0.3 s after its last sample: the drone's silent ticks began.
        drone.process.terminate()
        rc = drone.finish(30)
    finally:
        drone.process.kill()
    assert rc == 0, drone.output()
    assert f"SCHED_FIFO priority {RT_PRIORITY}" in drone.output(), drone.output()
    return json.loads(peer.stdout), control_summary(drone.output()), drone.output()


def test_each_imu_sample_is_one_tick_and_one_rotor_command(netns: list[str]) -> None:
    sent, control, _ = fly_imu(netns, IMU_SECONDS)
    # What arrived is what was sent, but for loopback's rare drops; each is one tick.
    assert MIN_LOOPBACK_DELIVERY * sent["sent"] <= control["imu_samples"] <= sent["sent"]
    assert control["imu_rejected"] == 0
    assert control["ticks"] - control["silent_ticks"] == control["imu_samples"]
    assert control["silent_ticks"] > 0
    # Every tick commands the rotors, and a disarmed drone commands them stopped.
    assert control["sent"] == control["ticks"] and control["unsent"] == 0
    assert MIN_LOOPBACK_DELIVERY * control["imu_samples"] <= sent["received"] <= control["sent"]
    assert set(sent["states"]) == {"0"} and sent["max_speed_rad_s"] == 0.0
    # The odometry's poses reached the stack, which started its estimator on them.
    assert control["estimator"] == "started"
    assert control["poses_fused"] + control["poses_rejected"] > 0
    assert control["mode"] == "disarmed" and control["mode_changes"] == 0
    assert control["imu_lost"] == 0  # a failsafe of flight, not of a drone on the ground


def test_the_control_task_allocates_at_start_only(netns: list[str], tmp_path: Path) -> None:
    """Every malloc counted by thread (tests/tools/alloc_counter.c): 1 s and 3 s of IMU at
    1 kHz give kfw-control the same count."""
    counter = built("tests/libkinfly_alloc_counter.so")
    counts = []
    for seconds in (1.0, IMU_SECONDS):
        report = tmp_path / f"alloc_{seconds}.txt"
        sent, control, _ = fly_imu(netns, seconds, env=[f"LD_PRELOAD={counter}",
                                                        f"KINFLY_ALLOC_REPORT={report}"])
        assert control["imu_samples"] >= MIN_LOOPBACK_DELIVERY * sent["sent"]
        counts.append(allocations_by_thread(report))
    short, long = counts
    assert "kfw-control" in short, short
    assert long["kfw-control"] == short["kfw-control"], (short, long)
    print(f"kfw-control allocations: {short['kfw-control']} after 1 s, {long['kfw-control']} "
          f"after {IMU_SECONDS:g} s of IMU")


def test_signed_commands_reach_the_flight_modes_and_unsigned_ones_do_not(
        netns: list[str], tmp_path: Path) -> None:
    """`kinfly-ground command` signs with the vehicle's key; the drone's link verifies and hands
    the command to the control task, whose flight modes answer it, and the answer comes back in
    the drone's flight status, which `kinfly-ground command` waits for: a disarm of a disarmed
    drone is accepted (nothing to do, exit 0), a take-off is refused (disarmed: arm first;
    exit 1). The disarm is first sent before the drone listens, as lost as on a Wi-Fi that took
    every copy: unanswered, it is sent again until the drone answers. A command sent again is
    acted on once. The same command unsigned is rejected by the link and never reaches the
    modes."""
    key = tmp_path / "v.key"
    subprocess.run([built("bin/kinfly-keygen"), "--out", key], check=True, capture_output=True)

    def command(*args: object) -> list[str]:
        """kinfly-ground command, waiting for the drone's answer (its flight status)."""
        return [*netns, str(GROUND), "command", *map(str, args), "--vehicle", str(VEHICLE),
                "--key", str(key), "--wait", str(STARTUP_TIMEOUT_S)]

    disarm = Watched(command("disarm"))
    drone = imu = None
    try:
        assert disarm.wait_for("(disarm) sent to vehicle", 1, STARTUP_TIMEOUT_S), \
            disarm.output()
        drone = Watched([*netns, *firmware("--vehicle.id", VEHICLE, "--source.kind",
                                           "synthetic", "--flight.backend", "motors",
                                           "--flight.rt_priority", RT_PRIORITY,
                                           key_file=str(key), lcm_url=None)])
        assert drone.wait_for("control: LCM started", 1, STARTUP_TIMEOUT_S), drone.output()
        # The control task takes commands on its ticks: the IMU runs throughout.
        imu = subprocess.Popen([*netns, sys.executable, str(IMU_PEER), "--vehicle",
                                str(VEHICLE), "--seconds", str(COMMAND_IMU_SECONDS)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert disarm.finish(2 * STARTUP_TIMEOUT_S) == 0, disarm.output()
        assert f"(disarm) accepted; vehicle {VEHICLE} is in disarmed (sent " in disarm.output()
        assert drone.wait_for("(disarm) accepted", 1, STARTUP_TIMEOUT_S), drone.output()
        take_off = subprocess.run(command("takeoff", 1.0), capture_output=True, text=True,
                                  timeout=2 * STARTUP_TIMEOUT_S)
        assert take_off.returncode == 1, take_off.stderr
        assert "(takeoff) refused: disarmed" in take_off.stderr, take_off.stderr
        assert drone.wait_for("(take-off) refused: disarmed", 1, STARTUP_TIMEOUT_S), \
            drone.output()
        resent = subprocess.run([*netns, sys.executable, "-c", RESENT_COMMAND, str(VEHICLE),
                                 str(key)], capture_output=True, text=True, timeout=60)
        assert resent.returncode == 0, resent.stderr
        assert drone.wait_for("command 4242 (land) refused: disarmed", 1, STARTUP_TIMEOUT_S), \
            drone.output()
        unsigned = subprocess.run(
            [*netns, sys.executable, "-c", UNSIGNED_COMMAND, str(VEHICLE)], capture_output=True,
            text=True, timeout=60)
        assert unsigned.returncode == 0, unsigned.stderr
        assert drone.wait_for("link: command rejected", 1, STARTUP_TIMEOUT_S), drone.output()
        imu.terminate()
        imu.wait(30)
        drone.process.terminate()
        rc = drone.finish(30)
    finally:
        disarm.process.kill()
        for process in (drone.process if drone else None, imu):
            if process is not None:
                process.kill()
    assert rc == 0, drone.output()
    control = control_summary(drone.output())
    # Each command once, however often it came: the land's later signings, and the resends of
    # the others that crossed their answer on a loaded machine, are repeats.
    assert control["passed"] == 3 and control["dropped"] == 0, control
    assert control["repeated"] >= 1, control
    assert control["commands_accepted"] == 1 and control["commands_refused"] == 2, control
    assert control["mode"] == "disarmed"


@pytest.mark.parametrize("args,message", [
    (["--flight.backend", "rotors"],
     'flight.backend must be none, motors or mavlink (got "rotors")'),
    (["--flight.attitude_law", "pid"], 'flight.attitude_law must be geometric or lqr (got "pid")'),
    (["--flight.rate_hz", "50"], "flight.rate_hz must be in [100, 4000] (got 50)"),
    (["--flight.rate_hz", "200", "--flight.position_rate_hz", "250"],
     "flight.position_rate_hz (250.000000) must not exceed flight.rate_hz (200.000000)"),
    (["--flight.mass_kg", "0"], "flight.mass_kg must be in (0, 50] (got 0)"),
    (["--flight.rt_priority", "120"], "flight.rt_priority must be in [0, 99] (got 120)"),
    (["--flight.lockstep_pose_age_s", "0.063"],
     "flight.lockstep_pose_age_s needs flight.lockstep = true"),
    (["--flight.lockstep", "true", "--flight.lockstep_pose_age_s", "0.15"],
     "flight.lockstep_pose_age_s must be in [0, 0.1] (got 0.15)"),
])
def test_a_wrong_flight_setting_refuses_to_start(args: list[str], message: str) -> None:
    run = subprocess.run(firmware("--source.kind", "synthetic", *args), capture_output=True,
                         text=True, timeout=60)
    assert run.returncode == 2, run.stderr
    assert message in run.stderr, run.stderr
