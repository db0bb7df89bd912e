"""A stand-in ground station for the firmware tests that run kinfly-fw in a network namespace
(tests/integration/test_firmware_faults.py, test_openni.py), run inside the same namespace. Two
roles:

    ground_probe.py beacon --seconds S [--key KEY --correct KEYFRAME]
        sends the ground station's status at 10 Hz for S seconds, as a ground station that is
        up; with --key, first one signed correction of KEYFRAME (a fresh Signer, as a
        restarted ground station has).
    ground_probe.py watch --seconds S
        records the drone's status_t for S seconds and prints one JSON list, each status with
        every field and t_s, the seconds since the watch began; exit 1 if none was heard.
"""
from __future__ import annotations

import argparse
import json
import select
import sys
import time

import lcm

from kinfly import status_t
from kinfly_ground import signing
from kinfly_ground.channels import Channel, channel_name
from kinfly_ground.conversions import decode
from uplink_probe import correction

STATUS_PERIOD_S = 0.1


def beacon(lc: lcm.LCM, vehicle: int, seconds: float, key: str | None, keyframe: int) -> None:
    if key is not None:
        signer = signing.Signer(signing.load_key_file(key), vehicle)
        lc.publish(channel_name(Channel.CORRECTION, vehicle),
                   signer.sign(correction(vehicle, keyframe)).encode())
    status = status_t()
    status.vehicle_id, status.source = vehicle, status_t.SOURCE_GROUND
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        status.utime = time.time_ns() // 1000
        lc.publish(channel_name(Channel.GROUND_STATUS, vehicle), status.encode())
        time.sleep(STATUS_PERIOD_S)


def watch(lc: lcm.LCM, vehicle: int, seconds: float) -> list[dict[str, float]]:
    start = time.monotonic()
    timeline: list[dict[str, float]] = []

    def on_status(_channel: str, data: bytes) -> None:
        s = decode(status_t, data)
        timeline.append({"t_s": round(time.monotonic() - start, 3),
                         **{field: getattr(s, field) for field in status_t.__slots__}})

    lc.subscribe(channel_name(Channel.STATUS, vehicle), on_status)
    while time.monotonic() - start < seconds:
        ready, _, _ = select.select([lc.fileno()], [], [], 0.05)
        if ready:
            lc.handle()
    return timeline


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("role", choices=("beacon", "watch"))
    parser.add_argument("--vehicle", type=int, default=7)
    parser.add_argument("--seconds", type=float, required=True)
    parser.add_argument("--key", help="beacon: send one signed correction with this key first")
    parser.add_argument("--correct", type=int, default=0, help="beacon: the keyframe corrected")
    args = parser.parse_args()
    lc = lcm.LCM()
    if args.role == "beacon":
        beacon(lc, args.vehicle, args.seconds, args.key, args.correct)
        return 0
    timeline = watch(lc, args.vehicle, args.seconds)
    print(json.dumps(timeline))
    return 0 if timeline else 1


if __name__ == "__main__":
    sys.exit(main())
