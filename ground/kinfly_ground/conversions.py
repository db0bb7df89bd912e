"""The Python side's message boundary: bounded decoding of received LCM messages (the same checks
as firmware/link/decode.cpp) and pose conversions. lcm-gen's Python decoder silently returns a
short payload when a message is truncated, so every received message goes through decode()."""
from __future__ import annotations

import io
import math
import struct
from dataclasses import dataclass
from typing import Sequence, TypeVar

import numpy as np
from scipy.spatial.transform import Rotation

from kinfly import (depth_keyframe_t, imu_t, odometry_t, pose_correction_t, pose_t, signed_t,
                    status_t)

from .channels import MAX_VEHICLE_ID

QUATERNION_NORM_TOLERANCE = 1e-3  # senders normalise; a far-off norm means a corrupted message


M = TypeVar("M")


@dataclass(frozen=True)
class DecodeBounds:
    max_width_px: int = 1280
    max_height_px: int = 1024
    max_keyframe_payload_bytes: int = 8 << 20
    max_signed_payload_bytes: int = 4096


class DecodeError(Exception):
    """A received message that was rejected. `status` is one of: wrong type, truncated,
    trailing bytes, out of bounds, bad field (as DecodeStatus in C++)."""

    def __init__(self, status: str, detail: str) -> None:
        super().__init__(f"{status}: {detail}")
        self.status = status
        self.detail = detail


def _fixed_size(msg_type: type) -> int:
    """Encoded size of a message with every variable array empty (fingerprint included)."""
    empty = msg_type()
    # lcm-gen's Python defaults byte arrays to "", which encodes as zero bytes even for mac[32].
    if hasattr(empty, "mac"):
        empty.mac = bytes(signed_t.MAC_BYTES)
    if hasattr(empty, "payload"):
        empty.payload = b""
        empty.payload_size = 0
    return len(empty.encode())


_FIXED_SIZES = {t: _fixed_size(t) for t in (depth_keyframe_t, imu_t, odometry_t, pose_t,
                                             pose_correction_t, signed_t, status_t)}


def has_fingerprint(msg_type: type, data: bytes) -> bool:
    return data[:8] == msg_type._get_packed_fingerprint()


def decode(msg_type: type[M], data: bytes, bounds: DecodeBounds = DecodeBounds()) -> M:
    """Decodes data as msg_type, or raises DecodeError naming what is wrong."""
    if len(data) < 8:
        raise DecodeError("truncated", f"{len(data)} bytes")
    if not has_fingerprint(msg_type, data):
        raise DecodeError("wrong type", f"not a {msg_type.__name__}")
    expected = _FIXED_SIZES[msg_type]
    if msg_type in (depth_keyframe_t, signed_t):
        # payload_size is the last fixed field (a C++ unit test checks the generated layout).
        if len(data) < expected:
            raise DecodeError("truncated", "header")
        (declared,) = struct.unpack_from(">i", data, expected - 4)
        bound = (bounds.max_keyframe_payload_bytes if msg_type is depth_keyframe_t
                 else bounds.max_signed_payload_bytes)
        if not 0 <= declared <= bound:
            raise DecodeError("out of bounds", f"payload_size {declared} outside [0, {bound}]")
        expected += declared
    if len(data) < expected:
        raise DecodeError("truncated", f"{len(data)} of {expected} bytes")
    if len(data) > expected:
        raise DecodeError("trailing bytes", f"{len(data)} bytes for a {expected}-byte message")
    message = msg_type._decode_one(io.BytesIO(data[8:]))
    problem = _field_problem(message, bounds)
    if problem:
        raise DecodeError("bad field", problem)
    return message


def _pose_problem(position_m: tuple[float, ...], orientation_xyzw: tuple[float, ...]) -> str:
    if not all(math.isfinite(v) for v in position_m):
        return "position_m is not finite"
    if not all(math.isfinite(v) for v in orientation_xyzw):
        return "orientation_xyzw is not finite"
    norm = math.sqrt(sum(v * v for v in orientation_xyzw))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        return f"orientation_xyzw is not a unit quaternion (norm {norm:g})"
    return ""


