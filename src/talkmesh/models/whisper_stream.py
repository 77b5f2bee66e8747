"""Whisper speech features from a stream's audio, a few motion frames at a time, so that a
CodeTalker with the Whisper encoder and a causal VQ decoder (the bundled ``codetalker-synth``)
streams: stage 2 reads frame ``t``'s own audio token only (the alignment mask) and the VQ decoder
is causal, so only the speech encoder, which attends both ways, needs the audio after a frame.

The frames go in blocks of ``block`` (default 3: 100 ms at 30 fps). Block ``k``'s features come
from one encoder window that ends ``lookahead_ms`` after the time of the block's last frame
(rounded down to a whole 20 ms feature) and starts ``context_s`` earlier (at the stream's start
at most): Whisper's log-mel of that audio alone, normalised by its own peak, encoded with the
first positions, the 50 Hz features linearly interpolated at each frame's time. A block's first
frame therefore waits ``lookahead_ms`` plus ``block - 1`` frames. The bundled model was trained
on 3 s crops encoded the same way (each on its own), so a window's right edge is what it saw at
the end of every crop. Everything is a function of the audio alone: the features do not depend
on how the audio was pushed (:func:`streamed_features` computes them offline).

Axis letters: S audio samples, N 50 Hz feature frames, T motion frames, D width.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from talkmesh.constants import SAMPLE_RATE
from talkmesh.errors import TalkmeshError
from talkmesh.models.whisper import ENCODER_HOP, FEATURE_RATE

DEFAULT_LOOKAHEAD_MS = 300.0
MAX_LOOKAHEAD_MS = 1000.0
DEFAULT_CONTEXT_S = 2.0
DEFAULT_BLOCK = 3  # frames per encoder window
MIN_WINDOW = 2 * ENCODER_HOP  # samples: the shortest window encoded (40 ms)


class WhisperFeatureStream:
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
        lookahead = DEFAULT_LOOKAHEAD_MS if lookahead_ms is None else float(lookahead_ms)
        if not 0.0 <= lookahead <= MAX_LOOKAHEAD_MS:
            raise TalkmeshError(
                f"look-ahead {lookahead:g} ms is out of range for a Whisper speech encoder: "
                f"use 0 to {MAX_LOOKAHEAD_MS:g} ms"
            )
        if not 0.1 <= context_s <= 30.0 or block < 1:
            raise TalkmeshError(
                f"context {context_s:g} s and block {block} are out of range: use 0.1-30 s and "
                "at least 1 frame"
            )
        self.features, self.fps, self.block = speech.features, float(fps), int(block)
        self.reads_ms = lookahead  # audio after each frame's block's last frame
        # what a block's first frame waits for: the stream's look-ahead
        self.lookahead_ms = lookahead + (self.block - 1) * 1000.0 / self.fps
        self.context = int(round(context_s * FEATURE_RATE)) * ENCODER_HOP  # whole features
        self.current = -1  # the block whose features are held
        self.held: Tensor | None = None

    def window_end(self, block: int) -> int:
        """The stream sample where block ``block``'s encoder window ends."""
        last = (block + 1) * self.block - 1
        end = math.floor((last / self.fps + self.reads_ms / 1000.0) * SAMPLE_RATE + 1e-6)
        return max(MIN_WINDOW, end // ENCODER_HOP * ENCODER_HOP)

    def window_start(self, block: int) -> int:
        return max(0, self.window_end(block) - self.context)

    def audio_needed(self, frame: int) -> float:
        """Samples that must have arrived before ``frame``'s feature can be computed."""
        return float(self.window_end(frame // self.block))

    def first_sample(self, frame: int) -> int:
        """The first stream sample ``frame``'s feature reads (no later frame reads earlier)."""
        return self.window_start(frame // self.block)

    def window(self, buffer: np.ndarray, buffer_start: int, frame: int) -> Tensor:
        """The speech feature (D,) of ``frame``, from the stream's audio ``buffer`` (its first
        sample is stream sample ``buffer_start``); frames are asked for in order. At the end of
        a stream the last windows end with the audio."""
        block = frame // self.block
        if block != self.current:
            self._hold(block, self._encode([self._audio(buffer, buffer_start, block)])[0])
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
            (stream, frame // stream.block, stream._audio(buffer, start, frame // stream.block))
            for stream, buffer, start, frame in requests
            if frame // stream.block != stream.current
        ]
        if not due:
            return
        feats = due[0][0]._encode([audio for _, _, audio in due])
        for (stream, block, _), f in zip(due, feats):
            stream._hold(block, f)

    def _audio(self, buffer: np.ndarray, buffer_start: int, block: int) -> np.ndarray:
        """Block ``block``'s encoder window (at least :data:`MIN_WINDOW` samples)."""
        start, end = self.window_start(block), self.window_end(block)
        if start < buffer_start:
            raise TalkmeshError(
                f"the stream's audio from sample {start} was dropped: it is needed for block "
                f"{block}"
            )
        audio = np.asarray(buffer[start - buffer_start : end - buffer_start], np.float32)
        if len(audio) < MIN_WINDOW:  # the end of a very short stream: silence after it
            audio = np.pad(audio, (0, MIN_WINDOW - len(audio)))
        return audio

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
        start = self.window_start(block)
        frames = torch.arange(block * self.block, (block + 1) * self.block, dtype=torch.float64)
        x = (frames / self.fps * FEATURE_RATE - start / ENCODER_HOP).clamp(0, len(feats) - 1)
        low = x.floor().long()
        high = (low + 1).clamp(max=len(feats) - 1)
        w = (x - low).to(feats.dtype)[:, None]
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
