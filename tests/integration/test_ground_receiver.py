"""The ground's receiving end over a real in-process LCM (memq://): good messages reach the
handler with their depth decoded; unknown channels, wrong fingerprints, truncated messages,
absurd sizes, payloads longer than declared, undecodable depth and another vehicle's messages
are rejected and counted, and nothing raises."""
from __future__ import annotations

import struct

import lcm
import numpy as np

from kinfly import depth_keyframe_t, odometry_t, status_t
from kinfly_ground._native import DepthCodec
from kinfly_ground.channels import Channel, channel_name
from kinfly_ground.conversions import _FIXED_SIZES
from kinfly_ground.link import Received, Receiver

VEHICLE = 4
SEED = 20261122


def keyframe(depth: np.ndarray, codec: DepthCodec) -> depth_keyframe_t:
    m = depth_keyframe_t()
    m.utime, m.vehicle_id, m.frame_id, m.keyframe_id = 1_700_000_000_000_000, VEHICLE, 9, 2
    m.height, m.width = depth.shape
    m.fx, m.fy, m.cx, m.cy = 535.4, 539.2, 320.1, 247.6
    m.depth_scale_m = 1 / 5000
    m.position_m, m.orientation_xyzw = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]
    m.tracking_status = odometry_t.TRACKING_OK
    m.encoding = depth_keyframe_t.ENCODING_PALETTE_RVL_ZSTD
    m.payload = codec.encode(depth)
    m.payload_size = len(m.payload)
    return m


def test_receiver_passes_the_good_and_counts_each_bad_kind() -> None:
    rng = np.random.default_rng(SEED)
    depth = rng.integers(0, 20000, size=(48, 64), dtype=np.uint16)
    depth[rng.random(depth.shape) < 0.2] = 0
    codec = DepthCodec()
    good = keyframe(depth, codec)
    good_bytes = good.encode()

    received: list[Received] = []
    receiver = Receiver(received.append)
    lc = lcm.LCM("memq://")
    lc.subscribe(".*", receiver.on_message)
    kf = channel_name(Channel.KEYFRAME, VEHICLE)

    def send(channel: str, data: bytes) -> None:
        lc.publish(channel, data)
        lc.handle_timeout(100)

    send(kf, good_bytes)
    assert len(received) == 1
    assert received[0].channel is Channel.KEYFRAME
    assert np.array_equal(received[0].depth, depth)

    send(f"KINFLY_{VEHICLE}_NO_SUCH", good_bytes)                # unknown channel
    send("SOMEONE_ELSES_CHANNEL", good_bytes)                   # unknown channel
    send(kf, status_t().encode()[:8] + good_bytes[8:])          # wrong fingerprint
    send(kf, good_bytes[:-1])                                   # truncated
    send(kf, good_bytes + b"\0\0")                              # payload longer than declared
    absurd = keyframe(depth, codec)
    absurd.width, absurd.height = 100_000, 100_000
    send(kf, absurd.encode())                                   # width x height beyond bound
    forged = bytearray(good_bytes)
    count_at = _FIXED_SIZES[depth_keyframe_t] - 4
    forged[count_at:count_at + 4] = struct.pack(">i", 2**31 - 1)
    send(kf, bytes(forged))                                     # absurd payload size
    garbled = keyframe(depth, codec)
    garbled.payload = bytes(len(garbled.payload))
    send(kf, garbled.encode())                                  # depth does not decode
    send(channel_name(Channel.KEYFRAME, VEHICLE + 1), good_bytes)  # another vehicle's channel

    assert len(received) == 1
    assert receiver.rejects.unknown_channel == 2
    assert receiver.rejects.malformed == 6
    assert receiver.rejects.wrong_vehicle == 1
    status = status_t()
    receiver.rejects.write_to(status)
    assert (status.rejected_malformed, status.rejected_unknown_channel,
            status.rejected_wrong_vehicle) == (6, 2, 1)
