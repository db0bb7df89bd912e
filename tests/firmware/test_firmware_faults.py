"""kinfly-fw under the faults of a real flight, the real binary each time: corrupt and empty
frames, a sensor that stops delivering, odometry slower than the sensor, a ground station that
goes away and comes back, a network that goes down; and, in steady state, no heap allocation per
frame and no memory growth. Each fault is counted (summary line, drone_status_t), logged, and the
program keeps flying."""
from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import lcm
from netns import MULTICAST_ROUTE

from conftest import REPO_ROOT, built
from demo import Watched
from firmware_run import allocations_by_thread, firmware, summary
from kinfly import depth_keyframe_t

SAMPLE_FRAMES = 60
VEHICLE = 7
GROUND_PROBE = REPO_ROOT / "tests" / "tools" / "ground_probe.py"
# A gap in the recording well over the default 1 s stall timeout, short enough for a quick test.
GAP_S = 2.5
# The odometry takes ~5-8 ms a frame: at 20 times the 30 Hz of the recording (1.7 ms a frame)
# it cannot keep up, whatever the machine's load.
OVERLOAD_SPEED = 20
# The longest wait for something the drone is expected to say (a loaded machine is slow).
EVENT_TIMEOUT_S = 60.0
# Longer than the drone's 2 s link timeout (link.timeout_s), with a second to spare.
GROUND_AWAY_S = 3.0
# 8 s at 15 frames a second: the network goes and comes back within it.
NETWORK_FLIGHT_FRAMES = 120
# Resident memory may move by allocator noise, not by the length of the flight.
RSS_GROWTH_TOLERANCE_KB = 1024


def rewrite_log(source: Path, target: Path, change) -> None:
    """Copies an LCM log event by event; change(index, event) returns the bytes to write for a
    depth event (None drops it), index counting depth events from 0."""
    out = lcm.EventLog(str(target), "w", overwrite=True)
    index = 0
    for event in lcm.EventLog(str(source), "r"):
        data, timestamp = event.data, event.timestamp
        if event.channel.endswith("_DEPTH"):
            result = change(index, event)
            index += 1
            if result is None:
                continue
            data, timestamp = result
        out.write_event(timestamp, event.channel, data)
    out.close()


