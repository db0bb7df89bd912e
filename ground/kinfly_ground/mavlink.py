"""The ground station's MAVLink boundary: autopilot telemetry in, kinfly poses out as
VISION_POSITION_ESTIMATE or ODOMETRY. NED/FRD frames exist only in this file (docs/mavlink.md).

The link always speaks MAVLink 2 (signing and `reset_counter` need it). pymavlink picks its wire
version from the MAVLINK20 environment variable once per process; rather than set that for every
other user of pymavlink, each bridge gives its connection its own MAVLink 2 parser, as mavutil
itself does when it meets a MAVLink 2 peer."""
from __future__ import annotations

import dataclasses
import math
import os
import socket
import stat
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink2
from scipy.spatial.transform import Rotation

FORWARD_MODES = ("vision", "odometry")
HEARTBEAT_PERIOD_S = 1.0  # MAVLink's heartbeat rate; autopilots time a component out after ~3 s
# A peer that floods faster than we parse must not keep poll() from returning to its caller.
MAX_MESSAGES_PER_POLL = 1000
# A pose up to this fraction of a period early still counts as due, so poses arriving at exactly
# rate_hz with some jitter are all forwarded rather than every other one.
RATE_SLACK_FRACTION = 0.25
SIGNING_KEY_BYTES = 32  # MAVLink 2's signing secret
ROTATION_TOLERANCE = 1e-6  # R_body_cam is a configured constant, orthonormal to float precision

# Body FRD from camera optical for a camera looking forward: body x = cam z, y = cam x, z = cam y.
R_BODY_CAM_FORWARD = np.array([[0.0, 0.0, 1.0],
                               [1.0, 0.0, 0.0],
                               [0.0, 1.0, 0.0]])

_UINT16_UNKNOWN = 0xFFFF
_COVARIANCE_LEN = 21  # upper-right triangle of a 6x6 matrix, row-major
_POSITION_DIAGONAL = (0, 6, 11)  # x, y, z variances in that triangle
_ATTITUDE_DIAGONAL = (15, 18, 20)  # roll, pitch, yaw variances
_UNKNOWN_COVARIANCE = [math.nan] + [0.0] * (_COVARIANCE_LEN - 1)  # MAVLink: NaN first = unknown
_SCHEMES = ("udpin", "udpout", "tcp")


class MavlinkError(Exception):
    """The bridge cannot start from these inputs (URL, device, key); the message names the input."""


# Identities and times: not values a time-series viewer plots.
_NOT_METRICS = frozenset({"heartbeat_type", "autopilot", "last_heard_utime",
                          "autopilot_system_id"})


@dataclass
class AutopilotState:
    """The latest telemetry heard from the autopilot; a field is None until its message is heard
    (or when the autopilot reports the value as unknown). Positions are the autopilot's own
    estimate: local NED from its EKF origin, global WGS84."""
    heartbeat_type: int | None = None  # MAV_TYPE
    autopilot: int | None = None  # MAV_AUTOPILOT
    base_mode: int | None = None  # MAV_MODE_FLAG bits
    custom_mode: int | None = None  # autopilot-specific flight mode
    system_status: int | None = None  # MAV_STATE
    armed: bool | None = None
    roll_rad: float | None = None
    pitch_rad: float | None = None
    yaw_rad: float | None = None
    battery_voltage_v: float | None = None
    battery_current_a: float | None = None
    battery_remaining_pct: int | None = None
    local_x_m: float | None = None  # north of the EKF origin
    local_y_m: float | None = None  # east
    local_z_m: float | None = None  # down
    latitude_deg: float | None = None
    longitude_deg: float | None = None
    altitude_msl_m: float | None = None
    relative_altitude_m: float | None = None  # above home
    last_heard_utime: int | None = None  # ground wall clock when the autopilot was last heard
    autopilot_system_id: int | None = None

    def as_metrics(self) -> dict[str, float]:
        """Known values by field name for a time-series viewer; identities and times left out."""
        metrics: dict[str, float] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if value is not None and f.name not in _NOT_METRICS:
                metrics[f.name] = float(value)
        return metrics


