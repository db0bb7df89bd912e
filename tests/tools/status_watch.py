"""Both ends' health as a soak run sees it (tests/system/soak.py), run inside the flight's network
namespace beside kinfly-fw and kinfly-ground:

    status_watch.py [--vehicle 1] [--period 1.0] [--lcm-url URL]

listens to the drone's drone_status_t and the ground's ground_status_t of one vehicle and prints,
every PERIOD seconds, one JSON line: each side's latest counters and rates, and what a stall
would show, kept over the whole flight:
  - `longest_zero_s`: for each rate (drone: depth, odometry, keyframes; ground: keyframes
    received, fused, corrections), the longest time it was reported at zero while the drone was
    flying, counted from its first non-zero value (start-up is not a stall) until the drone's
    source ended or it sent its final status;
  - `longest_gap_s`: for each side, the longest time between two of its status messages (10 Hz)
    while the drone was flying: a status thread that stopped.
It says "watching" on stderr once it listens, and runs until SIGTERM or SIGINT. Its memory does
not grow with the flight."""
from __future__ import annotations

import argparse
import json
import select
import signal
import sys
import time
from typing import Any

import lcm

from kinfly import drone_status_t, ground_status_t
from kinfly_ground._native import Channel, channel_name

DRONE_RATES = ("depth_rate_hz", "odometry_rate_hz", "keyframe_rate_hz")
GROUND_RATES = ("keyframe_rate_hz", "fused_rate_hz", "correction_rate_hz")
DRONE_COUNTS = ("frames_captured", "queue_drops", "frames_lost", "keyframes_sent",
                "keyframes_dropped", "last_keyframe_id", "corrections_accepted", "sensor_state",
                "run_state")
GROUND_COUNTS = ("keyframes_received", "keyframes_skipped", "keyframes_dropped", "keyframes_lost",
                 "corrections_sent", "last_keyframe_id", "run_state")


class Side:
    """One end's latest status and its stall figures."""

    def __init__(self, rates: tuple[str, ...], counts: tuple[str, ...]) -> None:
        self.rates, self.counts = rates, counts
        self.latest: dict[str, float] = {}
        self.heard_s: float | None = None
        self.longest_gap_s = 0.0
        self.seen_nonzero: set[str] = set()
        self.zero_since: dict[str, float] = {}
        self.longest_zero_s = {name: 0.0 for name in rates}

    def heard(self, message: Any, now_s: float, flying: bool) -> None:
        if flying and self.heard_s is not None:
            self.longest_gap_s = max(self.longest_gap_s, now_s - self.heard_s)
        self.heard_s = now_s
        self.latest = {name: getattr(message, name) for name in (*self.rates, *self.counts)}
        for name in self.rates:
            value = getattr(message, name)
            if value > 0:
                self.seen_nonzero.add(name)
                self.zero_since.pop(name, None)
            elif flying and name in self.seen_nonzero:
                since = self.zero_since.setdefault(name, now_s)
                self.longest_zero_s[name] = max(self.longest_zero_s[name], now_s - since)
            if not flying:
                self.zero_since.pop(name, None)

    def report(self) -> dict[str, Any]:
        return {**self.latest, "longest_zero_s": {k: round(v, 3)
                                                  for k, v in self.longest_zero_s.items()},
                "longest_gap_s": round(self.longest_gap_s, 3)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--vehicle", type=int, default=1)
    parser.add_argument("--period", type=float, default=1.0, metavar="S",
                        help="seconds between two printed lines (default 1)")
    parser.add_argument("--lcm-url", default="", help="LCM URL (default: LCM's)")
    args = parser.parse_args()
    stopping: list[bool] = []
    signal.signal(signal.SIGTERM, lambda *_: stopping.append(True))
    signal.signal(signal.SIGINT, lambda *_: stopping.append(True))
    drone = Side(DRONE_RATES, DRONE_COUNTS)
    ground = Side(GROUND_RATES, GROUND_COUNTS)
    # The drone flies from its first captured frame until its source ends or it stops.
    flying = [False]
    started = time.monotonic()

    def on_drone(_channel: str, data: bytes) -> None:
        s = drone_status_t.decode(data)
        flying[0] = (s.frames_captured > 0 and s.run_state == drone_status_t.RUN_ACTIVE
                     and s.sensor_state != drone_status_t.SENSOR_ENDED)
        drone.heard(s, time.monotonic(), flying[0])

    def on_ground(_channel: str, data: bytes) -> None:
        ground.heard(ground_status_t.decode(data), time.monotonic(), flying[0])

    lc = lcm.LCM(args.lcm_url)
    lc.subscribe(channel_name(Channel.STATUS, args.vehicle), on_drone)
    lc.subscribe(channel_name(Channel.GROUND_STATUS, args.vehicle), on_ground)
    print("watching", file=sys.stderr, flush=True)
    next_print = time.monotonic()
    while not stopping:
        if select.select([lc.fileno()], [], [], 0.05)[0]:
            lc.handle()
        now = time.monotonic()
        if now >= next_print:
            next_print = now + args.period
            print(json.dumps({"t_s": round(now - started, 3), "flying": flying[0],
                              "drone": drone.report(), "ground": ground.report()}), flush=True)
    print(json.dumps({"t_s": round(time.monotonic() - started, 3), "flying": flying[0],
                      "drone": drone.report(), "ground": ground.report()}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
