"""Keyframe chunks for the ground's tests, written from docs/wire.md's layout ("Keyframes in
chunks") with the generated Python messages, not by the C++ under test: one FEC group of
originals. `recovery` recovery chunks are declared in every header (the redundancy the ground
reports) but never made: the tests need only originals, and what a lost one costs."""
from __future__ import annotations

import hashlib

from kinfly import keyframe_chunk_t

BLOCK_BYTES = 1376  # ChunkEncoder::blockBytesFor(1500): a 1500-byte MTU (docs/wire.md)


def message_digest(message: bytes) -> int:
    """keyframe_chunk_t.message_digest: BLAKE2b-128 (libsodium's crypto_generichash, no key),
    its first 8 bytes big-endian, as LCM's signed int64."""
    return int.from_bytes(hashlib.blake2b(message, digest_size=16).digest()[:8], "big",
                          signed=True)


def chunks_of(message: bytes, *, utime: int, vehicle_id: int, keyframe_id: int,
              first_sequence: int, sent_utime: int, recovery: int = 0,
              block_bytes: int = BLOCK_BYTES) -> list[keyframe_chunk_t]:
    """The originals of an encoded depth_keyframe_t MESSAGE in one group, numbered from
    FIRST_SEQUENCE, each stamped SENT_UTIME (set .sent_utime per chunk for other times)."""
    originals = -(-len(message) // block_bytes)
    assert originals + recovery <= keyframe_chunk_t.MAX_GROUP_CHUNKS
    digest = message_digest(message)
    chunks = []
    for index in range(originals):
        c = keyframe_chunk_t()
        c.utime, c.vehicle_id, c.keyframe_id = utime, vehicle_id, keyframe_id
        c.sequence, c.sent_utime = first_sequence + index, sent_utime
        c.message_bytes, c.message_digest = len(message), digest
        c.groups, c.group, c.originals, c.recovery, c.index = 1, 0, originals, recovery, index
        c.block_size = block_bytes
        c.block = message[index * block_bytes:(index + 1) * block_bytes].ljust(block_bytes, b"\0")
        chunks.append(c)
    return chunks
