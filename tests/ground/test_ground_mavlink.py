"""The ground's MAVLink bridge against real pymavlink peers over loopback UDP: telemetry lands in
the state with units converted, poses leave in the vehicle's FRD frame (checked against numbers
derived by hand, not against the module's own conversion), forwarding is rate limited, signing
is enforced both ways, and bad inputs are refused with a message that names them."""
from __future__ import annotations

import math
import os
import re
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink2

from kinfly_ground.mavlink import MavlinkBridge, MavlinkError, _RateLimiter, load_signing_key
from kinfly_ground._native import KeyFileError

AUTOPILOT_SYSTEM, AUTOPILOT_COMPONENT = 1, 1
WAIT_S = 2.0  # loopback delivers in well under a millisecond; this only bounds a failing test
FLOAT32_TOLERANCE = 1e-6  # MAVLink floats are float32: ~7 significant digits of values near 1
UNLIMITED_RATE_HZ = 1e6  # for tests that send poses back to back and are not about the limit
KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def peer(url: str, *, key: bytes | None = None, system: int = AUTOPILOT_SYSTEM,
         component: int = AUTOPILOT_COMPONENT) -> Any:
    """A pymavlink endpoint speaking MAVLink 2 (as an autopilot does), optionally signing."""
    conn = mavutil.mavlink_connection(url, source_system=system, source_component=component)
    conn.mav = mavlink2.MAVLink(conn, srcSystem=system, srcComponent=component)
    conn.WIRE_PROTOCOL_VERSION = mavlink2.WIRE_PROTOCOL_VERSION
    if key is not None:
        conn.setup_signing(key, sign_outgoing=True)
    return conn


def poll_until(bridge: MavlinkBridge, done: Callable[[set[str]], bool]) -> set[str]:
    """Polls until done(names heard so far); fails after WAIT_S."""
    heard: set[str] = set()
    deadline = time.monotonic() + WAIT_S
    while not done(heard):
        assert time.monotonic() < deadline, f"only heard {sorted(heard)}; {bridge.counters}"
        heard.update(bridge.poll())
        time.sleep(0.001)
    return heard


def receive(conn: Any, msg_type: str) -> Any:
    """The next message of msg_type at a peer, anything else (our heartbeats) skipped."""
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        msg = conn.recv_msg()
        if msg is None:
            time.sleep(0.001)
        elif msg.get_type() == msg_type:
            return msg
        else:
            assert msg.get_type() != "BAD_DATA", f"peer could not read our message: {msg}"
    pytest.fail(f"no {msg_type} within {WAIT_S} s")


MakeUdpinBridge = Callable[..., tuple[MavlinkBridge, str]]
MakeAutopilotAndBridge = Callable[..., tuple[Any, MavlinkBridge]]


@pytest.fixture
def udpin_bridge() -> Iterator[MakeUdpinBridge]:
    """Makes bridges listening on a free loopback port; yields (bridge, url for a peer)."""
    made: list[MavlinkBridge] = []

    def make(**kwargs: Any) -> tuple[MavlinkBridge, str]:
        port = free_udp_port()
        bridge = MavlinkBridge(f"udpin:127.0.0.1:{port}", **kwargs)
        made.append(bridge)
        return bridge, f"udpout:127.0.0.1:{port}"

    yield make
    for bridge in made:
        bridge.close()


