#!/usr/bin/env python3
"""`make soak`: an hours-long flight through the real programs, memory sampled on both ends.

    .venv/bin/python tests/system/soak.py [--minutes 60] [--out out/soak] [--busy N]
                                          [--allow-queue-drops] [--sequence]

kinfly-fw replays a recorded flight bouncing (`source.loop = bounce`: forward, backward,
forward ..., capture times increasing, docs/firmware.md) in real time for --minutes, to
kinfly-ground over LCM multicast in a private network namespace, as `make demo` flies
(scripts/demo.py). The flight is the shipped TUM sample (2 s a lap), or with --sequence the
shared 200-frame TUM sequence converted to a log (6.9 s a lap). Its ground truth is left out of
the replayed log: a drone in the field has none, and the poses would be 30 more records a second
for the ground to keep. The ground records no .rrd (`--no-record`: it would take 2 GB an hour of
depth images on disk; the viewer's memory is not kinfly's).

Every few seconds it reads the resident memory (VmRSS) of both programs themselves (not of the
namespace's wrappers), and a watcher in the namespace (tests/tools/status_watch.py) follows both
ends' status messages. At the end it stops the ground as Ctrl-C would, once the drone has
exited and the ground heard its final status, and reads the ground's summary.json. It prints a
report and writes it with every sample to OUT/soak.json.

It fails (exit 1, saying which) unless:
  - both programs exited 0 and the ground heard the drone's final status;
  - kinfly-fw's memory did not grow: the least-squares slope of its RSS over the run after the
    warm-up (the first quarter), times that time, is at most 1 MB;
  - kinfly-ground's memory grew no faster than what it keeps by design: its map (the blocks
    added, each with its kept mesh) and a record per keyframe for its outputs (two poses, the
    latency and refinement times), plus a stated allowance for the allocator;
  - nothing was dropped that the link did not count: every keyframe the drone sent was received
    or counted as lost on the link, every one received was fused, counted as not refined, or
    counted as dropped by the ground's queue; the drone's capture and keyframe queues and the
    ground's queue dropped nothing (reported, not failed, with --busy or --allow-queue-drops);
    the drone's odometry lost no frame; no keyframe's handling failed;
  - no thread stalled: while the drone flew, no rate in either end's status (the drone's depth,
    odometry and keyframe rates, the ground's received, fused and correction rates) stayed at
    zero, and neither end's status went unheard, for longer than 5 s.

Run with the project's .venv python (the Makefile does). Needs root or passwordless sudo for the
namespace, and build/bin/kinfly-fw, kinfly-keygen (kinfly-tum-to-log with --sequence)."""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[2]
for folder in ("scripts", "tests/tools", "tests/eval"):
    sys.path.insert(0, str(REPO_ROOT / folder))
import demo  # noqa: E402  (scripts/demo.py: the demo's commands and process handling)
import kinfly_eval  # noqa: E402  (where the shared data is)
from busy import busy_cores  # noqa: E402
from firmware_run import parse_summary  # noqa: E402
from netns import LinkShape, NetnsUnavailable, network_namespace, send_signal  # noqa: E402

STATUS_WATCH = REPO_ROOT / "tests" / "tools" / "status_watch.py"
DEPTH_CHANNEL = f"KINFLY_{demo.VEHICLE_ID}_DEPTH"
# drone_status_t and ground_status_t (an LCM channel regular expression, matched whole).
STATUS_CHANNELS = f"KINFLY_{demo.VEHICLE_ID}_(GROUND_)?STATUS"
RUN_FINAL = 1  # drone_status_t.RUN_FINAL

