"""A stand-in simulator for the control task's tests (tests/firmware/test_control_task.py), run in
kinfly-fw's network namespace. It sends the imu_t of a body at rest (no rotation, the specific
force 1 g up: -9.81 m/s^2 along z_body, which points down) at --rate-hz for --seconds, stamped on
the wall clock as the synthetic depth source stamps its frames, and records the
motor_command_t that come back, listening --drain-s longer for the last ones. Prints one JSON
object: samples sent, commands received, their count per state, the largest rotor speed, the
first and last command's tick.

    imu_peer.py --vehicle V --seconds S [--rate-hz 1000] [--drain-s 0.3]
"""
from __future__ import annotations

import argparse
import json
import select
import time

import lcm

from kinfly import imu_t, motor_command_t
from kinfly_ground._native import Channel, channel_name

GRAVITY_M_S2 = 9.81
# LCM's default group, with the receive buffer and queue kinfly-fw's control task asks for: on a
# busy machine this process waits its turn too, and must not lose the commands meanwhile.
LCM_URL = "udpm://239.255.76.67:7667?ttl=0&recv_buf_size=2097152"
COMMAND_QUEUE_MESSAGES = 4000


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--vehicle", type=int, required=True)
    parser.add_argument("--seconds", type=float, required=True)
    parser.add_argument("--rate-hz", type=float, default=1000.0)
    parser.add_argument("--drain-s", type=float, default=0.3)
    args = parser.parse_args()

    lc = lcm.LCM(LCM_URL)
    states: dict[int, int] = {}
    received = {"count": 0, "max_speed_rad_s": 0.0, "first_tick": -1, "last_tick": -1}

    def on_command(_channel: str, data: bytes) -> None:
        m = motor_command_t.decode(data)
        if m.vehicle_id != args.vehicle:
            return
        received["count"] += 1
        states[m.state] = states.get(m.state, 0) + 1
        received["max_speed_rad_s"] = max(received["max_speed_rad_s"],
                                          max(abs(s) for s in m.rotor_speed_rad_s))
        if received["first_tick"] < 0:
            received["first_tick"] = m.tick
        received["last_tick"] = m.tick

    lc.subscribe(channel_name(Channel.MOTOR_COMMAND, args.vehicle),
                 on_command).set_queue_capacity(COMMAND_QUEUE_MESSAGES)
    sample = imu_t()
    sample.vehicle_id = args.vehicle
    sample.angular_velocity_rad_s = [0.0, 0.0, 0.0]
    sample.linear_acceleration_m_s2 = [0.0, 0.0, -GRAVITY_M_S2]
    sample.temperature_c = float("nan")
    channel = channel_name(Channel.IMU, args.vehicle)

    def listen(until: float) -> None:
        while True:
            left = until - time.monotonic()
            if left <= 0 and not select.select([lc.fileno()], [], [], 0)[0]:
                return  # past the time, and nothing left queued
            if select.select([lc.fileno()], [], [], max(left, 0))[0]:
                lc.handle()

    period_s = 1.0 / args.rate_hz
    start = time.monotonic()
    end = start + args.seconds
    sent = 0
    last_utime = 0
    next_send = start
    while next_send < end:
        # Strictly later than the last: a loaded machine sends late, never out of order.
        last_utime = max(time.time_ns() // 1000, last_utime + 1)
        sample.utime = last_utime
        lc.publish(channel, sample.encode())
        sent += 1
        next_send += period_s
        listen(next_send)
    listen(time.monotonic() + args.drain_s)
    print(json.dumps({"sent": sent, "received": received["count"],
                      "states": {str(k): v for k, v in sorted(states.items())},
                      "max_speed_rad_s": received["max_speed_rad_s"],
                      "first_tick": received["first_tick"], "last_tick": received["last_tick"]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