@dataclass
class MavlinkCounters:
    received: int = 0  # messages accepted (decoded, signature good where signing is on)
    sent: int = 0  # poses sent
    heartbeats_sent: int = 0
    skipped_rate: int = 0  # poses not sent: sooner than rate_hz allows (_RateLimiter)
    skipped_forward_off: int = 0  # poses not sent: the bridge forwards nothing
    skipped_invalid: int = 0  # poses not sent: not finite, or a negative time
    rejected_unsigned: int = 0  # signing on, message unsigned
    rejected_bad_signature: int = 0  # signing on, wrong key or a replayed/old timestamp
    bad_data: int = 0  # bytes that did not parse (bad CRC, garbage)
    unknown: int = 0  # message ids outside the common dialect, ignored unchecked
    other_source: int = 0  # accepted, but not from the autopilot whose telemetry is tracked
    link_errors: int = 0  # socket or device errors while reading or writing


@dataclass
class _ParsedUrl:
    scheme: str  # "udpin", "udpout", "tcp" or "serial"
    address: str  # HOST:PORT, or the device path


def _parse_url(url: str) -> _ParsedUrl:
    """Accepts only the connection forms documented in docs/mavlink.md, so a typo is reported
    here rather than becoming a log file that pymavlink opens or a serial port it waits on."""
    if url.startswith("/"):
        try:
            mode = os.stat(url).st_mode
        except OSError as err:
            raise MavlinkError(f"serial device {url}: {err.strerror}") from err
        if not stat.S_ISCHR(mode):
            raise MavlinkError(f"serial device {url} is not a character device")
        return _ParsedUrl("serial", url)
    scheme, sep, rest = url.partition(":")
    if not sep or scheme not in _SCHEMES:
        raise MavlinkError(f"MAVLink URL {url!r}: expected udpin:HOST:PORT, udpout:HOST:PORT, "
                           "tcp:HOST:PORT or a serial device path such as /dev/ttyACM0")
    host, sep, port_text = rest.rpartition(":")
    if not sep or not host or not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
        raise MavlinkError(f"MAVLink URL {url!r}: expected {scheme}:HOST:PORT with PORT in "
                           "1..65535")
    try:
        socket.getaddrinfo(host, int(port_text), socket.AF_INET)
    except socket.gaierror as err:
        raise MavlinkError(f"MAVLink URL {url!r}: cannot resolve host {host!r}: {err}") from err
    return _ParsedUrl(scheme, rest)


def _validated_rotation(R: np.ndarray) -> np.ndarray:
    R = np.asarray(R, dtype=float)
    if (R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=ROTATION_TOLERANCE)
            or np.linalg.det(R) <= 0):
        raise ValueError(f"R_body_cam must be a 3x3 rotation matrix, got {R.tolist()}")
    return R


class _RateLimiter:
    """At most rate_hz on average: each send moves the due time on by one period, and a pose
    RATE_SLACK_FRACTION of a period early is still due. Never more than one pose per
    (1 - slack) periods, and no credit builds up while idle."""

    def __init__(self, rate_hz: float) -> None:
        self._period_s = 1.0 / rate_hz
        self._slack_s = RATE_SLACK_FRACTION * self._period_s
        self._due_s = -math.inf

    def allow(self, now_s: float) -> bool:
        if now_s < self._due_s - self._slack_s:
            return False
        self._due_s = max(self._due_s, now_s) + self._period_s
        return True


