"""kinfly-fuse's command line: bad input is reported (naming the file, line or flag) with a
non-zero exit, and bad sensor data inside a good sequence is survived, not fatal.

Inputs are small folders built in tmp_path from the bundled tests/data sample."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from png_write import write_gray_png

# Any single run here fuses a handful of frames; a minute means it hangs.
RUN_TIMEOUT_S = 120
SAMPLE_WIDTH, SAMPLE_HEIGHT = 640, 480
DEPTH_HEADER = ["# depth maps", "# file: 'rgbd_dataset_freiburg3_teddy.bag'",
                "# timestamp filename"]
FUSE_FLAGS = ("--tum", "--out", "--intrinsics", "--depth-scale", "--volume", "--voxel-size",
              "--threads", "--max-frames", "--poses", "--downsample")


def run_fuse(fuse_bin: Path, *args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(fuse_bin), *map(str, args)], capture_output=True, text=True,
                          timeout=RUN_TIMEOUT_S)


def output_of(proc: subprocess.CompletedProcess[str]) -> str:
    return proc.stdout + proc.stderr


def sample_entries(sample_dir: Path, count: int) -> list[tuple[str, str]]:
    """The first `count` (timestamp, relative path) pairs of the sample's depth.txt."""
    lines = [line.split() for line in (sample_dir / "depth.txt").read_text().splitlines()
             if line.strip() and not line.startswith("#")]
    return [(t, path) for t, path in lines[:count]]


def make_sequence(sample_dir: Path, dest: Path, count: int) -> list[tuple[str, str]]:
    """Copies the first `count` sample frames into a fresh TUM folder at dest."""
    entries = sample_entries(sample_dir, count)
    (dest / "depth").mkdir(parents=True)
    for _, rel in entries:
        shutil.copyfile(sample_dir / rel, dest / rel)
    write_depth_txt(dest, [f"{t} {rel}" for t, rel in entries])
    return entries


def write_depth_txt(dest: Path, body: list[str]) -> None:
    (dest / "depth.txt").write_text("\n".join(DEPTH_HEADER + body) + "\n")


def trajectory_line_count(path: Path) -> int:
    return sum(1 for line in path.read_text().splitlines()
               if line.strip() and not line.startswith("#"))


def test_help_exits_zero_and_names_every_flag(fuse_bin: Path) -> None:
    proc = run_fuse(fuse_bin, "--help")
    assert proc.returncode == 0, output_of(proc)
    for flag in FUSE_FLAGS:
        assert flag in output_of(proc), f"--help does not mention {flag}"


def test_missing_folder_is_named(fuse_bin: Path, tmp_path: Path) -> None:
    missing = tmp_path / "no_such_sequence"
    proc = run_fuse(fuse_bin, "--tum", missing, "--out", tmp_path / "out")
    assert proc.returncode != 0
    assert str(missing) in output_of(proc)


@pytest.mark.parametrize("bad_line", ["not_a_time depth/x.png", "1341841873.5"],
                         ids=["bad-timestamp", "missing-filename"])
def test_malformed_depth_txt_names_file_and_line(fuse_bin: Path, sample_dir: Path,
                                                 tmp_path: Path, bad_line: str) -> None:
    seq = tmp_path / "seq"
    entries = make_sequence(sample_dir, seq, 2)
    body = [f"{t} {rel}" for t, rel in entries] + [bad_line]
    write_depth_txt(seq, body)
    bad_line_number = len(DEPTH_HEADER) + len(body)  # 1-based, comment lines counted
    proc = run_fuse(fuse_bin, "--tum", seq, "--out", tmp_path / "out")
    assert proc.returncode != 0
    message = output_of(proc)
    assert "depth.txt" in message, message
    assert re.search(rf"\b{bad_line_number}\b", message), \
        f"message does not give line {bad_line_number}: {message}"


def test_8bit_png_is_named(fuse_bin: Path, sample_dir: Path, tmp_path: Path) -> None:
    seq = tmp_path / "seq"
    entries = make_sequence(sample_dir, seq, 2)
    t, rel = entries[1]
    write_gray_png(seq / rel, np.full((SAMPLE_HEIGHT, SAMPLE_WIDTH), 100, np.uint8))
    proc = run_fuse(fuse_bin, "--tum", seq, "--out", tmp_path / "out")
    assert proc.returncode != 0
    assert Path(rel).name in output_of(proc), output_of(proc)


@pytest.mark.parametrize("intrinsics", ["1,2,3", "-535.4,539.2,320.1,247.6", "535.4,x,320.1,247.6"],
                         ids=["three-values", "negative-fx", "not-a-number"])
def test_bad_intrinsics_rejected(fuse_bin: Path, sample_dir: Path, tmp_path: Path,
                                 intrinsics: str) -> None:
    seq = tmp_path / "seq"
    make_sequence(sample_dir, seq, 2)
    proc = run_fuse(fuse_bin, "--tum", seq, "--out", tmp_path / "out", "--intrinsics", intrinsics)
    assert proc.returncode != 0
    assert "intrinsics" in output_of(proc).lower(), output_of(proc)


def test_all_zero_frame_is_lost_not_fatal(fuse_bin: Path, sample_dir: Path,
                                          tmp_path: Path) -> None:
    frames = 6
    seq, out = tmp_path / "seq", tmp_path / "out"
    entries = make_sequence(sample_dir, seq, frames)
    # A sensor dropout mid-sequence: every pixel invalid (0 = no measurement).
    _, blank = entries[frames // 2]
    write_gray_png(seq / blank, np.zeros((SAMPLE_HEIGHT, SAMPLE_WIDTH), np.uint16))

    proc = run_fuse(fuse_bin, "--tum", seq, "--out", out)
    assert proc.returncode == 0, output_of(proc)
    stats = json.loads((out / "stats.json").read_text())
    assert stats["frames"] == frames
    assert stats["tracking"].get("lost", 0) >= 1, stats["tracking"]
    # The frames around the dropout are consecutive real frames 33 ms apart: they track.
    assert stats["tracking"].get("ok", 0) >= frames - 2, stats["tracking"]
    assert trajectory_line_count(out / "trajectory.tum") == frames
    assert (out / "mesh.ply").is_file()