def test_telemetry_reaches_the_state_in_si_units(udpin_bridge: MakeUdpinBridge) -> None:
    bridge, url = udpin_bridge()
    gcs = peer(url, system=255, component=mavlink2.MAV_COMP_ID_MISSIONPLANNER)
    autopilot = peer(url)

    # A ground control station on the same link is not the autopilot: its messages are counted
    # but do not touch the state.
    gcs.mav.heartbeat_send(mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    gcs.mav.attitude_send(0, 3.0, 3.0, 3.0, 0.0, 0.0, 0.0)
    armed_guided = mavlink2.MAV_MODE_FLAG_SAFETY_ARMED | mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    autopilot.mav.heartbeat_send(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                 armed_guided, 4, mavlink2.MAV_STATE_ACTIVE)
    autopilot.mav.attitude_send(1000, 0.125, -0.25, 1.5, 0.0, 0.0, 0.0)
    autopilot.mav.sys_status_send(0, 0, 0, 0, 12345, 1234, 76, 0, 0, 0, 0, 0, 0)
    autopilot.mav.local_position_ned_send(1000, 1.5, -2.25, -3.0, 0.0, 0.0, 0.0)
    autopilot.mav.global_position_int_send(1000, 473977420, 85455940, 488120, 12340, 0, 0, 0, 0)
    wanted = {"HEARTBEAT", "ATTITUDE", "SYS_STATUS", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"}
    poll_until(bridge, lambda heard: wanted <= heard and bridge.state.local_x_m is not None
               and bridge.state.latitude_deg is not None)

    s = bridge.state
    assert s.autopilot_system_id == AUTOPILOT_SYSTEM
    assert (s.heartbeat_type, s.autopilot) == (mavlink2.MAV_TYPE_QUADROTOR,
                                               mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA)
    assert (s.base_mode, s.custom_mode, s.system_status) == (armed_guided, 4,
                                                             mavlink2.MAV_STATE_ACTIVE)
    assert s.armed is True
    assert (s.roll_rad, s.pitch_rad) == (0.125, -0.25)  # exact in float32
    assert s.yaw_rad == pytest.approx(1.5, abs=FLOAT32_TOLERANCE)
    assert s.battery_voltage_v == pytest.approx(12.345)  # mV
    assert s.battery_current_a == pytest.approx(12.34)  # cA
    assert s.battery_remaining_pct == 76
    assert (s.local_x_m, s.local_y_m, s.local_z_m) == (1.5, -2.25, -3.0)
    assert s.latitude_deg == pytest.approx(47.3977420)  # degE7
    assert s.longitude_deg == pytest.approx(8.5455940)
    assert s.altitude_msl_m == pytest.approx(488.12)  # mm
    assert s.relative_altitude_m == pytest.approx(12.34)
    assert s.last_heard_utime is not None
    assert bridge.counters.other_source == 2

    # BATTERY_STATUS gives cells (unused ones UINT16_MAX); the pack voltage is their sum.
    cells_mv = [4100, 4150, 4200] + [0xFFFF] * 7
    autopilot.mav.battery_status_send(0, 0, 0, 2500, cells_mv, 250, -1, -1, 55)
    poll_until(bridge, lambda heard: "BATTERY_STATUS" in heard)
    assert s.battery_voltage_v == pytest.approx(12.45)
    assert s.battery_current_a == pytest.approx(2.5)
    assert s.battery_remaining_pct == 55

    metrics = s.as_metrics()
    assert metrics["armed"] == 1.0
    assert metrics["battery_voltage_v"] == pytest.approx(12.45)
    assert metrics["roll_rad"] == 0.125
    assert "autopilot_system_id" not in metrics and "last_heard_utime" not in metrics
    assert all(isinstance(v, float) for v in metrics.values())
    gcs.close()
    autopilot.close()


def rotation_about(axis: str, angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
            "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def pose(R_world_cam: np.ndarray, p_world_cam: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_world_cam, p_world_cam
    return T


# With the camera looking forward (body x = optical z, body y = optical x, body z = optical y):
# (T_world_cam, expected x/y/z [m] in the local FRD frame, roll/pitch/yaw [rad], q (w, x, y, z)).
HAND_DERIVED = [
    # 1 m along optical z (forward) and 0.5 m along y (down), turned 90° about optical y: the
    # optical z axis now points along the first keyframe's x (right), so the nose is yawed
    # right, which is +90° in NED.
    (pose(rotation_about("y", math.pi / 2), (0.0, 0.5, 1.0)),
     (1.0, 0.0, 0.5), (0.0, 0.0, math.pi / 2),
     (math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4))),
    # 30° about optical x (right) turns optical z towards -y (up): nose up, +30° pitch.
    (pose(rotation_about("x", math.radians(30)), (0.0, 0.0, 0.0)),
     (0.0, 0.0, 0.0), (0.0, math.radians(30), 0.0),
     (math.cos(math.radians(15)), 0.0, math.sin(math.radians(15)), 0.0)),
    # 20° about optical z (forward) turns optical x towards +y (down): right side down, +20° roll;
    # 2 m along optical x is 2 m to the right.
    (pose(rotation_about("z", math.radians(20)), (2.0, 0.0, 0.0)),
     (0.0, 2.0, 0.0), (math.radians(20), 0.0, 0.0),
     (math.cos(math.radians(10)), math.sin(math.radians(10)), 0.0, 0.0)),
]
HAND_DERIVED_IDS = ["yaw_right_90", "pitch_up_30", "roll_right_20"]


@pytest.fixture
def autopilot_and_bridge() -> Iterator[MakeAutopilotAndBridge]:
    """An autopilot-like peer listening on a free port and a bridge sending to it."""
    made: list[Any] = []

    def make(**kwargs: Any) -> tuple[Any, MavlinkBridge]:
        port = free_udp_port()
        autopilot = peer(f"udpin:127.0.0.1:{port}", key=kwargs.get("signing_key"))
        bridge = MavlinkBridge(f"udpout:127.0.0.1:{port}", **kwargs)
        made.extend((bridge, autopilot))
        return autopilot, bridge

    yield make
    for conn in made:
        conn.close()


@pytest.mark.parametrize("T_world_cam, xyz_m, rpy_rad, q_wxyz", HAND_DERIVED,
                         ids=HAND_DERIVED_IDS)
def test_vision_position_estimate_is_in_the_vehicle_frame(
        autopilot_and_bridge: MakeAutopilotAndBridge, T_world_cam: np.ndarray,
        xyz_m: tuple[float, ...], rpy_rad: tuple[float, ...], q_wxyz: tuple[float, ...]) -> None:
    autopilot, bridge = autopilot_and_bridge(forward="vision", rate_hz=UNLIMITED_RATE_HZ)
    utime = 1_700_000_000_123_456
    assert bridge.send_pose(utime, T_world_cam, reset_counter=3)
    msg = receive(autopilot, "VISION_POSITION_ESTIMATE")
    assert msg.usec == utime
    assert (msg.x, msg.y, msg.z) == pytest.approx(xyz_m, abs=FLOAT32_TOLERANCE)
    assert (msg.roll, msg.pitch, msg.yaw) == pytest.approx(rpy_rad, abs=FLOAT32_TOLERANCE)
    assert msg.reset_counter == 3
    assert math.isnan(msg.covariance[0])  # no covariance given: unknown
    assert bridge.counters.sent == 1


@pytest.mark.parametrize("T_world_cam, xyz_m, rpy_rad, q_wxyz", HAND_DERIVED,
                         ids=HAND_DERIVED_IDS)
def test_odometry_is_in_the_vehicle_frame(
        autopilot_and_bridge: MakeAutopilotAndBridge, T_world_cam: np.ndarray,
        xyz_m: tuple[float, ...], rpy_rad: tuple[float, ...], q_wxyz: tuple[float, ...]) -> None:
    autopilot, bridge = autopilot_and_bridge(forward="odometry", rate_hz=UNLIMITED_RATE_HZ)
    utime = 1_700_000_000_654_321
    assert bridge.send_pose(utime, T_world_cam, reset_counter=258, covariance_m2=0.01,
                            covariance_rad2=0.0025)
    msg = receive(autopilot, "ODOMETRY")
    assert msg.time_usec == utime
    assert (msg.frame_id, msg.child_frame_id) == (mavlink2.MAV_FRAME_LOCAL_FRD,
                                                  mavlink2.MAV_FRAME_BODY_FRD)
    assert (msg.x, msg.y, msg.z) == pytest.approx(xyz_m, abs=FLOAT32_TOLERANCE)
    q = np.array(msg.q)
    q = q if q[0] >= 0 else -q  # q and -q are the same rotation
    assert q == pytest.approx(q_wxyz, abs=FLOAT32_TOLERANCE)
    assert all(math.isnan(v) for v in (msg.vx, msg.vy, msg.vz, msg.rollspeed, msg.pitchspeed,
                                       msg.yawspeed, msg.velocity_covariance[0]))
    assert [msg.pose_covariance[i] for i in (0, 6, 11)] == pytest.approx([0.01] * 3)
    assert [msg.pose_covariance[i] for i in (15, 18, 20)] == pytest.approx([0.0025] * 3)
    assert msg.reset_counter == 258 % 256  # uint8 on the wire: wraps, autopilots watch changes
    assert msg.estimator_type == mavlink2.MAV_ESTIMATOR_TYPE_VISION


def test_a_camera_mounted_looking_down(autopilot_and_bridge: MakeAutopilotAndBridge) -> None:
    # Optical z = body down, optical x = body right, so optical y = body back (-x).
    R_body_cam = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    autopilot, bridge = autopilot_and_bridge(forward="vision", rate_hz=UNLIMITED_RATE_HZ,
                                             R_body_cam=R_body_cam)
    # 1 m along optical -y is 1 m forward; 0.5 m along optical z is 0.5 m down.
    assert bridge.send_pose(1, pose(np.eye(3), (0.0, -1.0, 0.5)), 0)
    msg = receive(autopilot, "VISION_POSITION_ESTIMATE")
    assert (msg.x, msg.y, msg.z) == pytest.approx((1.0, 0.0, 0.5), abs=FLOAT32_TOLERANCE)
    assert (msg.roll, msg.pitch, msg.yaw) == pytest.approx((0.0, 0.0, 0.0), abs=FLOAT32_TOLERANCE)


RATE_COUNT_TOLERANCE = 2  # the send at t=0 plus one for where the 5 ms call grid meets a period


def test_forwarding_is_rate_limited(autopilot_and_bridge: MakeAutopilotAndBridge) -> None:
    rate_hz = 20.0
    autopilot, bridge = autopilot_and_bridge(forward="vision", rate_hz=rate_hz)
    start_s = time.monotonic()
    for i in range(100):
        bridge.send_pose(i, np.eye(4), 0)
        time.sleep(0.005)
    elapsed_s = time.monotonic() - start_s

    assert bridge.counters.sent + bridge.counters.skipped_rate == 100
    assert abs(bridge.counters.sent - elapsed_s * rate_hz) <= RATE_COUNT_TOLERANCE
    delivered = 0
    deadline = time.monotonic() + WAIT_S
    while delivered < bridge.counters.sent and time.monotonic() < deadline:
        msg = autopilot.recv_msg()
        if msg is None:
            time.sleep(0.001)
        elif msg.get_type() == "VISION_POSITION_ESTIMATE":
            delivered += 1
    assert delivered == bridge.counters.sent


def test_poses_at_the_rate_with_jitter_all_pass_the_limiter() -> None:
    rate_hz, jitter_s = 30.0, 0.004  # a camera's frame times wander by a few ms
    limiter = _RateLimiter(rate_hz)
    rng = np.random.default_rng(20261201)
    arrivals_s = np.arange(300) / rate_hz + rng.uniform(-jitter_s, jitter_s, 300)
    assert all(limiter.allow(t) for t in arrivals_s)
    faster = _RateLimiter(rate_hz)
    sent = sum(faster.allow(t) for t in np.arange(1000) / (5 * rate_hz))
    assert sent == pytest.approx(1000 / 5, abs=1)  # never more than rate_hz on average


def test_poses_not_sent_are_counted(autopilot_and_bridge: MakeAutopilotAndBridge) -> None:
    _, telemetry_only = autopilot_and_bridge()
    assert not telemetry_only.send_pose(1, np.eye(4), 0)
    assert telemetry_only.counters.skipped_forward_off == 1
    _, bridge = autopilot_and_bridge(forward="odometry", rate_hz=UNLIMITED_RATE_HZ)
    assert not bridge.send_pose(1, np.full((4, 4), np.nan), 0)
    assert bridge.counters.skipped_invalid == 1
    with pytest.raises(ValueError, match="covariance_rad2 needs covariance_m2"):
        bridge.send_pose(1, np.eye(4), 0, covariance_rad2=0.01)
    assert bridge.counters.sent == 0


def test_signing_is_enforced_both_ways(udpin_bridge: MakeUdpinBridge) -> None:
    bridge, url = udpin_bridge(forward="vision", rate_hz=UNLIMITED_RATE_HZ, signing_key=KEY)
    autopilot = peer(url, key=KEY)
    autopilot.mav.heartbeat_send(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_PX4,
                                 0, 0, mavlink2.MAV_STATE_STANDBY)
    autopilot.mav.attitude_send(0, 0.125, 0.0, 0.0, 0.0, 0.0, 0.0)
    poll_until(bridge, lambda heard: "ATTITUDE" in heard)
    assert bridge.state.roll_rad == 0.125

    # The bridge now knows the autopilot's address; what it sends is signed with the key.
    assert bridge.send_pose(42, np.eye(4), 0)
    msg = receive(autopilot, "VISION_POSITION_ESTIMATE")
    assert msg.get_signed()
    assert autopilot.mav.signing.goodsig_count >= 1
    assert autopilot.mav.signing.badsig_count == 0

    # Someone on the link pretending to be the autopilot, unsigned and then with another key.
    unsigned = peer(url)
    unsigned.mav.attitude_send(0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    poll_until(bridge, lambda _: bridge.counters.rejected_unsigned == 1)
    wrong_key = peer(url, key=OTHER_KEY)
    wrong_key.mav.attitude_send(0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    poll_until(bridge, lambda _: bridge.counters.rejected_bad_signature == 1)
    assert bridge.state.roll_rad == 0.125
    for conn in (autopilot, unsigned, wrong_key):
        conn.close()


@pytest.mark.parametrize("url", ["notaurl", "http://example.com:80", "udpin:127.0.0.1",
                                 "udpin:127.0.0.1:99999", "udpout::14550", "tcp:localhost:port"])
def test_unparsable_urls_are_refused(url: str) -> None:
    with pytest.raises(MavlinkError, match=re.escape(url)):
        MavlinkBridge(url)


def test_a_missing_or_wrong_serial_device_is_refused(tmp_path: Path) -> None:
    missing = "/dev/ttyKINFLY_NO_SUCH_DEVICE"
    with pytest.raises(MavlinkError, match=re.escape(missing)):
        MavlinkBridge(missing)
    regular = tmp_path / "flight.tlog"
    regular.write_bytes(b"")
    with pytest.raises(MavlinkError, match=re.escape(f"{regular} is not a character device")):
        MavlinkBridge(str(regular))


def write_key(path: Path, key: bytes, mode: int) -> Path:
    path.write_bytes(key)
    os.chmod(path, mode)
    return path


def test_signing_key_files(tmp_path: Path) -> None:
    assert load_signing_key(write_key(tmp_path / "good.key", KEY, 0o600)) == KEY
    readable = write_key(tmp_path / "readable.key", KEY, 0o644)
    with pytest.raises(KeyFileError, match=re.escape(f"{readable} has mode 0644")):
        load_signing_key(readable)
    short = write_key(tmp_path / "short.key", KEY[:16], 0o600)
    with pytest.raises(KeyFileError, match=re.escape(f"{short} holds 16 bytes")):
        load_signing_key(short)


def test_a_serial_autopilot_over_a_pseudo_terminal() -> None:
    """The serial path with a real tty: a pseudo-terminal stands in for the USB/UART cable, the
    autopilot writes its frames into the other end and reads our pose frames from it."""
    controller, device = os.openpty()
    try:
        bridge = MavlinkBridge(os.ttyname(device), forward="vision", baud=115200)
        try:
            encoder = mavlink2.MAVLink(None, srcSystem=AUTOPILOT_SYSTEM,
                                       srcComponent=AUTOPILOT_COMPONENT)
            os.write(controller, encoder.heartbeat_encode(
                mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_PX4, 0, 0,
                mavlink2.MAV_STATE_STANDBY).pack(encoder))
            os.write(controller, encoder.attitude_encode(0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0)
                     .pack(encoder))
            poll_until(bridge, lambda heard: {"HEARTBEAT", "ATTITUDE"} <= heard)
            assert bridge.state.roll_rad == pytest.approx(0.5)
            assert bridge.send_pose(1_000_000, np.eye(4), 3)
            parser = mavlink2.MAVLink(None)
            deadline = time.monotonic() + WAIT_S
            vision = None
            while vision is None:
                assert time.monotonic() < deadline, "no VISION_POSITION_ESTIMATE on the tty"
                for msg in parser.parse_buffer(os.read(controller, 4096)) or []:
                    if msg.get_type() == "VISION_POSITION_ESTIMATE":
                        vision = msg
            assert vision.usec == 1_000_000 and vision.reset_counter == 3
            assert (vision.x, vision.y, vision.z) == (0.0, 0.0, 0.0)
        finally:
            bridge.close()
    finally:
        os.close(controller)
        os.close(device)
