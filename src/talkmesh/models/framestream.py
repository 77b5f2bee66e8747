"""One stream's frames, one at a time, and the frames of many streams computed together: the
interface :func:`talkmesh.serve.stream.push_together` drives, without torch (an ONNX Runtime
stream, :mod:`talkmesh.models.onnx_stream`, needs none; :mod:`talkmesh.models.base` re-exports
these names)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import NamedTuple

import numpy as np


class FrameStream(ABC):
    """One stream's incremental generator (:meth:`MotionModel.open_frame_stream`): frames one at a
    time from the audio received so far, each exactly what ``generate`` computes offline.

    The caller keeps the stream's audio in a buffer whose first sample is stream sample
    ``buffer_start``; it may drop the samples before :meth:`first_sample` of the next frame.
    """

    fps: float  # motion frames per second
    lookahead_ms: float  # audio after a frame's time that the frame reads

    @abstractmethod
    def audio_needed(self, frame: int) -> float:
        """Stream samples that must have arrived before ``frame`` can be computed."""

    @abstractmethod
    def first_sample(self, frame: int) -> int:
        """The first stream sample that ``frame`` reads (no later frame reads earlier ones)."""

    @abstractmethod
    def frame(self, buffer: np.ndarray, buffer_start: int, frame: int) -> np.ndarray:
        """The next frame's motion, (V * 3,) float32 offsets from the template; frames are asked
        for in order, each once, when :meth:`audio_needed` samples have arrived."""

    def frames_together(
        self, requests: list[FrameRequest], basis: np.ndarray | None = None
    ) -> np.ndarray:
        """The next frame of each request's stream (streams of this one's ``engine``, each at
        most once) -> (B, V * 3), what each stream's :meth:`frame` gives alone; with ``basis``
        (K, V * 3) only the frames' projections onto it, (B, K) float64 (an engine can compute
        them without the V * 3 coordinates). This default computes the frames one by one; a
        family whose streams share an engine runs them as a batch."""
        motion = np.stack([r.stream.frame(r.buffer, r.buffer_start, r.frame) for r in requests])
        return motion if basis is None else motion.astype(np.float64) @ basis.T


class FrameRequest(NamedTuple):
    """The next frame of one stream, and the stream's audio buffer (first sample
    ``buffer_start``), as :meth:`FrameStream.frame` takes them."""

    stream: FrameStream
    buffer: np.ndarray
    buffer_start: int
    frame: int


def next_frames(requests: list[FrameRequest], basis: np.ndarray | None = None) -> list[np.ndarray]:
    """The next frame of several streams (each at most once) -> each (V * 3,), as each stream's
    :meth:`FrameStream.frame` computes it alone, or with ``basis`` (K, V * 3) its projection
    (K,) onto it; streams that share an ``engine`` (the streams of one loaded model) compute
    theirs in one batch."""
    groups: dict[int, list[int]] = {}
    for i, r in enumerate(requests):
        engine = getattr(r.stream, "engine", None)
        groups.setdefault(id(r.stream) if engine is None else id(engine), []).append(i)
    out: list[np.ndarray] = [np.empty(0)] * len(requests)
    for members in groups.values():
        group = [requests[i] for i in members]
        for i, motion in zip(members, group[0].stream.frames_together(group, basis)):
            out[i] = motion
    return out


__all__ = ["FrameRequest", "FrameStream", "next_frames"]
