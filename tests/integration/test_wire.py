"""The wire contract across languages: messages encoded by C++ decode in Python to the same
values and back (same fingerprints, same bytes); Python's bounded decoder rejects each kind of bad
input; Python's signer, key files and channel names agree with the C++ ones."""
from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from conftest import built
from kinfly import (depth_keyframe_t, imu_t, odometry_t, pose_correction_t, pose_t, signed_t,
                    status_t)
from kinfly_ground import channels, conversions, signing
from kinfly_ground.conversions import DecodeError, decode

TYPES = (depth_keyframe_t, odometry_t, imu_t, pose_t, pose_correction_t, status_t, signed_t)

# The same samples as tests/wire/wire_roundtrip.cpp, written independently: every float is exact
# in float32, so equal values mean equal bytes.
POSITION = [1.25, -2.5, 0.75]
ORIENTATION = [0.5, -0.5, 0.5, 0.5]


def sample_correction() -> pose_correction_t:
    m = pose_correction_t()
    m.utime, m.vehicle_id, m.keyframe_id = 1_700_000_000_123_456, 7, 56
    m.position_m, m.orientation_xyzw, m.reset_counter = POSITION, ORIENTATION, 2
    return m


def samples() -> dict[type, object]:
    kf = depth_keyframe_t()
    kf.utime, kf.vehicle_id, kf.frame_id, kf.keyframe_id = 1_700_000_000_123_456, 7, 1234, 56
    kf.width, kf.height = 640, 480
    kf.fx, kf.fy, kf.cx, kf.cy = 535.25, 539.125, 320.5, 247.75
    kf.depth_scale_m = 0.0002
    kf.position_m, kf.orientation_xyzw = POSITION, ORIENTATION
    kf.tracking_status = odometry_t.TRACKING_OK
    kf.encoding = depth_keyframe_t.ENCODING_RVL_ZSTD
    kf.payload = bytes((i * 37) % 251 for i in range(1000))
    kf.payload_size = len(kf.payload)

    odo = odometry_t()
    odo.utime, odo.vehicle_id, odo.frame_id = 1_700_000_000_200_000, 7, 1240
    odo.position_m, odo.orientation_xyzw = POSITION, ORIENTATION
    odo.tracking_status = odometry_t.TRACKING_LOST
    odo.inlier_fraction, odo.residual_m, odo.reset_counter = 0.625, 0.0078125, 3

    imu = imu_t()
    imu.utime, imu.vehicle_id = 1_700_000_000_201_000, 7
    imu.angular_velocity_rad_s = [0.125, -0.25, 0.5]
    imu.linear_acceleration_m_s2 = [0.5, -0.25, -9.8125]
    imu.temperature_c = 41.5

    pose = pose_t()
    pose.utime, pose.vehicle_id = 1_700_000_000_300_000, 7
    pose.position_m, pose.orientation_xyzw = POSITION, ORIENTATION

    st = status_t()
    st.utime, st.vehicle_id, st.source = 1_700_000_000_400_000, 7, status_t.SOURCE_DRONE
    st.depth_rate_hz, st.odometry_rate_hz, st.keyframe_rate_hz = 30.0, 29.5, 5.25
    st.frames_captured, st.queue_drops, st.keyframes_sent, st.keyframes_dropped = 9000, 12, 1500, 4
    st.tracking_state, st.link_state = odometry_t.TRACKING_OK, status_t.LINK_UP
    st.sensor_state, st.sensor_connects, st.sensor_stalls = status_t.SENSOR_STALLED, 2, 3
    st.frames_skipped, st.frames_lost = 11, 13
    st.last_keyframe_id, st.run_state = 1503, status_t.RUN_FINAL
    (st.rejected_unsigned, st.rejected_wrong_key, st.rejected_bad_mac, st.rejected_stale,
     st.rejected_replayed, st.rejected_malformed, st.rejected_unknown_channel,
     st.rejected_wrong_vehicle) = range(1, 9)
    st.corrections_accepted, st.corrections_unknown_keyframe = 1400, 9

    env = signed_t()
    env.utime, env.vehicle_id, env.key_id = 1_700_000_000_500_000, 7, -123456789
    env.sequence = 1_700_000_000_000_001
    env.mac = bytes(255 - i for i in range(32))
    env.payload = sample_correction().encode()
    env.payload_size = len(env.payload)
    return {depth_keyframe_t: kf, odometry_t: odo, imu_t: imu, pose_t: pose,
            pose_correction_t: sample_correction(), status_t: st, signed_t: env}


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
        got = decode(msg_type, data)
        want = expected[msg_type]
        for field in msg_type.__slots__:
            assert as_list(getattr(got, field)) == as_list(getattr(want, field)), \
                f"{msg_type.__name__}.{field}"
        assert data == want.encode(), msg_type.__name__


