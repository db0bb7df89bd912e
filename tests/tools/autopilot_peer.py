"""A stand-in PX4 autopilot for the mavlink backend's tests (tests/firmware/test_mavlink_backend.py),
run in kinfly-fw's network namespace with pymavlink, as the real one behaves towards a companion
computer:

- HEARTBEAT at 1 Hz as a PX4 quadrotor: armed flag, custom mode (main mode in bits 16-23);
- its IMU (HIGHRES_IMU of a body at rest, seeded noise; every tenth carries a barometer's
  pressure altitude, as fields_updated marks it) and attitude (ATTITUDE_QUATERNION,
  level) only once asked for with SET_MESSAGE_INTERVAL, at the interval asked;
- DO_SET_MODE to offboard accepted only while setpoints stream (at least OFFBOARD_MIN_SETPOINTS in
  the last OFFBOARD_WINDOW_S, as PX4 wants an offboard signal before the switch), otherwise
  TEMPORARILY_REJECTED; arming accepted in offboard; offboard left for hold when the setpoints
  stop for OFFBOARD_LOSS_S (PX4's COM_OF_LOSS_T);
- MAVLink 2 signing with --key (pymavlink rejects and counts what is not signed with it).

SIGUSR1 is a pilot's mode switch: position mode, out of offboard (what the companion sends
after it is recorded apart). It runs until SIGTERM, then disappears at once (no more heartbeats: the autopilot lost, for
kinfly-fw) and prints one JSON object of what it received; progress lines ("peer: offboard",
"peer: armed", "peer: climb thrust ...", "peer: rejected a frame: bad signature") go to stdout
as they happen.

    autopilot_peer.py --url udpout:127.0.0.1:14540 [--key FILE] [--seed 1]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import random
import signal
import time
from pathlib import Path

os.environ["MAVLINK20"] = "1"  # this process only: pymavlink picks its wire version at import
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

GRAVITY_M_S2 = 9.81
PX4_MAIN_MODE_HOLD = 4 << 16 | 3 << 24  # AUTO.LOITER
PX4_MAIN_MODE_OFFBOARD = 6
PX4_MAIN_MODE_POSCTL = 3 << 16
OFFBOARD_WINDOW_S = 0.5
OFFBOARD_MIN_SETPOINTS = 2  # PX4 wants more than 2 Hz
OFFBOARD_LOSS_S = 0.5
# A MEMS IMU at rest: white noise of these standard deviations per sample.
ACCEL_NOISE_M_S2 = 0.02
GYRO_NOISE_RAD_S = 0.002
ALL_IMU_FIELDS = 0x3F
PRESSURE_ALT_FIELD = 1 << 11
PRESSURE_ALT_EVERY = 10  # IMU messages: 25 Hz at the 250 Hz the test asks for
SITE_ALTITUDE_M = 231.0
BARO_NOISE_M = 0.1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--url", required=True)
    parser.add_argument("--key", type=Path, help="32-byte MAVLink 2 signing key file")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()

    conn = mavutil.mavlink_connection(args.url, source_system=1, source_component=1,
                                      dialect="common")
    if args.key is not None:
        conn.setup_signing(args.key.read_bytes(), sign_outgoing=True)
    rng = random.Random(args.seed)
    stop = {"now": False, "takeover": False}
    signal.signal(signal.SIGTERM, lambda *_: stop.update(now=True))
    signal.signal(signal.SIGUSR1, lambda *_: stop.update(takeover=True))
    taken_over = False

    boot = time.monotonic()
    armed = False
    custom_mode = PX4_MAIN_MODE_HOLD
    intervals: dict[int, float] = {}  # message id -> seconds, as asked
    due: dict[int, float] = {}
    next_heartbeat = boot
    imu_sent = 0
    setpoints: list[float] = []       # arrival times (monotonic)
    got: dict[str, object] = {
        "setpoints": 0, "max_thrust": 0.0, "type_masks": [], "setpoint_targets": [],
        "odometry": 0, "odometry_frames": [], "odometry_estimator_types": [],
        "odometry_max_distance_m": 0.0, "reset_counters": [], "companion_heartbeats": 0,
        "mode_requests": 0, "mode_rejected": 0, "arm_requests": 0, "disarm_requests": 0,
        "stream_requests": {}, "offboard_at_s": None, "armed_at_s": None,
        "first_setpoint_at_s": None, "setpoints_before_offboard": 0,
        "climb_setpoints": 0, "climb_rate_hz": None,
        "mode_requests_after_takeover": 0, "arm_requests_after_takeover": 0,
        "heartbeats_after_takeover": 0,
    }
    climb: list[float] = []  # arrival times of setpoints with thrust, armed in offboard

    def now_s() -> float:
        return time.monotonic() - boot

    def ack(command: int, result: int) -> None:
        conn.mav.command_ack_send(command, result)

    def heartbeat() -> None:
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (
            mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
        conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base,
                                custom_mode, mavlink.MAV_STATE_ACTIVE if armed
                                else mavlink.MAV_STATE_STANDBY)

    def offboard() -> bool:
        return (custom_mode >> 16) & 0xFF == PX4_MAIN_MODE_OFFBOARD

    def handle(msg: mavlink.MAVLink_message) -> None:
        nonlocal armed, custom_mode
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            got["companion_heartbeats"] += 1
            if taken_over:
                got["heartbeats_after_takeover"] += 1
                if got["heartbeats_after_takeover"] == 1:
                    print("peer: companion heartbeat after the takeover", flush=True)
        elif kind == "SET_ATTITUDE_TARGET":
            t = time.monotonic()
            setpoints.append(t)
            got["setpoints"] += 1
            if got["first_setpoint_at_s"] is None:
                got["first_setpoint_at_s"] = now_s()
            if msg.type_mask not in got["type_masks"]:
                got["type_masks"].append(msg.type_mask)
            target = [msg.target_system, msg.target_component]
            if target not in got["setpoint_targets"]:
                got["setpoint_targets"].append(target)
            if msg.thrust > 0.0 and armed and offboard():
                climb.append(t)
                if msg.thrust > got["max_thrust"]:
                    print(f"peer: climb thrust {msg.thrust:.3f}", flush=True)
            got["max_thrust"] = max(got["max_thrust"], msg.thrust)
        elif kind == "ODOMETRY":
            got["odometry"] += 1
            frames = [msg.frame_id, msg.child_frame_id]
            if frames not in got["odometry_frames"]:
                got["odometry_frames"].append(frames)
            if msg.estimator_type not in got["odometry_estimator_types"]:
                got["odometry_estimator_types"].append(msg.estimator_type)
            if msg.reset_counter not in got["reset_counters"]:
                got["reset_counters"].append(msg.reset_counter)
            got["odometry_max_distance_m"] = max(got["odometry_max_distance_m"],
                                                 math.sqrt(msg.x**2 + msg.y**2 + msg.z**2))
        elif kind == "COMMAND_LONG":
            if msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
                message_id, interval_us = int(msg.param1), msg.param2
                got["stream_requests"][str(message_id)] = interval_us
                if interval_us > 0:
                    intervals[message_id] = interval_us * 1e-6
                    due.setdefault(message_id, time.monotonic())
                ack(msg.command, mavlink.MAV_RESULT_ACCEPTED)
            elif msg.command == mavlink.MAV_CMD_DO_SET_MODE:
                got["mode_requests"] += 1
                got["mode_requests_after_takeover"] += taken_over
                wanted = int(msg.param2)
                recent = [t for t in setpoints if t >= time.monotonic() - OFFBOARD_WINDOW_S]
                if (int(msg.param1) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and
                        wanted == PX4_MAIN_MODE_OFFBOARD and
                        len(recent) >= OFFBOARD_MIN_SETPOINTS):
                    if not offboard():
                        got["offboard_at_s"] = now_s()
                        got["setpoints_before_offboard"] = got["setpoints"]
                        print("peer: offboard", flush=True)
                    custom_mode = PX4_MAIN_MODE_OFFBOARD << 16
                    ack(msg.command, mavlink.MAV_RESULT_ACCEPTED)
                else:
                    got["mode_rejected"] += 1
                    ack(msg.command, mavlink.MAV_RESULT_TEMPORARILY_REJECTED)
            elif msg.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
                if msg.param1 == 1.0:
                    got["arm_requests"] += 1
                    got["arm_requests_after_takeover"] += taken_over
                    if offboard():
                        if not armed:
                            got["armed_at_s"] = now_s()
                            print("peer: armed", flush=True)
                        armed = True
                        ack(msg.command, mavlink.MAV_RESULT_ACCEPTED)
                    else:
                        ack(msg.command, mavlink.MAV_RESULT_DENIED)
                else:
                    got["disarm_requests"] += 1
                    armed = False
                    print("peer: disarmed", flush=True)
                    ack(msg.command, mavlink.MAV_RESULT_ACCEPTED)
            else:
                ack(msg.command, mavlink.MAV_RESULT_UNSUPPORTED)

    reported_bad_signature = False
    while not stop["now"]:
        t = time.monotonic()
        if stop["takeover"] and not taken_over:
            taken_over = True
            custom_mode = PX4_MAIN_MODE_POSCTL
            heartbeat()  # a mode change is announced at once, as PX4 does
            print("peer: pilot took over", flush=True)
        if t >= next_heartbeat:
            heartbeat()
            next_heartbeat += 1.0
        time_usec = int((t - boot) * 1e6)
        for message_id, interval_s in intervals.items():
            if t < due[message_id]:
                continue
            # On schedule, but never a burst after this process waited for a core.
            due[message_id] = max(due[message_id] + interval_s, t)
            if message_id == mavlink.MAVLINK_MSG_ID_HIGHRES_IMU:
                acc = [rng.gauss(0.0, ACCEL_NOISE_M_S2) for _ in range(3)]
                gyro = [rng.gauss(0.0, GYRO_NOISE_RAD_S) for _ in range(3)]
                imu_sent += 1
                fields, pressure_alt = ALL_IMU_FIELDS, 0.0
                if imu_sent % PRESSURE_ALT_EVERY == 0:
                    fields |= PRESSURE_ALT_FIELD
                    pressure_alt = SITE_ALTITUDE_M + rng.gauss(0.0, BARO_NOISE_M)
                conn.mav.highres_imu_send(time_usec, acc[0], acc[1], acc[2] - GRAVITY_M_S2,
                                          gyro[0], gyro[1], gyro[2], 0.0, 0.0, 0.0, 1013.0, 0.0,
                                          pressure_alt, 20.0, fields)
            elif message_id == mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
                conn.mav.attitude_quaternion_send(time_usec // 1000, 1.0, 0.0, 0.0, 0.0,
                                                  0.0, 0.0, 0.0)
        if offboard() and (not setpoints or setpoints[-1] < t - OFFBOARD_LOSS_S):
            custom_mode = PX4_MAIN_MODE_HOLD
            print("peer: offboard lost: hold", flush=True)
        msg = conn.recv_match(blocking=True, timeout=0.001)
        while msg is not None:
            if msg.get_type() != "BAD_DATA":
                handle(msg)
            msg = conn.recv_match(blocking=False)
        if conn.mav.signing.badsig_count > 0 and not reported_bad_signature:
            reported_bad_signature = True
            print("peer: rejected a frame: bad signature", flush=True)

    if len(setpoints) >= 2:
        got["setpoint_rate_hz"] = (len(setpoints) - 1) / (setpoints[-1] - setpoints[0])
    got["climb_setpoints"] = len(climb)
    if len(climb) >= 2:
        got["climb_rate_hz"] = (len(climb) - 1) / (climb[-1] - climb[0])
    signing = conn.mav.signing
    got["signing"] = {"good": signing.goodsig_count, "bad": signing.badsig_count,
                      "unsigned": signing.unsigned_count, "rejected": signing.reject_count}
    print(json.dumps(got), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
