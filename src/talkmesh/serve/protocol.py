"""The WebSocket wire format of ``talkmesh serve``: one binary message per frame, and the close
codes. Layout of a frame message (little-endian): a 16-byte header (magic ``TMF1``, frame index
uint32, time float32 in s, number of weights uint16, flags uint16), the ARKit weights as float32,
then, with flag ``FLAG_OFFSETS``, the (V, 3) vertex offsets as float16."""

from __future__ import annotations

import struct

import numpy as np

from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.serve.stream import StreamFrame

FRAME_MAGIC = b"TMF1"
FRAME_HEADER = struct.Struct("<4sIfHH")  # magic, index, time, number of weights, flags
FLAG_OFFSETS = 1
assert FRAME_HEADER.size == 16

CLOSE_NORMAL = 1000
CLOSE_GOING_AWAY = 1001
CLOSE_POLICY = 1008  # bad input
CLOSE_TOO_BIG = 1009
CLOSE_INTERNAL = 1011
CLOSE_BUSY = 1013  # try again later


def encode_frame(frame: StreamFrame) -> bytes:
    """A frame as one binary WebSocket message (layout in the module docstring)."""
    weights = np.asarray(frame.weights, "<f4")
    assert weights.shape == (len(ARKIT_NAMES),), weights.shape
    flags = 0 if frame.offsets is None else FLAG_OFFSETS
    parts = [
        FRAME_HEADER.pack(FRAME_MAGIC, frame.index, frame.time, len(weights), flags),
        weights.tobytes(),
    ]
    if frame.offsets is not None:
        assert frame.offsets.ndim == 2 and frame.offsets.shape[1] == 3, frame.offsets.shape
        parts.append(np.asarray(frame.offsets, "<f2").tobytes())
    return b"".join(parts)


def decode_frame(data: bytes) -> StreamFrame:
    """One binary message back into a frame (weights float32, offsets float32 (V, 3) or None)."""
    magic, index, time, count, flags = FRAME_HEADER.unpack_from(data)
    if magic != FRAME_MAGIC:
        raise ValueError(f"not a talkmesh frame (magic {magic!r})")
    end = FRAME_HEADER.size + 4 * count
    weights = np.frombuffer(data, "<f4", count, FRAME_HEADER.size).astype(np.float32)
    offsets = None
    if flags & FLAG_OFFSETS:
        offsets = np.frombuffer(data, "<f2", offset=end).astype(np.float32).reshape(-1, 3)
    elif len(data) != end:
        raise ValueError(f"frame message of {len(data)} bytes, expected {end}")
    return StreamFrame(index, time, weights, offsets)
