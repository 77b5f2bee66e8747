"""Sample-rate conversion, one function per method, chosen by name.

Our own models take the polyphase filter of :mod:`talkmesh.audio.loading` (``"polyphase"``:
``scipy.signal.resample_poly`` with the exact rational factor, streamed block by block). Models
imported from the papers' releases hear their audio as the official code made it, so that their
output equals the official code's at every input rate, not only at 16 kHz:

* ``"sinc_hann"``: MeshTalk's ``utils/helpers.py`` resamples with
  ``torchaudio.transforms.Resample(sr, 16000)``, whose documented kernel
  (``torchaudio.functional.resample``, method ``sinc_interp_hann``) is a Hann-windowed sinc with
  ``lowpass_filter_width`` 6 zero crossings and a cut-off at ``rolloff`` 0.99 of the lower
  Nyquist rate, applied as a strided convolution over the signal zero-padded either side.
* ``"kaiser_best"``: FaceFormer and CodeTalker read audio with ``librosa.load(path, sr=16000)``;
  their pinned environments (``librosa==0.8.1``) resample with resampy's ``kaiser_best`` filter
  (bandlimited interpolation, J. O. Smith's method: a Kaiser-windowed sinc table, 50 zero
  crossings, 2**13 entries between crossings, beta 12.9846, roll-off 0.917347, interpolated
  linearly between entries), then pad or cut to ``ceil(S * sr / orig_sr)`` samples.

Both are written here from those descriptions in numpy (float64 inside, float32 out);
``tests/test_resamplers.py`` checks them against torchaudio and resampy themselves.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

POLYPHASE = "polyphase"
SINC_HANN = "sinc_hann"
KAISER_BEST = "kaiser_best"
RESAMPLERS = (POLYPHASE, SINC_HANN, KAISER_BEST)

# torchaudio.functional.resample's defaults (sinc_interp_hann)
HANN_ZEROS = 6  # lowpass_filter_width: zero crossings of the sinc either side
HANN_ROLLOFF = 0.99  # cut-off as a share of the lower rate's Nyquist frequency
# resampy's kaiser_best filter, as its documentation states it
KAISER_ZEROS = 50
KAISER_PRECISION = 13  # 2**13 table entries per zero crossing
KAISER_BETA = 12.9846
KAISER_ROLLOFF = 0.917347

ROWS_PER_PIECE = 4096  # output rows computed at once (bounds the temporary arrays)


def check_resampler(name: str) -> str:
    if name not in RESAMPLERS:
        raise ValueError(f"unknown resampler {name!r}: use one of {', '.join(RESAMPLERS)}")
    return name


def resample_with(audio: np.ndarray, orig_sr: int, sr: int, method: str) -> np.ndarray:
    """(S,) waveform at ``orig_sr`` -> (S',) float32 at ``sr`` by an official code's ``method``
    (``sinc_hann`` or ``kaiser_best``; the polyphase filter is
    :func:`talkmesh.audio.loading.resample`, which takes any method)."""
    audio = np.asarray(audio, dtype=np.float32)
    assert audio.ndim == 1, f"expected a (S,) waveform, got shape {audio.shape}"
    if method not in (SINC_HANN, KAISER_BEST):
        raise ValueError(f"resample_with takes sinc_hann or kaiser_best, not {method!r}")
    if orig_sr == sr:
        return audio.copy()
    return (sinc_hann if method == SINC_HANN else kaiser_best)(audio, orig_sr, sr)


def hann_kernel(orig: int, new: int, zeros: int = HANN_ZEROS, rolloff: float = HANN_ROLLOFF):
    """torchaudio's sinc_interp_hann kernel for the reduced rates ``orig`` -> ``new``:
    (new, 2 * width + orig) taps, output phase j against input offsets -width..width+orig-1,
    and the padding ``width`` either side."""
    base = min(orig, new) * rolloff  # cut-off, in cycles per ``orig`` reduced samples
    width = math.ceil(zeros * orig / base)
    idx = np.arange(-width, width + orig, dtype=np.float64) / orig
    t = (-np.arange(new, dtype=np.float64) / new)[:, None] + idx[None, :]
    t = np.clip(t * base, -zeros, zeros)
    window = np.cos(t * math.pi / zeros / 2) ** 2
    t = t * math.pi
    with np.errstate(invalid="ignore", divide="ignore"):
        sinc = np.where(t == 0, 1.0, np.sin(t) / t)
    return sinc * window * (base / orig), width


def sinc_hann(audio: np.ndarray, orig_sr: int, sr: int) -> np.ndarray:
    """(S,) -> (ceil(S * sr / orig_sr),) as ``torchaudio.functional.resample`` (defaults)."""
    g = math.gcd(orig_sr, sr)
    orig, new = orig_sr // g, sr // g
    kernel, width = hann_kernel(orig, new)
    taps = kernel.shape[1]
    padded = np.pad(audio.astype(np.float64), (width, width + orig))
    windows = np.lib.stride_tricks.sliding_window_view(padded, taps)[::orig]  # (blocks, taps)
    n_out = math.ceil(new * len(audio) / orig)
    out = np.empty(len(windows) * new, np.float32)
    for a in range(0, len(windows), ROWS_PER_PIECE):
        rows = windows[a : a + ROWS_PER_PIECE]
        out[a * new : (a + len(rows)) * new] = (rows @ kernel.T).reshape(-1)
    return out[:n_out]


@lru_cache(maxsize=1)
def kaiser_table() -> np.ndarray:
    """The right half of resampy's kaiser_best filter: (KAISER_ZEROS * 2**KAISER_PRECISION + 1,)
    samples of the windowed sinc from 0 to the last zero crossing."""
    n = 2**KAISER_PRECISION * KAISER_ZEROS
    sinc = KAISER_ROLLOFF * np.sinc(KAISER_ROLLOFF * np.linspace(0, KAISER_ZEROS, n + 1))
    return np.kaiser(2 * n + 1, KAISER_BETA)[n:] * sinc


def kaiser_best(audio: np.ndarray, orig_sr: int, sr: int) -> np.ndarray:
    """(S,) -> (ceil(S * sr / orig_sr),) as ``librosa.load(sr=sr)`` resampled it with resampy's
    ``kaiser_best``: output sample t sits at input time t / ratio, between input samples n and
    n + 1; the left wing weighs x[n - i], the right wing x[n + 1 + k], each tap read from the
    table (scaled by the ratio when downsampling) with linear interpolation between entries."""
    x = audio.astype(np.float64)
    ratio = sr / orig_sr
    table = kaiser_table() * (ratio if ratio < 1 else 1.0)
    delta = np.diff(table, append=table[-1])
    per_zero = 2**KAISER_PRECISION
    scale = min(1.0, ratio)
    step = int(scale * per_zero)  # table entries between consecutive input samples
    n_core = int(len(x) * ratio)  # resampy's length; librosa then pads to the ceiling
    out = np.zeros(math.ceil(len(x) * ratio), np.float32)
    times = np.arange(n_core) * (1.0 / ratio)
    for a in range(0, n_core, ROWS_PER_PIECE):
        t = times[a : a + ROWS_PER_PIECE]
        n = t.astype(np.int64)
        frac = scale * (t - n)
        left = _wing(x, table, delta, step, per_zero, frac, n, n + 1, -1)
        right = _wing(x, table, delta, step, per_zero, scale - frac, n + 1, len(x) - n - 1, 1)
        out[a : a + len(t)] = left + right
    return out


def _wing(x, table, delta, step, per_zero, frac, first, available, direction) -> np.ndarray:
    """One wing of the interpolation for a piece of outputs: sum over taps i < min(available,
    taps left in the table) of the table at ``frac`` + i zero-crossing steps times
    x[first + direction * i]."""
    index = frac * per_zero
    offset = index.astype(np.int64)
    eta = (index - offset)[:, None]
    count = np.minimum(available, (len(table) - offset) // step)  # taps this output uses
    taps = np.arange(int(count.max()) if len(count) else 0)
    used = taps[None, :] < count[:, None]
    where = np.where(used, offset[:, None] + taps[None, :] * step, 0)
    weight = table[where] + eta * delta[where]
    sample = np.where(used, first[:, None] + direction * taps[None, :], 0)
    return np.sum(np.where(used, weight * x[sample], 0.0), axis=1)
