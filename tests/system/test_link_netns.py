"""Two processes talking LCM over UDP multicast in a private network namespace: keyframes from the
drone end, in chunks, arrive complete and bit-exact at the ground end, and signed corrections from the
Python ground station are accepted by the C++ drone end while one of every bad kind is rejected
and counted, as its drone_status_t reports."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO_ROOT, built, wait_for_line

VEHICLE = 7


def test_keyframes_arrive_complete_and_bit_exact(netns: list[str], sample_dir: Path) -> None:
    bench = built("bin/kinfly-link-bench")
    frames = 20
    ground = subprocess.Popen(
        [*netns, bench, "ground", "--vehicle", str(VEHICLE), "--tum", sample_dir,
         "--seconds", "30", "--expect", str(frames)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for_line(ground, "listening")
        subprocess.run([*netns, bench, "drone", "--vehicle", str(VEHICLE), "--tum", sample_dir,
                        "--rate", "10", "--seconds", str(frames / 10 + 0.5)],
                       check=True, capture_output=True, timeout=60)
        out, _ = ground.communicate(timeout=60)
    finally:
        ground.kill()
    report = json.loads(out)
    assert report["received"] == frames
    assert report["lost"] == 0
    assert report["first_keyframe_id"] == 0
    # In chunks, none of them lost on a perfect loopback.
    assert report["chunks"]["received"] > frames
    assert report["link_loss"]["fraction"] == 0
    assert report["bit_exact"] is True
    assert sum(report["rejected"].values()) == 0


def test_signed_corrections_accepted_and_each_bad_kind_counted(
        netns: list[str], sample_dir: Path, tmp_path: Path) -> None:
    bench = built("bin/kinfly-link-bench")
    keygen = built("bin/kinfly-keygen")
    key, other_key = tmp_path / "v7.key", tmp_path / "other.key"
    for path in (key, other_key):
        subprocess.run([keygen, "--out", path], check=True, capture_output=True)
    good = 5
    drone = subprocess.Popen(
        [*netns, bench, "drone", "--vehicle", str(VEHICLE), "--tum", sample_dir,
         "--max-frames", "5", "--rate", "1", "--seconds", "8", "--key", key],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        probe = subprocess.run(
            [*netns, sys.executable, REPO_ROOT / "tests" / "tools" / "uplink_probe.py",
             "--key", key, "--other-key", other_key, "--vehicle", str(VEHICLE),
             "--good", str(good)],
            capture_output=True, text=True, timeout=60)
        assert probe.returncode == 0, probe.stderr
        drone_out, drone_err = drone.communicate(timeout=60)
    finally:
        drone.kill()
    assert drone.returncode == 0, drone_err

    # What the drone says in its drone_status_t, decoded by Python ...
    status = json.loads(probe.stdout)
    assert status["corrections_accepted"] == good
    for kind in ("unsigned", "bad_mac", "wrong_key", "stale", "replayed", "malformed",
                 "wrong_vehicle", "unknown_channel"):
        assert status[f"rejected_{kind}"] == 1, (kind, status)
    # ... and in its own summary at exit.
    summary = json.loads(drone_out)
    assert summary["corrections_accepted"] == good
    assert all(count == 1 for count in summary["rejected"].values()), summary
