"""Speech features of long audio a chunk of motion frames at a time, so that memory does not grow
with the length of the audio (:meth:`talkmesh.models.codetalker.model.CodeTalker.generate_chunks`).

:class:`FrameFeatures` hands out the (1, t, D) features of consecutive motion frames. With the
Whisper encoder it encodes one 30 s window at a time, as the whole-audio forward does (its
windows are independent: no context crosses them, :class:`~talkmesh.models.whisper.WhisperFeatures`),
with the log-mel clamped below the whole audio's peak (a first pass finds it) and the features
interpolated to the frames at the same positions; the numbers match the whole-audio forward up
to float rounding. Other encoders run once over the whole audio and are sliced (their (T, D)
features are then held, a few hundred bytes per frame). The audio may be a
:class:`~talkmesh.audio.waveform.Waveform`, read from its file a window at a time.

Axis letters: S audio samples, M mel frames, N 50 Hz feature frames, T motion frames, D width.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from talkmesh.audio.waveform import Waveform
from talkmesh.constants import SAMPLE_RATE
from talkmesh.models.speech import WhisperEncoder
from talkmesh.models.whisper import (
    ENCODER_HOP,
    HOP_LENGTH,
    N_FFT,
    WhisperFeatures,
    _mel_filters,
)


def audio_tensor(audio: Tensor | Waveform) -> Tensor:
    """(1, S) audio as a tensor: a :class:`Waveform` is read whole (for what needs it all)."""
    if isinstance(audio, Waveform):
        return torch.from_numpy(np.asarray(audio))[None]
    return audio


def log10_mel_frames(
    audio: Tensor | Waveform, m0: int, m1: int, filters: Tensor, length: int | None = None
) -> Tensor:
    """(S,) audio -> (n_mels, m1 - m0) log10 mel power of frames m0..m1-1 of
    :func:`~talkmesh.models.whisper.log_mel`'s centred, reflect-padded STFT (before its clamp).
    ``length`` >= S: the audio as if zero-padded to that many samples (no padded copy made).
    Only the samples these frames see are read (a slice of a :class:`Waveform`)."""
    S, half = len(audio), N_FFT // 2
    L = S if length is None else length
    idx = torch.arange(m0 * HOP_LENGTH - half, (m1 - 1) * HOP_LENGTH + half)
    idx = torch.where(idx < 0, -idx, idx)  # reflect padding at both ends, as torch.stft's
    idx = torch.where(idx >= L, 2 * (L - 1) - idx, idx)
    lo = min(int(idx.min()), S - 1)
    hi = max(lo + 1, min(S, int(idx.max()) + 1))
    piece = audio[lo:hi]
    piece = torch.from_numpy(piece) if isinstance(piece, np.ndarray) else piece.float()
    at = idx.clamp(min=lo, max=hi - 1) - lo
    samples = torch.where(idx < S, piece[at], 0.0)  # zeros past the audio
    window = torch.hann_window(N_FFT, device=piece.device)
    stft = torch.stft(samples, N_FFT, HOP_LENGTH, window=window, center=False, return_complex=True)
    return torch.clamp(filters @ (stft.abs() ** 2), min=1e-10).log10()


class WhisperRows:
    """The 50 Hz Whisper features of one (S,) waveform, computed window by window on demand:
    :meth:`rows` keeps only the windows it was last asked for."""

    def __init__(self, features: WhisperFeatures, audio: Tensor | Waveform) -> None:
        self.features = features
        S = len(audio)
        step = features.window * ENCODER_HOP if features.pad_to_window else ENCODER_HOP
        # zero-padded to whole windows as the whole-audio forward pads it, but without a padded
        # copy; a Waveform is read from its file a window at a time (else the audio is the
        # longest thing held: 3.8 MB a minute)
        self.audio = audio
        self.length = -(-S // step) * step
        self.count = -(-S // ENCODER_HOP)  # N: features of the valid audio
        self.mels = self.length // HOP_LENGTH  # M: log_mel's frames (the last dropped)
        self.span = 2 * features.window  # mel frames per window
        self.filters = torch.from_numpy(_mel_filters(SAMPLE_RATE, N_FFT, features.n_mels))
        # log_mel clamps to 8 below the whole audio's peak: find it first, a window at a time
        self.peak = max(
            float(
                log10_mel_frames(
                    self.audio, m, min(m + self.span, self.mels), self.filters, self.length
                ).max()
            )
            for m in range(0, self.mels, self.span)
        )
        self.cache: dict[int, Tensor] = {}

    def _window(self, w: int) -> Tensor:
        """Window ``w``'s features (n, D)."""
        if w not in self.cache:
            m0 = w * self.span
            spec = log10_mel_frames(
                self.audio, m0, min(m0 + self.span, self.mels), self.filters, self.length
            )
            mel = (torch.maximum(spec, torch.tensor(self.peak - 8.0)) + 4.0) / 4.0
            self.cache[w] = self.features._encode(mel[None])[0]
        return self.cache[w]

    def rows(self, i0: int, i1: int) -> Tensor:
        """Features i0..i1-1 (i1 - i0, D); windows before ``i0``'s are forgotten."""
        w0, w1 = i0 // self.features.window, (i1 - 1) // self.features.window
        for w in [w for w in self.cache if w < w0]:
            del self.cache[w]
        out = torch.cat([self._window(w) for w in range(w0, w1 + 1)])
        return out[i0 - w0 * self.features.window : i1 - w0 * self.features.window]


class FrameFeatures:
    """The speech features of ``positions`` frames spread over (1, S) ``audio`` or a
    :class:`Waveform` (what ``speech(audio, None, positions)`` returns), handed out by
    :meth:`__call__` in slices."""

    def __init__(self, speech: nn.Module, audio: Tensor | Waveform, positions: int) -> None:
        streamed = isinstance(audio, Waveform)
        assert streamed or (audio.dim() == 2 and audio.shape[0] == 1), audio.shape
        self.positions = positions
        self.rows: WhisperRows | None = None
        self.full: Tensor | None = None
        if isinstance(speech, WhisperEncoder):
            self.rows = WhisperRows(speech.features, audio if streamed else audio[0])
        else:
            self.full = speech(audio_tensor(audio), None, positions)

    def __call__(self, p0: int, p1: int) -> Tensor:
        """Features of frames p0..p1-1: (1, p1 - p0, D)."""
        if self.full is not None:
            return self.full[:, p0:p1]
        assert self.rows is not None
        # interpolate_frames' linear interpolation with align_corners over all N features
        N, n = self.rows.count, self.positions
        scale = (N - 1) / (n - 1) if n > 1 else 0.0
        pos = torch.arange(p0, p1, dtype=torch.float64) * scale
        i0 = pos.floor().long().clamp(max=N - 1)
        i1 = (i0 + 1).clamp(max=N - 1)
        lam = (pos - i0).float()[:, None]
        first = int(i0[0])
        block = self.rows.rows(first, int(i1[-1]) + 1)
        out = block[i0 - first] * (1 - lam) + block[i1 - first] * lam
        return out[None]
