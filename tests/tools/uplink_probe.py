"""The ground's side of the signed-uplink test (tests/integration/test_link_netns.py), run in
the test's network namespace: waits for the drone's status, sends good corrections and one of
every kind of bad message, then prints the drone's last status_t counters as one JSON object."""
from __future__ import annotations

import argparse
import json
import select
import sys
import time

import lcm

from kinfly import pose_correction_t, status_t
from kinfly_ground import signing
from kinfly_ground.channels import Channel, channel_name
from kinfly_ground.conversions import decode

STALE_BY_S = 10.0  # well outside the drone's default 2 s window


def correction(vehicle_id: int, keyframe_id: int) -> bytes:
    m = pose_correction_t()
    m.utime = time.time_ns() // 1000
    m.vehicle_id, m.keyframe_id = vehicle_id, keyframe_id
    m.position_m, m.orientation_xyzw, m.reset_counter = [0.1, 0.2, 0.3], [0.0, 0.0, 0.0, 1.0], 0
    return m.encode()


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
    statuses: list[status_t] = []
    lc.subscribe(channel_name(Channel.STATUS, args.vehicle),
                 lambda _channel, data: statuses.append(decode(status_t, data)))

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

    key = signing.load_key_file(args.key)
    signer = signing.Signer(key, args.vehicle)
    channel = channel_name(Channel.CORRECTION, args.vehicle)
    good = [signer.sign(correction(args.vehicle, i)).encode() for i in range(args.good)]
    for envelope in good:
        lc.publish(channel, envelope)
        time.sleep(0.01)

    bad_mac = signer.sign(correction(args.vehicle, 100))
    bad_mac.mac = bytes([bad_mac.mac[0] ^ 1]) + bad_mac.mac[1:]
    now_us = time.time_ns() // 1000
    bad = [
        correction(args.vehicle, 101),                                            # unsigned
        bad_mac.encode(),                                                         # bad MAC
        signing.Signer(signing.load_key_file(args.other_key), args.vehicle)
        .sign(correction(args.vehicle, 102)).encode(),                            # wrong key
        signer.sign(correction(args.vehicle, 103),
                    now_us - int(STALE_BY_S * 1e6)).encode(),                     # stale
        good[-1],                                                                 # replayed
        signer.sign(correction(args.vehicle, 104)).encode()[:-3],                 # malformed
        signing.Signer(key, args.vehicle + 1)
        .sign(correction(args.vehicle + 1, 105)).encode(),                        # wrong vehicle
    ]
    for message in bad:
        lc.publish(channel, message)
        time.sleep(0.01)
    lc.publish(f"KINFLY_{args.vehicle}_NO_SUCH_CHANNEL", correction(args.vehicle, 106))
    if args.unknown_keyframe:
        lc.publish(channel, signer.sign(correction(args.vehicle, 10**9)).encode())

    expected_total = args.good + len(bad) + 1 + int(args.unknown_keyframe)

    def counted(s: status_t) -> int:
        return (s.corrections_accepted + s.rejected_unsigned + s.rejected_wrong_key
                + s.rejected_bad_mac + s.rejected_stale + s.rejected_replayed
                + s.rejected_malformed + s.rejected_unknown_channel + s.rejected_wrong_vehicle
                + s.corrections_unknown_keyframe)

    pump_until(lambda: counted(statuses[-1]) >= expected_total, args.timeout)
    last = statuses[-1]
    print(json.dumps({field: getattr(last, field) for field in status_t.__slots__
                      if field.startswith(("rejected_", "corrections_"))}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
