"""kinfly-codec-bench on the shared TUM sequence: every encoding gives back every real Kinect frame
bit for bit, and the JSON it prints has the documented shape. Timings are printed by the bench
(`make bench`), never asserted here: this machine is shared and noisy."""
from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import pytest

import kinfly_eval

ENCODINGS = ("raw16", "rvl", "rvl_zstd", "palette_rvl_zstd")  # toString(DepthEncoding)
# 200 frames, each encoded once per encoding for the baselines: a few seconds; minutes mean a hang.
RUN_TIMEOUT_S = 300
TOP_KEYS = ("encoding", "zstd_level", "frames", "width", "height", "repeat", "raw_bytes",
            "compressed_bytes", "ratio", "encode_ms", "decode_ms", "bit_exact", "bit_exact_frames",
            "baseline_ratio")


def run_bench(bench: Path, *args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(bench), *map(str, args)], capture_output=True, text=True,
                          timeout=RUN_TIMEOUT_S)


@pytest.fixture(scope="module", params=ENCODINGS)
def bench_result(request: pytest.FixtureRequest, codec_bench_bin: Path,
                 tum_sequence: Path) -> dict[str, Any]:
    proc = run_bench(codec_bench_bin, "--tum", tum_sequence, "--encoding", request.param,
                     "--repeat", "1")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return json.loads(proc.stdout)


def test_every_frame_bit_exact(bench_result: dict[str, Any], tum_sequence: Path) -> None:
    frames = kinfly_eval.depth_frame_count(tum_sequence)
    assert bench_result["frames"] == frames
    assert bench_result["bit_exact"] is True
    assert bench_result["bit_exact_frames"] == frames


def test_report_shape(bench_result: dict[str, Any]) -> None:
    assert set(TOP_KEYS) <= bench_result.keys()
    assert bench_result["raw_bytes"] == (bench_result["frames"] * bench_result["width"]
                                         * bench_result["height"] * 2)
    assert bench_result["ratio"] == pytest.approx(
        bench_result["raw_bytes"] / bench_result["compressed_bytes"], rel=1e-3)  # printed to 3 dp
    for timing in ("encode_ms", "decode_ms"):
        assert 0 <= bench_result[timing]["median"] <= bench_result[timing]["p90"]
    assert set(ENCODINGS) <= bench_result["baseline_ratio"].keys()
    assert bench_result["baseline_ratio"][bench_result["encoding"]] == bench_result["ratio"]


def test_rejects_unknown_encoding(codec_bench_bin: Path, tmp_path: Path) -> None:
    proc = run_bench(codec_bench_bin, "--tum", tmp_path, "--encoding", "png")
    assert proc.returncode != 0
    assert "--encoding" in proc.stdout + proc.stderr
