#!/usr/bin/env python3
"""The drone's figures (issue 4, "Targets"), on the shared TUM freiburg3_teddy sequence.

    .venv/bin/python tests/bench/bench_onboard.py [--data SHARED_DATA] [--out out/bench]
        [--repeats 3] [--callgrind-frames 40] [--aarch64 build-aarch64]

Measures, each with the real binaries:
  - odometry time per frame at 320x240, one thread, preprocessing + tracking + integration +
    raycast (kinfly-fuse in the onboard configuration, the engine kinfly-fw runs: a test checks
    their trajectories agree to 1 um): median and p99 of each of `--repeats` runs, and the
    median of those;
  - kinfly-fw replaying the sequence as a flight log with its default configuration, as fast as
    possible: peak resident memory, the onboard trajectory's ATE against the motion capture
    (kinfly_eval.ate), and the keyframes it sent at the default thresholds (count, rate over the
    sequence's capture time, bytes per second), read from what it published (LCM's file://
    provider writes every published message to a log);
  - instructions per frame of the odometry, counted only inside FusionPipeline::processFrame:
    by `valgrind --tool=callgrind` on the native build and, with --aarch64, by a QEMU plugin on
    the aarch64 build under qemu-aarch64 (qemu_count.py; with its share of NEON instructions),
    the same frames; with estimates of the frame rate on a Cortex-A72 at 1.5 GHz and a
    Cortex-A76 at 2.4 GHz (docs/firmware.md gives the reasoning).
Prints one JSON object with the targets beside the figures. A benchmark: it reports and never
fails on a figure (a non-zero exit means something could not run).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import lcm

from kinfly import keyframe_chunk_t, odometry_t

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "tests" / "tools"))
sys.path.insert(0, str(REPO_ROOT / "tests" / "eval"))
sys.path.insert(0, str(REPO_ROOT / "scripts"))  # netns.py, shared with make demo
import kinfly_eval  # noqa: E402
from arm_cores import (A72_HZ, A72_IPC_RANGE, A76_HZ, A76_IPC_RANGE,  # noqa: E402
                       callgrind_instructions, core_estimate)
from qemu_count import count_in, count_in_plugin, mangled_symbol  # noqa: E402
from firmware_run import firmware, summary  # noqa: E402
from netns import network_namespace  # noqa: E402

BUILD = REPO_ROOT / "build"
ONBOARD_ARGS = kinfly_eval.ONBOARD_ARGS
# Issue 4, "Targets".
TARGETS = {"frame_ms_median": 8.0, "frame_ms_p99": 15.0, "ate_m": 0.04, "peak_rss_mb": 64.0,
           # Issue 18's: 30 frames a second on one A72 core at IPC 0.8 would allow 40 M; the
           # issue asks 35 M, a margin kept as it is.
           "aarch64_instructions_per_frame": 35e6}


def odometry_timing(tum: Path, out: Path, repeats: int) -> dict[str, Any]:
    runs = []
    for i in range(repeats):
        run_dir = out / f"onboard_{i}"
        subprocess.run([BUILD / "bin" / "kinfly-fuse", "--tum", tum, "--out", run_dir,
                        *ONBOARD_ARGS], check=True, capture_output=True)
        stats = json.loads((run_dir / "stats.json").read_text())
        runs.append({"median": stats["frame_ms"]["median"], "p99": stats["frame_ms"]["p99"],
                     "cpu_median": stats["frame_cpu_ms"]["median"],
                     "cpu_p99": stats["frame_cpu_ms"]["p99"],
                     "stages_median": {k: v["median"] for k, v in stats["stage_ms"].items()}})
    # Wall time is what the drone sees; the thread's CPU time is the same work without the
    # time this shared machine's scheduler gave to other processes.
    return {"runs": runs,
            "median_ms": statistics.median(r["median"] for r in runs),
            "p99_ms": statistics.median(r["p99"] for r in runs),
            "cpu_median_ms": statistics.median(r["cpu_median"] for r in runs),
            "cpu_p99_ms": statistics.median(r["cpu_p99"] for r in runs)}


def keyframe_traffic(published: Path) -> dict[str, Any]:
    # What each keyframe cost on the link: its chunks' bytes, recovery chunks included.
    chunk_bytes: dict[int, int] = {}
    frame_utimes = []
    for event in lcm.EventLog(str(published), "r"):
        if event.channel.endswith("_KEYFRAME_CHUNK"):
            keyframe_id = keyframe_chunk_t.decode(event.data).keyframe_id
            chunk_bytes[keyframe_id] = chunk_bytes.get(keyframe_id, 0) + len(event.data)
        elif event.channel.endswith("_ODOMETRY"):
            frame_utimes.append(odometry_t.decode(event.data).utime)
    keyframes = list(chunk_bytes.values())
    span_s = (max(frame_utimes) - min(frame_utimes)) * 1e-6 if frame_utimes else 0.0
    return {"keyframes": len(keyframes), "frames": len(frame_utimes),
            "sequence_s": round(span_s, 3),
            "keyframe_rate_hz": len(keyframes) / span_s if span_s else 0.0,
            "mean_keyframe_bytes": statistics.mean(keyframes) if keyframes else 0,
            "bytes_per_s": sum(keyframes) / span_s if span_s else 0.0,
            "mbit_per_s": 8e-6 * sum(keyframes) / span_s if span_s else 0.0}


def firmware_flight(tum: Path, out: Path) -> dict[str, Any]:
    log = out / "teddy.lcmlog"
    log.unlink(missing_ok=True)
    subprocess.run([BUILD / "bin" / "kinfly-tum-to-log", "--tum", tum, "--out", log],
                   check=True, capture_output=True)
    published, trajectory = out / "published.lcmlog", out / "fw_trajectory.tum"
    published.unlink(missing_ok=True)
    stdout, stderr = out / "fw.stdout", out / "fw.stderr"
    # What the drone sends, recorded by LCM's own logger on the multicast group in a private
    # network namespace, as a ground station would hear it.
    with network_namespace("bench") as netns:
        logger = subprocess.Popen([*netns, "lcm-logger", "--quiet", "--channel",
                                   ".*_KEYFRAME_CHUNK|.*_ODOMETRY", str(published)],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(0.5)  # the logger joins the group before the first message
        start = time.monotonic()
        with stdout.open("w") as o, stderr.open("w") as e:
            process = subprocess.Popen(
                [*netns, *firmware("--source.path", log, "--source.realtime", "false",
                                   "--output.trajectory", trajectory, lcm_url=None)],
                stdout=o, stderr=e)
            # wait4: the resource usage of this child alone, peak resident memory included.
            _, status, usage = os.wait4(process.pid, 0)
            process.returncode = os.waitstatus_to_exitcode(status)
        wall_s = time.monotonic() - start
        time.sleep(0.5)
        logger.send_signal(signal.SIGINT)
        logger.wait(timeout=10)
    if process.returncode != 0:
        raise RuntimeError(f"kinfly-fw failed: {stderr.read_text()}")
    run_stdout = stdout.read_text()
    counts = summary(run_stdout)
    return {"summary": counts.__dict__, "wall_s": round(wall_s, 2),
            "peak_rss_mb": round(usage.ru_maxrss / 1024, 1),
            "ate": kinfly_eval.ate(trajectory, tum / "groundtruth.txt"),
            "traffic": keyframe_traffic(published)}


def estimates(per_frame: float) -> dict[str, Any]:
    return {"a72_1500mhz": core_estimate(per_frame, A72_HZ, A72_IPC_RANGE),
            "a76_2400mhz": core_estimate(per_frame, A76_HZ, A76_IPC_RANGE)}


def instructions_per_frame(tum: Path, out: Path, frames: int) -> dict[str, Any]:
    total = callgrind_instructions(
        [BUILD / "bin" / "kinfly-fuse", "--tum", tum, "--out", out / "callgrind_run",
         "--max-frames", str(frames), *ONBOARD_ARGS],
        "kinfly::FusionPipeline::processFrame*", out / "callgrind.out")
    per_frame = total / frames
    return {"frames": frames, "instructions_per_frame": round(per_frame),
            "counted_by": "valgrind --tool=callgrind, native build", **estimates(per_frame)}


def aarch64_instructions_per_frame(tum: Path, out: Path, frames: int,
                                   aarch64_dir: Path) -> dict[str, Any]:
    """The same count on the aarch64 kinfly-fuse, from processFrame's entry until main, its
    caller, runs again."""
    program = aarch64_dir / "build" / "bin" / "kinfly-fuse"
    if not program.is_file():
        raise RuntimeError(f"{program} is not built: make firmware-aarch64")
    counted = count_in([program, "--tum", tum, "--out", out / "qemu_run",
                        "--max-frames", str(frames), *ONBOARD_ARGS],
                       aarch64_dir / "sysroot",
                       mangled_symbol(program, r"_ZN6kinfly14FusionPipeline12processFrameE.*"),
                       "main", count_in_plugin(aarch64_dir / "qemu-plugin"),
                       out / "qemu_count.log")
    if counted.calls != frames:
        raise RuntimeError(f"the plugin saw processFrame entered {counted.calls} times, "
                           f"not once for each of {frames} frames")
    per_frame = counted.instructions / frames
    return {"frames": frames, "instructions_per_frame": round(per_frame),
            "neon_share": round(counted.simd_instructions / counted.instructions, 3),
            "counted_by": "qemu-aarch64 with tests/bench/qemu_count_in.c, aarch64 build",
            **estimates(per_frame)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=None, help="shared data folder")
    parser.add_argument("--out", default=None, help="output folder (default: a temporary one)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--callgrind-frames", type=int, default=40)
    parser.add_argument("--aarch64", type=Path, default=None,
                        help="the aarch64 build folder (make firmware-aarch64): count there too")
    args = parser.parse_args()
    tum = (Path(args.data) if args.data else kinfly_eval.data_root()) / \
        kinfly_eval.TUM_SEQUENCE_SUBDIR
    if not tum.is_dir():
        print(f"bench_onboard: no TUM sequence at {tum} (--data)", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory() as scratch:
        out = Path(args.out) if args.out else Path(scratch)
        out.mkdir(parents=True, exist_ok=True)
        print("bench_onboard: kinfly-fw flight ...", file=sys.stderr)
        flight = firmware_flight(tum, out)
        print("bench_onboard: odometry timing ...", file=sys.stderr)
        timing = odometry_timing(tum, out, args.repeats)
        print("bench_onboard: callgrind ...", file=sys.stderr)
        instructions = {"native": instructions_per_frame(tum, out, args.callgrind_frames)}
        if args.aarch64:
            print("bench_onboard: qemu-aarch64 count ...", file=sys.stderr)
            instructions["aarch64"] = aarch64_instructions_per_frame(
                tum, out, args.callgrind_frames, args.aarch64)
        report = {"targets": TARGETS, "odometry_timing": timing, "firmware": flight,
                  "instructions": instructions,
                  "met": {"frame_ms_median": timing["median_ms"] <= TARGETS["frame_ms_median"],
                          "frame_cpu_ms_p99": timing["cpu_p99_ms"] <= TARGETS["frame_ms_p99"],
                          "frame_ms_p99": timing["p99_ms"] <= TARGETS["frame_ms_p99"],
                          "ate_m": flight["ate"]["rmse_m"] <= TARGETS["ate_m"],
                          "peak_rss_mb": flight["peak_rss_mb"] <= TARGETS["peak_rss_mb"]}}
        if "aarch64" in instructions:
            report["met"]["aarch64_instructions_per_frame"] = (
                instructions["aarch64"]["instructions_per_frame"]
                <= TARGETS["aarch64_instructions_per_frame"])
        text = json.dumps(report, indent=2)
        print(text)
        if args.out:
            (out / "onboard.json").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
