"""Single-channel PNG encoding (8-bit masks, 16-bit depth) with the standard library and numpy.

The server takes a dynamic-object mask as an 8-bit PNG and depth as a 16-bit PNG; this writes
those from numpy arrays so the SDK needs no image library.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _chunk(kind: bytes, payload: bytes) -> bytes:
    crc = zlib.crc32(kind + payload) & 0xFFFFFFFF
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc)


def encode_gray_png(image: np.ndarray) -> bytes:
    """A grayscale PNG of a 2-D ``uint8`` or ``uint16`` array (bit depth 8 or 16)."""
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"a 2-D uint8 or uint16 array is needed, got {image.dtype} {image.shape}")
    height, width = image.shape
    if width == 0 or height == 0:
        raise ValueError("an empty image has no PNG")
    bit_depth = 8 if image.dtype == np.uint8 else 16
    # PNG samples are big-endian; each row starts with filter type 0 (none).
    rows = np.ascontiguousarray(image.astype(">u2") if bit_depth == 16 else image)
    raw = rows.view(np.uint8).reshape(height, -1)
    filtered = np.concatenate([np.zeros((height, 1), np.uint8), raw], axis=1)
    header = struct.pack(">IIBBBBB", width, height, bit_depth, 0, 0, 0, 0)
    return (
        _SIGNATURE
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(filtered.tobytes(), 6))
        + _chunk(b"IEND", b"")
    )
