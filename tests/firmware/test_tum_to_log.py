"""kinfly-tum-to-log: a TUM folder becomes an LCM event log in lcm-logger's format that the
Python lcm library reads back: every depth frame, at its capture time, decoding bit for bit to
the PNG it came from, and the ground truth on its own channel."""
from __future__ import annotations

import subprocess
from pathlib import Path

import lcm
import numpy as np
import pytest
from PIL import Image

from conftest import built
from kinfly import depth_keyframe_t, ground_truth_t, odometry_t
from kinfly_ground._native import Channel, DepthCodec, channel_name

VEHICLE = 3


def read_list(path: Path) -> list[tuple[float, str]]:
    rows = []
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            t, rest = line.split(maxsplit=1)
            rows.append((float(t), rest.split()[0] if path.name == "depth.txt" else rest))
    return rows


@pytest.fixture(scope="module")
def converted(sample_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("log") / "sample.lcmlog"
    subprocess.run([built("bin/kinfly-tum-to-log"), "--tum", sample_dir, "--out", out,
                    "--vehicle", str(VEHICLE)], check=True, capture_output=True)
    return out


def test_every_depth_frame_is_in_the_log_bit_exact(converted: Path, sample_dir: Path) -> None:
    frames = read_list(sample_dir / "depth.txt")
    events = list(lcm.EventLog(str(converted), "r"))
    timestamps = [e.timestamp for e in events]
    assert timestamps == sorted(timestamps), "events must be in time order for replay"

    depth_events = [e for e in events if e.channel == channel_name(Channel.DEPTH, VEHICLE)]
    assert len(depth_events) == len(frames)
    codec = DepthCodec()
    for i, (event, (t, name)) in enumerate(zip(depth_events, frames)):
        message = depth_keyframe_t.decode(event.data)
        assert message.utime == event.timestamp == round(t * 1e6)
        assert (message.vehicle_id, message.frame_id, message.keyframe_id) == (VEHICLE, i, -1)
        assert message.tracking_status == odometry_t.TRACKING_NONE
        assert message.depth_scale_m == pytest.approx(1 / 5000)
        depth = codec.decode(message.payload, message.encoding, message.camera.width,
                             message.camera.height)
        png = np.asarray(Image.open(sample_dir / name))
        assert np.array_equal(depth, png), f"frame {i} ({name})"


def test_ground_truth_is_on_its_own_channel(converted: Path, sample_dir: Path) -> None:
    frames = read_list(sample_dir / "depth.txt")
    truth_channel = channel_name(Channel.GROUND_TRUTH, VEHICLE)
    poses = [ground_truth_t.decode(e.data) for e in lcm.EventLog(str(converted), "r")
             if e.channel == truth_channel]
    assert poses
    # Ground truth outside the frames' span (plus the tool's 1 s margin) is left out.
    assert poses[0].utime >= round((frames[0][0] - 1.0) * 1e6)
    assert poses[-1].utime <= round((frames[-1][0] + 1.0) * 1e6)
    first_truth = next(r for r in read_list(sample_dir / "groundtruth.txt")
                       if r[0] >= frames[0][0] - 1.0)
    values = np.array(first_truth[1].split(), dtype=float)
    assert list(poses[0].T_world_cam.position_m) == pytest.approx(values[:3], abs=1e-9)
    # TUM writes 4 decimals, so the file's quaternion is unit only to ~1e-4; the log's is
    # normalised (and q and -q are the same rotation).
    q = values[3:] / np.linalg.norm(values[3:])
    got = np.array(poses[0].T_world_cam.orientation_xyzw)
    assert min(np.abs(got - q).max(), np.abs(got + q).max()) < 1e-9


def test_refuses_to_overwrite_and_names_bad_input(converted: Path, tmp_path: Path) -> None:
    tool = built("bin/kinfly-tum-to-log")
    again = subprocess.run([tool, "--tum", converted.parent, "--out", converted],
                           capture_output=True, text=True)
    assert again.returncode != 0
    empty = tmp_path / "not_tum"
    empty.mkdir()
    bad = subprocess.run([tool, "--tum", empty, "--out", tmp_path / "x.lcmlog"],
                         capture_output=True, text=True)
    assert bad.returncode != 0 and "depth.txt" in bad.stderr
    assert not (tmp_path / "x.lcmlog").exists()
