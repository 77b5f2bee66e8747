"""Whisper's log-mel spectrogram in numpy: the speech features' input, computed without torch
(the ONNX Runtime path of :mod:`talkmesh.models.onnx`; the same numbers as
:func:`talkmesh.models.whisper.log_mel` within float32 rounding, ``tests/test_onnx.py``)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from talkmesh.constants import SAMPLE_RATE
from talkmesh.errors import TalkmeshError

N_FFT = 400
HOP_LENGTH = 160  # 10 ms mel frames
N_MELS = 80
DYNAMIC_RANGE = 8.0  # log10 units kept below each clip's peak


@lru_cache(maxsize=8)
def mel_filters(sample_rate: int, n_fft: int, n_mels: int) -> np.ndarray:
    """(n_mels, n_fft // 2 + 1) triangular filters on the Slaney mel scale, Slaney-normalized
    (area-normalized), as Whisper and librosa's defaults use."""
    f_sp = 200.0 / 3  # Hz per mel below 1 kHz
    min_log_hz = 1000.0
    min_log_mel = min_log_hz / f_sp
    logstep = np.log(6.4) / 27.0

    def hz_to_mel(f: np.ndarray) -> np.ndarray:
        f = np.asarray(f, dtype=np.float64)
        return np.where(
            f >= min_log_hz,
            min_log_mel + np.log(np.maximum(f, min_log_hz) / min_log_hz) / logstep,
            f / f_sp,
        )

    def mel_to_hz(m: np.ndarray) -> np.ndarray:
        return np.where(
            m >= min_log_mel, min_log_hz * np.exp(logstep * (m - min_log_mel)), f_sp * m
        )

    fft_hz = np.linspace(0.0, sample_rate / 2, n_fft // 2 + 1)
    mel_hz = mel_to_hz(np.linspace(hz_to_mel(0.0), hz_to_mel(sample_rate / 2), n_mels + 2))
    ramps = mel_hz[:, None] - fft_hz[None, :]
    widths = np.diff(mel_hz)
    lower = -ramps[:-2] / widths[:-1, None]
    upper = ramps[2:] / widths[1:, None]
    weights = np.maximum(0.0, np.minimum(lower, upper))
    weights *= (2.0 / (mel_hz[2:] - mel_hz[:-2]))[:, None]
    return weights.astype(np.float32)


def log_mel(audio: np.ndarray, n_mels: int = N_MELS) -> np.ndarray:
    """(S,) float 16 kHz audio -> (n_mels, S // 160) float32: a periodic-Hann STFT (n_fft 400,
    hop 160, centred, reflect-padded, last frame dropped), power, Slaney mel filters, ``log10``
    floored 8 below the clip's peak, then ``(x + 4) / 4``."""
    audio = np.asarray(audio, np.float32)
    if audio.ndim != 1 or len(audio) <= N_FFT // 2:
        raise TalkmeshError(
            f"audio too short for a log-mel spectrogram: {audio.shape} samples "
            f"(needs more than {N_FFT // 2} in one channel)"
        )
    padded = np.pad(audio, N_FFT // 2, mode="reflect")
    count = len(audio) // HOP_LENGTH  # 1 + S // hop frames, the last dropped
    frames = np.lib.stride_tricks.sliding_window_view(padded, N_FFT)[::HOP_LENGTH][:count]
    window = (0.5 - 0.5 * np.cos(2 * np.pi * np.arange(N_FFT) / N_FFT)).astype(np.float32)
    spectrum = np.fft.rfft(frames * window, axis=-1)
    power = (spectrum.real**2 + spectrum.imag**2).astype(np.float32)
    spec = np.log10(np.maximum(mel_filters(SAMPLE_RATE, N_FFT, n_mels) @ power.T, 1e-10))
    spec = np.maximum(spec, spec.max() - DYNAMIC_RANGE)
    return ((spec + 4.0) / 4.0).astype(np.float32)


def interpolate_rows(features: np.ndarray, num_frames: int) -> np.ndarray:
    """(N, D) rows at any rate -> (num_frames, D) by linear interpolation with the ends aligned
    (``torch.nn.functional.interpolate(..., mode="linear", align_corners=True)``)."""
    n = len(features)
    if num_frames == 1 or n == 1:
        pos = np.zeros(num_frames)
    else:
        # float32 positions, as torch computes them
        pos = np.arange(num_frames, dtype=np.float32) * np.float32((n - 1) / (num_frames - 1))
    i0 = np.minimum(np.floor(pos).astype(int), n - 1)
    i1 = np.minimum(i0 + 1, n - 1)
    w = (pos - i0)[:, None].astype(np.float32)
    return features[i0] * (1 - w) + features[i1] * w
