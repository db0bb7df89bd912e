"""A stand-in ground station for the firmware tests that run kinfly-fw in a network namespace
(tests/firmware/test_firmware_faults.py, test_openni.py), run inside the same namespace. Two
roles:

    ground_probe.py beacon --seconds S [--key KEY --correct KEYFRAME]
        sends the ground station's status at 10 Hz for S seconds, as a ground station that is
        up; with --key, first one signed correction of KEYFRAME (a fresh Signer, as a
        restarted ground station has).
    ground_probe.py watch [--seconds S] [--until-sensor STATE:CONNECTS]
        records the drone's drone_status_t for S seconds (without --seconds: until SIGTERM, or until
        a status reports that sensor_state and sensor_connects, and with --until-frame until the
        odometry of that capture or a later one was heard too) and prints one JSON list, each
        status with every field and t_s, the seconds since the watch began; exit 1 if none was
        heard. It says "watching" on stderr once it listens.
"""
from __future__ import annotations

import argparse
import json
import select
import signal
import sys
import time

import lcm

from kinfly import drone_status_t, ground_status_t, odometry_t
from kinfly_ground._native import Channel, Signer, channel_name, load_key_file
from uplink_probe import signed

STATUS_PERIOD_S = 0.1
DRAIN_S = 0.2  # after a stop: what LCM had taken in by then is handled within this


def beacon(lc: lcm.LCM, vehicle: int, seconds: float, key: str | None, keyframe: int) -> None:
    if key is not None:
        signer = Signer(load_key_file(key), vehicle)
        lc.publish(channel_name(Channel.CORRECTION, vehicle), signed(signer, keyframe))
    status = ground_status_t()
    status.vehicle_id, status.last_keyframe_id = vehicle, -1
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        status.utime = time.time_ns() // 1000
        lc.publish(channel_name(Channel.GROUND_STATUS, vehicle), status.encode())
        time.sleep(STATUS_PERIOD_S)


def watch(lc: lcm.LCM, vehicle: int, seconds: float | None,
          until_sensor: tuple[int, int] | None, until_frame: int | None = None,
          ) -> list[dict[str, float]]:
    start = time.monotonic()
    timeline: list[dict[str, float]] = []
    stopping: list[bool] = []
    signal.signal(signal.SIGTERM, lambda *_: stopping.append(True))
    sensor_seen = until_sensor is None
    frame_seen = until_frame is None

    def on_status(_channel: str, data: bytes) -> None:
        nonlocal sensor_seen
        s = drone_status_t.decode(data)
        timeline.append({"t_s": round(time.monotonic() - start, 3),
                         **{field: getattr(s, field) for field in drone_status_t.__slots__}})
        sensor_seen = sensor_seen or (s.sensor_state, s.sensor_connects) == until_sensor
        if until_sensor is not None and sensor_seen and frame_seen:
            stopping.append(True)

    def on_odometry(_channel: str, data: bytes) -> None:
        nonlocal frame_seen
        frame_seen = frame_seen or odometry_t.decode(data).frame_id >= until_frame
        if sensor_seen and frame_seen:
            stopping.append(True)

    if until_frame is not None:
        lc.subscribe(channel_name(Channel.ODOMETRY, vehicle), on_odometry)

    lc.subscribe(channel_name(Channel.STATUS, vehicle), on_status)
    print("watching", file=sys.stderr, flush=True)
    while not stopping and (seconds is None or time.monotonic() - start < seconds):
        ready, _, _ = select.select([lc.fileno()], [], [], 0.05)
        if ready:
            lc.handle()
    # What had arrived when told to stop (a drone's last status, sent as it exited) still counts.
    drained = time.monotonic() + DRAIN_S
    while select.select([lc.fileno()], [], [], max(0.0, drained - time.monotonic()))[0]:
        lc.handle()
    return timeline


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("role", choices=("beacon", "watch"))
    parser.add_argument("--vehicle", type=int, default=7)
    parser.add_argument("--seconds", type=float,
                        help="how long to beacon or watch (watch: until SIGTERM without it)")
    parser.add_argument("--until-sensor", metavar="STATE:CONNECTS",
                        type=lambda v: tuple(int(x) for x in v.split(":")),
                        help="watch: stop once a status reports this sensor_state and "
                             "sensor_connects")
    parser.add_argument("--until-frame", type=int, metavar="FRAME_ID",
                        help="watch, with --until-sensor: and once the odometry of this capture "
                             "(odometry_t.frame_id) or a later one was heard")
    parser.add_argument("--key", help="beacon: send one signed correction with this key first")
    parser.add_argument("--correct", type=int, default=0, help="beacon: the keyframe corrected")
    args = parser.parse_args()
    lc = lcm.LCM()
    if args.role == "beacon":
        if args.seconds is None:
            parser.error("beacon needs --seconds")
        beacon(lc, args.vehicle, args.seconds, args.key, args.correct)
        return 0
    timeline = watch(lc, args.vehicle, args.seconds, args.until_sensor, args.until_frame)
    print(json.dumps(timeline))
    return 0 if timeline else 1


if __name__ == "__main__":
    sys.exit(main())
