"""Listens to a drone's status_t for a while and prints every message as one JSON object per line
(all fields), for tests that run kinfly-fw in a network namespace and check what its status
says (tests/integration/test_openni.py). Run it inside the same namespace."""
from __future__ import annotations

import argparse
import json
import select
import sys
import time

import lcm

from kinfly import status_t
from kinfly_ground.channels import Channel, channel_name
from kinfly_ground.conversions import decode


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--vehicle", type=int, default=1)
    parser.add_argument("--seconds", type=float, required=True, help="how long to listen")
    args = parser.parse_args()

    lc = lcm.LCM()
    received: list[status_t] = []
    lc.subscribe(channel_name(Channel.STATUS, args.vehicle),
                 lambda _channel, data: received.append(decode(status_t, data)))
    deadline = time.monotonic() + args.seconds
    while (left := deadline - time.monotonic()) > 0:
        ready, _, _ = select.select([lc.fileno()], [], [], min(left, 0.05))
        if ready:
            lc.handle()
    for status in received:
        print(json.dumps({field: getattr(status, field) for field in status_t.__slots__}))
    return 0 if received else 1


if __name__ == "__main__":
    sys.exit(main())
