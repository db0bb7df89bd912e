"""kinfly-fw, the real binary: a replayed flight log gives exactly the onboard trajectory of the
offline engine, a synthetic flight follows its ground truth; configuration errors and unsafe key
files refuse to start with a message naming the value; SIGTERM stops it within a second with a
summary. Faults in flight: test_firmware_faults.py."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO_ROOT, built, wait_for_line
import demo  # scripts/demo.py (conftest puts scripts/ on the path)
from demo import Watched
from firmware_run import CONFIG, firmware, read_tum, summary

# Same engine, same parameters, same frames in the same order: only float summation order could
# differ, and it does not (the engine's reductions are fixed-order), so agreement is to rounding.
SAME_ENGINE_TOLERANCE_M = 1e-6
# The synthetic flight against its own ground truth: a 3 cm voxel volume and one full swing of
# the flight; drift well under a voxel.
SYNTHETIC_MAX_ERROR_M = 0.02
# A lockstep replay that hears no ground station waits this long for each keyframe: short, so
# that the 9 keyframes of the sample cost under 2 s.
NO_GROUND_WAIT_S = 0.2
# The longest wait for kinfly-fw to start flying (a loaded machine is slow, never this slow).
STARTUP_TIMEOUT_S = 60.0


def test_log_replay_matches_the_offline_engine(sample_log: Path, sample_dir: Path,
                                               tmp_path: Path) -> None:
    trajectory = tmp_path / "fw.tum"
    run = subprocess.run(firmware("--source.path", sample_log, "--source.realtime", "false",
                                  "--output.trajectory", trajectory),
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "60 frames captured, 60 processed (0 lost," in run.stdout, run.stdout
    subprocess.run([built("bin/kinfly-fuse"), "--tum", sample_dir, "--out", tmp_path / "fuse",
                    "--downsample", "2", "--volume", "dense", "--threads", "1",
                    "--icp-fine-iterations", "2", "--model-level", "1"],
                   check=True, capture_output=True, timeout=120)
    fw, fuse = read_tum(trajectory), read_tum(tmp_path / "fuse" / "trajectory.tum")
    assert fw.shape == fuse.shape
    assert np.abs(fw[:, 0] - fuse[:, 0]).max() < 1e-6  # same capture times
    assert np.abs(fw[:, 1:4] - fuse[:, 1:4]).max() < SAME_ENGINE_TOLERANCE_M


def test_dataset_replay_matches_the_log_replay(sample_log: Path, sample_dir: Path,
                                               tmp_path: Path) -> None:
    """The TUM folder read directly and the same frames through a flight log: one flight."""
    trajectories = []
    for kind, path in (("log", sample_log), ("dataset", sample_dir)):
        out = tmp_path / f"{kind}.tum"
        run = subprocess.run(firmware("--source.kind", kind, "--source.path", path,
                                      "--source.realtime", "false", "--output.trajectory", out),
                             capture_output=True, text=True, timeout=120)
        assert run.returncode == 0, run.stderr
        trajectories.append(read_tum(out))
    log, dataset = trajectories
    assert log.shape == dataset.shape == (60, 8)
    assert np.abs(log - dataset).max() < SAME_ENGINE_TOLERANCE_M


@pytest.mark.parametrize("args,message", [
    (["--vehicle.id", "70000"], "vehicle.id must be in [0, 65535]"),
    (["--odometry.downsample", "3"], "odometry.downsample must be 1, 2 or 4"),
    (["--keyframe.min_interval_s", "5"], "keyframe.min_interval_s"),
    (["--keyframe.min_covisibility", "1"], "keyframe.min_covisibility must be in [0, 1)"),
    (["--odometry.model_level", "2"], "odometry.model_level must be in [0, 1]"),
    (["--source.kind", "camera"], "source.kind must be log, dataset, openni, synthetic or lcm"),
    (["--link.status_rate_hz", "0"], "link.status_rate_hz"),
    (["--output.log_level", "loud"], "output.log_level"),
    (["--source.speed", "0"], "source.speed must be in (0, 100]"),
    (["--source.loop", "sideways"], 'source.loop must be none or bounce (got "sideways")'),
    (["--source.laps", "3"],
     "source.laps needs source.loop = bounce (got laps = 3 with loop = none)"),
    (["--source.loop", "bounce", "--source.laps", "-1"], "source.laps must be in [0, "),
    (["--source.stall_timeout_s", "0"], "source.stall_timeout_s must be in (0, 60]"),
    (["--source.reconnect_min_s", "2", "--source.reconnect_max_s", "1"],
     "source.reconnect_max_s must be in [2, 600]"),
    (["--source.kind", "synthetic", "--source.width", "8"], "source.width must be in [16, 4096]"),
    (["--odometry.volume_vox", "100"], "odometry.volume_vox must be a multiple of 8"),
    (["--odometry.voxel_m", "0.5"], "odometry.voxel_m must be in (0, 0.2]"),
    (["--link.signing_window_s", "0"], "link.signing_window_s must be in (0, 3600]"),
    (["--source.depth_scale_m", "0"], "source.depth_scale_m must be in [1e-06, 1]"),
    (["--source.depth_units_per_m", "0"], "source.depth_units_per_m must be in (0, 1e+06]"),
    # A URL no network can mend is a configuration error (a missing route is not: the drone waits).
    (["--link.lcm_url", "udpm://10.1.2.3:7667"],
     'link.lcm_url "udpm://10.1.2.3:7667": 10.1.2.3 is not a multicast group'),
    (["--link.lcm_url", "udpm://239.255.76.67:0"], "the port must be in [1, 65535]"),
    (["--link.lcm_url", "udpm://drone.local:7667"], '"drone.local" is not an IPv4 address'),
    (["--link.peers", "ground"], 'link.peers: peer "ground" is not ADDRESS:PORT'),
    (["--link.peers", "10.0.0.2:7668,ground:0"],
     'link.peers: peer "ground:0": the port must be a number in [1, 65535]'),
    (["--link.peer_port", "0"], "link.peer_port must be in [1, 65535]"),
    (["--link.peers", "ground.local:7668"],
     'link.peers: peer "ground.local:7668": "ground.local" is not an IPv4 address'),
    # Unicast beside multicast that leaves the drone would send everything twice.
    (["--link.peers", "10.0.0.2:7668", "--link.lcm_url", "udpm://239.255.76.67:7667?ttl=1"],
     "sends multicast off the drone (ttl=1); with link.peers it must stay on it"),
    # Frames paced to their capture times cannot wait for the ground.
    (["--source.lockstep", "true"], "source.lockstep needs source.realtime = false"),
])
def test_bad_configuration_refuses_to_start(sample_log: Path, args: list[str],
                                            message: str) -> None:
    run = subprocess.run(firmware("--source.path", sample_log, *args), capture_output=True,
                         text=True, timeout=30)
    assert run.returncode == 2
    assert message in run.stdout + run.stderr


def test_the_deprecated_depth_units_key_still_works_and_says_so(sample_dir: Path,
                                                               tmp_path: Path) -> None:
    """Config files written before source.depth_scale_m (an installed conffile a user edited)
    keep working: source.depth_units_per_m = 5000 is source.depth_scale_m = 0.0002."""
    config = tmp_path / "old.toml"
    config.write_text(CONFIG.read_text().replace("depth_scale_m = 0.0002 ",
                                                 "depth_units_per_m = 5000 "))
    trajectories = []
    for name, extra in (("old", ["--config", str(config)]), ("new", [])):
        out = tmp_path / f"{name}.tum"
        run = subprocess.run(firmware("--source.kind", "dataset", "--source.path", sample_dir,
                                      "--source.realtime", "false", "--source.max_frames", 10,
                                      "--output.trajectory", out) + extra,
                             capture_output=True, text=True, timeout=60)
        assert run.returncode == 0, run.stderr
        assert ("source.depth_units_per_m is deprecated" in run.stderr) == (name == "old")
        trajectories.append(out.read_text())
    assert trajectories[0] == trajectories[1]


def test_config_file_with_a_wrong_type_names_the_key(sample_log: Path, tmp_path: Path) -> None:
    config = tmp_path / "bad.toml"
    config.write_text(CONFIG.read_text().replace("stall_timeout_s = 1.0", 'stall_timeout_s = "soon"'))
    run = subprocess.run(firmware("--source.path", sample_log) + ["--config", str(config)],
                         capture_output=True, text=True, timeout=30)
    assert run.returncode == 2
    assert "stall_timeout_s" in run.stdout + run.stderr, run.stdout + run.stderr


def test_config_file_sections_apply_and_unknown_keys_are_refused(sample_log: Path,
                                                                tmp_path: Path) -> None:
    config = tmp_path / "seven.toml"
    config.write_text(CONFIG.read_text().replace("max_frames = 0 ", "max_frames = 7 "))
    run = subprocess.run(firmware("--source.path", sample_log, "--source.realtime", "false")
                         + ["--config", str(config)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert summary(run.stdout).captured == 7
    # --print-config writes what --config reads back.
    printed = subprocess.run(firmware("--print-config") + ["--config", str(config)],
                             capture_output=True, text=True, check=True).stdout
    assert "source.max_frames=7" in printed
    (tmp_path / "printed.toml").write_text(printed)
    again = subprocess.run(firmware("--print-config") + ["--config", str(tmp_path / "printed.toml")],
                           capture_output=True, text=True, check=True).stdout
    assert again == printed
    config.write_text(CONFIG.read_text().replace("max_frames = 0 ", "max_frame = 7 "))
    run = subprocess.run(firmware("--source.path", sample_log) + ["--config", str(config)],
                         capture_output=True, text=True, timeout=30)
    assert run.returncode == 2
    assert f'unknown key "source.max_frame" in {config}' in run.stderr, run.stderr
    # The same misspelling on the command line.
    run = subprocess.run(firmware("--source.path", sample_log, "--source.max_frame", "7"),
                         capture_output=True, text=True, timeout=30)
    assert run.returncode == 2 and "--source.max_frame" in run.stderr, run.stderr


def test_synthetic_flight_tracks_its_ground_truth(tmp_path: Path) -> None:
    """The simulated flight in the corner room of shared/, rendered with the Kinect noise model:
    the onboard trajectory stays on the true one, both in the first camera's frame."""
    trajectory, truth = tmp_path / "fw.tum", tmp_path / "truth.tum"
    run = subprocess.run(firmware("--source.kind", "synthetic", "--source.realtime", "false",
                                  "--source.max_frames", "240", "--output.trajectory", trajectory,
                                  "--output.ground_truth", truth),
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    counts = summary(run.stdout)
    assert counts.captured == counts.processed == 240 and counts.lost == 0
    fw, gt = read_tum(trajectory), read_tum(truth)
    assert np.array_equal(fw[:, 0], gt[:, 0])
    error_m = np.linalg.norm(fw[:, 1:4] - gt[:, 1:4], axis=1)
    assert error_m.max() < SYNTHETIC_MAX_ERROR_M, error_m.max()
    # The flight really moves: half a metre of swing, not a camera standing still.
    assert np.ptp(gt[:, 1]) > 0.5


def test_wrong_types_and_unsafe_keys_refuse_to_start(sample_log: Path, tmp_path: Path) -> None:
    run = subprocess.run(firmware("--source.path", sample_log, "--vehicle.id", "seven"),
                         capture_output=True, text=True, timeout=30)
    assert run.returncode == 2 and "vehicle.id" in run.stderr
    key = tmp_path / "v1.key"
    subprocess.run([built("bin/kinfly-keygen"), "--out", key], check=True, capture_output=True)
    os.chmod(key, 0o644)
    run = subprocess.run(firmware("--source.path", sample_log, "--vehicle.key_file", key),
                         capture_output=True, text=True, timeout=30)
    assert run.returncode == 2 and "chmod 600" in run.stdout + run.stderr
    run = subprocess.run(firmware("--source.path", tmp_path / "missing.lcmlog"),
                         capture_output=True, text=True, timeout=30)
    assert run.returncode == 2 and "missing.lcmlog" in run.stdout + run.stderr


def test_sigterm_stops_within_a_second_with_a_summary(sample_log: Path) -> None:
    drone = Watched(firmware("--source.path", sample_log, "--source.realtime", "true"))
    try:
        # Flying: both threads that send have started LCM.
        assert drone.wait_for("LCM started", 2, STARTUP_TIMEOUT_S), drone.output()
        assert drone.process.poll() is None, "the 2 s replay ended early"
        sent = time.monotonic()
        drone.process.send_signal(signal.SIGTERM)
        assert drone.finish(10) == 0
        assert time.monotonic() - sent < 1.0
    finally:
        drone.process.kill()
    assert "kinfly-fw: stopped:" in drone.output()


def test_flight_over_lcm_keyframes_bit_exact_and_corrections_checked(
        netns: list[str], tum_sequence: Path, tmp_path: Path) -> None:
    """The real sequence replayed in real time by kinfly-fw in a network namespace: keyframes
    reach a ground end bit for bit, and signed corrections from Python are applied while each
    bad kind (and a correction of a keyframe never sent) is refused and counted."""
    log = tmp_path / "teddy.lcmlog"
    subprocess.run([built("bin/kinfly-tum-to-log"), "--tum", tum_sequence, "--out", log,
                    "--vehicle", "7"], check=True, capture_output=True, timeout=120)
    key, other = tmp_path / "v7.key", tmp_path / "other.key"
    for path in (key, other):
        subprocess.run([built("bin/kinfly-keygen"), "--out", path], check=True,
                       capture_output=True)
    good = 5
    ground = subprocess.Popen(
        [*netns, built("bin/kinfly-link-bench"), "ground", "--vehicle", "7", "--tum",
         tum_sequence, "--seconds", "60"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for_line(ground, "listening")
        drone = subprocess.Popen(
            [*netns, built("bin/kinfly-fw"), "--config", CONFIG, "--vehicle.id", "7",
             "--vehicle.key_file", key, "--source.path", log],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        probe = subprocess.run(
            [*netns, sys.executable, REPO_ROOT / "tests" / "tools" / "uplink_probe.py",
             "--key", key, "--other-key", other, "--vehicle", "7", "--good", str(good),
             "--min-keyframes", str(good), "--unknown-keyframe", "--timeout", "20"],
            capture_output=True, text=True, timeout=60)
        drone_out, drone_err = drone.communicate(timeout=60)
        ground.send_signal(signal.SIGTERM)
        ground_out, _ = ground.communicate(timeout=30)
    finally:
        ground.kill()
    assert probe.returncode == 0, probe.stderr + drone_err
    assert drone.returncode == 0, drone_err
    status = json.loads(probe.stdout)
    assert status["corrections_accepted"] == good, status
    assert status["corrections_unknown_keyframe"] == 1, status
    for kind in ("unsigned", "bad_mac", "wrong_key", "stale", "replayed", "malformed",
                 "wrong_vehicle", "unknown_channel"):
        assert status[f"rejected_{kind}"] == 1, (kind, status)
    assert "200 frames captured" in drone_out, drone_out
    sent = int(re.search(r"(\d+) keyframes sent", drone_out).group(1))
    received = json.loads(ground_out)
    assert received["received"] == sent > 0
    assert received["bit_exact"] is True


def lockstep_flight(netns: list[str], out: Path) -> np.ndarray:
    """The sample replayed as fast as possible in lockstep against the real kinfly-ground
    (scripts/demo.py's flight); every correction sent was applied. The drone's published poses."""
    out.mkdir()
    key = demo.make_key(out / "vehicle.key")
    drone = [*demo.drone_command(demo.SAMPLE_LOG, key=key, trajectory=out / "drone.tum"),
             "--source.realtime", "false", "--source.lockstep", "true"]
    flight = demo.fly(netns, demo.ground_command(out, key=key), [drone], quiet=True)
    assert flight.drone_rcs == [0] and flight.ground_rc == 0, flight.ground_output
    assert "no answer from the ground station" not in flight.drone_output, flight.drone_output
    counts = summary(flight.drone_output)
    sent = json.loads((out / "summary.json").read_text())["vehicles"]["1"]["keyframes"]
    assert counts.processed == 60 and counts.keyframes_sent == sent["keyframes_fused"] > 0
    assert counts.applied == sent["corrections_sent"] == counts.keyframes_sent
    return read_tum(out / "drone.tum")


def test_lockstep_replays_against_the_ground_are_the_same(netns: list[str],
                                                          tmp_path: Path) -> None:
    """source.lockstep: each keyframe's correction applies from the next frame on, however fast
    the drone runs, so two replays as fast as possible against the ground give one trajectory
    (without lockstep they differ by up to 14 mm: docs/firmware.md). The first correction that
    moves the drone applies at the frame after its keyframe."""
    first = lockstep_flight(netns, tmp_path / "first")
    second = lockstep_flight(netns, tmp_path / "second")
    assert first.shape == second.shape == (60, 8)
    assert np.array_equal(first[:, 0], second[:, 0])
    assert np.abs(first[:, 1:] - second[:, 1:]).max() < SAME_ENGINE_TOLERANCE_M
    alone = tmp_path / "alone.tum"
    run = subprocess.run(firmware("--source.path", demo.SAMPLE_LOG, "--source.realtime", "false",
                                  "--output.trajectory", alone),
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    moved = np.flatnonzero(np.abs(read_tum(alone)[:, 1:4] - first[:, 1:4]).max(axis=1)
                           > SAME_ENGINE_TOLERANCE_M)
    assert moved.size > 0
    keyframe_times = np.loadtxt(tmp_path / "first" / "trajectory_onboard.tum")[:, 0]
    first_moved_after = np.searchsorted(first[:, 0], keyframe_times, side="right")
    assert moved[0] in first_moved_after, (moved[0], first_moved_after)


def test_lockstep_without_a_ground_station_goes_on(sample_log: Path) -> None:
    """No ground station answers: the first keyframe waits link.final_wait_s and says so, no
    later one waits (a ground that is gone would cost each the whole wait), and the replay still
    flies every frame."""
    run = subprocess.run(firmware("--source.path", sample_log, "--source.realtime", "false",
                                  "--source.lockstep", "true", "--link.final_wait_s",
                                  NO_GROUND_WAIT_S),
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    counts = summary(run.stdout)
    assert counts.processed == 60 and counts.keyframes_sent > 1
    log = run.stdout + run.stderr
    assert "odometry: lockstep: no answer from the ground station to keyframe 0 within 0.2 s" in log
    assert log.count("no answer from the ground station") == 1, log
