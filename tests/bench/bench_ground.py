#!/usr/bin/env python3
"""The ground station's figures (issue 5, "Targets"), on the shared TUM freiburg3_teddy sequence.

    .venv/bin/python tests/bench/bench_ground.py [--data SHARED_DATA] [--out out/bench]
        [--repeats 3] [--config NAME ...]

Each run flies the whole 200-frame sequence end to end as `make demo` does: kinfly-fw replays it
(converted with kinfly-tum-to-log) in real time and kinfly-ground serves it, over LCM multicast
in a private network namespace, with the session recorded to .rrd as by default. The drone sends
a keyframe at least every 0.15 s (`keyframe.max_interval_s`), so keyframes come at 5 Hz or more, as
the latency target asks; a second configuration keeps the drone's default thresholds. From the
ground's summary.json: correction latency (a keyframe off the socket to its signed correction
sent) median and p99, the ATE of the onboard and the corrected keyframe trajectories against the
motion capture, and the ground process's memory after the sequence (resident once every keyframe
is fused, resident at exit after the final mesh and the evaluation, and the peak). Prints
one JSON object with the targets beside the figures, the median over `--repeats` runs. A
benchmark: it reports and never fails on a figure (a non-zero exit means something could not
run).

The cost of loop closure (issue 17, "ground cost of loop closure"): the sequence flown out and
back (its frames again in reverse, the capture times mirrored, so the way back revisits the way
out), once with the station's default of one map and once with a submap every 0.5 m (four or
five each way), whose loop candidates are checked while the keyframes arrive. Both report the
latency beside the loops found and the ATE of the optimised trajectory.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "tests" / "tools"))
sys.path.insert(0, str(REPO_ROOT / "tests" / "eval"))
sys.path.insert(0, str(REPO_ROOT / "scripts"))
import demo  # noqa: E402
import kinfly_eval  # noqa: E402
from netns import network_namespace  # noqa: E402

# Issue 5, "Targets".
TARGETS = {"latency_ms_median": 50.0, "latency_ms_p99": 150.0, "ate_corrected_m": 0.03,
           "ate_corrected_vs_onboard": "<="}
KEYFRAMES_5HZ = ["--keyframe.max_interval_s", "0.15"]
# Name: (sequence, the drone's arguments, the ground's).
CONFIGS: dict[str, tuple[str, list[str], list[str]]] = {
    "keyframes_5hz": ("forward", KEYFRAMES_5HZ, []),
    "default_thresholds": ("forward", [], []),
    "out_and_back_one_map": ("out_and_back", KEYFRAMES_5HZ, []),
    "out_and_back_submaps_0.5m": ("out_and_back", KEYFRAMES_5HZ, ["--submap-distance", "0.5"]),
}


def out_and_back(tum: Path, dest: Path) -> Path:
    """DEST made a TUM folder of TUM's frames, then the same frames in reverse, each at its time
    mirrored about the last frame's; the ground truth mirrored the same way."""
    frames = kinfly_eval.tum_rows(tum / "depth.txt")
    truth = kinfly_eval.tum_rows(tum / "groundtruth.txt")
    first, last = frames[0][0], frames[-1][0]
    dest.mkdir()
    (dest / "depth").symlink_to((tum / "depth").resolve())
    back = [(2 * last - t, rest) for t, rest in reversed(frames[:-1])]
    (dest / "depth.txt").write_text("".join(f"{t:.6f} {rest}\n" for t, rest in frames + back))
    # The truth from a little before the first frame (the evaluation matches within 20 ms).
    out = [(t, rest) for t, rest in truth if first - 0.1 <= t <= last]
    mirrored = [(2 * last - t, rest) for t, rest in reversed(out) if t < last]
    (dest / "groundtruth.txt").write_text("".join(f"{t:.6f} {rest}\n"
                                                  for t, rest in out + mirrored))
    return dest


