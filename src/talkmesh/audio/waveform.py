"""A speech file's waveform read from the file a piece at a time, so that long audio is never
held whole (an hour at 16 kHz is 230 MB of float32).

:class:`Waveform` looks like the (S,) float32 array :func:`~talkmesh.audio.loading.load_audio`
returns to code that takes slices of it (``len(w)``, ``w[a:b]``): each slice is read from the
file (``SoundFile.seek``), mixed down and resampled with enough context either side that it
equals the same slice of the whole file's ``load_audio`` (the polyphase filter's pieces start on
multiples of ``down`` input samples, as in :func:`~talkmesh.audio.loading._resample_blocks`).
:func:`open_audio` makes one for the files libsndfile reads and loads the rest (mp3, m4a: ffmpeg
decodes them through a pipe) whole, as before.
"""

from __future__ import annotations

import math
from fractions import Fraction
from pathlib import Path

import numpy as np
import soundfile as sf

from talkmesh.audio.loading import (
    BLOCK_S,
    MAX_DURATION_S,
    SOUNDFILE_EXTENSIONS,
    UNKNOWN_FRAMES,
    _check_duration,
    _check_file,
    _riff_stated_seconds,
    load_audio,
    refuse_nonfinite,
    warn_if_cut,
)
from talkmesh.constants import SAMPLE_RATE
from talkmesh.errors import TalkmeshError


class Waveform:
    """The (S,) float32 mono waveform of ``path`` at ``sr``, read a slice at a time.

    ``len(w)``, ``w.shape``, ``w[a:b]`` (an ndarray, equal to ``load_audio(path, sr)[a:b]``),
    ``np.asarray(w)`` (the whole waveform: only for what needs it all, e.g. a video's sound).
    """

    ndim = 1
    dtype = np.dtype(np.float32)

    def __init__(self, path: str | Path, sr: int = SAMPLE_RATE) -> None:
        self.path = Path(path)
        info = sf.info(str(self.path))
        self.frames, self.channels, self.orig_sr = info.frames, info.channels, info.samplerate
        ratio = Fraction(sr, self.orig_sr)
        self.up, self.down = ratio.numerator, ratio.denominator
        self.sr = sr
        self.length = -(-self.frames * self.up // self.down)
        # input samples of context either side: resample_poly's filter reaches
        # 10 * max(up, down) samples at the upsampled rate (as _resample_blocks)
        self.margin = math.ceil(10 * max(self.up, self.down) / self.up) + 1

    def __len__(self) -> int:
        return self.length

    @property
    def shape(self) -> tuple[int]:
        return (self.length,)

    def __getitem__(self, key: slice) -> np.ndarray:
        if not isinstance(key, slice):
            raise TypeError("a Waveform is read by slices: w[a:b]")
        start, stop, step = key.indices(self.length)
        if step != 1:
            raise TypeError("a Waveform is read by contiguous slices")
        return self.read(start, stop)

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        out = self.read(0, self.length)
        return out if dtype is None else out.astype(dtype, copy=False)

    def _input(self, i0: int, i1: int) -> np.ndarray:
        """Input samples i0..i1-1 mixed down to mono (float32, as load_audio mixes them)."""
        with sf.SoundFile(str(self.path)) as f:
            f.seek(i0)
            b = f.read(i1 - i0, dtype="float32", always_2d=True)
        return b[:, 0] if b.shape[1] == 1 else b.mean(axis=1, dtype=np.float32)

    def read(self, start: int, stop: int) -> np.ndarray:
        """Samples start..stop-1 (clipped to the waveform) as a (stop - start,) float32 array."""
        start, stop = max(0, start), min(self.length, stop)
        if stop <= start:
            return np.zeros(0, np.float32)
        up, down = self.up, self.down
        if up == down:
            return np.ascontiguousarray(self._input(start, stop))
        # output j is input j * down / up; the piece starts on a multiple of down, where an
        # input sample falls exactly on an output sample
        first = max(0, (start * down // up - self.margin) // down * down)
        last = min(self.frames, -(-stop * down // up) + self.margin)
        from scipy.signal import resample_poly  # here: scipy.signal takes a second to import

        y = resample_poly(self._input(first, last), up, down)
        lo = start - first * up // down
        return np.ascontiguousarray(y[lo : lo + stop - start], np.float32)

    def blocks(self, size: int):
        """Consecutive (size,) slices (the last shorter) from the start."""
        for a in range(0, self.length, size):
            yield self.read(a, a + size)


def open_audio(
    path: str | Path, sr: int = SAMPLE_RATE, *, max_seconds: float | None = None
) -> Waveform | np.ndarray:
    """:func:`~talkmesh.audio.loading.load_audio`'s waveform, the same checks and errors, as a
    :class:`Waveform` read from the file on demand when libsndfile reads it (else an array).

    The samples are read once here, a block at a time, to refuse NaN or infinite ones."""
    path = _check_file(path)
    if sr <= 0:
        raise TalkmeshError(f"sample rate must be positive, got {sr}")
    if path.suffix.lower() not in SOUNDFILE_EXTENSIONS:
        return load_audio(path, sr, max_seconds=max_seconds)
    try:
        wave = Waveform(path, sr)
    except sf.LibsndfileError:  # a codec only ffmpeg reads: load_audio falls back to it
        return load_audio(path, sr, max_seconds=max_seconds)
    if wave.frames >= UNKNOWN_FRAMES:  # no length in the header (FLAC from a pipe): no seeking
        return load_audio(path, sr, max_seconds=max_seconds)
    if wave.frames <= 0:
        raise TalkmeshError(f"{path} contains no audio samples: re-export or re-record it")
    limit = MAX_DURATION_S if max_seconds is None else max_seconds
    _check_duration(path, wave.frames / wave.orig_sr, limit)
    try:
        blocks = wave.blocks(int(BLOCK_S * sr))
        bad = sum(int(np.count_nonzero(~np.isfinite(b))) for b in blocks)
    except sf.LibsndfileError:  # truncated or corrupt: ffmpeg reads what is there
        return load_audio(path, sr, max_seconds=max_seconds)
    refuse_nonfinite(path, bad)
    stated = _riff_stated_seconds(path) or wave.frames / wave.orig_sr
    warn_if_cut(path, len(wave) / sr, stated, sr, stacklevel=2)
    return wave
