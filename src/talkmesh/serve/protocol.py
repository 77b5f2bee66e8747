"""The WebSocket wire format of ``talkmesh serve``: one binary message per frame, and the close
codes. Layout of a frame message (little-endian): a 16-byte header (magic ``TMF1``, frame index
uint32, time float32 in s, number of weights uint16, flags uint16), the ARKit weights as float32,
then, with flag ``FLAG_HEAD``, the head pose as 6 float32, then, with flag ``FLAG_OFFSETS``, the
(V, 3) vertex offsets as float16.

Streaming protocol
==================

``GET /ws/stream?model=procedural&lookahead_ms=100&offsets=0`` upgrades to a WebSocket. All the
parameters are optional: ``model`` is one of the names the server was started with (``procedural``,
or a ``--model`` .safetensors file by its stem; default the first ``--model``), ``lookahead_ms``
the audio a frame waits for after its time (default 100, at most 300), ``offsets=1`` asks for the
vertex offsets of every frame as well as its weights, ``head_motion`` how much the head moves
with the speech (0 to 1, default 0.5; 0 sends no head pose; :mod:`talkmesh.face.head_stream`),
``idle=0`` turns off the idle frames (below). Clients never name files on the server.

1. On accept the server sends one text message::

       {"type": "hello", "fps": 30.0, "sample_rate": 16000, "lookahead_ms": 100.0,
        "model": "procedural", "names": [the 52 ARKit blendshape names]}

2. Client -> server:

   * binary: raw mono 16 kHz PCM, signed 16-bit little-endian, any length up to the message limit
     (an odd number of bytes is an error);
   * text ``{"type": "end"}``: the end of the audio; the server flushes the remaining frames;
   * idle life: from the first message on, when no audio has come for ``IDLE_AFTER_S`` (0.5 s)
     the server streams silence in the client's place, in real time, so frames keep coming with
     blinks, gaze, breathing and head sway (:mod:`talkmesh.serve.session`); the client's next
     audio follows it. A client sending faster than real time gets none until the clock catches
     up with its audio;
   * text ``{"type": "emotion", "emotion": "happy:0.6,surprised:0.2"}``: the face's emotion
     from the next frame sent on, blended in over 0.3 s (``neutral`` returns to none;
     :mod:`talkmesh.serve.emotion`); an unknown emotion or an intensity outside 0 to 1 is an
     error.

3. Server -> client, one binary message per frame, all little-endian::

       offset  size  field
       0       4     magic b"TMF1"
       4       4     uint32  frame index (0, 1, 2, ... with no gaps)
       8       4     float32 frame time in seconds (index / fps)
       12      2     uint16  number of weights N (52)
       14      2     uint16  flags: bit 0 = vertex offsets follow, bit 1 = head pose follows
       16      4N    float32 weights in [0, 1], in the order of the hello's ``names``
       16+4N   24    (flag bit 1 only) float32 head pose: pitch, yaw, roll (radians; pitch > 0
                     nods the chin down, yaw > 0 turns the face to its left, roll > 0 tilts the
                     top of the head to its right) and translation x, y, z (metres); a vertex
                     v of the face goes to R v + t, R = Ry(yaw) Rx(pitch) Rz(roll)
       then    6V    (flag bit 0 only) float16 vertex offsets from the neutral face, (V, 3), metres

   Idle life (``idle=0`` in the query turns it off): when the client sends no audio for 0.5 s
   the server streams silence in its place, so frames keep coming. When the client's audio (or
   its end) comes again, text ``{"type": "silence", "sample": S, "samples": N}`` says that N
   samples of silence went into the stream from its sample S on; it comes before any frame of
   the audio after it (a client that times frames against its own audio subtracts them).

   After the flush: text ``{"type": "end", "frames": N}`` and a normal close (1000).

4. Errors end the session: text ``{"type": "error", "message": "<what is wrong and what to do>"}``
   then a close with code 1008 (bad input: garbage, odd byte count, invalid JSON, unknown model or
   bad look-ahead, no message for ``--idle-timeout`` seconds), 1009 (a message over
   ``--max-message-bytes``), 1011 (a bug in the server) or 1013 (all ``--max-sessions`` are busy).
   On shutdown (Ctrl-C, SIGTERM) open sessions are closed with 1001 and no error message.
"""

from __future__ import annotations

import json
import struct

import numpy as np

from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.performance import Mix
from talkmesh.serve.emotion import parse_emotion_message
from talkmesh.serve.stream import StreamFrame

FRAME_MAGIC = b"TMF1"
FRAME_HEADER = struct.Struct("<4sIfHH")  # magic, index, time, number of weights, flags
FLAG_OFFSETS = 1
FLAG_HEAD = 2
HEAD_VALUES = 6
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
    flags = (0 if frame.offsets is None else FLAG_OFFSETS) | (
        0 if frame.head_pose is None else FLAG_HEAD
    )
    parts = [
        FRAME_HEADER.pack(FRAME_MAGIC, frame.index, frame.time, len(weights), flags),
        weights.tobytes(),
    ]
    if frame.head_pose is not None:
        pose = np.asarray(frame.head_pose, "<f4")
        assert pose.shape == (HEAD_VALUES,), pose.shape
        parts.append(pose.tobytes())
    if frame.offsets is not None:
        assert frame.offsets.ndim == 2 and frame.offsets.shape[1] == 3, frame.offsets.shape
        parts.append(np.asarray(frame.offsets, "<f2").tobytes())
    return b"".join(parts)


def decode_frame(data: bytes) -> StreamFrame:
    """One binary message back into a frame (weights float32, head pose float32 (6,) or None,
    offsets float32 (V, 3) or None)."""
    magic, index, time, count, flags = FRAME_HEADER.unpack_from(data)
    if magic != FRAME_MAGIC:
        raise ValueError(f"not a talkmesh frame (magic {magic!r})")
    end = FRAME_HEADER.size + 4 * count
    weights = np.frombuffer(data, "<f4", count, FRAME_HEADER.size).astype(np.float32)
    pose = None
    if flags & FLAG_HEAD:
        pose = np.frombuffer(data, "<f4", HEAD_VALUES, end).astype(np.float32)
        end += 4 * HEAD_VALUES
    offsets = None
    if flags & FLAG_OFFSETS:
        offsets = np.frombuffer(data, "<f2", offset=end).astype(np.float32).reshape(-1, 3)
    elif len(data) != end:
        raise ValueError(f"frame message of {len(data)} bytes, expected {end}")
    return StreamFrame(index, time, weights, offsets, pose)


def parse_text(text: str | None) -> Mix | None:
    """A text message: None for the end message, the mix of an emotion message
    (``TalkmeshError`` saying what is wrong for anything else)."""
    try:
        message = json.loads(text or "")
    except ValueError:
        raise TalkmeshError(
            'text messages must be JSON: send {"type": "end"} to end the audio'
        ) from None
    except RecursionError:  # '[' x 30000: a protocol error, not a bug
        raise TalkmeshError(
            'text messages are {"type": "end"}, not JSON nested thousands deep'
        ) from None
    kind = message.get("type") if isinstance(message, dict) else None
    if kind == "end":
        return None
    if kind == "emotion":
        return parse_emotion_message(message)
    raise TalkmeshError(
        f'unknown message {str(message)[:80]}: the text messages are {{"type": "end"}} and '
        '{"type": "emotion", "emotion": "happy:0.6"}'
    )
