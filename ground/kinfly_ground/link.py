"""The ground station's receiving end: one handler for every channel of the vehicles it listens
to. Each message is decoded within bounds (conversions.decode) and dispatched by channel kind;
whatever is rejected is counted by reason, for the ground's status_t (as RejectCounters does on
the drone)."""
from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from kinfly import depth_keyframe_t, imu_t, odometry_t, pose_t, status_t

from ._native import DepthCodec
from .channels import Channel, parse_channel
from .conversions import DecodeBounds, DecodeError, decode

# What the ground expects on each channel it consumes; the rest are its own (CORRECTION,
# GROUND_STATUS) and are ignored when they loop back on multicast.
_TYPES: dict[Channel, type] = {
    Channel.DEPTH: depth_keyframe_t,
    Channel.KEYFRAME: depth_keyframe_t,
    Channel.ODOMETRY: odometry_t,
    Channel.IMU: imu_t,
    Channel.STATUS: status_t,
    Channel.GROUND_TRUTH: pose_t,
}


@dataclasses.dataclass
class RejectCounters:
    malformed: int = 0        # wrong fingerprint, truncated, sizes or values out of bounds
    unknown_channel: int = 0  # not a kinfly channel name this side knows
    wrong_vehicle: int = 0    # the message's vehicle id is not the channel's

    def write_to(self, status: status_t) -> None:
        status.rejected_malformed = self.malformed
        status.rejected_unknown_channel = self.unknown_channel
        status.rejected_wrong_vehicle = self.wrong_vehicle


class Received(NamedTuple):
    channel: Channel
    message: Any
    depth: np.ndarray | None  # keyframes and depth frames: the decoded uint16 image


Handler = Callable[[Received], None]


class Receiver:
    """Decodes and dispatches received messages; the handler sees only messages that passed
    every check. Depth payloads are decoded here too, so one that does not decode is rejected
    and counted at the boundary, not deep in the fusion."""

    def __init__(self, handler: Handler, bounds: DecodeBounds = DecodeBounds()) -> None:
        self._handler = handler
        self._bounds = bounds
        self._codec = DepthCodec(max_width_px=bounds.max_width_px,
                                 max_height_px=bounds.max_height_px)
        self.rejects = RejectCounters()

    def on_message(self, channel_name: str, data: bytes) -> None:
        parsed = parse_channel(channel_name)
        if parsed is None:
            self.rejects.unknown_channel += 1
            return
        msg_type = _TYPES.get(parsed.channel)
        if msg_type is None:
            return
        depth = None
        try:
            message = decode(msg_type, data, self._bounds)
            if msg_type is depth_keyframe_t:
                depth = self._codec.decode(message.payload, message.encoding, message.width,
                                           message.height)
        except (DecodeError, ValueError):
            self.rejects.malformed += 1
            return
        if message.vehicle_id != parsed.vehicle_id:
            self.rejects.wrong_vehicle += 1
            return
        self._handler(Received(parsed.channel, message, depth))
