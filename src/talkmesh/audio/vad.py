"""Where speech is, in any language: Silero VAD (the ``silero-vad`` wheel ships its weights).

The pause gate of :mod:`talkmesh.face.corrections` shuts the mouth where nobody speaks. Finding
those pauses with the English phone recogniser works on English only; a voice activity detector
trained on many languages finds them in any. :func:`speech_pauses` returns the clip as timed
``SIL`` / ``SPEECH`` segments, the shape :func:`talkmesh.face.pauses.speech_gate` reads.

The model is the ONNX file inside the installed ``silero_vad`` package (trusted data that ships
with it, never a user's file), run by ONNX Runtime without importing the package (which imports
torch) and opened once per process. :func:`speech_probabilities` feeds it 32 ms windows with the
64 samples before each as context and carries its recurrent state, as the package's own wrapper
does; :func:`speech_segments` turns the probabilities into segments by the package's documented
rules (``get_speech_timestamps``: enter speech at ``threshold``, leave below ``threshold - 0.15``
after ``min_silence_duration_ms``, drop segments shorter than ``min_speech_duration_ms``, pad
each by ``speech_pad_ms``, splitting shorter gaps evenly). ``tests/test_vad.py`` checks both
against the package on real and synthetic speech.
"""

from __future__ import annotations

import functools
from importlib.util import find_spec
from pathlib import Path

import numpy as np

from talkmesh.audio.phonemes import SILENCE, Phone
from talkmesh.constants import SAMPLE_RATE
from talkmesh.errors import MissingDependencyError, TalkmeshError

SPEECH = "SPEECH"
THRESHOLD = 0.5  # speech probability above which a 32 ms window is speech
EXIT_MARGIN = 0.15  # speech ends below THRESHOLD - EXIT_MARGIN (the package's default)
MIN_SILENCE_MS = 100  # shorter gaps are within speech
MIN_SPEECH_MS = 250  # shorter segments are dropped (the package's default)
SPEECH_PAD_MS = 10  # each speech segment is widened this much on both sides (the gate ramps)
WINDOW = 512  # samples per probability at 16 kHz
CONTEXT = 64  # samples of the previous window fed before each window
STATE_SHAPE = (2, 1, 128)
MODEL_FILE = "silero_vad.onnx"


@functools.lru_cache(maxsize=1)
def _session():
    """ONNX Runtime's session of the installed package's model, on one thread (a 32 ms window's
    small products lose to a team of threads)."""
    spec = find_spec("silero_vad")
    if spec is None or spec.origin is None:
        raise MissingDependencyError("silero-vad", "speech", "the pause gate")
    try:
        import onnxruntime as ort
    except ImportError:
        raise MissingDependencyError("onnxruntime", "speech", "the pause gate") from None
    path = Path(spec.origin).parent / "data" / MODEL_FILE
    if not path.is_file():
        raise TalkmeshError(
            f"the silero-vad package has no {MODEL_FILE}: reinstall it (pip install silero-vad)"
        )
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def speech_probabilities(wave: np.ndarray) -> np.ndarray:
    """(S,) float32 at 16 kHz -> (ceil(S / 512),) the model's speech probability of each 32 ms
    window (the last zero-padded)."""
    session = _session()
    count = -(-len(wave) // WINDOW)
    padded = np.zeros(CONTEXT + count * WINDOW, np.float32)
    padded[CONTEXT : CONTEXT + len(wave)] = wave
    state = np.zeros(STATE_SHAPE, np.float32)
    rate = np.array(SAMPLE_RATE, np.int64)
    out = np.empty(count, np.float32)
    for i in range(count):
        window = padded[None, i * WINDOW : (i + 1) * WINDOW + CONTEXT]
        prob, state = session.run(None, {"input": window, "state": state, "sr": rate})
        out[i] = prob[0, 0]
    return out


def speech_segments(
    probs: np.ndarray,
    samples: int,
    threshold: float = THRESHOLD,
    min_silence_ms: float = MIN_SILENCE_MS,
    min_speech_ms: float = MIN_SPEECH_MS,
    pad_ms: float = SPEECH_PAD_MS,
) -> list[tuple[int, int]]:
    """Speech segments [start, end) in samples of a ``samples``-long clip from its windows'
    probabilities (module docstring)."""
    exit_below = max(threshold - EXIT_MARGIN, 0.01)
    min_silence = SAMPLE_RATE * min_silence_ms / 1000
    min_speech = SAMPLE_RATE * min_speech_ms / 1000
    pad = SAMPLE_RATE * pad_ms / 1000
    found: list[list[int]] = []
    start = quiet_from = None  # the open segment's start; where its trailing quiet began
    for i, p in enumerate(probs):
        at = i * WINDOW
        if p >= threshold:
            quiet_from = None
            if start is None:
                start = at
            continue
        if start is None or p >= exit_below:
            continue
        quiet_from = at if quiet_from is None else quiet_from
        if at - quiet_from >= min_silence:
            if quiet_from - start > min_speech:
                found.append([start, quiet_from])
            start = quiet_from = None
    if start is not None and samples - start > min_speech:
        found.append([start, samples])
    for i, seg in enumerate(found):  # widen by the pad; a gap under two pads is split evenly
        if i == 0:
            seg[0] = int(max(0, seg[0] - pad))
        if i + 1 < len(found):
            gap = found[i + 1][0] - seg[1]
            share = gap // 2 if gap < 2 * pad else pad
            seg[1] = int(min(samples, seg[1] + share))
            found[i + 1][0] = int(max(0, found[i + 1][0] - share))
        else:
            seg[1] = int(min(samples, seg[1] + pad))
    return [(a, b) for a, b in found]


def speech_pauses(wave: np.ndarray, sr: int = SAMPLE_RATE) -> list[Phone]:
    """(S,) float32 at 16 kHz -> contiguous ``SIL`` / ``SPEECH`` segments covering the clip."""
    assert sr == SAMPLE_RATE, sr
    duration = len(wave) / sr
    if not len(wave):
        return []
    wave = np.ascontiguousarray(wave, dtype=np.float32)
    stamps = speech_segments(speech_probabilities(wave), len(wave))
    out: list[Phone] = []
    t = 0.0
    for a, b in stamps:
        start, end = a / sr, min(duration, b / sr)
        if start > t:
            out.append(Phone(SILENCE, t, start))
        out.append(Phone(SPEECH, max(t, start), end))
        t = end
    if t < duration:
        out.append(Phone(SILENCE, t, duration))
    return out
