"""What still crosses a language boundary on the wire: the lcm-gen Python types, which the tests
and tools write and read messages with, agree with the C++ ones kinfly-fw and the ground
station's native module decode with. Messages encoded by C++ decode in Python to the same values
and back (same fingerprints, same bytes). Decoding within bounds, signing, key files and channel
names have one implementation, firmware/link, tested in tests/firmware/test_link.cpp."""
from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from conftest import built
from kinfly import (chunk_request_t, depth_keyframe_t, drone_status_t, ground_status_t,
                    ground_truth_t, imu_t, keyframe_chunk_t, odometry_t, pose3d_t,
                    pose_correction_t, signed_t)

TYPES = (depth_keyframe_t, odometry_t, imu_t, ground_truth_t, pose_correction_t, drone_status_t,
         ground_status_t, signed_t, keyframe_chunk_t, chunk_request_t)

# The same samples as tests/system/wire_roundtrip.cpp, written independently: every float is exact
# in float32, so equal values mean equal bytes.
POSITION = [1.25, -2.5, 0.75]
ORIENTATION = [0.5, -0.5, 0.5, 0.5]


def sample_pose() -> pose3d_t:
    pose = pose3d_t()
    pose.position_m, pose.orientation_xyzw = POSITION, ORIENTATION
    return pose


def sample_correction() -> pose_correction_t:
    m = pose_correction_t()
    m.utime, m.vehicle_id, m.keyframe_id = 1_700_000_000_123_456, 7, 56
    m.T_world_cam, m.reset_counter = sample_pose(), 2
    return m


def samples() -> dict[type, object]:
    kf = depth_keyframe_t()
    kf.utime, kf.vehicle_id, kf.frame_id, kf.keyframe_id = 1_700_000_000_123_456, 7, 1234, 56
    kf.camera.width, kf.camera.height = 640, 480
    kf.camera.fx, kf.camera.fy, kf.camera.cx, kf.camera.cy = 535.25, 539.125, 320.5, 247.75
    kf.depth_scale_m = 0.0002
    kf.T_world_cam = sample_pose()
    kf.tracking_status = odometry_t.TRACKING_OK
    kf.encoding = depth_keyframe_t.ENCODING_RVL_ZSTD
    kf.payload = bytes((i * 37) % 251 for i in range(1000))
    kf.payload_size = len(kf.payload)

    odo = odometry_t()
    odo.utime, odo.vehicle_id, odo.frame_id = 1_700_000_000_200_000, 7, 1240
    odo.T_world_cam = sample_pose()
    odo.tracking_status = odometry_t.TRACKING_LOST
    odo.inlier_fraction, odo.residual_m, odo.reset_counter = 0.625, 0.0078125, 3

    imu = imu_t()
    imu.utime, imu.vehicle_id = 1_700_000_000_201_000, 7
    imu.angular_velocity_rad_s = [0.125, -0.25, 0.5]
    imu.linear_acceleration_m_s2 = [0.5, -0.25, -9.8125]
    imu.temperature_c = 41.5
    imu.has_pressure_altitude, imu.pressure_altitude_m = True, 112.375

    truth = ground_truth_t()
    truth.utime, truth.vehicle_id = 1_700_000_000_300_000, 7
    truth.T_world_cam = sample_pose()

    st = drone_status_t()
    st.utime, st.vehicle_id = 1_700_000_000_400_000, 7
    st.depth_rate_hz, st.odometry_rate_hz, st.keyframe_rate_hz = 30.0, 29.5, 5.25
    st.frames_captured, st.queue_drops, st.keyframes_sent, st.keyframes_dropped = 9000, 12, 1500, 4
    st.tracking_state, st.link_state = odometry_t.TRACKING_OK, drone_status_t.LINK_UP
    st.sensor_state, st.sensor_connects, st.sensor_stalls = drone_status_t.SENSOR_STALLED, 2, 3
    st.frames_skipped, st.frames_lost = 11, 13
    st.last_keyframe_id, st.run_state = 1503, drone_status_t.RUN_FINAL
    st.send_budget_bps, st.redundancy, st.keyframe_scale = 8e6, 0.25, 2  # exact in float32
    st.chunks_sent, st.chunks_resent, st.keyframes_skipped = 55_000, 120, 7
    (st.rejected_unsigned, st.rejected_wrong_key, st.rejected_bad_mac, st.rejected_stale,
     st.rejected_replayed, st.rejected_malformed, st.rejected_unknown_channel,
     st.rejected_wrong_vehicle) = range(1, 9)
    st.corrections_accepted, st.corrections_unknown_keyframe = 1400, 9
    st.commands_passed = 3

    gs = ground_status_t()
    gs.utime, gs.vehicle_id = 1_700_000_000_450_000, 7
    gs.keyframe_rate_hz, gs.fused_rate_hz, gs.correction_rate_hz = 5.25, 5.0, 4.75
    (gs.keyframes_received, gs.keyframes_skipped, gs.keyframes_dropped, gs.keyframes_lost,
     gs.corrections_sent, gs.last_keyframe_id) = 1490, 3, 2, 5, 1480, 1499
    gs.run_state, gs.tracking_state = ground_status_t.RUN_ACTIVE, odometry_t.TRACKING_OK
    gs.link_state = ground_status_t.LINK_STALE
    gs.link_loss, gs.link_loss_run, gs.goodput_bps = 0.0625, 2.5, 6.5e6  # exact in float32
    gs.queue_delay_ms, gs.redundancy, gs.keyframe_age_ms = 12.5, 0.25, 85.5
    (gs.chunks_received, gs.keyframes_recovered, gs.keyframes_incomplete,
     gs.repair_requests) = 54_000, 40, 2, 17
    gs.rejected_malformed, gs.rejected_unknown_channel, gs.rejected_wrong_vehicle = 6, 7, 8

    env = signed_t()
    env.utime, env.vehicle_id, env.key_id = 1_700_000_000_500_000, 7, -123456789
    env.sequence = 1_700_000_000_000_001
    env.mac = bytes(255 - i for i in range(32))
    env.payload = sample_correction().encode()
    env.payload_size = len(env.payload)

    chunk = keyframe_chunk_t()
    chunk.utime, chunk.vehicle_id, chunk.keyframe_id = 1_700_000_000_123_456, 7, 56
    chunk.sequence, chunk.message_bytes, chunk.message_digest = 2_024, 3_000, -1_234_567_890_123
    chunk.sent_utime = 1_700_000_000_124_000
    chunk.groups, chunk.group, chunk.originals, chunk.recovery, chunk.index = 2, 1, 2, 2, 3
    chunk.block = bytes((i * 13) % 256 for i in range(600))
    chunk.block_size = len(chunk.block)

    request = chunk_request_t()
    request.utime, request.vehicle_id, request.keyframe_id = 1_700_000_000_123_456, 7, 56
    request.group, request.indices = 1, bytes([0, 3, 6])
    request.index_count = len(request.indices)
    return {depth_keyframe_t: kf, odometry_t: odo, imu_t: imu, ground_truth_t: truth,
            pose_correction_t: sample_correction(), drone_status_t: st, ground_status_t: gs,
            signed_t: env, keyframe_chunk_t: chunk, chunk_request_t: request}