def as_list(v: object) -> object:
    """Arrays decode as tuples or bytes; compare them as lists."""
    return list(v) if isinstance(v, (tuple, list, bytes)) else v


def test_python_encodes_what_cpp_decodes(roundtrip_bin: Path, tmp_path: Path) -> None:
    for msg_type, message in samples().items():
        (tmp_path / f"{msg_type.__name__}.bin").write_bytes(message.encode())
    result = subprocess.run([roundtrip_bin, "decode", tmp_path], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.split() == [w for t in TYPES for w in (t.__name__, "ok")]


# ---- bad input, Python side ----------------------------------------------------------------

def test_every_truncation_is_rejected() -> None:
    data = samples()[depth_keyframe_t].encode()
    for n in range(len(data)):
        with pytest.raises(DecodeError) as err:
            decode(depth_keyframe_t, data[:n])
        assert err.value.status == "truncated", n


def test_trailing_bytes_wrong_type_and_forged_sizes_are_rejected() -> None:
    data = sample_correction().encode()
    with pytest.raises(DecodeError, match="trailing bytes"):
        decode(pose_correction_t, data + b"\0")
    with pytest.raises(DecodeError, match="wrong type"):
        decode(odometry_t, data)
    keyframe = bytearray(samples()[depth_keyframe_t].encode())
    count_at = conversions._FIXED_SIZES[depth_keyframe_t] - 4
    for forged in (b"\xff\xff\xff\xff", b"\x7f\xff\xff\xff", (8 << 20 | 1).to_bytes(4, "big")):
        keyframe[count_at:count_at + 4] = forged
        with pytest.raises(DecodeError, match="out of bounds"):
            decode(depth_keyframe_t, bytes(keyframe))


@pytest.mark.parametrize("field,value", [
    ("width", 4096), ("height", 0), ("encoding", 9), ("tracking_status", 17),
    ("depth_scale_m", 0.0), ("fx", float("inf")), ("vehicle_id", -1),
    ("position_m", [0.0, float("nan"), 0.0]), ("orientation_xyzw", [0.0, 0.0, 0.0, 2.0]),
])
def test_impossible_fields_are_rejected(field: str, value: object) -> None:
    message = samples()[depth_keyframe_t]
    setattr(message, field, value)
    with pytest.raises(DecodeError, match="bad field"):
        decode(depth_keyframe_t, message.encode())


# ---- signing, keys, channels ---------------------------------------------------------------

def test_mac_matches_the_cpp_vector() -> None:
    """The vector of tests/unit/test_link.cpp (SigningVector)."""
    key = bytes(range(32))
    assert signing.key_id_of(key) & 0xFFFFFFFF == 0x630DCD29
    mac = signing.compute_mac(key, 7, 42, 1_700_000_000_000_000, b"kinfly")
    assert mac.hex() == "1092b8d8ce1e9d43676c5c9ed98aeb77fff29d8a676a849ea16f3d8ee1616561"


def test_signer_sequences_increase_and_envelopes_decode() -> None:
    signer = signing.Signer(bytes(range(32)), 7, first_sequence=100)
    inner = sample_correction().encode()
    first, second = signer.sign(inner), signer.sign(inner)
    assert (first.sequence, second.sequence) == (100, 101)
    got = decode(signed_t, first.encode())
    assert decode(pose_correction_t, got.payload).keyframe_id == 56


def test_keygen_key_loads_in_python_with_the_same_id(tmp_path: Path) -> None:
    keygen = built("bin/kinfly-keygen")
    path = tmp_path / "v7.key"
    out = subprocess.run([keygen, "--out", path], check=True, capture_output=True,
                         text=True).stdout
    key = signing.load_key_file(path)
    assert f"0x{signing.key_id_of(key) & 0xFFFFFFFF:08x}" in out
    again = subprocess.run([keygen, "--out", path], capture_output=True, text=True)
    assert again.returncode != 0 and "exists" in again.stderr

    os.chmod(path, 0o644)
    with pytest.raises(signing.KeyFileError, match="chmod 600"):
        signing.load_key_file(path)
    short = tmp_path / "short.key"
    short.write_bytes(b"short")
    short.chmod(0o600)
    with pytest.raises(signing.KeyFileError, match="bytes"):
        signing.load_key_file(short)
    link = tmp_path / "link.key"
    link.symlink_to(path)
    with pytest.raises(signing.KeyFileError):
        signing.load_key_file(link)


def test_channel_names_match_the_cpp_spelling() -> None:
    assert channels.channel_name(channels.Channel.KEYFRAME, 7) == "KINFLY_7_KEYFRAME"
    for channel in channels.Channel:
        assert channels.parse_channel(channels.channel_name(channel, 65535)) == (channel, 65535)
    for bad in ("KINFLY_07_IMU", "KINFLY_65536_IMU", "KINFLY_7_NOPE", "OTHER_7_IMU", ""):
        assert channels.parse_channel(bad) is None
