"""kinfly-fw's OpenNI2 source against the real OpenNI2 library (Debian's libopenni2), on a machine
with no depth sensor:
- with nothing attached it starts, says there is no depth sensor, retries with doubling
  intervals up to the configured ceiling, reports SENSOR_WAITING in its status, and stops on
  SIGTERM within a second;
- OpenNI2's own test device ("Dummy") streams through it with the device's timestamps;
- a sensor that is unplugged and plugged back (the TUM feed driver standing in for one) is
  reconnected with backoff, at once when it announces itself, and counted;
- a real TUM sequence, recorded into an .oni file by the stock openni::Recorder (through the TUM
  feed driver in tests/tools/oni/, since no sensor can make one here), replays through OpenNI2's
  file driver frame for frame and gives the trajectory the LCM log replay of the same frames gives;
- recordings that are missing, unreadable, or whose frames the file driver will not replay are
  reported as such."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO_ROOT, built
from firmware_run import firmware as firmware_command
from firmware_run import read_tum

GROUND_PROBE = REPO_ROOT / "tests" / "tools" / "ground_probe.py"
VEHICLE = 1
# drone_status_t.SENSOR_* (proto/kinfly/drone_status_t.lcm)
SENSOR_STREAMING, SENSOR_WAITING = 0, 1
# The TUM sample's camera (freiburg3), as the log replay uses it.
TUM_INTRINSICS = "535.4,539.2,320.1,247.6"

# Short retry intervals so the test sees the doubling and the ceiling within two seconds.
RETRY_MIN_S, RETRY_MAX_S = 0.1, 0.4
# A retry starts when it is due, give or take the wake-up of a thread on a busy two-core machine
# (1-2 ms measured when idle).
RETRY_LATE_S = 0.1
# spdlog stamps its lines to the millisecond, truncated: an interval read from two stamps can
# come out up to this much short.
LOG_STAMP_S = 0.002
STOP_WITHIN_S = 1.0
# OpenNI2's Dummy device stamps frame k at k * 33 ms.
DUMMY_FRAME_S = 0.033
# Trajectory files print times of ~1.8e9 s with 6 decimals, in doubles: differences of stamps
# survive to well under this.
TIMESTAMP_S = 2e-6
# The recording holds the sample's depth rounded to whole millimetres (TUM stores 0.2 mm units),
# so every depth differs from the log replay's by at most 0.4 mm; each pose is fitted to thousands
# of such pixels and moves far less (0.07 mm and 0.1 mrad measured over the 60 frames).
QUANTISATION_POSITION_M = 1e-3
QUANTISATION_ROTATION_RAD = 1e-3
# The feed is unplugged after 30 frames (1 s) and back 1.2 s later; retries come 0.3 s, then
# 0.6 s apart, so the scheduled attempts (0, 0.3, 0.9, 1.5 s after the unplug is noticed) miss
# the replug and only the plug-in notice reconnects within RETRY_LATE_S of it.
UNPLUG_AFTER_FRAMES, AWAY_S = 30, 1.2
REPLUG_RETRY_MIN_S, REPLUG_RETRY_MAX_S = 0.3, 0.6
# The source reads with this timeout, so it notices an unplug at most this late, on a machine
# that runs its capture thread at once.
READ_TIMEOUT_S = 0.1
# A machine busy with other work runs the capture thread later than that: with two busy loops
# beside the tests it noticed the unplug 0.19 s after the feed pulled the cable.
NOTICE_LATE_S = 0.5
# A log line awaited longer than this will not come: kinfly-fw is killed and the test fails.
LOG_WAIT_S = 30.0

LOG_LINE = re.compile(r"^\[(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3})\] \[kinfly-fw\] \[(\w+)\] (.*)$")


def firmware(*args: object, lcm_url: str | None = "memq://") -> list[str]:
    """kinfly-fw on the OpenNI2 source, with the shipped configuration and the given overrides."""
    return firmware_command("--source.kind", "openni", *args, binary=built("bin/kinfly-fw"),
                            lcm_url=lcm_url)


def read_until(process: subprocess.Popen, text: str, lines: list[str]) -> None:
    """Reads stderr into lines until one contains text (killing the process after LOG_WAIT_S,
    which ends the read)."""
    assert process.stderr is not None
    killer = threading.Timer(LOG_WAIT_S, process.kill)
    killer.start()
    try:
        for line in process.stderr:
            lines.append(line.rstrip("\n"))
            if text in line:
                return
    finally:
        killer.cancel()
    pytest.fail(f"kinfly-fw did not log {text!r}:\n" + "\n".join(lines))


def statuses(netns: list[str], seconds: float) -> list[dict]:
    probe = subprocess.run([*netns, sys.executable, GROUND_PROBE, "watch", "--vehicle",
                            str(VEHICLE), "--seconds", str(seconds)],
                           capture_output=True, text=True, timeout=seconds + 30)
    assert probe.returncode == 0, "no drone_status_t from kinfly-fw: " + probe.stderr
    return json.loads(probe.stdout)


def stop(process: subprocess.Popen, lines: list[str]) -> tuple[str, float]:
    """SIGTERM; returns stdout and the seconds until the process was gone."""
    sent = time.monotonic()
    process.send_signal(signal.SIGTERM)
    out, err = process.communicate(timeout=10)
    elapsed = time.monotonic() - sent
    lines.extend(err.splitlines())
    return out, elapsed


def rotation_between_rad(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """Angle of q_a^-1 q_b per row (xyzw), from the vector part, which stays accurate for the tiny
    angles compared here where arccos of the scalar part does not."""
    x1, y1, z1, w1 = -q_a[:, 0], -q_a[:, 1], -q_a[:, 2], q_a[:, 3]
    x2, y2, z2, w2 = q_b.T
    w = w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2
    v = np.stack([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                  w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                  w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=1)
    return 2 * np.arctan2(np.linalg.norm(v, axis=1), np.abs(w))


def test_no_sensor_waits_retries_with_backoff_and_stops_on_sigterm(netns: list[str]) -> None:
    process = subprocess.Popen(
        [*netns, *firmware("--source.path", "", "--source.reconnect_min_s", RETRY_MIN_S,
                           "--source.reconnect_max_s", RETRY_MAX_S, lcm_url=None)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    try:
        # From the first failed attempt on the source says it is waiting, so every status the
        # probe hears after it must say so.
        read_until(process, "attempt 1 failed", lines)
        heard = statuses(netns, seconds=2.0)
        assert process.poll() is None, "kinfly-fw gave up without a sensor"
        out, elapsed = stop(process, lines)
    finally:
        process.kill()
    log = "\n".join(lines)

    assert elapsed < STOP_WITHIN_S, elapsed
    assert process.returncode == 0, log
    assert out.startswith("kinfly-fw: stopped: 0 frames captured"), out
    assert "sensor opened 0 times" in out, out
    # The real library was loaded and started.
    version = re.search(r"openni: OpenNI2 (\d+)\.\d+\.\d+\.\d+ initialised", log)
    assert version and version.group(1) == "2", log

    attempts = []
    for line in lines:
        match = LOG_LINE.match(line)
        said = match and re.fullmatch(
            r"capture: no depth sensor: OpenNI2 lists none \(supported sensors on USB: \w+\); "
            r"attempt (\d+) failed, retrying in ([\d.]+) s", match.group(3))
        if said:
            stamp = datetime.strptime(match.group(1), "%Y-%m-%d %H:%M:%S.%f").timestamp()
            attempts.append((int(said.group(1)), float(said.group(2)), stamp))
    assert [n for n, _, _ in attempts] == list(range(1, len(attempts) + 1)), log
    # 0.1 + 0.2 + 0.4 s to the ceiling, then every 0.4 s: at least two retries at the ceiling.
    assert len(attempts) >= 5, log
    promised = [wait_s for _, wait_s, _ in attempts]
    assert promised == [min(RETRY_MIN_S * 2 ** k, RETRY_MAX_S) for k in range(len(attempts))]
    for (_, wait_s, at), (_, _, next_at) in zip(attempts, attempts[1:]):
        assert wait_s - LOG_STAMP_S <= next_at - at <= wait_s + RETRY_LATE_S, (wait_s, log)

    assert len(heard) >= 10, heard  # 10 Hz for 2 s
    assert all(s["sensor_state"] == SENSOR_WAITING for s in heard), heard
    assert all(s["sensor_connects"] == 0 and s["frames_captured"] == 0 for s in heard), heard


def test_dummy_device_streams_with_its_own_timestamps(netns: list[str], tmp_path: Path) -> None:
    trajectory = tmp_path / "dummy.tum"
    process = subprocess.Popen(
        [*netns, *firmware("--source.path", "Dummy", "--source.width", 320, "--source.height", 240,
                           "--odometry.downsample", 1, "--output.trajectory", trajectory,
                           lcm_url=None)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    try:
        read_until(process, "openni: Dummy streaming 320x240 depth (connection 1)", lines)
        heard = statuses(netns, seconds=1.5)
        out, elapsed = stop(process, lines)
    finally:
        process.kill()
    log = "\n".join(lines)

    assert elapsed < STOP_WITHIN_S, elapsed
    assert process.returncode == 0, log
    assert "sensor opened 1 times" in out, out
    captured = int(re.search(r"(\d+) frames captured", out).group(1))
    assert captured > 0, out
    assert heard and all(s["sensor_state"] == SENSOR_STREAMING and s["sensor_connects"] == 1
                         for s in heard), heard
    assert heard[-1]["frames_captured"] > 0, heard

    # The scene is nearly empty, so tracking is lost; every frame still has its pose written,
    # stamped with the device's clock: exact multiples of 33 ms apart (host times would jitter),
    # mostly one frame period (the odometry keeps up with these frames).
    times = read_tum(trajectory)[:, 0]
    assert len(times) > 1
    periods = np.diff(times) / DUMMY_FRAME_S
    assert np.all(np.abs(periods - np.round(periods)) * DUMMY_FRAME_S < TIMESTAMP_S), np.diff(times)
    assert np.all(np.round(periods) >= 1), np.diff(times)
    assert np.median(np.round(periods)) == 1, np.diff(times)


def test_unplugged_sensor_is_reconnected_and_counted(netns: list[str], sample_dir: Path,
                                                     tmp_path: Path) -> None:
    """kinfly-fw runs against the private OpenNI2 folder of tests/tools/oni (the system library
    and drivers plus the TUM feed), the feed streaming the sample live as a sensor would."""
    openni2 = built("tests/oni/kinfly-oni-record").parent / "openni2"
    uri = f"tumfeed://{sample_dir}?live&unplug_after={UNPLUG_AFTER_FRAMES}&away_s={AWAY_S}"
    trajectory = tmp_path / "replugged.tum"
    # Listening from before the drone starts (the first connection streams for only a second,
    # less than the listener takes to start on a loaded machine) until it has heard the second
    # connection streaming and the odometry of one of its frames (capture UNPLUG_AFTER_FRAMES is
    # its first): a pose on each side of the reconnection before the drone is stopped.
    probe = subprocess.Popen([*netns, sys.executable, GROUND_PROBE, "watch", "--vehicle",
                              str(VEHICLE), "--until-sensor", f"{SENSOR_STREAMING}:2",
                              "--until-frame", str(UNPLUG_AFTER_FRAMES)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             start_new_session=True)
    assert probe.stderr.readline().strip() == "watching"
    process = subprocess.Popen(
        [*netns, *firmware("--source.path", uri, "--source.intrinsics", TUM_INTRINSICS,
                           "--source.reconnect_min_s", REPLUG_RETRY_MIN_S,
                           "--source.reconnect_max_s", REPLUG_RETRY_MAX_S,
                           "--output.trajectory", trajectory, lcm_url=None)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "LD_LIBRARY_PATH": str(openni2)})
    lines: list[str] = []
    try:
        read_until(process, "streaming 640x480 depth (connection 1)", lines)
        read_until(process, "streaming 640x480 depth (connection 2)", lines)
        read_until(process, "delivering again", lines)
        probe_out, probe_err = probe.communicate(timeout=LOG_WAIT_S)
        out, elapsed = stop(process, lines)
    finally:
        process.kill()
        probe.kill()
    log = "\n".join(lines)
    assert elapsed < STOP_WITHIN_S, elapsed
    assert process.returncode == 0, log
    assert "sensor opened 2 times, stalled 0 times" in out, out

    stamps = {}
    for line in lines:
        match = LOG_LINE.match(line)
        if match:
            for key in ("depth sensor unplugged: closed, reconnecting", "(connection 2)"):
                if key in match.group(3):
                    stamps[key] = datetime.strptime(match.group(1),
                                                    "%Y-%m-%d %H:%M:%S.%f").timestamp()
    promised = [float(x) for x in re.findall(r"cannot open depth sensor tumfeed://.*attempt \d+ "
                                              r"failed, retrying in ([\d.]+) s", log)]
    assert promised[:2] == [REPLUG_RETRY_MIN_S, REPLUG_RETRY_MAX_S], log
    assert all(wait_s == REPLUG_RETRY_MAX_S for wait_s in promised[2:]), log
    away_s = stamps["(connection 2)"] - stamps["depth sensor unplugged: closed, reconnecting"]
    assert AWAY_S - READ_TIMEOUT_S - NOTICE_LATE_S - LOG_STAMP_S <= away_s, log
    assert away_s <= AWAY_S + RETRY_LATE_S, log

    assert probe.returncode == 0, probe_err
    heard = json.loads(probe_out)
    # Streaming on the first connection, waiting while unplugged, streaming on the second; heard
    # from before the start, where the first statuses may come before the first connection, or
    # after it opened and before its first frame (a first read that timed out on a busy machine
    # reads as waiting on connection 1: seen once in a CI run).
    phases = [(s["sensor_state"], s["sensor_connects"]) for s in heard]
    collapsed = [p for i, p in enumerate(phases) if i == 0 or p != phases[i - 1]]
    while collapsed and collapsed[0][0] == SENSOR_WAITING and collapsed[0][1] <= 1:
        collapsed = collapsed[1:]
    assert collapsed == [(SENSOR_STREAMING, 1), (SENSOR_WAITING, 1), (SENSOR_STREAMING, 2)], phases

    # Capture times go on increasing across the reconnection, though the device's own clock
    # started again: poses on both sides of the gap the unplug left. (On a loaded machine the
    # capture queue may drop some of the first connection's frames: their count is no measure.)
    times = read_tum(trajectory)[:, 0]
    assert len(times) >= 2 and np.all(np.diff(times) > 0), times
    # The largest step is the unplug's: without a pose after it, it would be a frame period.
    assert np.diff(times).max() >= AWAY_S - READ_TIMEOUT_S - NOTICE_LATE_S, times


@pytest.fixture(scope="module")
def sample_recording(sample_dir: Path, tmp_path_factory: pytest.TempPathFactory
                     ) -> tuple[Path, dict]:
    """The 60-frame TUM sample recorded into an .oni file through the TUM feed driver, and the
    recorder's report of its own replay check."""
    out = tmp_path_factory.mktemp("oni") / "teddy.oni"
    run = subprocess.run([built("tests/oni/kinfly-oni-record"), "--uri",
                          f"tumfeed://{sample_dir}", "--out", out],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    return out, json.loads(run.stdout)


def test_recorder_writes_every_sample_frame_bit_exact(sample_recording: tuple[Path, dict]
                                                      ) -> None:
    _, report = sample_recording
    assert report["sent"] == report["recorded"] == report["replayed"] == 60, report
    assert report["in_order"] is True and report["bit_exact"] is True, report
    # The recorder keeps the spacing of the device's times and starts them at 0: the sample's
    # first and last frames are 1.976008 s apart.
    assert report["first_us"] == 0 and report["last_us"] == 1_976_008, report


def test_recording_replays_every_frame_like_the_log_replay(
        sample_recording: tuple[Path, dict], sample_log: Path, tmp_path: Path) -> None:
    recording, _ = sample_recording
    from_oni, from_log = tmp_path / "oni.tum", tmp_path / "log.tum"
    run = subprocess.run(firmware("--source.path", recording, "--source.realtime", "false",
                                  "--source.intrinsics", TUM_INTRINSICS,
                                  "--output.trajectory", from_oni),
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("kinfly-fw: source ended: 60 frames captured, 60 processed "
                                 "(0 lost, 0 in degenerate geometry; tracking back 0 times (0 "
                                 "relocalised, 0 in a new map), after 0 lost frames at most), 0 "
                                 "dropped by the "
                                 "queue, "
                                 "0 skipped; sensor opened 1 times"), run.stdout
    assert "all 60 frames read" in run.stderr, run.stderr

    replay = subprocess.run(
        firmware_command("--source.path", sample_log, "--source.realtime", "false",
                         "--output.trajectory", from_log, binary=built("bin/kinfly-fw")),
        capture_output=True, text=True, timeout=120)
    assert replay.returncode == 0, replay.stderr

    oni, ref = read_tum(from_oni), read_tum(from_log)
    assert oni.shape == ref.shape == (60, 8)
    # The recorder restarts the clock at 0, so poses pair by frame order; the spacing of the
    # capture times is the sample's own.
    assert np.abs(np.diff(oni[:, 0]) - np.diff(ref[:, 0])).max() < TIMESTAMP_S
    assert np.linalg.norm(ref[-1, 1:4] - ref[0, 1:4]) > 100 * QUANTISATION_POSITION_M  # it moves
    assert np.linalg.norm(oni[:, 1:4] - ref[:, 1:4], axis=1).max() < QUANTISATION_POSITION_M
    assert rotation_between_rad(oni[:, 4:8], ref[:, 4:8]).max() < QUANTISATION_ROTATION_RAD


@pytest.mark.parametrize("name,content,message", [
    ("missing.oni", None, "recording {path} does not exist"),
    ("garbage.oni", b"not an OpenNI2 recording\n" * 100, "cannot open recording {path}"),
])
def test_unusable_recording_refuses_to_start(tmp_path: Path, name: str, content: bytes | None,
                                             message: str) -> None:
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    run = subprocess.run(firmware("--source.path", path), capture_output=True, text=True,
                         timeout=30)
    assert run.returncode == 2, run.stdout + run.stderr
    assert message.format(path=path) in run.stderr, run.stderr


def test_recording_the_file_driver_will_not_replay_is_reported(tmp_path: Path) -> None:
    """Recordings of a stream without the cropping property (OpenNI2's Dummy device has none)
    lose every frame in Debian's file driver: the recorder's check says so, and kinfly-fw ends the
    replay saying how many frames it got, and fails: a replay of nothing is not a flight."""
    recording = tmp_path / "dummy.oni"
    run = subprocess.run([built("tests/oni/kinfly-oni-record"), "--uri", "Dummy", "--out",
                          recording, "--frames", "10"],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 1, run.stdout + run.stderr
    report = json.loads(run.stdout)
    assert report["recorded"] >= 10 and report["replayed"] == 0, report
    assert "reports no cropping" in run.stderr, run.stderr
    assert f"replays 0 of its {report['recorded']} frames" in run.stderr, run.stderr

    replay = subprocess.run(firmware("--source.path", recording, "--source.width", 320,
                                     "--source.height", 240, "--source.realtime", "false"),
                            capture_output=True, text=True, timeout=60)
    assert replay.returncode == 1, replay.stderr
    assert replay.stdout.startswith("kinfly-fw: source ended: 0 frames captured"), replay.stdout
    assert "ended without delivering a frame" in replay.stderr, replay.stderr
    assert (f"recording {recording} stopped delivering after 0 of its {report['recorded']} "
            "frames") in replay.stderr, replay.stderr
