"""Running the real kinfly-fw in tests: its command line with the shipped configuration, and its
summary line read back into numbers."""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[2]
CONFIG = REPO_ROOT / "firmware" / "config" / "kinfly-fw.toml"
BINARY = REPO_ROOT / "build" / "bin" / "kinfly-fw"

_SUMMARY = re.compile(
    r"kinfly-fw: (?P<how>stopped|source ended): (?P<captured>\d+) frames captured, "
    r"(?P<processed>\d+) processed \((?P<lost>\d+) lost, (?P<weak>\d+) in degenerate geometry; "
    r"tracking back (?P<recoveries>\d+) times \((?P<relocalisations>\d+) relocalised, "
    r"(?P<new_maps>\d+) in a new map\), after (?P<longest_loss>\d+) lost frames at most\), "
    r"(?P<queue_drops>\d+) dropped by the "
    r"queue, (?P<skipped>\d+) skipped; sensor opened (?P<connects>\d+) times, stalled "
    r"(?P<stalls>\d+) times; (?P<keyframes_sent>\d+) keyframes sent, (?P<keyframes_dropped>\d+) "
    r"dropped; (?P<applied>\d+) corrections applied, (?P<rejected>\d+) rejected, "
    r"(?P<unknown>\d+) for unknown keyframes")


def firmware(*args: object, binary: Path = BINARY, key_file: str = "",
             lcm_url: str | None = "memq://") -> list[str]:
    """kinfly-fw with the shipped defaults, no key, LCM in memory unless told otherwise; later
    arguments override earlier ones."""
    command = [str(binary), "--config", str(CONFIG), "--vehicle.key_file", key_file]
    if lcm_url is not None:
        command += ["--link.lcm_url", lcm_url]
    return command + [str(a) for a in args]


@dataclass
class Summary:
    how: str
    captured: int
    processed: int
    lost: int
    weak: int  # tracked with weak directions
    recoveries: int  # tracked again after lost frames
    relocalisations: int  # of those, from a keyframe's pose
    new_maps: int  # of those, in a new map (every try had failed)
    longest_loss: int  # the most frames lost before one of those
    queue_drops: int
    skipped: int
    connects: int
    stalls: int
    keyframes_sent: int
    keyframes_dropped: int
    applied: int
    rejected: int
    unknown: int


def parse_summary(output: str) -> Summary | None:
    """The counts of kinfly-fw's summary line in OUTPUT; None if there is none."""
    match = _SUMMARY.search(output)
    if match is None:
        return None
    values = match.groupdict()
    how = values.pop("how")
    return Summary(how, **{k: int(v) for k, v in values.items()})


def summary(stdout: str) -> Summary:
    """The counts of kinfly-fw's last line; fails the test if there is none."""
    counts = parse_summary(stdout)
    assert counts is not None, f"no summary line in {stdout!r}"
    return counts


def allocations_by_thread(report: Path) -> dict[str, int]:
    """What the allocation counter (tests/tools/alloc_counter.c, KINFLY_ALLOC_REPORT) wrote:
    malloc-family calls per thread name, threads of one name added up."""
    counts: dict[str, int] = {}
    for line in report.read_text().splitlines():
        name, count = line.rsplit(" ", 1)
        counts[name] = counts.get(name, 0) + int(count)
    return counts


def read_tum(path: Path) -> np.ndarray:
    return np.loadtxt(path, comments="#").reshape(-1, 8)


_CONTROL = re.compile(
    r"kinfly-fw: control: (?P<imu_samples>\d+) IMU samples \((?P<imu_rejected>\d+) rejected\), "
    r"(?P<ticks>\d+) ticks \((?P<silent_ticks>\d+) without a new sample\); (?P<poses_fused>\d+) "
    r"poses fused \((?P<poses_late>\d+) after their lockstep age\), (?P<poses_rejected>\d+) "
    r"rejected, (?P<pose_resets>\d+) resets to a pose, "
    r"(?P<resets>\d+) resets \((?P<resets_rejected>\d+) "
    r"before the start\); (?P<baro_fused>\d+) barometer readings fused "
    r"\((?P<baro_rejected>\d+) gated\); estimator (?P<estimator>started|not "
    r"started); mode (?P<mode>[a-z -]+), (?P<mode_changes>\d+) mode changes, "
    r"(?P<commands_accepted>\d+) commands accepted, (?P<commands_refused>\d+) refused; "
    r"failsafes: (?P<vision_lost>\d+) vision lost, (?P<estimator_diverged>\d+) estimator "
    r"diverged, (?P<attitude_limit>\d+) attitude limit, (?P<imu_lost>\d+) IMU lost, "
    r"(?P<geofence>\d+) geofence; (?P<sent>\d+) rotor commands sent, (?P<unsent>\d+) not; "
    r"(?P<passed>\d+) signed commands passed by the link, (?P<dropped>\d+) dropped, "
    r"(?P<repeated>\d+) repeats ignored")


_MAVLINK = re.compile(
    r"kinfly-fw: mavlink: (?P<heartbeats>\d+) heartbeats, (?P<imu_samples>\d+) IMU samples "
    r"\((?P<imu_rejected>\d+) rejected\), (?P<attitudes>\d+) attitudes \(tilt against the "
    r"estimate at most (?P<max_tilt_deg>[\d.]+) deg\); (?P<setpoints>\d+) setpoints and "
    r"(?P<poses>\d+) poses sent, (?P<unsent>\d+) not; (?P<mode_requests>\d+) mode, "
    r"(?P<arm_requests>\d+) arm and (?P<disarm_requests>\d+) disarm requests, "
    r"(?P<accepted>\d+) accepted, (?P<refused>\d+) refused; (?P<bad_signature>\d+) bad "
    r"signatures, (?P<bad_crc>\d+) bad CRC, (?P<other_source>\d+) from other sources; lost "
    r"(?P<lost>\d+) times; (?P<port_errors>\d+) port errors")


def mavlink_summary(stdout: str) -> dict[str, float]:
    """The counts of kinfly-fw's mavlink line (flight.backend = mavlink); fails the test if
    there is none."""
    match = _MAVLINK.search(stdout)
    assert match is not None, f"no mavlink summary line in {stdout!r}"
    return {k: float(v) for k, v in match.groupdict().items()}


def control_summary(stdout: str) -> dict[str, int | str]:
    """The counts of kinfly-fw's control line (flight.backend other than none), the estimator's
    and the mode's words as strings; fails the test if there is none."""
    match = _CONTROL.search(stdout)
    assert match is not None, f"no control summary line in {stdout!r}"
    return {k: v if k in ("estimator", "mode") else int(v) for k, v in match.groupdict().items()}
