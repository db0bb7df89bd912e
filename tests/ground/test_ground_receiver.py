"""The ground's receiving end, the native Receiver (firmware/link's C++), over a real in-process LCM
(memq://): good messages come out typed (a Keyframe with its depth decoded, the drone's status,
poses); unknown channels, wrong fingerprints, truncated messages, absurd sizes, payloads longer
than declared, undecodable depth and another vehicle's messages are rejected and counted, and
nothing raises. Keyframes in chunks (made here from docs/wire.md's layout) come out as the same
Keyframe, a missing chunk is asked for (again, while it stays missing, up to the asks allowed),
and the link's quality is measured. Then the rest of
the link as Python sees it: channel names, key files, signing."""
from __future__ import annotations

import os
import struct
import subprocess
from pathlib import Path

import lcm
import numpy as np
import pytest

from conftest import built
from keyframe_chunks import chunks_of
from kinfly import chunk_request_t, depth_keyframe_t, drone_status_t, odometry_t
from kinfly_ground._native import (MAX_LINK_VEHICLES, MAX_VEHICLE_ID, Channel, CorrectionReceiver,
                                   DepthCodec, KeyFileError, PinholeCamera, Receiver, Signer,
                                   TrackingStatus, channel_name, ground_subscriptions, key_id,
                                   load_key_file, parse_channel)

VEHICLE = 4
SEED = 20261122
NOW = 1_700_000_000_000_000  # [us]
ASKS, RETRY_S = 3, 0.2  # a Receiver's repair settings in the tests that ask for chunks
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


# --- keyframes in chunks ------------------------------------------------------------------------

BLOCK_BYTES = 500        # small blocks: the test's small keyframe is several chunks
CHUNK_PERIOD_US = 1_000  # the chunks arrive a millisecond apart
LINK_DELAY_US = 3_000    # one-way: arrival - sent_utime on the test's one clock
RECOVERY = 2             # declared in the headers (never sent): the redundancy reported
# The figures are exact functions of the arrival times given; only float round-off is left.
ROUNDOFF = 1e-9


def small_depth(seed: int = SEED) -> np.ndarray:
    rng = np.random.default_rng(seed)
    depth = rng.integers(0, 20000, size=(48, 64), dtype=np.uint16)
    depth[rng.random(depth.shape) < 0.2] = 0
    return depth


def chunked(message: depth_keyframe_t, first_sequence: int, first_arrival: int,
            **kwargs) -> list[tuple[int, bytes]]:
    """(arrival_utime, datagram) of each chunk of MESSAGE, CHUNK_PERIOD_US apart."""
    chunks = chunks_of(message.encode(), utime=message.utime, vehicle_id=message.vehicle_id,
                       keyframe_id=message.keyframe_id, first_sequence=first_sequence,
                       sent_utime=0, block_bytes=BLOCK_BYTES, **kwargs)
    out = []
    for i, c in enumerate(chunks):
        arrival = first_arrival + i * CHUNK_PERIOD_US
        c.sent_utime = arrival - LINK_DELAY_US
        out.append((arrival, c.encode()))
    return out


def test_a_chunked_keyframe_arrives_as_a_whole_one_would() -> None:
    depth = small_depth()
    message = keyframe(depth, DepthCodec())
    chunks = chunked(message, first_sequence=0, first_arrival=NOW, recovery=RECOVERY)
    assert len(chunks) >= 3
    receiver = Receiver()
    channel = channel_name(Channel.KEYFRAME_CHUNK, VEHICLE)
    results = [receiver.receive(channel, data, arrival_utime=t) for t, data in chunks]
    assert all(r == (Channel.KEYFRAME_CHUNK, VEHICLE, None) for r in results[:-1])
    kind, vehicle, k = results[-1]
    assert (kind, vehicle) == (Channel.KEYFRAME_CHUNK, VEHICLE)

    last_arrival = chunks[-1][0]
    q = receiver.link_quality(VEHICLE, now_utime=last_arrival)
    assert (q.chunks_received, q.chunks.stored, q.chunks.keyframes_completed) == (len(chunks),) * 2 + (1,)
    assert (q.keyframes_recovered, q.keyframes_incomplete, q.repair_requests) == (0, 0, 0)
    assert q.link_loss == 0.0 and q.link_loss_run == 1.0
    assert q.redundancy == pytest.approx(RECOVERY / len(chunks), abs=ROUNDOFF)
    assert q.keyframe_age_ms == pytest.approx((last_arrival - message.utime) * 1e-3, abs=ROUNDOFF)
    # Every datagram within the last second, and one link delay for all: no queueing.
    bits = 8 * sum(len(data) for _, data in chunks)
    assert q.goodput_bps == pytest.approx(bits, rel=ROUNDOFF)
    assert q.queue_delay_ms == pytest.approx(0.0, abs=ROUNDOFF)
    assert q.newest_keyframe_id == message.keyframe_id
    assert receiver.link_quality(VEHICLE + 1) is None
    assert receiver.rejects.total() == 0

    # The same Keyframe as the whole message gives.
    whole = receiver.receive(channel_name(Channel.KEYFRAME, VEHICLE), message.encode())[2]
    for name in ("utime", "frame_id", "keyframe_id", "depth_scale_m", "camera", "tracking"):
        assert getattr(k, name) == getattr(whole, name), name
    assert np.array_equal(k.depth, depth) and np.array_equal(k.T_world_cam, whole.T_world_cam)

    # A chunk that does not decode is counted like any malformed message; the ground's own
    # requests looping back are ignored.
    assert receiver.receive(channel, chunks[0][1][:-1]) is None
    assert receiver.receive(channel_name(Channel.CHUNK_REQUEST, VEHICLE), b"anything") is None
    assert (receiver.rejects.malformed, receiver.rejects.total()) == (1, 1)


