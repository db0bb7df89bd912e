"""The ground's receiving end, the native Receiver (firmware/link's C++), over a real in-process LCM
(memq://): good messages come out typed (a Keyframe with its depth decoded, the drone's status,
poses); unknown channels, wrong fingerprints, truncated messages, absurd sizes, payloads longer
than declared, undecodable depth and another vehicle's messages are rejected and counted, and
nothing raises. Then the rest of the link as Python sees it: channel names, key files, signing."""
from __future__ import annotations

import os
import struct
import subprocess
from pathlib import Path

import lcm
import numpy as np
import pytest

from conftest import built
from kinfly import depth_keyframe_t, drone_status_t, odometry_t
from kinfly_ground._native import (MAX_VEHICLE_ID, Channel, CorrectionReceiver, DepthCodec,
                                   KeyFileError, PinholeCamera, Receiver, Signer, TrackingStatus,
                                   channel_name, ground_subscriptions, key_id, load_key_file,
                                   parse_channel)

VEHICLE = 4
SEED = 20261122
NOW = 1_700_000_000_000_000  # [us]
# The payload_size field's offset: the fixed part of a keyframe with an empty payload, less 4.
PAYLOAD_SIZE_AT = len(depth_keyframe_t().encode()) - 4


def keyframe(depth: np.ndarray, codec: DepthCodec) -> depth_keyframe_t:
    m = depth_keyframe_t()
    m.utime, m.vehicle_id, m.frame_id, m.keyframe_id = NOW, VEHICLE, 9, 2
    m.camera.height, m.camera.width = depth.shape
    m.camera.fx, m.camera.fy, m.camera.cx, m.camera.cy = 535.4, 539.2, 320.1, 247.6
    m.depth_scale_m = 1 / 5000
    m.T_world_cam.position_m = [0.5, 0.0, 0.0]
    m.T_world_cam.orientation_xyzw = [0.0, 0.0, 0.0, 1.0]
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

    received = []
    receiver = Receiver()

    def on_message(channel: str, data: bytes) -> None:
        result = receiver.receive(channel, data)
        if result is not None:
            received.append(result)

    lc = lcm.LCM("memq://")
    lc.subscribe(".*", on_message)
    kf = channel_name(Channel.KEYFRAME, VEHICLE)

    def send(channel: str, data: bytes) -> None:
        lc.publish(channel, data)
        lc.handle_timeout(100)

    send(kf, good_bytes)
    assert len(received) == 1
    channel, vehicle, k = received[0]
    assert channel is Channel.KEYFRAME and vehicle == VEHICLE
    assert np.array_equal(k.depth, depth)
    assert (k.utime, k.frame_id, k.keyframe_id, k.depth_scale_m) == (NOW, 9, 2, 1 / 5000)
    assert k.camera == PinholeCamera(width=64, height=48, fx=np.float32(535.4),
                                     fy=np.float32(539.2), cx=np.float32(320.1),
                                     cy=np.float32(247.6))
    assert k.tracking is TrackingStatus.OK
    assert np.allclose(k.T_world_cam, [[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])

    send(f"KINFLY_{VEHICLE}_NO_SUCH", good_bytes)                # unknown channel
    send("SOMEONE_ELSES_CHANNEL", good_bytes)                   # unknown channel
    send(kf, drone_status_t().encode()[:8] + good_bytes[8:])    # wrong fingerprint
    send(kf, good_bytes[:-1])                                   # truncated
    send(kf, good_bytes + b"\0\0")                              # payload longer than declared
    absurd = keyframe(depth, codec)
    absurd.camera.width, absurd.camera.height = 100_000, 100_000
    send(kf, absurd.encode())                                   # width x height beyond bound
    forged = bytearray(good_bytes)
    forged[PAYLOAD_SIZE_AT:PAYLOAD_SIZE_AT + 4] = struct.pack(">i", 2**31 - 1)
    send(kf, bytes(forged))                                     # absurd payload size
    garbled = keyframe(depth, codec)
    garbled.payload = bytes(len(garbled.payload))
    send(kf, garbled.encode())                                  # depth does not decode
    send(channel_name(Channel.KEYFRAME, VEHICLE + 1), good_bytes)  # another vehicle's channel
    send(channel_name(Channel.CORRECTION, VEHICLE), good_bytes)    # the ground's own: ignored

    assert len(received) == 1
    rejects = receiver.rejects
    assert (rejects.malformed, rejects.unknown_channel, rejects.wrong_vehicle) == (6, 2, 1)
    assert rejects.total() == 9

    # A raw capture has no onboard pose.
    raw = keyframe(depth, codec)
    raw.tracking_status = odometry_t.TRACKING_NONE
    _, _, k = receiver.receive(channel_name(Channel.DEPTH, VEHICLE), raw.encode())
    assert k.tracking is None and k.T_world_cam is None

    status = drone_status_t()
    status.vehicle_id, status.keyframes_sent, status.run_state = VEHICLE, 5, drone_status_t.RUN_FINAL
    channel, _, s = receiver.receive(channel_name(Channel.STATUS, VEHICLE), status.encode())
    assert channel is Channel.STATUS and s.keyframes_sent == 5 and s.final


def test_channel_names_are_the_links() -> None:
    assert channel_name(Channel.KEYFRAME, 7) == "KINFLY_7_KEYFRAME"
    for channel in Channel:
        assert parse_channel(channel_name(channel, MAX_VEHICLE_ID)) == (channel, MAX_VEHICLE_ID)
    assert parse_channel("KINFLY_07_IMU") is None
    with pytest.raises(ValueError):
        channel_name(Channel.IMU, MAX_VEHICLE_ID + 1)
    assert ground_subscriptions(None) == ("KINFLY_[0-9]+_KEYFRAME(_CHUNK)?",
                                          "KINFLY_[0-9]+_(?!KEYFRAME(_CHUNK)?$).*")


def test_keygen_key_loads_with_the_same_id_and_bad_files_are_refused(tmp_path: Path) -> None:
    keygen = built("bin/kinfly-keygen")
    path = tmp_path / "v7.key"
    out = subprocess.run([keygen, "--out", path], check=True, capture_output=True,
                         text=True).stdout
    assert f"0x{key_id(load_key_file(path)):08x}" in out
    os.chmod(path, 0o644)
    with pytest.raises(KeyFileError, match="chmod 600"):
        load_key_file(path)
    short = tmp_path / "short.key"
    short.write_bytes(b"short")
    short.chmod(0o600)
    with pytest.raises(KeyFileError, match="bytes"):
        load_key_file(short)


def test_signed_corrections_pass_the_drones_receiver() -> None:
    key = bytes(range(32))
    signer = Signer(key, VEHICLE, first_sequence=100)
    drone = CorrectionReceiver(key, VEHICLE)
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    first = signer.sign_correction(12, NOW - 1000, T, 3, utime_now=NOW)
    correction = drone.receive(first, NOW)
    assert (correction.keyframe_id, correction.utime, correction.reset_counter) == (12, NOW - 1000, 3)
    assert np.allclose(correction.T_world_cam, T)
    assert drone.receive(first, NOW) is None  # replayed
    other = CorrectionReceiver(bytes(range(1, 33)), VEHICLE)
    assert other.receive(first, NOW) is None  # another key
    assert (drone.rejects.replayed, other.rejects.wrong_key, drone.accepted) == (1, 1, 1)
