"""Where speech is, in any language: Silero VAD (the ``silero-vad`` wheel ships its weights).

The pause gate of :mod:`talkmesh.face.corrections` shuts the mouth where nobody speaks. Finding
those pauses with the English phone recogniser works on English only; a voice activity detector
trained on many languages finds them in any. :func:`speech_pauses` returns the clip as timed
``SIL`` / ``SPEECH`` segments, the shape :func:`talkmesh.face.pauses.speech_gate` reads.

The model is TorchScript from the installed ``silero_vad`` package (trusted code that ships with
it, never a user's file), loaded once per process.
"""

from __future__ import annotations

import functools
import warnings

import numpy as np

from talkmesh.audio.phonemes import SILENCE, Phone
from talkmesh.constants import SAMPLE_RATE
from talkmesh.errors import MissingDependencyError

SPEECH = "SPEECH"
THRESHOLD = 0.5  # speech probability above which a 32 ms window is speech
MIN_SILENCE_MS = 100  # shorter gaps are within speech
SPEECH_PAD_MS = 10  # each speech segment is widened this much on both sides (the gate ramps)


@functools.lru_cache(maxsize=1)
def _model():
    try:
        from silero_vad import load_silero_vad
    except ImportError:
        raise MissingDependencyError("silero-vad", "speech", "the pause gate") from None
    with warnings.catch_warnings():  # the package's own deprecations, not the user's business
        warnings.simplefilter("ignore", DeprecationWarning)
        return load_silero_vad()


def speech_pauses(wave: np.ndarray, sr: int = SAMPLE_RATE) -> list[Phone]:
    """(S,) float32 at 16 kHz -> contiguous ``SIL`` / ``SPEECH`` segments covering the clip."""
    import torch
    from silero_vad import get_speech_timestamps

    assert sr == SAMPLE_RATE, sr
    duration = len(wave) / sr
    if not len(wave):
        return []
    with torch.inference_mode():
        stamps = get_speech_timestamps(
            torch.from_numpy(np.ascontiguousarray(wave, dtype=np.float32)),
            _model(),
            sampling_rate=sr,
            threshold=THRESHOLD,
            min_silence_duration_ms=MIN_SILENCE_MS,
            speech_pad_ms=SPEECH_PAD_MS,
        )
    out: list[Phone] = []
    t = 0.0
    for s in stamps:
        start, end = s["start"] / sr, min(duration, s["end"] / sr)
        if start > t:
            out.append(Phone(SILENCE, t, start))
        out.append(Phone(SPEECH, max(t, start), end))
        t = end
    if t < duration:
        out.append(Phone(SILENCE, t, duration))
    return out