def test_corrupt_and_empty_frames_are_counted_and_the_flight_goes_on(sample_log: Path,
                                                                     tmp_path: Path) -> None:
    corrupt = {10: "flipped", 20: "truncated", 30: "empty"}

    def change(index: int, event: lcm.Event) -> tuple[bytes, int]:
        kind = corrupt.get(index)
        if kind == "flipped":  # the compressed payload's bytes inverted: zstd refuses it
            head = len(event.data) - 2000
            return event.data[:head] + bytes(b ^ 0xFF for b in event.data[head:]), event.timestamp
        if kind == "truncated":
            return event.data[: len(event.data) // 2], event.timestamp
        if kind == "empty":  # a well-formed frame without one valid pixel
            m = depth_keyframe_t.decode(event.data)
            m.encoding = depth_keyframe_t.ENCODING_RAW16
            m.payload = bytes(2 * m.camera.width * m.camera.height)
            m.payload_size = len(m.payload)
            return m.encode(), event.timestamp
        return event.data, event.timestamp

    log = tmp_path / "faulty.lcmlog"
    rewrite_log(sample_log, log, change)
    run = subprocess.run(firmware("--source.path", log, "--source.realtime", "false"),
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    counts = summary(run.stdout)
    assert counts.skipped == 2, run.stdout
    assert counts.captured == counts.processed == SAMPLE_FRAMES - 2
    assert counts.lost >= 1  # the empty frame, and none crashed the odometry
    assert "frame skipped" in run.stderr and "lost" in run.stderr


def test_a_sensor_that_stops_delivering_is_reported_as_a_stall(sample_log: Path,
                                                               tmp_path: Path) -> None:
    gap_us = int(GAP_S * 1e6)

    def change(index: int, event: lcm.Event) -> tuple[bytes, int]:
        if index < SAMPLE_FRAMES // 2:
            return event.data, event.timestamp
        m = depth_keyframe_t.decode(event.data)
        m.utime += gap_us
        return m.encode(), event.timestamp + gap_us

    log = tmp_path / "gap.lcmlog"
    rewrite_log(sample_log, log, change)
    run = subprocess.run(firmware("--source.path", log), capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 0, run.stderr
    counts = summary(run.stdout)
    assert counts.stalls == 1
    assert counts.captured == counts.processed == SAMPLE_FRAMES
    assert "no depth frame for" in run.stderr and "frames again after" in run.stderr


def test_odometry_slower_than_the_sensor_drops_the_oldest_frames(sample_log: Path) -> None:
    run = subprocess.run(firmware("--source.path", sample_log, "--source.speed", OVERLOAD_SPEED),
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    counts = summary(run.stdout)
    assert counts.captured == SAMPLE_FRAMES
    assert counts.queue_drops > 0
    assert counts.processed + counts.queue_drops == counts.captured
    assert "oldest frame dropped" in run.stderr


def probe(netns: list[str], *args: object) -> list[str]:
    return [*netns, sys.executable, str(GROUND_PROBE), "--vehicle", str(VEHICLE),
            *map(str, args)]


def test_ground_station_gone_and_restarted(netns: list[str], tmp_path: Path) -> None:
    """The drone sees the ground station up, then stale when it goes quiet, then up again when a
    restarted one (a new process, a new signer) is heard, and applies that one's correction;
    keyframes go out all along, heard or not."""
    key = tmp_path / "v7.key"
    subprocess.run([built("bin/kinfly-keygen"), "--out", key], check=True, capture_output=True)
    drone = Watched(
        [*netns, *firmware("--vehicle.id", VEHICLE, "--source.kind", "synthetic",
                           "--source.max_frames", 300, key_file=str(key), lcm_url=None)])
    watcher = subprocess.Popen(probe(netns, "watch", "--seconds", 9), stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    try:
        assert drone.wait_for("link: LCM started", 1, EVENT_TIMEOUT_S), drone.output()
        subprocess.run(probe(netns, "beacon", "--seconds", 1.5), check=True, timeout=30)
        # The scenario itself, not a wait for something: the ground station stays away for
        # longer than the drone's 2 s link timeout.
        time.sleep(GROUND_AWAY_S)
        subprocess.run(probe(netns, "beacon", "--seconds", 1.5, "--key", key, "--correct", 3),
                       check=True, timeout=30)
        timeline = json.loads(watcher.communicate(timeout=30)[0])
        rc = drone.finish(30)
    finally:
        drone.process.kill()
        watcher.kill()
    assert rc == 0, drone.output()
    drone_out = drone.output()
    states = [s["link_state"] for s in timeline]
    # 0 unknown, 1 up, 2 stale: up, then stale, then up again.
    first_up = states.index(1)
    stale = states.index(2, first_up)
    assert 1 in states[stale:], states
    during_silence = [s for s in timeline if s["link_state"] == 2]
    assert during_silence[-1]["keyframes_sent"] > during_silence[0]["keyframes_sent"]
    assert timeline[-1]["corrections_accepted"] == 1
    assert timeline[-1]["rejected_replayed"] == 0 and timeline[-1]["rejected_stale"] == 0
    assert summary(drone_out).applied == 1


def route(netns: list[str], action: str) -> None:
    """Adds or deletes the namespace's multicast route, as Wi-Fi coming up or going away does."""
    subprocess.run([*netns, "ip", "route", action, MULTICAST_ROUTE, "dev", "lo"], check=True)


def synthetic_flight(netns: list[str]) -> Watched:
    """kinfly-fw on the synthetic source at half its real-time rate (15 frames a second): room
    for the odometry on a loaded machine, so that every frame it misses is the network's doing."""
    return Watched([*netns, *firmware("--vehicle.id", VEHICLE, "--source.kind", "synthetic",
                                      "--source.speed", 0.5,
                                      "--source.max_frames", NETWORK_FLIGHT_FRAMES,
                                      lcm_url=None)])


def check_flown_through(drone: Watched) -> None:
    """The flight ended as flights do, its odometry flew every frame, and keyframes were both
    dropped (while the network was away) and sent (once it was there)."""
    assert drone.finish(EVENT_TIMEOUT_S) == 0, drone.output()
    counts = summary(drone.output())
    assert counts.captured == counts.processed == NETWORK_FLIGHT_FRAMES
    assert counts.keyframes_dropped > 0 and counts.keyframes_sent > 0


def test_network_down_costs_keyframes_never_odometry(netns: list[str]) -> None:
    drone = synthetic_flight(netns)
    try:
        assert drone.wait_for("link: LCM started", 1, EVENT_TIMEOUT_S), drone.output()
        route(netns, "del")
        # Noticed at the next status (10 Hz); keyframes selected meanwhile are counted dropped.
        assert drone.wait_for("not sent: the network is down", 1, EVENT_TIMEOUT_S), \
            drone.output()
        route(netns, "add")
        assert drone.wait_for("link: the network is back", 1, EVENT_TIMEOUT_S), drone.output()
        check_flown_through(drone)
    finally:
        drone.process.kill()


def test_starts_without_a_network_and_links_once_it_is_there(netns: list[str]) -> None:
    """A drone that boots before its Wi-Fi (no multicast route at all): kinfly-fw starts, flies
    its odometry, drops its keyframes (counted), and starts LCM as soon as the route is there;
    then its status reaches a listener. Exit 2 stays for configuration errors."""
    route(netns, "del")
    drone = synthetic_flight(netns)
    try:
        assert drone.wait_for("link: no route to the multicast group", 1, EVENT_TIMEOUT_S), \
            drone.output()
        # Not necessarily keyframe 0: on a busy machine the link may take two queued keyframes
        # at once and skip the older for the newer (counted as skipped).
        assert drone.wait_for("not sent: the network is down", 1, EVENT_TIMEOUT_S), \
            drone.output()
        assert drone.process.poll() is None, drone.output()
        route(netns, "add")
        assert drone.wait_for("link: LCM started", 1, EVENT_TIMEOUT_S), drone.output()
        watch = subprocess.run(probe(netns, "watch", "--seconds", 1.0), capture_output=True,
                               text=True, timeout=60)
        check_flown_through(drone)
    finally:
        drone.process.kill()
    heard = json.loads(watch.stdout)
    assert heard and heard[-1]["keyframes_dropped"] > 0, watch.stderr


def allocations_in_flight(netns: list[str], counter: Path, report: Path,
                          frames: int) -> dict[str, int]:
    report.unlink(missing_ok=True)
    run = subprocess.run(
        [*netns, "env", f"LD_PRELOAD={counter}", f"KINFLY_ALLOC_REPORT={report}",
         *firmware("--source.kind", "synthetic", "--source.realtime", "false",
                   "--source.max_frames", frames, lcm_url=None)],
        capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert summary(run.stdout).processed == frames
    return allocations_by_thread(report)


def test_no_heap_allocation_per_frame_in_steady_state(netns: list[str], tmp_path: Path) -> None:
    """The same flight, 90 and 240 frames long, with every malloc counted by thread: kinfly-fw's
    own threads allocate at start-up only, so the counts do not grow with the flight. (LCM's
    receive thread, which reassembles the drone's own looped-back keyframes, is LCM's.)"""
    counter = built("tests/libkinfly_alloc_counter.so")
    short = allocations_in_flight(netns, counter, tmp_path / "short.txt", 90)
    long = allocations_in_flight(netns, counter, tmp_path / "long.txt", 240)
    for thread in ("kfw-capture", "kfw-odometry", "kfw-link"):
        assert thread in short, short
        assert long[thread] == short[thread], (thread, short, long)
    # The counter sees allocations at all: start-up makes plenty.
    assert short["kfw-odometry"] > 0 and short["kinfly-fw"] > 100


def test_memory_stays_flat_over_a_long_flight() -> None:
    """Resident memory sampled through a 600-frame flight: after the first quarter (buffers
    touched, volume filled) it does not grow with the flight."""
    process = subprocess.Popen(firmware("--source.kind", "synthetic", "--source.realtime",
                                        "false", "--source.max_frames", 600),
                               stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    samples: list[int] = []

    def sample() -> None:
        status = Path(f"/proc/{process.pid}/status")
        while process.poll() is None:
            try:
                for line in status.read_text().splitlines():
                    if line.startswith("VmRSS:"):
                        samples.append(int(line.split()[1]))
            except (FileNotFoundError, ProcessLookupError):
                break
            time.sleep(0.05)

    sampler = threading.Thread(target=sample)
    sampler.start()
    out, _ = process.communicate(timeout=300)
    sampler.join()
    assert process.returncode == 0
    assert summary(out).processed == 600
    assert len(samples) > 20, "too few samples to judge"
    quarter = len(samples) // 4
    settled, end = max(samples[quarter: 2 * quarter]), max(samples[3 * quarter:])
    assert end - settled <= RSS_GROWTH_TOLERANCE_KB, (settled, end)