def test_a_missing_chunk_is_asked_for_again_until_it_comes_or_the_asks_run_out() -> None:
    codec = DepthCodec()
    first = keyframe(small_depth(), codec)
    second = keyframe(small_depth(SEED + 1), codec)
    second.keyframe_id, second.utime = first.keyframe_id + 1, first.utime + 200_000
    one = chunked(first, first_sequence=0, first_arrival=NOW)
    two = chunked(second, first_sequence=len(one), first_arrival=NOW + 200_000)
    missing = 1
    receiver = Receiver(repair_max_asks=ASKS, repair_retry_s=RETRY_S)
    retry_us = round(RETRY_S * 1e6)
    channel = channel_name(Channel.KEYFRAME_CHUNK, VEHICLE)
    for t, data in one[:missing] + one[missing + 1:]:
        assert receiver.receive(channel, data, arrival_utime=t)[2] is None
    # Still the newest keyframe: its chunk may be on its way.
    assert receiver.repair_requests(VEHICLE, include_newest=False, now_us=0) == []
    receiver.receive(channel, two[0][1], arrival_utime=two[0][0])
    requests = receiver.repair_requests(VEHICLE, include_newest=False, now_us=0)
    assert len(requests) == 1
    request = chunk_request_t.decode(requests[0])
    assert (request.utime, request.vehicle_id, request.keyframe_id, request.group) == \
        (first.utime, VEHICLE, first.keyframe_id, 0)
    assert list(request.indices) == [missing]
    # The newest, while it arrives, only when asked to include it.
    newest = receiver.repair_requests(VEHICLE, include_newest=True, now_us=0)
    assert [chunk_request_t.decode(r).keyframe_id for r in newest] == [second.keyframe_id]
    # Not again before the retry time; then again, each retry time, until ASKS asks in all.
    assert receiver.repair_requests(VEHICLE, include_newest=True, now_us=retry_us - 1) == []
    for ask in range(1, ASKS):
        again = receiver.repair_requests(VEHICLE, include_newest=False, now_us=ask * retry_us)
        assert [list(chunk_request_t.decode(r).indices) for r in again] == [[missing]], ask
    end_us = 10 * ASKS * retry_us
    assert receiver.repair_requests(VEHICLE, include_newest=False, now_us=end_us) == []

    # The drone resends the chunk (a new sequence number): the keyframe is complete, repaired.
    resent = chunks_of(first.encode(), utime=first.utime, vehicle_id=VEHICLE,
                       keyframe_id=first.keyframe_id, first_sequence=0,
                       sent_utime=NOW + 210_000, block_bytes=BLOCK_BYTES)[missing]
    resent.sequence = len(one) + len(two)
    _, _, k = receiver.receive(channel, resent.encode(), arrival_utime=NOW + 213_000)
    assert k is not None and k.keyframe_id == first.keyframe_id
    q = receiver.link_quality(VEHICLE, now_utime=NOW + 213_000)
    assert (q.repair_requests, q.keyframes_recovered, q.keyframes_repaired) == (ASKS + 1, 1, 1)
    assert q.chunks.keyframes_completed == 1 and q.newest_keyframe_id == second.keyframe_id
    # The newest, asked for once, is due again by now, unless it is complete: it is not asked
    # for again once its chunks have come.
    assert [chunk_request_t.decode(r).keyframe_id for r in receiver.repair_requests(
        VEHICLE, include_newest=True, now_us=end_us)] == [second.keyframe_id]
    for t, data in two[1:]:
        receiver.receive(channel, data, arrival_utime=t)
    assert receiver.repair_requests(VEHICLE, include_newest=True, now_us=2 * end_us) == []


def test_repair_settings_out_of_range_are_refused() -> None:
    with pytest.raises(ValueError, match=r"max_asks must be in \[1, 16\]"):
        Receiver(repair_max_asks=0)
    with pytest.raises(ValueError, match=r"retry_s must be in \[0.01, 10\] s"):
        Receiver(repair_retry_s=0.001)


def test_chunks_of_too_many_vehicles_are_refused_and_counted() -> None:
    receiver = Receiver()
    message = keyframe(small_depth(), DepthCodec())
    for vehicle in range(MAX_LINK_VEHICLES + 2):
        message.vehicle_id = vehicle
        (t, data), *_ = chunked(message, first_sequence=0, first_arrival=NOW)
        receiver.receive(channel_name(Channel.KEYFRAME_CHUNK, vehicle), data, arrival_utime=t)
    assert receiver.link_vehicles_refused == 2
    assert receiver.link_quality(MAX_LINK_VEHICLES - 1) is not None
    assert receiver.link_quality(MAX_LINK_VEHICLES) is None


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
    assert drone.receive(first, NOW) is None  # a copy (the ground sends each more than once)
    other = CorrectionReceiver(bytes(range(1, 33)), VEHICLE)
    assert other.receive(first, NOW) is None  # another key
    assert (drone.duplicates, drone.rejects.replayed, other.rejects.wrong_key,
            drone.accepted) == (1, 0, 1, 1)