def one_run(netns: list[str], log: Path, work: Path, drone_args: list[str],
            ground_args: list[str]) -> dict[str, Any]:
    key = demo.make_key(work / "vehicle.key")
    out = work / "out"
    flight = demo.fly(netns, demo.ground_command(out, key=key) + ground_args,
                      [demo.drone_command(log, key=key) + drone_args], quiet=True)
    # The machine's load over the flight, with it: a latency means little without it.
    load = os.getloadavg()[0]
    if flight.ground_rc != 0 or flight.drone_rcs != [0]:
        raise RuntimeError(f"flight failed:\n{flight.ground_output}\n{flight.drone_output}")
    summary = json.loads((out / "summary.json").read_text())
    utimes = [float(line.split()[0]) for line in
              (out / "trajectory_onboard.tum").read_text().splitlines()]
    v = summary["vehicles"]["1"]
    corrected, onboard = v["ate"]["corrected"], v["ate"]["onboard"]
    keyframes = v["keyframes"]
    return {
        "load_average_1min": load,
        "keyframes_sent": v["drone_reported"]["keyframes_sent"],
        "keyframes": v["keyframes"]["keyframes_received"],
        "lost_on_link": v["keyframes"]["lost_on_link"],
        "keyframe_rate_hz": (len(utimes) - 1) / (utimes[-1] - utimes[0]),
        "keyframes_dropped": v["keyframes"]["keyframes_dropped"],
        "corrections_sent": v["keyframes"]["corrections_sent"],
        "corrections_applied_by_drone": v["drone_reported"]["corrections_accepted"],
        "latency_ms_median": v["latency_ms"]["median"],
        "latency_ms_p99": v["latency_ms"]["p99"],
        "refine_ms_median": v["refine_ms"]["median"],
        "ate_onboard_m": onboard["rmse_m"],
        "ate_corrected_m": corrected["rmse_m"],
        "ate_optimised_m": v["ate"]["optimised"]["rmse_m"],
        "matched_poses": corrected["matched_poses"],
        "submaps": v["submaps"],
        "loop_candidates": keyframes["loop_candidates"],
        "loops_accepted": keyframes["loops_accepted"],
        "loops_refused": keyframes["loops_refused_by_check"] + keyframes["loops_refused_by_graph"],
        "rss_mb_after_fusion": summary["memory_after_fusion"]["rss_mb"],
        "rss_mb_at_exit": summary["memory"]["rss_mb"],
        "peak_rss_mb": summary["memory"]["peak_rss_mb"],
        "map_blocks": v["map_blocks"],
        "map_memory_mb": v["map_memory_mb"],
    }


def median_of(runs: list[dict[str, Any]]) -> dict[str, Any]:
    return {k: statistics.median(r[k] for r in runs) for k in runs[0]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=kinfly_eval.data_root(REPO_ROOT))
    p.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "bench")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--config", action="append", choices=list(CONFIGS),
                   help="fly only this configuration (again for more; default: all)")
    args = p.parse_args()
    configs = {name: CONFIGS[name] for name in args.config or CONFIGS}
    tum = args.data / kinfly_eval.TUM_SEQUENCE_SUBDIR
    if not tum.is_dir():
        print(f"bench_ground: no TUM sequence at {tum}", file=sys.stderr)
        return 1
    args.out.mkdir(parents=True, exist_ok=True)
    result: dict[str, Any] = {"targets": TARGETS, "sequence": str(tum), "repeats": args.repeats}
    with tempfile.TemporaryDirectory(prefix="kinfly-bench-ground-") as tmp:
        logs: dict[str, Path] = {}
        for sequence in sorted({sequence for sequence, _, _ in configs.values()}):
            folder = tum if sequence == "forward" else out_and_back(tum, Path(tmp) / sequence)
            logs[sequence] = Path(tmp) / f"teddy200_{sequence}.lcmlog"
            subprocess.run([demo.BUILD / "kinfly-tum-to-log", "--tum", folder,
                            "--out", logs[sequence]], check=True, capture_output=True)
        for name, (sequence, drone_args, ground_args) in configs.items():
            runs = []
            for i in range(args.repeats):
                work = Path(tmp) / f"{name}-{i}"
                work.mkdir()
                with network_namespace("bench") as netns:
                    runs.append(one_run(netns, logs[sequence], work, drone_args, ground_args))
                print(f"bench_ground: {name} run {i + 1}/{args.repeats}: "
                      f"{json.dumps(runs[-1])}", file=sys.stderr)
            result[name] = {"median": median_of(runs), "runs": runs}
    text = json.dumps(result, indent=2)
    (args.out / "ground.json").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