@pytest.fixture(scope="module")
def roundtrip_bin() -> Path:
    return built("tests/wire_roundtrip")


def test_cpp_encodes_what_python_decodes(roundtrip_bin: Path, tmp_path: Path) -> None:
    out = subprocess.run([roundtrip_bin, "encode", tmp_path], check=True, capture_output=True,
                         text=True).stdout
    fingerprints = dict(line.split() for line in out.splitlines())
    expected = samples()
    assert set(fingerprints) == {t.__name__ for t in TYPES}
    for msg_type in TYPES:
        assert fingerprints[msg_type.__name__] == msg_type._get_packed_fingerprint().hex()
        data = (tmp_path / f"{msg_type.__name__}.bin").read_bytes()
        got = msg_type.decode(data)
        want = expected[msg_type]
        assert fields(got) == fields(want), msg_type.__name__
        assert data == want.encode(), msg_type.__name__


def fields(message: object) -> object:
    """Every field's value, nested messages as dicts; arrays (tuples or bytes) as lists."""
    if hasattr(message, "__slots__"):
        return {name: fields(getattr(message, name)) for name in message.__slots__}
    return list(message) if isinstance(message, (tuple, list, bytes)) else message


def test_python_encodes_what_cpp_decodes(roundtrip_bin: Path, tmp_path: Path) -> None:
    for msg_type, message in samples().items():
        (tmp_path / f"{msg_type.__name__}.bin").write_bytes(message.encode())
    result = subprocess.run([roundtrip_bin, "decode", tmp_path], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.split() == [w for t in TYPES for w in (t.__name__, "ok")]


def test_python_encodes_what_cpp_decodes(roundtrip_bin: Path, tmp_path: Path) -> None:
    for msg_type, message in samples().items():
        (tmp_path / f"{msg_type.__name__}.bin").write_bytes(message.encode())
    result = subprocess.run([roundtrip_bin, "decode", tmp_path], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.split() == [w for t in TYPES for w in (t.__name__, "ok")]