# The figures a soak must hold.
# Issue 14: kinfly-fw allocates everything at start (docs/firmware.md), so its resident memory
# must not grow; 1 MB is the page-granular noise of the C library's allocator and LCM's buffers.
FIRMWARE_GROWTH_LIMIT_MB = 1.0
# The first quarter is warm-up: the map's first laps, the allocators' pools, rerun-free Python's
# lazy imports at the first keyframe, the mesher's first meshes.
WARM_UP_FRACTION = 0.25
# What kinfly-ground keeps per keyframe for its outputs, by design: the onboard and the corrected
# pose (a tuple of an int and a 4x4 float64 array, about 330 B each), the latency and the
# refinement time (32 B each in their lists) and the id in the link's set (about 60 B): 800 B,
# rounded up.
KEYFRAME_RECORD_BYTES = 1000
# Per byte of map (the hashed volume's blocks, its own memory_bytes): the block itself and the
# mesh kept for it (kinfly::IncrementalMesher), about the block's size again.
MAP_RSS_PER_MAP_BYTE = 2.0
# Every 5 s the ground's mesher joins the whole map's mesh from its per-block pieces (docs/
# ground.md, "Meshing"): arrays about mesh.ply's size, made and freed, up to three times over at
# once (the joined vectors as they grow, the arrays handed to Python). glibc keeps freed memory of
# that size for the next time once it has seen it (its mmap threshold rises with each large free),
# so the process settles a step higher whenever the mesh reaches a size it had not: bounded by
# the map's mesh, not by the flight (measured: steps of 5 to 30 MB with a 20 MB mesh, in the
# first minutes).
MESH_WORKING_SETS = 3.0
# Python's and glibc's allocators hand memory back to the kernel in their own time: a flat
# process still moves by a few MB between samples.
GROUND_NOISE_MB = 8.0
# A stall: the drone sends a keyframe at least every second while it tracks (keyframe.max_
# interval_s) and both ends average their rates over 1-2 s windows, so a rate at zero this long,
# or a status unheard this long (they come at 10 Hz), is a thread that stopped.
STALL_BOUND_S = 5.0

# How often memory is sampled: about 200 samples a run, every 1 to 5 s.
SAMPLES_PER_RUN = 200
SAMPLE_PERIOD_RANGE_S = (1.0, 5.0)
REPORT_PERIOD_S = 60.0          # a progress line on stdout
# Bounds on waits for events, not waits.
DRONE_START_TIMEOUT_S = 60.0    # its first log line: the source open, the volume allocated
WATCHER_START_TIMEOUT_S = 60.0  # it imports lcm and the ground's native module
# Beyond the flight itself: start-up, the final wait for corrections (link.final_wait_s, 5 s).
DRONE_EXIT_MARGIN_S = 120.0

# kinfly-ground's progress line (cli._progress), every 2 s.
_PROGRESS = re.compile(r"vehicle \d+: (?P<received>\d+) keyframes, .*; map (?P<blocks>\d+) blocks")


@dataclasses.dataclass
class Flight:
    """The replayed log: its frames and how long one pass over them lasts."""
    log: Path
    frames: int
    lap_s: float


@dataclasses.dataclass(frozen=True)
class SoakPlan:
    """What one soak flight is: how long, which flight, beside what load, over which link, and
    what it keeps beyond its report (tests/bench/bench_fw_link.py flies several)."""
    minutes: float
    sequence: bool = False  # the shared 200-frame TUM sequence instead of the shipped sample
    busy: int = 0  # processes each keeping a core busy beside the flight
    shape: LinkShape | None = None  # None: plain loopback
    status_log: Path | None = None  # both ends' status messages, recorded there by lcm-logger
    label: str = "soak"  # what its progress lines start with
    verbose: bool = False  # echo both programs' output


def depth_only(source: Path, out: Path) -> Flight:
    """A copy of SOURCE with only the drone's depth frames (no ground truth), and its length."""
    import lcm

    from kinfly import depth_keyframe_t

    utimes = []
    reader = lcm.EventLog(str(source), "r")
    writer = lcm.EventLog(str(out), "w", overwrite=True)
    for event in reader:
        if event.channel == DEPTH_CHANNEL:
            writer.write_event(event.timestamp, event.channel, event.data)
            utimes.append(depth_keyframe_t.decode(event.data).utime)
    reader.close()
    writer.close()
    if len(utimes) < 2:
        raise SystemExit(f"soak: {source} has {len(utimes)} frames on {DEPTH_CHANNEL}; a bounce "
                         "needs two at least")
    return Flight(out, len(utimes), (max(utimes) - min(utimes)) / 1e6)


def flight_log(sequence: bool, out: Path) -> Flight:
    if not sequence:
        return depth_only(demo.SAMPLE_LOG, out / "flight.lcmlog")
    tum = kinfly_eval.data_root(REPO_ROOT) / kinfly_eval.TUM_SEQUENCE_SUBDIR
    if not tum.is_dir():
        raise SystemExit(f"soak: no TUM sequence at {tum} (set KINFLY_DATA)")
    converted = out / "sequence.lcmlog"
    subprocess.run([str(demo.BUILD / "kinfly-tum-to-log"), "--tum", str(tum), "--out",
                    str(converted)], check=True, stdout=subprocess.DEVNULL)
    flight = depth_only(converted, out / "flight.lcmlog")
    converted.unlink()
    return flight


