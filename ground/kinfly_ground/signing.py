"""The ground's end of the signed uplink: HMAC-SHA256 over the encoded inner message plus vehicle
id, key id, sequence number and signing time, in a `kinfly.signed_t` envelope. The same layout as
firmware/link/signing.cpp (docs/wire.md); a shared test vector keeps the two equal."""
from __future__ import annotations

import hashlib
import hmac
import os
import stat
import struct
import time
from pathlib import Path

from kinfly import signed_t

KEY_BYTES = 32
_DOMAIN = b"kinfly-signed-v1"


class KeyFileError(Exception):
    """A key file that must not be used; the message says why and how to fix it."""


def key_id_of(key: bytes) -> int:
    """First 4 bytes of SHA-256 of the key, big-endian, as a signed int32 for the wire."""
    return struct.unpack(">i", hashlib.sha256(key).digest()[:4])[0]


def load_key_file(path: str | os.PathLike[str]) -> bytes:
    """Reads a 32-byte key, refusing (like ssh) a file that group or others may access."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC | os.O_NOFOLLOW)
    except OSError as err:
        raise KeyFileError(f"cannot open key file {path}: {err.strerror}") from err
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise KeyFileError(f"key file {path} is not a regular file")
        if st.st_mode & 0o077:
            raise KeyFileError(
                f"key file {path} has mode {stat.S_IMODE(st.st_mode):04o}: group and others "
                f"must have no access (chmod 600 {path})")
        key = f.read(KEY_BYTES + 1)
    if len(key) != KEY_BYTES:
        raise KeyFileError(f"key file {path} holds {len(key)} bytes, not {KEY_BYTES} "
                           "(create one with kinfly-keygen)")
    return key


def compute_mac(key: bytes, vehicle_id: int, sequence: int, utime: int, payload: bytes) -> bytes:
    message = (_DOMAIN + struct.pack(">iiqq", vehicle_id, key_id_of(key), sequence, utime)
               + payload)
    return hmac.new(key, message, hashlib.sha256).digest()


class Signer:
    """Wraps encoded messages for one vehicle. Sequence numbers start at the wall clock in
    microseconds, so a restarted ground station continues above every number it used before."""

    def __init__(self, key: bytes, vehicle_id: int, first_sequence: int | None = None) -> None:
        if len(key) != KEY_BYTES:
            raise ValueError(f"key must be {KEY_BYTES} bytes, got {len(key)}")
        self._key = key
        self._key_id = key_id_of(key)
        self._vehicle_id = vehicle_id
        self._next_sequence = (time.time_ns() // 1000 if first_sequence is None
                               else first_sequence)

    def sign(self, inner: bytes, utime_now: int | None = None) -> signed_t:
        envelope = signed_t()
        envelope.utime = time.time_ns() // 1000 if utime_now is None else utime_now
        envelope.vehicle_id = self._vehicle_id
        envelope.key_id = self._key_id
        envelope.sequence = self._next_sequence
        self._next_sequence += 1
        envelope.mac = compute_mac(self._key, self._vehicle_id, envelope.sequence,
                                   envelope.utime, inner)
        envelope.payload = inner
        envelope.payload_size = len(inner)
        return envelope
