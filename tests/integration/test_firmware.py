"""kinfly-fw, the real binary: a replayed flight log gives exactly the onboard trajectory of the
offline engine; configuration errors and unsafe key files refuse to start with a message naming
the value; SIGTERM stops it within a second with a summary."""
from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO_ROOT, built

CONFIG = REPO_ROOT / "firmware" / "config" / "kinfly-fw.toml"
# Same engine, same parameters, same frames in the same order: only float summation order could
# differ, and it does not (the engine's reductions are fixed-order), so agreement is to rounding.
SAME_ENGINE_TOLERANCE_M = 1e-6


@pytest.fixture(scope="module")
def sample_log(sample_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("fw") / "sample.lcmlog"
    subprocess.run([built("bin/kinfly-tum-to-log"), "--tum", sample_dir, "--out", out],
                   check=True, capture_output=True)
    return out


def firmware(*args: object) -> list[str]:
    return [str(built("bin/kinfly-fw")), "--config", str(CONFIG), "--vehicle.key_file", "",
            "--link.lcm_url", "memq://", *map(str, args)]


def read_tum(path: Path) -> np.ndarray:
    return np.loadtxt(path, comments="#").reshape(-1, 8)


def test_log_replay_matches_the_offline_engine(sample_log: Path, sample_dir: Path,
                                               tmp_path: Path) -> None:
    trajectory = tmp_path / "fw.tum"
    run = subprocess.run(firmware("--source.path", sample_log, "--source.realtime", "false",
                                  "--output.trajectory", trajectory),
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "60 frames captured, 60 processed (0 lost)" in run.stdout, run.stdout
    subprocess.run([built("bin/kinfly-fuse"), "--tum", sample_dir, "--out", tmp_path / "fuse",
                    "--downsample", "2", "--volume", "dense", "--threads", "1"],
                   check=True, capture_output=True, timeout=120)
    fw, fuse = read_tum(trajectory), read_tum(tmp_path / "fuse" / "trajectory.tum")
    assert fw.shape == fuse.shape
    assert np.abs(fw[:, 0] - fuse[:, 0]).max() < 1e-6  # same capture times
    assert np.abs(fw[:, 1:4] - fuse[:, 1:4]).max() < SAME_ENGINE_TOLERANCE_M


@pytest.mark.parametrize("args,message", [
    (["--vehicle.id", "70000"], "vehicle.id must be in [0, 65535]"),
    (["--odometry.downsample", "3"], "odometry.downsample must be 1, 2 or 4"),
    (["--keyframe.min_interval_s", "5"], "keyframe.min_interval_s"),
    (["--source.kind", "camera"], "source.kind must be log or dataset"),
    (["--link.status_rate_hz", "0"], "link.status_rate_hz"),
    (["--output.log_level", "loud"], "output.log_level"),
])
def test_bad_configuration_refuses_to_start(sample_log: Path, args: list[str],
                                            message: str) -> None:
    run = subprocess.run(firmware("--source.path", sample_log, *args), capture_output=True,
                         text=True, timeout=30)
    assert run.returncode == 2
    assert message in run.stdout + run.stderr


def test_wrong_types_and_unsafe_keys_refuse_to_start(sample_log: Path, tmp_path: Path) -> None:
    run = subprocess.run(firmware("--source.path", sample_log, "--vehicle.id", "seven"),
                         capture_output=True, text=True, timeout=30)
    assert run.returncode != 0 and "vehicle.id" in run.stderr
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
    process = subprocess.Popen(firmware("--source.path", sample_log, "--source.realtime", "true"),
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(0.8)
    assert process.poll() is None, "the 2 s replay ended early"
    sent = time.monotonic()
    process.send_signal(signal.SIGTERM)
    out, _ = process.communicate(timeout=10)
    assert time.monotonic() - sent < 1.0
    assert process.returncode == 0
    assert out.startswith("kinfly-fw: stopped:")