def program_pid(pid: int, name: str) -> int | None:
    """The process named NAME at or below PID: the program itself, under whatever the namespace
    put in front of it (`ip netns exec` and `env` exec it; sudo forks it)."""
    todo = [pid]
    while todo:
        candidate = todo.pop(0)
        try:
            if Path(f"/proc/{candidate}/comm").read_text().strip() == name[:15]:
                return candidate
            for task in Path(f"/proc/{candidate}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            continue
    return None


def rss_mb(pid: int) -> float | None:
    """VmRSS of PID [MB, 10^6 bytes, as kinfly-ground's summary]; None once it has exited."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024 / 1e6
    except OSError:
        pass
    return None


class Sampler:
    """Samples both programs' memory, the ground's map and both ends' counts every PERIOD_S on
    a thread of its own, and prints a progress line every REPORT_PERIOD_S."""

    def __init__(self, drone_pid: int, ground_pid: int, ground: demo.Watched,
                 watcher: demo.Watched, period_s: float, total_s: float, label: str) -> None:
        self.samples: list[dict[str, Any]] = []
        self._label = label
        self._pids = {"firmware": drone_pid, "ground": ground_pid}
        self._ground, self._watcher = ground, watcher
        self._period_s, self._total_s = period_s, total_s
        self._stop = threading.Event()
        self._started = time.monotonic()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _sample(self) -> dict[str, Any] | None:
        firmware, ground = (rss_mb(self._pids["firmware"]), rss_mb(self._pids["ground"]))
        if firmware is None or ground is None:
            return None
        sample: dict[str, Any] = {"t_s": round(time.monotonic() - self._started, 2),
                                  "firmware_rss_mb": firmware, "ground_rss_mb": ground,
                                  "load_1min": os.getloadavg()[0]}
        progress = self._ground.latest("map ")
        match = _PROGRESS.search(progress or "")
        if match:
            sample["map_blocks"] = int(match["blocks"])
            sample["keyframes_received"] = int(match["received"])
        status = self._watcher.latest('"drone"')
        if status:
            drone = json.loads(status)["drone"]
            sample.update(frames_captured=drone.get("frames_captured"),
                          keyframes_sent=drone.get("keyframes_sent"))
        return sample

    def _run(self) -> None:
        next_report = self._started + REPORT_PERIOD_S
        while not self._stop.wait(self._period_s):
            sample = self._sample()
            if sample is None:
                return
            self.samples.append(sample)
            if time.monotonic() >= next_report:
                next_report += REPORT_PERIOD_S
                print(f"{self._label}: {sample['t_s'] / 60:5.1f} of {self._total_s / 60:.1f} min: "
                      f"kinfly-fw {sample['firmware_rss_mb']:.1f} MB, kinfly-ground "
                      f"{sample['ground_rss_mb']:.1f} MB; {sample.get('keyframes_sent')} "
                      f"keyframes sent, {sample.get('keyframes_received')} received; map "
                      f"{sample.get('map_blocks')} blocks", flush=True)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def growth_mb(samples: list[dict[str, Any]], key: str) -> dict[str, Any]:
    """KEY's start, end and maximum, and its growth after the warm-up: the least-squares slope
    over the samples after the first WARM_UP_FRACTION, times the time they span."""
    values = [s[key] for s in samples]
    window = samples[int(len(samples) * WARM_UP_FRACTION):]
    t = np.array([s["t_s"] for s in window])
    v = np.array([s[key] for s in window])
    slope = float(np.polyfit(t, v, 1)[0]) if len(window) >= 3 else math.nan
    return {"start_mb": values[0], "end_mb": values[-1], "max_mb": max(values),
            "after_warm_up_mb": window[0][key], "slope_mb_per_h": slope * 3600,
            "growth_after_warm_up_mb": slope * float(t[-1] - t[0]) if len(window) >= 3
            else math.nan,
            "window_s": float(t[-1] - t[0]) if len(window) else 0.0}


def counted_between(samples: list[dict[str, Any]], key: str) -> int:
    """How much KEY (a count) rose over the samples after the warm-up."""
    window = [s[key] for s in samples[int(len(samples) * WARM_UP_FRACTION):]
              if s.get(key) is not None]
    return window[-1] - window[0] if window else 0


def clean_exit(report: dict[str, Any]) -> tuple[bool, str]:
    """Whether both programs exited 0 and the ground heard the drone's final status, and what
    happened."""
    final = report["drone"].get("final", False)
    return (report["firmware_exit"] == 0 and report["ground_exit"] == 0 and final,
            f"kinfly-fw exited {report['firmware_exit']}, kinfly-ground {report['ground_exit']}; "
            f"the drone's final status {'heard' if final else 'NOT heard'}")


def judge(report: dict[str, Any], drops_reported: str | None) -> list[tuple[str, bool, str]]:
    """Each criterion: its name, whether it held, and the figures."""
    k, drone = report["keyframes"], report["drone"]
    fw, gr = report["rss"]["firmware"], report["rss"]["ground"]
    stalls = report["stalls"]
    criteria = [
        ("clean exit", *clean_exit(report)),
        ("firmware memory flat", fw["growth_after_warm_up_mb"] <= FIRMWARE_GROWTH_LIMIT_MB,
         f"kinfly-fw RSS grew {fw['growth_after_warm_up_mb']:+.2f} MB over the "
         f"{fw['window_s'] / 60:.1f} min after the warm-up (at most "
         f"{FIRMWARE_GROWTH_LIMIT_MB} MB)"),
        ("ground memory follows the map",
         gr["growth_after_warm_up_mb"] <= report["ground_allowance"]["total_mb"],
         f"kinfly-ground RSS grew {gr['growth_after_warm_up_mb']:+.1f} MB after the warm-up; "
         f"what it keeps by design: {report['ground_allowance']['total_mb']:.1f} MB (map "
         f"{report['ground_allowance']['map_mb']:.1f} MB for "
         f"{report['ground_allowance']['map_blocks_added']} blocks added, "
         f"{report['ground_allowance']['keyframes_mb']:.1f} MB for "
         f"{report['ground_allowance']['keyframes']} keyframes, "
         f"{report['ground_allowance']['mesher_mb']:.1f} MB the mesher's working set, "
         f"{GROUND_NOISE_MB} MB allocator noise)"),
        ("every keyframe sent received or counted lost on the link",
         k["sent"] == k["received"] + k["late"] + k["lost_on_link"],
         f"sent {k['sent']} = received {k['received']} + late {k['late']} + lost on the link "
         f"{k['lost_on_link']}"),
        ("every keyframe received fused or counted",
         k["received"] == k["fused"] + k["not_refined"] + k["dropped_by_ground"] + k["failed"],
         f"received {k['received']} = fused {k['fused']} + not refined {k['not_refined']} + "
         f"dropped by the ground's queue {k['dropped_by_ground']} + failed {k['failed']}"),
        ("no handling failed", k["failed"] == 0, f"{k['failed']} keyframes failed"),
        ("the odometry lost no frame", drone.get("frames_lost") == 0,
         f"{drone.get('frames_lost')} frames lost by the drone's odometry"),
    ]
    drops = (drone.get("queue_drops"), drone.get("keyframes_dropped"), k["dropped_by_ground"])
    drops_text = (f"the drone's capture queue dropped {drops[0]} frames, its link "
                  f"{drops[1]} keyframes; the ground's queue {drops[2]} keyframes")
    criteria.append(("no queue dropped anything" if drops_reported is None
                     else f"queue drops (reported only: {drops_reported})",
                     drops_reported is not None or drops == (0, 0, 0), drops_text))
    zero = {f"{side}.{rate}": seconds for side in ("drone", "ground")
            for rate, seconds in stalls[side]["longest_zero_s"].items()}
    gaps = {side: stalls[side]["longest_gap_s"] for side in ("drone", "ground")}
    worst_rate = max(zero, key=zero.get)
    # The watcher's figures cover the flight only if it heard the drone to its final status.
    followed = stalls["drone"].get("run_state") == RUN_FINAL
    criteria.append(("no stall", followed and max(zero.values()) <= STALL_BOUND_S
                     and max(gaps.values()) <= STALL_BOUND_S,
                     f"longest at zero: {worst_rate} {zero[worst_rate]:.1f} s; longest without a "
                     f"status: drone {gaps['drone']:.1f} s, ground {gaps['ground']:.1f} s (at most "
                     f"{STALL_BOUND_S} s)"
                     + ("" if followed else "; the watcher did not hear the drone's final status")))
    return criteria


def fly(plan: SoakPlan, out: Path) -> dict[str, Any]:
    """Flies PLAN with its outputs in OUT; the report so far (account() adds the ground's
    summary)."""
    flight = flight_log(plan.sequence, out)
    laps = max(1, math.ceil(plan.minutes * 60.0 / flight.lap_s))
    flight_s = laps * flight.lap_s
    print(f"{plan.label}: {flight.log.name}: {flight.frames} frames, {flight.lap_s:.2f} s a lap; "
          f"{laps} laps bounced, {flight_s / 60:.1f} min of flight"
          f"{f', {plan.busy} busy loops beside it' if plan.busy else ''}", flush=True)
    key = demo.make_key(out / "vehicle.key")
    ground_out = out / "ground"
    period_s = min(max(flight_s / SAMPLES_PER_RUN, SAMPLE_PERIOD_RANGE_S[0]),
                   SAMPLE_PERIOD_RANGE_S[1])
    report: dict[str, Any] = {"minutes": plan.minutes, "busy": plan.busy, "log": str(flight.log),
                              "load_average_at_start": os.getloadavg(),
                              "frames_per_lap": flight.frames, "lap_s": flight.lap_s,
                              "laps": laps, "flight_s": flight_s, "sample_period_s": period_s}
    report["link"] = plan.shape.label() if plan.shape else "loopback"
    with busy_cores(plan.busy), network_namespace("soak", plan.shape) as netns:
        ground = demo.Watched([*netns, *demo.ground_command(ground_out, key=key), "--no-record"],
                              "[ground] ", quiet=not plan.verbose)
        logger = watcher = drone = sampler = None
        try:
            # It listens within a moment, long before the drone starts: it has all its statuses.
            if plan.status_log is not None:
                logger = subprocess.Popen([*netns, "lcm-logger", "--quiet", "--lcm-url",
                                           demo.LCM_URL, "--channel", STATUS_CHANNELS,
                                           str(plan.status_log)],
                                          stdout=subprocess.DEVNULL, start_new_session=True)
            if not ground.wait_for("listening on", 1, demo.GROUND_READY_TIMEOUT_S):
                raise RuntimeError("kinfly-ground did not start listening:\n" + ground.output())
            watcher = demo.Watched([*netns, sys.executable, str(STATUS_WATCH), "--vehicle",
                                    str(demo.VEHICLE_ID), "--lcm-url", demo.LCM_URL])
            if not watcher.wait_for("watching", 1, WATCHER_START_TIMEOUT_S):
                raise RuntimeError("the status watcher did not start:\n" + watcher.output())
            drone = demo.Watched([*netns, *demo.drone_command(flight.log, key=key),
                                  "--source.loop", "bounce", "--source.laps", str(laps)],
                                 "[drone]  ", quiet=not plan.verbose)
            if not drone.wait_for("kinfly-fw ", 1, DRONE_START_TIMEOUT_S):
                raise RuntimeError("kinfly-fw did not start:\n" + drone.output())
            drone_pid = program_pid(drone.process.pid, "kinfly-fw")
            ground_pid = program_pid(ground.process.pid, "kinfly-ground")
            if drone_pid is None or ground_pid is None:
                raise RuntimeError(f"cannot find the programs' processes (kinfly-fw {drone_pid}, "
                                   f"kinfly-ground {ground_pid})")
            sampler = Sampler(drone_pid, ground_pid, ground, watcher, period_s, flight_s,
                              plan.label)
            try:
                report["firmware_exit"] = drone.finish(flight_s + DRONE_EXIT_MARGIN_S)
            except subprocess.TimeoutExpired:
                raise RuntimeError(f"kinfly-fw was still running {DRONE_EXIT_MARGIN_S:.0f} s "
                                   "after its flight should have ended") from None
            sampler.stop()
            if report["firmware_exit"] == 0 and not ground.wait_for(
                    demo.DRONE_STOPPED, 1, demo.DRONE_FINAL_TIMEOUT_S):
                print(f"{plan.label}: the ground did not hear the drone's final status",
                      file=sys.stderr)
        finally:
            if sampler is not None:
                sampler.stop()
            if drone is not None and drone.process.poll() is None:
                send_signal(drone.process, signal.SIGINT)
                drone.finish(demo.DRONE_FINAL_TIMEOUT_S)
            send_signal(ground.process, signal.SIGTERM)
            report["ground_exit"] = ground.finish(demo.GROUND_EXIT_TIMEOUT_S)
            if watcher is not None:
                send_signal(watcher.process, signal.SIGTERM)
                watcher.finish(demo.DRONE_FINAL_TIMEOUT_S)
            if logger is not None:
                send_signal(logger, signal.SIGINT)
                logger.wait(demo.DRONE_FINAL_TIMEOUT_S)
    (out / "ground.txt").write_text(ground.output())
    (out / "drone.txt").write_text(drone.output())
    report["load_average_at_end"] = os.getloadavg()
    report["samples"] = sampler.samples
    counts = parse_summary(drone.output())
    report["firmware_summary"] = None if counts is None else dataclasses.asdict(counts)
    watched = watcher.latest('"drone"')
    if watched is None:
        raise RuntimeError("the status watcher heard nothing:\n" + watcher.output())
    report["stalls"] = json.loads(watched)
    return report


def account(report: dict[str, Any], out: Path) -> None:
    """Adds the ground's and the drone's counts, the memory figures and the ground's allowance
    to REPORT, from the ground's summary.json and the samples."""
    summary = json.loads((out / "ground" / "summary.json").read_text())
    vehicle = summary["vehicles"][str(demo.VEHICLE_ID)]
    k, drone = vehicle["keyframes"], vehicle.get("drone_reported") or {}
    report["drone"] = drone
    report["keyframes"] = {
        "sent": drone.get("keyframes_sent"), "received": k["keyframes_received"],
        "late": k["out_of_order"], "duplicates": k["duplicates"],
        "lost_on_link": k["lost_on_link"], "fused": k["keyframes_fused"],
        "not_refined": k["keyframes_lost"], "dropped_by_ground": k["keyframes_dropped"],
        "failed": k["failed"], "corrections_sent": k["corrections_sent"],
        "corrections_applied_by_drone": drone.get("corrections_accepted")}
    report["latency_ms"] = vehicle["latency_ms"]
    samples = report["samples"]
    report["rss"] = {"firmware": growth_mb(samples, "firmware_rss_mb"),
                     "ground": growth_mb(samples, "ground_rss_mb")}
    blocks = vehicle.get("map_blocks") or 0
    bytes_per_block = vehicle["map_memory_mb"] * 1e6 / blocks if blocks else 0.0
    blocks_added = counted_between(samples, "map_blocks")
    keyframes = counted_between(samples, "keyframes_received")
    mesh = out / "ground" / "mesh.ply"
    allowance = {"map_blocks": blocks, "map_memory_mb": vehicle.get("map_memory_mb"),
                 "map_blocks_added": blocks_added, "keyframes": keyframes,
                 "map_mb": MAP_RSS_PER_MAP_BYTE * blocks_added * bytes_per_block / 1e6,
                 "keyframes_mb": KEYFRAME_RECORD_BYTES * keyframes / 1e6,
                 "mesh_ply_mb": mesh.stat().st_size / 1e6 if mesh.is_file() else 0.0,
                 "noise_mb": GROUND_NOISE_MB}
    allowance["mesher_mb"] = MESH_WORKING_SETS * allowance["mesh_ply_mb"]
    allowance["total_mb"] = (allowance["map_mb"] + allowance["keyframes_mb"]
                             + allowance["mesher_mb"] + GROUND_NOISE_MB)
    report["ground_allowance"] = allowance
    report["ground_memory"] = summary["memory"]


def fly_and_account(plan: SoakPlan, out: Path) -> dict[str, Any]:
    """fly() then account(): the whole report but the criteria. RuntimeError, saying what, when
    a program did not start, did not exit or wrote no summary (NetnsUnavailable, one of them,
    when there is no namespace)."""
    try:
        report = fly(plan, out)
    except subprocess.TimeoutExpired as error:
        raise RuntimeError(f"{error.cmd[0]} did not exit within {error.timeout:.0f} s") from None
    if not (out / "ground" / "summary.json").is_file():
        raise RuntimeError("kinfly-ground wrote no summary.json (ground.txt has its output)")
    account(report, out)
    return report


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=60.0,
                   help="flight time: the log is bounced for as many laps as cover it "
                        "(default 60)")
    p.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "soak",
                   help="where the report (soak.json), the programs' output and the ground's "
                        "outputs go; emptied first (default out/soak)")
    p.add_argument("--busy", type=int, default=0, metavar="N",
                   help="N processes each keeping a core busy beside the flight (queue drops "
                        "are then reported, not failed)")
    p.add_argument("--allow-queue-drops", action="store_true",
                   help="report queue drops instead of failing on them (as --busy does): on a "
                        "machine loaded by other work the drone's odometry falls behind and drops "
                        "frames, counted, as designed; make test's 2 minutes run so, since make "
                        "test must hold beside busy loops (make test-runs)")
    p.add_argument("--sequence", action="store_true",
                   help="fly the shared 200-frame TUM sequence (KINFLY_DATA) instead of the "
                        "shipped 60-frame sample")
    p.add_argument("--loss", type=float, default=0.0, metavar="P",
                   help="fly over a Wi-Fi-like link losing this fraction of packets "
                        "(scripts/netns.py LinkShape: MTU 1500, nftables drops); default 0: "
                        "plain loopback")
    p.add_argument("--loss-run", type=float, default=1.0, metavar="L",
                   help="with --loss: mean length of a run of lost packets (1: independent)")
    p.add_argument("--rate-kbit", type=float, default=None, metavar="R",
                   help="cap the link at R kbit/s (a tbf queue, as scripts/netns.py shapes it): "
                        "the drone's send budget must find it")
    p.add_argument("--verbose", action="store_true", help="echo both programs' output")
    args = p.parse_args()
    if args.minutes <= 0:
        p.error("--minutes must be positive")
    out = args.out
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    started = time.monotonic()
    # A Wi-Fi-like link when asked (scripts/netns.py): the chunks' erasure coding and repair
    # requests then work for the whole flight, and what they could not save is counted lost.
    shape = (LinkShape(loss=args.loss, loss_run_packets=args.loss_run,
                       rate_kbit_s=args.rate_kbit)
             if args.loss > 0.0 or args.rate_kbit is not None else None)
    plan = SoakPlan(minutes=args.minutes, sequence=args.sequence, busy=args.busy, shape=shape,
                    verbose=args.verbose)
    try:
        report = fly_and_account(plan, out)
    except NetnsUnavailable as error:
        print(f"soak: {error}", file=sys.stderr)
        return 1
    except RuntimeError as error:
        print(f"soak: FAILED: {error}", file=sys.stderr)
        return 1
    report["wall_s"] = time.monotonic() - started
    drops_reported = (f"--busy {args.busy}" if args.busy else
                      "--allow-queue-drops" if args.allow_queue_drops else None)
    report["queue_drops_reported_only"] = drops_reported is not None
    criteria = judge(report, drops_reported)
    report["criteria"] = [{"name": n, "ok": ok, "detail": d} for n, ok, d in criteria]
    report["ok"] = all(ok for _, ok, _ in criteria)
    (out / "soak.json").write_text(json.dumps(report, indent=2) + "\n")
    k, fw, gr = report["keyframes"], report["rss"]["firmware"], report["rss"]["ground"]
    print(f"soak: {report['flight_s'] / 60:.1f} min of flight ({report['laps']} laps), "
          f"{report['drone'].get('frames_captured')} frames; keyframes: {k['sent']} sent, "
          f"{k['received']} received, {k['fused']} fused, {k['lost_on_link']} lost on the link, "
          f"{k['dropped_by_ground']} dropped by the ground, {report['drone'].get('queue_drops')} "
          f"frames dropped by the drone; latency median {report['latency_ms']['median']:.1f} ms")
    print(f"soak: kinfly-fw RSS {fw['start_mb']:.1f} -> {fw['end_mb']:.1f} MB (max "
          f"{fw['max_mb']:.1f}), {fw['growth_after_warm_up_mb']:+.2f} MB after the warm-up; "
          f"kinfly-ground RSS {gr['start_mb']:.1f} -> {gr['end_mb']:.1f} MB (max "
          f"{gr['max_mb']:.1f}), {gr['growth_after_warm_up_mb']:+.1f} MB after the warm-up; "
          f"map {report['ground_allowance']['map_blocks']} blocks")
    for name, ok, detail in criteria:
        print(f"  {'ok  ' if ok else 'FAIL'} {name}: {detail}")
    print(f"soak: report in {out / 'soak.json'}")
    if not report["ok"]:
        print("soak: FAILED: " + "; ".join(n for n, ok, _ in criteria if not ok),
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
