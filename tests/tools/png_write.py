"""Minimal grayscale PNG writer (8- or 16-bit), so tests can make depth images without OpenCV or
Pillow in the product environment. Only what PNG requires: signature, IHDR, one IDAT, IEND."""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_COLOR_TYPE_GRAY = 0


def _chunk(kind: bytes, data: bytes) -> bytes:
    crc = zlib.crc32(kind + data) & 0xFFFFFFFF
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)


def write_gray_png(path: str | Path, image: np.ndarray) -> None:
    """Writes a 2-D uint8 or uint16 array as a grayscale PNG of the same bit depth."""
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"need a 2-D uint8/uint16 array, got {image.dtype} {image.shape}")
    height, width = image.shape
    bit_depth = 8 * image.itemsize
    # PNG stores samples big-endian; each row starts with filter type 0 (none).
    rows = image.astype(image.dtype.newbyteorder(">"), copy=False)
    raw = b"".join(b"\x00" + rows[y].tobytes() for y in range(height))
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, _COLOR_TYPE_GRAY, 0, 0, 0)
    Path(path).write_bytes(_SIGNATURE + _chunk(b"IHDR", ihdr)
                           + _chunk(b"IDAT", zlib.compress(raw)) + _chunk(b"IEND", b""))
