"""An ONNX export streams, without torch: the windows of :class:`talkmesh.models.blocks.BlockWindows`
(a block of 3 frames per speech-graph window, ending a look-ahead after the block and starting
2 s before it) through the export's speech graph, then the step graph one frame at a time, the
streams of one :class:`~talkmesh.models.onnx.OnnxModel` in one batch per step (the step graph's
inputs all have the batch axis first). The frames are those of the PyTorch stream of the same
model (:class:`talkmesh.models.whisper_stream.WhisperFeatureStream`, float rounding apart):
every export is of a CodeTalker with the Whisper encoder and a causal VQ decoder.

Axis letters: B streams in a step, N 50 Hz features, D width, V vertices.
"""

from __future__ import annotations

import numpy as np

from talkmesh.audio.logmel import log_mel
from talkmesh.blas import one_blas_thread
from talkmesh.models.blocks import DEFAULT_BLOCK, DEFAULT_CONTEXT_S, ENCODER_HOP, BlockWindows
from talkmesh.models.framestream import FrameRequest, FrameStream


class OnnxFeatureStream(BlockWindows):
    """One stream's speech features from the export's speech graph, a block of frames at a
    time."""

    def __init__(
        self,
        model,
        lookahead_ms: float | None = None,
        context_s: float = DEFAULT_CONTEXT_S,
        block: int = DEFAULT_BLOCK,
    ) -> None:
        super().__init__(model.motion_fps, lookahead_ms, context_s, block)
        self.model = model
        self.held: np.ndarray | None = None

    def feature(self, buffer: np.ndarray, buffer_start: int, frame: int) -> np.ndarray:
        """The speech feature (D,) of ``frame`` (frames in order; its block's window is encoded
        at the block's first frame)."""
        block = frame // self.block
        if block != self.current:
            feats = self.encode(self.audio(buffer, buffer_start, block))
            low, high, w = self.positions(block, len(feats))
            w = w.astype(feats.dtype)[:, None]
            self.held, self.current = feats[low] * (1 - w) + feats[high] * w, block
        assert self.held is not None
        return self.held[frame - block * self.block]

    def encode(self, audio: np.ndarray) -> np.ndarray:
        """(S,) one window -> (N, D) its 50 Hz features (the log-mel of the window alone)."""
        n = len(audio)
        padded = np.zeros(-(-n // ENCODER_HOP) * ENCODER_HOP, np.float32)
        padded[:n] = audio
        with one_blas_thread():  # a small product every 100 ms: a team of threads costs more
            mel = log_mel(padded, self.model.n_mels)[None]
        return self.model.speech.run(None, {"mel": mel})[0][0][: -(-n // ENCODER_HOP)]


class OnnxFrameStream(FrameStream):
    """One stream of an :class:`~talkmesh.models.onnx.OnnxModel`: its style, VQ decoder head
    term and step state (batch 1), stepped together with the model's other streams."""

    def __init__(
        self,
        model,
        style_weights: np.ndarray | None,
        lookahead_ms: float | None,
        template: np.ndarray | None,
    ) -> None:
        self.features = OnnxFeatureStream(model, lookahead_ms)
        self.engine = model  # the streams of one model step together (next_frames)
        self.fps, self.lookahead_ms = model.motion_fps, self.features.lookahead_ms
        self.style = model.style(style_weights, template)  # (1, d)
        self.face = model.face(template)  # (1, hidden), or None for a model without the term
        self.state = model.start(self.style)
        self.t = 0

    def audio_needed(self, frame: int) -> float:
        return self.features.audio_needed(frame)

    def first_sample(self, frame: int) -> int:
        return self.features.first_sample(frame)

    def frame(self, buffer: np.ndarray, buffer_start: int, frame: int) -> np.ndarray:
        return self.frames_together([FrameRequest(self, buffer, buffer_start, frame)])[0]

    def frames_together(
        self, requests: list[FrameRequest], basis: np.ndarray | None = None
    ) -> np.ndarray:
        """One step graph run for the next frame of each request's stream (streams of this
        model, each at most once) -> (B, V * 3) offsets, or (B, K) projections onto ``basis``."""
        streams = [r.stream for r in requests]
        if len({id(s) for s in streams}) != len(streams):
            raise ValueError("a step computes one frame per stream")
        for s, r in zip(streams, requests):
            if r.frame != s.t:
                raise ValueError(f"frame {r.frame} asked for out of order")
        feats = np.stack(
            [
                s.features.feature(r.buffer, r.buffer_start, r.frame)
                for s, r in zip(streams, requests)
            ]
        )
        model = self.engine

        def batch(arrays: list[np.ndarray]) -> np.ndarray:  # one stream's state as it is
            return arrays[0] if len(arrays) == 1 else np.concatenate(arrays)

        state = {n: batch([s.state[n] for s in streams]) for n in model.state}
        face = batch([s.face for s in streams]) if model.has_face else None
        t = np.array([r.frame for r in requests], np.int64)
        style = batch([s.style for s in streams])
        motion, state = model.step_frames(feats.astype(np.float32), t, style, state, face)
        for b, s in enumerate(streams):
            s.state = {n: v[b : b + 1] for n, v in state.items()}
            s.t += 1
        if basis is None:
            return motion
        # not BLAS: a product each frame wakes BLAS's team of threads, which then spin (it doubled
        # a stream's CPU time)
        return np.einsum("bi,ki->bk", motion.astype(np.float64), basis)


__all__ = ["OnnxFeatureStream", "OnnxFrameStream"]
