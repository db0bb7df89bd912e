"""LCM channel names: the one place the Python side spells them (firmware/link/channels.h is the
C++ one; proto/README.md is the table both follow). KINFLY_<vehicle id>_<KIND>."""
from __future__ import annotations

import enum
import re
from typing import NamedTuple

MAX_VEHICLE_ID = 65535
_PREFIX = "KINFLY_"


class Channel(enum.Enum):
    """Each kind of channel, with the suffix it has on the wire."""

    DEPTH = "DEPTH"                  # depth_keyframe_t, every captured frame (flight logs only)
    KEYFRAME = "KEYFRAME"            # depth_keyframe_t, keyframes with the onboard pose
    ODOMETRY = "ODOMETRY"            # odometry_t
    IMU = "IMU"                      # imu_t
    STATUS = "STATUS"                # status_t, the drone's
    CORRECTION = "CORRECTION"        # signed_t around pose_correction_t (ground -> drone)
    GROUND_STATUS = "GROUND_STATUS"  # status_t, the ground station's
    GROUND_TRUTH = "GROUND_TRUTH"    # pose_t, in converted datasets only


class ParsedChannel(NamedTuple):
    channel: Channel
    vehicle_id: int


# No leading zeros, at most 5 digits: every id has exactly one name.
_NAME = re.compile(r"KINFLY_(0|[1-9][0-9]{0,4})_([A-Z_]+)")
_SUFFIXES = {c.value: c for c in Channel}


def channel_name(channel: Channel, vehicle_id: int) -> str:
    if not 0 <= vehicle_id <= MAX_VEHICLE_ID:
        raise ValueError(f"vehicle id {vehicle_id} outside [0, {MAX_VEHICLE_ID}]")
    return f"{_PREFIX}{vehicle_id}_{channel.value}"


def parse_channel(name: str) -> ParsedChannel | None:
    """The channel and vehicle of a kinfly channel name; None for anything else."""
    match = _NAME.fullmatch(name)
    if match is None:
        return None
    vehicle_id = int(match.group(1))
    channel = _SUFFIXES.get(match.group(2))
    if channel is None or vehicle_id > MAX_VEHICLE_ID:
        return None
    return ParsedChannel(channel, vehicle_id)


def channels_regex(vehicle_id: int | None) -> tuple[str, str]:
    """LCM subscription patterns (LCM anchors them) for the keyframes and for every other
    channel of one vehicle, or of every vehicle when VEHICLE_ID is None: two subscriptions,
    so that each has its own queue in LCM."""
    vid = "[0-9]+" if vehicle_id is None else str(vehicle_id)
    keyframe = Channel.KEYFRAME.value
    return f"{_PREFIX}{vid}_{keyframe}", f"{_PREFIX}{vid}_(?!{keyframe}$).*"
