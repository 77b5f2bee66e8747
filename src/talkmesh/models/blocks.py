"""When a streamed Whisper encoder reads which audio: the windows of
:mod:`talkmesh.models.whisper_stream` (PyTorch) and :mod:`talkmesh.models.onnx_stream` (ONNX
Runtime), without torch.

The frames go in blocks of ``block`` (default 3: 100 ms at 30 fps). Block ``k``'s features come
from one encoder window that ends ``lookahead_ms`` after the time of the block's last frame
(rounded down to a whole 20 ms feature) and starts ``context_s`` earlier (at the stream's start
at most), the 50 Hz features linearly interpolated at each frame's time. A block's first frame
therefore waits ``lookahead_ms`` plus ``block - 1`` frames.

Axis letters: S audio samples, N 50 Hz feature frames, T motion frames, D width.
"""

from __future__ import annotations

import math

import numpy as np

from talkmesh.audio.logmel import HOP_LENGTH
from talkmesh.constants import SAMPLE_RATE
from talkmesh.errors import TalkmeshError

ENCODER_HOP = 2 * HOP_LENGTH  # one feature per 20 ms
FEATURE_RATE = SAMPLE_RATE / ENCODER_HOP  # 50 Hz
DEFAULT_LOOKAHEAD_MS = 300.0
MAX_LOOKAHEAD_MS = 1000.0
DEFAULT_CONTEXT_S = 2.0
DEFAULT_BLOCK = 3  # frames per encoder window
MIN_WINDOW = 2 * ENCODER_HOP  # samples: the shortest window encoded (40 ms)


class BlockWindows:
    """One stream's encoder windows, a block of frames each (module docstring). A subclass
    encodes them and keeps the block's frame features (``current``, ``held``)."""

    def __init__(
        self,
        fps: float,
        lookahead_ms: float | None = None,
        context_s: float = DEFAULT_CONTEXT_S,
        block: int = DEFAULT_BLOCK,
    ) -> None:
        """``lookahead_ms`` (None: :data:`DEFAULT_LOOKAHEAD_MS`): the audio after each block's
        last frame that its window reads."""
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
        self.fps, self.block = float(fps), int(block)
        self.reads_ms = lookahead  # audio after each frame's block's last frame
        # what a block's first frame waits for: the stream's look-ahead
        self.lookahead_ms = lookahead + (self.block - 1) * 1000.0 / self.fps
        self.context = int(round(context_s * FEATURE_RATE)) * ENCODER_HOP  # whole features
        self.current = -1  # the block whose features are held

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

    def audio(self, buffer: np.ndarray, buffer_start: int, block: int) -> np.ndarray:
        """Block ``block``'s encoder window from the stream's audio ``buffer`` (its first sample
        is stream sample ``buffer_start``), at least :data:`MIN_WINDOW` samples: at the end of a
        stream the last windows end with the audio."""
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

    def positions(self, block: int, num_features: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where block ``block``'s frames fall among its window's ``num_features`` features:
        (low, high, weight) so that a frame's feature is ``f[low] * (1 - w) + f[high] * w``."""
        start = self.window_start(block)
        frames = np.arange(block * self.block, (block + 1) * self.block, dtype=np.float64)
        x = np.clip(frames / self.fps * FEATURE_RATE - start / ENCODER_HOP, 0, num_features - 1)
        low = np.floor(x).astype(np.int64)
        high = np.minimum(low + 1, num_features - 1)
        return low, high, x - low


__all__ = [
    "DEFAULT_BLOCK",
    "DEFAULT_CONTEXT_S",
    "DEFAULT_LOOKAHEAD_MS",
    "ENCODER_HOP",
    "FEATURE_RATE",
    "MAX_LOOKAHEAD_MS",
    "MIN_WINDOW",
    "BlockWindows",
]
