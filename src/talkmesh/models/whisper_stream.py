"""Whisper speech features from a stream's audio, a few motion frames at a time, so that a
CodeTalker with the Whisper encoder and a causal VQ decoder (the bundled ``codetalker-synth``)
streams: stage 2 reads frame ``t``'s own audio token only (the alignment mask) and the VQ decoder
is causal, so only the speech encoder, which attends both ways, needs the audio after a frame.

The windows (:class:`talkmesh.models.blocks.BlockWindows`): block ``k`` of ``block`` frames
(default 3: 100 ms at 30 fps) gets one encoder window that ends ``lookahead_ms`` after its last
frame and starts ``context_s`` earlier: Whisper's log-mel of that audio alone, normalised by its
own peak, encoded with the first positions, the 50 Hz features linearly interpolated at each
frame's time. The bundled model was trained on 3 s crops encoded the same way (each on its own),
so a window's right edge is what it saw at the end of every crop. Everything is a function of the
audio alone: the features do not depend on how the audio was pushed (:func:`streamed_features`
computes them offline).

Axis letters: S audio samples, N 50 Hz feature frames, T motion frames, D width.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from talkmesh.models.blocks import (
    DEFAULT_BLOCK,
    DEFAULT_CONTEXT_S,
    DEFAULT_LOOKAHEAD_MS,
    BlockWindows,
)


class WhisperFeatureStream(BlockWindows):
    """A Whisper encoder's features for one stream's frames, block by block (module docstring).

    The interface of :class:`talkmesh.models.speech.MelFeatureStream` that
    :class:`talkmesh.models.codetalker.batch.FrameBatch` uses: :meth:`window` gives a frame's
    feature (D,) (its block's encoder window runs once, at the block's first frame) and
    :meth:`encode` stacks those of a step's streams."""

    shift = 0  # no look-ahead embedding: every stream of the model shares encode()

    def __init__(
        self,
        speech,
        fps: float,
        lookahead_ms: float | None = None,
        context_s: float = DEFAULT_CONTEXT_S,
        block: int = DEFAULT_BLOCK,
    ) -> None:
        """``speech``: a :class:`talkmesh.models.speech.WhisperEncoder`; ``lookahead_ms`` (None:
        :data:`DEFAULT_LOOKAHEAD_MS`) the audio after each block's last frame that it reads."""
        super().__init__(fps, lookahead_ms, context_s, block)
        self.features = speech.features
        self.held: Tensor | None = None

    def window(self, buffer: np.ndarray, buffer_start: int, frame: int) -> Tensor:
        """The speech feature (D,) of ``frame``, from the stream's audio ``buffer`` (its first
        sample is stream sample ``buffer_start``); frames are asked for in order. At the end of
        a stream the last windows end with the audio."""
        block = frame // self.block
        if block != self.current:
            self._hold(block, self._encode([self.audio(buffer, buffer_start, block)])[0])
        assert self.held is not None
        return self.held[frame - block * self.block]

    @staticmethod
    def prepare(requests: list[tuple[WhisperFeatureStream, np.ndarray, int, int]]) -> None:
        """Encode together the windows that a step's streams of one model start with this step
        (each request: stream, buffer, buffer_start, frame, as :meth:`window` takes them): one
        encoder batch for windows of equal length (a full ``context_s`` once a stream is that
        old), instead of one encoder call per stream. The features are those of :meth:`window`
        (float32 rounding apart)."""
        due = [
            (stream, frame // stream.block, stream.audio(buffer, start, frame // stream.block))
            for stream, buffer, start, frame in requests
            if frame // stream.block != stream.current
        ]
        if not due:
            return
        feats = due[0][0]._encode([audio for _, _, audio in due])
        for (stream, block, _), f in zip(due, feats):
            stream._hold(block, f)

    def _encode(self, windows: list[np.ndarray]) -> list[Tensor]:
        """The 50 Hz features (N_b, D) of each window, in one call of the encoder (which runs
        windows of equal length as one batch)."""
        lengths = [len(a) for a in windows]
        batch = np.zeros((len(windows), max(lengths)), np.float32)
        for b, a in enumerate(windows):
            batch[b, : len(a)] = a
        with torch.inference_mode():
            return self.features.features(torch.from_numpy(batch), torch.tensor(lengths))

    def _hold(self, block: int, feats: Tensor) -> None:
        """Keep block ``block``'s frame features, interpolated from its window's ``feats``."""
        low, high, w = (torch.from_numpy(a) for a in self.positions(block, len(feats)))
        w = w.to(feats.dtype)[:, None]
        self.held, self.current = feats[low] * (1 - w) + feats[high] * w, block

    def encode(self, windows: Tensor, shifts: list[int]) -> Tensor:
        """The features (B, D) of a step's streams, as :meth:`window` gave them."""
        return windows


def streamed_features(
    speech,
    audio: np.ndarray,
    num_frames: int,
    fps: float,
    lookahead_ms: float | None = None,
    context_s: float = DEFAULT_CONTEXT_S,
    block: int = DEFAULT_BLOCK,
) -> Tensor:
    """(T, D): the features a stream of ``audio`` (S,) computes for its ``num_frames`` frames,
    whatever the sizes of its pushes."""
    stream = WhisperFeatureStream(speech, fps, lookahead_ms, context_s, block)
    audio = np.asarray(audio, np.float32)
    return torch.stack([stream.window(audio, 0, t) for t in range(num_frames)])


__all__ = [
    "DEFAULT_BLOCK",
    "DEFAULT_CONTEXT_S",
    "DEFAULT_LOOKAHEAD_MS",
    "WhisperFeatureStream",
    "streamed_features",
]