def local_pose(T_world_cam: np.ndarray, R_body_cam: np.ndarray) -> tuple[np.ndarray, Rotation]:
    """kinfly's camera pose as the vehicle's pose in the local frame, which is the body FRD frame
    at the first keyframe: T_local_body = T_body_cam T_world_cam T_cam_body with the mount taken
    as a pure rotation. Returns (position in the local frame [m], R_local_body)."""
    R_world_cam = T_world_cam[:3, :3]
    p_world_cam = T_world_cam[:3, 3]
    R_local_body = R_body_cam @ R_world_cam @ R_body_cam.T
    return R_body_cam @ p_world_cam, Rotation.from_matrix(R_local_body)


def load_signing_key(path: str | os.PathLike[str]) -> bytes:
    """A 32-byte MAVLink 2 signing secret, under the same file rules as the kinfly uplink key
    (KeyFileError when the file is open to group/others or not 32 bytes)."""
    from ._native import load_key_file  # the uplink key's rules (firmware/link/signing.cpp)
    return load_key_file(path)


class MavlinkBridge:
    """One MAVLink link to an autopilot. poll() reads telemetry and keeps our heartbeat going;
    send_pose() forwards kinfly poses. The two may run on different threads."""

    def __init__(self, url: str, *, forward: str | None = None, rate_hz: float = 30.0,
                 signing_key: bytes | None = None, baud: int = 57600, source_system: int = 1,
                 source_component: int = mavlink2.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY,
                 R_body_cam: np.ndarray | None = None) -> None:
        if forward is not None and forward not in FORWARD_MODES:
            raise ValueError(f"forward must be None or one of {FORWARD_MODES}, got {forward!r}")
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        if signing_key is not None and len(signing_key) != SIGNING_KEY_BYTES:
            raise ValueError(f"signing_key must be {SIGNING_KEY_BYTES} bytes, "
                             f"got {len(signing_key)}")
        self.url = url
        self.forward = forward
        self.state = AutopilotState()
        self.counters = MavlinkCounters()
        self._R_body_cam = _validated_rotation(
            R_BODY_CAM_FORWARD if R_body_cam is None else R_body_cam)
        self._rate = _RateLimiter(rate_hz)
        self._next_heartbeat_s = -math.inf
        self._autopilot_source: tuple[int, int] | None = None
        self._lock = threading.Lock()
        self._conn = self._open(_parse_url(url), baud, source_system, source_component)
        if signing_key is not None:
            # No allow_unsigned_callback: every unsigned message is refused, RADIO_STATUS too.
            self._conn.setup_signing(signing_key, sign_outgoing=True)

    def _open(self, parsed: _ParsedUrl, baud: int, source_system: int,
              source_component: int) -> Any:
        try:
            if parsed.scheme == "serial":
                # Directly, not through mavlink_connection, which guesses from the name and
                # would read some paths as log files or UDP addresses.
                conn = mavutil.mavserial(parsed.address, baud=baud, source_system=source_system,
                                         source_component=source_component)
            else:
                conn = mavutil.mavlink_connection(f"{parsed.scheme}:{parsed.address}",
                                                  source_system=source_system,
                                                  source_component=source_component)
        except ImportError as err:  # pyserial is imported only when a serial port is opened
            raise MavlinkError(f"serial device {parsed.address} needs pyserial: {err}") from err
        except (OSError, ValueError) as err:
            raise MavlinkError(f"cannot open MAVLink {self.url!r}: {err}") from err
        conn.mav = mavlink2.MAVLink(conn, srcSystem=source_system, srcComponent=source_component)
        conn.mav.robust_parsing = True  # bad bytes become BAD_DATA messages, counted, not raised
        # Marks the link as MAVLink 2 already, so mavutil does not switch the process-wide
        # dialect when the first MAVLink 2 byte arrives.
        conn.WIRE_PROTOCOL_VERSION = mavlink2.WIRE_PROTOCOL_VERSION
        return conn

    def poll(self) -> list[str]:
        """Reads everything pending without blocking, updates `state`, sends our heartbeat when
        due; returns the types of the messages accepted this call, each once, in arrival order."""
        heard: dict[str, None] = {}
        with self._lock:
            self._heartbeat_if_due()
            for _ in range(MAX_MESSAGES_PER_POLL):
                try:
                    msg = self._conn.recv_msg()
                except OSError:
                    self.counters.link_errors += 1
                    break
                if msg is None:
                    break
                name = self._classify(msg)
                if name is not None:
                    heard[name] = None
        return list(heard)

    def _heartbeat_if_due(self) -> None:
        now_s = time.monotonic()
        if now_s < self._next_heartbeat_s:
            return
        self._next_heartbeat_s = now_s + HEARTBEAT_PERIOD_S
        if self._send(self._conn.mav.heartbeat_send, mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
                      mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, mavlink2.MAV_STATE_ACTIVE):
            self.counters.heartbeats_sent += 1

    def _classify(self, msg: Any) -> str | None:
        """Counts a parsed message and applies it to the state; its type when it was accepted."""
        name = msg.get_type()
        if name == "BAD_DATA":
            if msg.reason != "Invalid signature":
                self.counters.bad_data += 1
            elif _is_signed_frame(msg.data):
                self.counters.rejected_bad_signature += 1
            else:
                self.counters.rejected_unsigned += 1
            return None
        if name.startswith("UNKNOWN_"):
            self.counters.unknown += 1
            return None
        self.counters.received += 1
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        if (name == "HEARTBEAT" and self._autopilot_source is None
                and msg.autopilot != mavlink2.MAV_AUTOPILOT_INVALID):
            # GCSs, companions (us included) and gimbals send MAV_AUTOPILOT_INVALID.
            self._autopilot_source = source
            self.state.autopilot_system_id = source[0]
        if source != self._autopilot_source:
            self.counters.other_source += 1
            return name
        self._apply(name, msg)
        self.state.last_heard_utime = time.time_ns() // 1000
        return name

    def _apply(self, name: str, msg: Any) -> None:
        s = self.state
        if name == "HEARTBEAT":
            s.heartbeat_type, s.autopilot = msg.type, msg.autopilot
            s.base_mode, s.custom_mode = msg.base_mode, msg.custom_mode
            s.system_status = msg.system_status
            s.armed = bool(msg.base_mode & mavlink2.MAV_MODE_FLAG_SAFETY_ARMED)
        elif name == "ATTITUDE":
            s.roll_rad, s.pitch_rad, s.yaw_rad = msg.roll, msg.pitch, msg.yaw
        elif name == "SYS_STATUS":
            s.battery_voltage_v = (None if msg.voltage_battery == _UINT16_UNKNOWN
                                   else msg.voltage_battery / 1000.0)
            s.battery_current_a = _current_a(msg.current_battery)
            s.battery_remaining_pct = _remaining_pct(msg.battery_remaining)
        elif name == "BATTERY_STATUS" and msg.id == 0:
            # Battery 0 is the one SYS_STATUS reports. Cells, or the whole pack in cell 0 when
            # cells are not measured: unused ones are UINT16_MAX in voltages and 0 in
            # voltages_ext, so the sum is the pack voltage.
            cells_mv = [v for v in msg.voltages if v != _UINT16_UNKNOWN]
            cells_mv += [v for v in msg.voltages_ext if v != 0]
            s.battery_voltage_v = sum(cells_mv) / 1000.0 if cells_mv else None
            s.battery_current_a = _current_a(msg.current_battery)
            s.battery_remaining_pct = _remaining_pct(msg.battery_remaining)
        elif name == "LOCAL_POSITION_NED":
            s.local_x_m, s.local_y_m, s.local_z_m = msg.x, msg.y, msg.z
        elif name == "GLOBAL_POSITION_INT":
            s.latitude_deg, s.longitude_deg = msg.lat * 1e-7, msg.lon * 1e-7
            s.altitude_msl_m, s.relative_altitude_m = msg.alt / 1000.0, msg.relative_alt / 1000.0

    def send_pose(self, utime: int, T_world_cam: np.ndarray, reset_counter: int, *,
                  covariance_m2: float | None = None,
                  covariance_rad2: float | None = None) -> bool:
        """Sends kinfly's T_world_cam (4x4, camera to map) as the vehicle's pose in the local FRD
        frame, stamped `utime` [us, capture time]. reset_counter is sent modulo 256; bump it when
        the map jumps (a loop closure or a re-anchoring). covariance_m2 is the position variance
        on each axis; covariance_rad2 the attitude variance, 0 when not given, which both
        ArduPilot and PX4 raise to their configured noise floor. Without covariance_m2 the
        covariance is sent as unknown. False, and counted, when forwarding is off, the pose is
        not finite, or it came before rate_hz makes the next pose due."""
        T_world_cam = np.asarray(T_world_cam, dtype=float)
        if T_world_cam.shape != (4, 4):
            raise ValueError(f"T_world_cam must be 4x4, got shape {T_world_cam.shape}")
        covariance = _pose_covariance(covariance_m2, covariance_rad2)
        with self._lock:
            if self.forward is None:
                self.counters.skipped_forward_off += 1
                return False
            # MAVLink's time fields are unsigned: a negative utime cannot be sent.
            if not np.all(np.isfinite(T_world_cam)) or utime < 0:
                self.counters.skipped_invalid += 1
                return False
            if not self._rate.allow(time.monotonic()):
                self.counters.skipped_rate += 1
                return False
            p_local, R_local_body = local_pose(T_world_cam, self._R_body_cam)
            x, y, z = (float(v) for v in p_local)
            if self.forward == "vision":
                yaw, pitch, roll = R_local_body.as_euler("ZYX")
                sent = self._send(self._conn.mav.vision_position_estimate_send, utime, x, y, z,
                                  roll, pitch, yaw, covariance, reset_counter % 256)
            else:
                qx, qy, qz, qw = R_local_body.as_quat()
                nan3 = (math.nan,) * 3  # velocities are not estimated: NaN, as MAVLink asks
                sent = self._send(self._conn.mav.odometry_send, utime,
                                  mavlink2.MAV_FRAME_LOCAL_FRD, mavlink2.MAV_FRAME_BODY_FRD,
                                  x, y, z, [qw, qx, qy, qz], *nan3, *nan3, covariance,
                                  _UNKNOWN_COVARIANCE, reset_counter % 256,
                                  mavlink2.MAV_ESTIMATOR_TYPE_VISION, 0)  # quality 0: unknown
            if sent:
                self.counters.sent += 1
            return sent

    def _send(self, send: Any, *args: Any) -> bool:
        try:
            send(*args)
        except OSError:
            self.counters.link_errors += 1
            return False
        return True

    def close(self) -> None:
        with self._lock:
            self._conn.close()


def _is_signed_frame(frame: bytes | bytearray) -> bool:
    return (len(frame) > 2 and frame[0] == mavlink2.PROTOCOL_MARKER_V2
            and bool(frame[2] & mavlink2.MAVLINK_IFLAG_SIGNED))


def _current_a(current_ca: int) -> float | None:
    return None if current_ca == -1 else current_ca / 100.0


def _remaining_pct(remaining: int) -> int | None:
    return None if remaining == -1 else remaining


def _pose_covariance(position_m2: float | None, attitude_rad2: float | None) -> list[float]:
    if position_m2 is None:
        if attitude_rad2 is not None:
            raise ValueError("covariance_rad2 needs covariance_m2: MAVLink has no way to send "
                             "an attitude variance with the position's unknown")
        return list(_UNKNOWN_COVARIANCE)
    covariance = [0.0] * _COVARIANCE_LEN
    for i in _POSITION_DIAGONAL:
        covariance[i] = position_m2
    for i in _ATTITUDE_DIAGONAL:
        covariance[i] = 0.0 if attitude_rad2 is None else attitude_rad2
    return covariance
