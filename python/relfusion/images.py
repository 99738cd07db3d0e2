"""Frames as the service takes them: JPEG or PNG bytes. numpy arrays are encoded as PNG here
(zlib, no imaging library needed); bytes that already are JPEG or PNG pass through."""

from __future__ import annotations

import struct
import zlib
from typing import Union

import numpy as np

Frame = Union[bytes, bytearray, "np.ndarray"]


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def png_bytes(image: np.ndarray) -> bytes:
    """A uint8 image (H×W grey, H×W×3 RGB or H×W×4 RGBA) as PNG."""
    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise TypeError(f"frames must be uint8 arrays, got {a.dtype}")
    if a.ndim == 2:
        color = 0
        channels = 1
    elif a.ndim == 3 and a.shape[2] in (3, 4):
        color = 2 if a.shape[2] == 3 else 6
        channels = a.shape[2]
    else:
        raise ValueError(f"frames must be H×W, H×W×3 or H×W×4, got shape {a.shape}")
    h, w = a.shape[:2]
    rows = np.ascontiguousarray(a).reshape(h, w * channels)
    raw = np.empty((h, w * channels + 1), dtype=np.uint8)
    raw[:, 0] = 0  # filter: none
    raw[:, 1:] = rows
    header = struct.pack(">IIBBBBB", w, h, 8, color, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(raw.tobytes(), 1))
        + _chunk(b"IEND", b"")
    )


def encode(frame: Frame) -> "tuple[bytes, str]":
    """The frame's bytes and content type."""
    if isinstance(frame, (bytes, bytearray)):
        data = bytes(frame)
        if data.startswith(b"\xff\xd8\xff"):
            return data, "image/jpeg"
        if data.startswith(b"\x89PNG\r\n\x1a\n"):
            return data, "image/png"
        raise ValueError("frame bytes must be JPEG or PNG")
    return png_bytes(np.asarray(frame)), "image/png"


def image_size(data: bytes) -> "tuple[int, int]":
    """(width, height) of JPEG or PNG bytes, from the header."""
    if data.startswith(b"\x89PNG\r\n\x1a\n") and len(data) >= 24:
        w, h = struct.unpack(">II", data[16:24])
        return int(w), int(h)
    if data.startswith(b"\xff\xd8"):
        i = 2
        while i + 9 < len(data):
            if data[i] != 0xFF:
                i += 1
                continue
            marker = data[i + 1]
            if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
                h, w = struct.unpack(">HH", data[i + 5 : i + 9])
                return int(w), int(h)
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
                i += 2
                continue
            (length,) = struct.unpack(">H", data[i + 2 : i + 4])
            i += 2 + length
    raise ValueError("not a JPEG or PNG image")
