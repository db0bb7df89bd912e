"""The ground's side of the signed-uplink test (tests/system/test_link_netns.py), run in
the test's network namespace: waits for the drone's status, sends good corrections and one of
every kind of bad message, then prints the drone's last drone_status_t counters as one JSON object."""
from __future__ import annotations

import argparse
import json
import select
import sys
import time

import lcm

import numpy as np

from kinfly import drone_status_t, pose_correction_t, signed_t
from kinfly_ground._native import Channel, Signer, channel_name, load_key_file

STALE_BY_S = 10.0  # well outside the drone's default 2 s window


POSE = np.eye(4)
POSE[:3, 3] = [0.1, 0.2, 0.3]


def unsigned_correction(vehicle_id: int, keyframe_id: int) -> bytes:
    m = pose_correction_t()
    m.utime = time.time_ns() // 1000
    m.vehicle_id, m.keyframe_id = vehicle_id, keyframe_id
    m.T_world_cam.position_m = [0.1, 0.2, 0.3]
    m.T_world_cam.orientation_xyzw = [0.0, 0.0, 0.0, 1.0]
    m.reset_counter = 0
    return m.encode()


def signed(signer: Signer, keyframe_id: int, utime_now: int | None = None) -> bytes:
    """The signed correction of KEYFRAME_ID (to POSE), as the ground station sends it."""
    return signer.sign_correction(keyframe_id, time.time_ns() // 1000, POSE, 0,
                                  utime_now=utime_now)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--key", required=True)
    parser.add_argument("--other-key", required=True, help="a key the drone does not hold")
    parser.add_argument("--vehicle", type=int, default=7)
    parser.add_argument("--good", type=int, default=5, help="authentic corrections to send")
    parser.add_argument("--min-keyframes", type=int, default=0,
                        help="wait until the drone has sent this many keyframes (the good "
                             "corrections refer to keyframes 0..good-1)")
    parser.add_argument("--unknown-keyframe", action="store_true",
                        help="also send an authentic correction of a keyframe never sent")
    parser.add_argument("--timeout", type=float, default=10.0)
    args = parser.parse_args()

    lc = lcm.LCM()
    statuses: list[drone_status_t] = []
    lc.subscribe(channel_name(Channel.STATUS, args.vehicle),
                 lambda _channel, data: statuses.append(drone_status_t.decode(data)))

    def pump_until(done, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not done() and time.monotonic() < deadline:
            ready, _, _ = select.select([lc.fileno()], [], [], 0.05)
            if ready:
                lc.handle()
        return done()

    if not pump_until(lambda: statuses and statuses[-1].keyframes_sent >= args.min_keyframes,
                      args.timeout):
        print("uplink_probe: no status from the drone, or too few keyframes", file=sys.stderr)
        return 1

    key = load_key_file(args.key)
    signer = Signer(key, args.vehicle)
    channel = channel_name(Channel.CORRECTION, args.vehicle)
    # Signed first, sent last: a sequence number below the last accepted one, never accepted
    # itself (a recorded message played back later). A copy of an accepted one is not a replay
    # but a duplicate (the ground sends each correction more than once): not applied, not refused.
    held_back = signed(signer, 99)
    good = [signed(signer, i) for i in range(args.good)]
    for envelope in good:
        lc.publish(channel, envelope)
        time.sleep(0.01)
    lc.publish(channel, good[-1])

    bad_mac = signed_t.decode(signed(signer, 100))
    bad_mac.mac = bytes([bad_mac.mac[0] ^ 1]) + bad_mac.mac[1:]
    now_us = time.time_ns() // 1000
    bad = [
        unsigned_correction(args.vehicle, 101),                                   # unsigned
        bad_mac.encode(),                                                         # bad MAC
        signed(Signer(load_key_file(args.other_key), args.vehicle), 102),         # wrong key
        signed(signer, 103, now_us - int(STALE_BY_S * 1e6)),                      # stale
        held_back,                                                                # replayed
        signed(signer, 104)[:-3],                                                 # malformed
        signed(Signer(key, args.vehicle + 1), 105),                               # wrong vehicle
    ]
    for message in bad:
        lc.publish(channel, message)
        time.sleep(0.01)
    lc.publish(f"KINFLY_{args.vehicle}_NO_SUCH_CHANNEL", unsigned_correction(args.vehicle, 106))
    if args.unknown_keyframe:
        lc.publish(channel, signed(signer, 10**9))

    expected_total = args.good + len(bad) + 1 + int(args.unknown_keyframe)

    def counted(s: drone_status_t) -> int:
        return (s.corrections_accepted + s.rejected_unsigned + s.rejected_wrong_key
                + s.rejected_bad_mac + s.rejected_stale + s.rejected_replayed
                + s.rejected_malformed + s.rejected_unknown_channel + s.rejected_wrong_vehicle
                + s.corrections_unknown_keyframe)

    pump_until(lambda: counted(statuses[-1]) >= expected_total, args.timeout)
    last = statuses[-1]
    print(json.dumps({field: getattr(last, field) for field in drone_status_t.__slots__
                      if field.startswith(("rejected_", "corrections_"))}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