def _field_problem(m: object, bounds: DecodeBounds) -> str:
    vehicle_id = getattr(m, "vehicle_id")
    if not 0 <= vehicle_id <= MAX_VEHICLE_ID:
        return f"vehicle_id {vehicle_id} outside [0, {MAX_VEHICLE_ID}]"
    tracking = getattr(m, "tracking_status", None)
    if tracking is not None and not (odometry_t.TRACKING_NONE <= tracking
                                     <= odometry_t.TRACKING_GIVEN):
        return f"unknown tracking_status {tracking}"
    if isinstance(m, depth_keyframe_t):
        if not (0 < m.width <= bounds.max_width_px and 0 < m.height <= bounds.max_height_px):
            return (f"image {m.width}x{m.height} outside 1x1..{bounds.max_width_px}x"
                    f"{bounds.max_height_px}")
        if not all(math.isfinite(v) for v in (m.fx, m.fy, m.cx, m.cy)):
            return "intrinsics are not finite"
        if not (m.fx > 0 and m.fy > 0):
            return "focal lengths must be positive"
        if not (m.depth_scale_m > 0 and math.isfinite(m.depth_scale_m)):
            return "depth_scale_m must be positive and finite"
        if not (depth_keyframe_t.ENCODING_RAW16 <= m.encoding
                <= depth_keyframe_t.ENCODING_PALETTE_RVL_ZSTD):
            return f"unknown encoding {m.encoding}"
        if m.tracking_status == odometry_t.TRACKING_NONE:
            return ""
    if isinstance(m, odometry_t) and not 0.0 <= m.inlier_fraction <= 1.0:
        return "inlier_fraction outside [0, 1]"
    if isinstance(m, imu_t):
        values = (*m.angular_velocity_rad_s, *m.linear_acceleration_m_s2)
        return "" if all(math.isfinite(v) for v in values) else "IMU sample is not finite"
    if isinstance(m, pose_correction_t):
        if m.keyframe_id < 0:
            return "keyframe_id is negative"
        if m.reset_counter < 0:
            return "reset_counter is negative"
    if isinstance(m, status_t):
        if m.source not in (status_t.SOURCE_DRONE, status_t.SOURCE_GROUND):
            return f"unknown source {m.source}"
        if m.run_state not in (status_t.RUN_ACTIVE, status_t.RUN_FINAL):
            return f"unknown run_state {m.run_state}"
        if m.last_keyframe_id < -1:
            return "last_keyframe_id below -1"
    if hasattr(m, "orientation_xyzw"):
        return _pose_problem(m.position_m, m.orientation_xyzw)
    return ""


def pose_to_matrix(position_m: Sequence[float], orientation_xyzw: Sequence[float]) -> np.ndarray:
    """T_world_cam as a 4x4 matrix from a message's position and (x, y, z, w) quaternion."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(orientation_xyzw).as_matrix()  # scipy's order is (x, y, z, w)
    T[:3, 3] = position_m
    return T


def correction_message(vehicle_id: int, keyframe_id: int, utime: int, T_world_cam: np.ndarray,
                       reset_counter: int) -> pose_correction_t:
    """The refined pose of one keyframe, for the drone (to be signed)."""
    m = pose_correction_t()
    m.utime = utime
    m.vehicle_id = vehicle_id
    m.keyframe_id = keyframe_id
    m.position_m, m.orientation_xyzw = matrix_to_pose(T_world_cam)
    m.reset_counter = reset_counter
    return m


def matrix_to_pose(T: np.ndarray) -> tuple[list[float], list[float]]:
    """(position_m, orientation_xyzw) of a 4x4 T_world_cam, with w >= 0."""
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    if q[3] < 0:
        q = -q
    return [float(v) for v in T[:3, 3]], [float(v) for v in q]
