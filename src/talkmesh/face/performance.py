"""Emotion for the whole clip, over spans of it or from tags in the transcript, as ARKit weights.

Without emotional 4D captures, the faces are built from what is known about them: the Facial
Action Coding System (FACS; Ekman & Friesen 1978, revised by Ekman, Friesen & Hager 2002) names
the muscle movements (action units, AUs) a face can make, and EMFACS (Friesen & Ekman 1983) lists
the prototype AU combinations of the basic emotions. The prototypes used here are the commonly
cited EMFACS ones (Ekman, Friesen & Hager 2002, *FACS Investigator's Guide*, table 10-1):

========== ===================== =============================================
emotion    AUs                   what moves
========== ===================== =============================================
happy      6 + 12                cheeks raised, lip corners pulled up
sad        1 + 4 + 15            inner brows up and drawn together, corners down
surprised  1 + 2 + 5 + 26        brows raised, eyes wide, jaw dropped
fearful    1 + 2 + 4 + 5 + 7     brows raised and drawn together, eyes wide
           + 20 + 26             and tense, lips stretched, jaw dropped
angry      4 + 5 + 7 + 23        brows lowered, eyes glaring, lips tightened
disgusted  9 + 15 + 16           nose wrinkled, corners down, lower lip down
========== ===================== =============================================

Each AU is expressed in the ARKit channels that make that movement (:data:`AU_ARKIT`; AU23, the
lip tightener, has no ARKit shape of its own and is given ``mouthPress``, the nearest). An emotion
at intensity 1 is its AUs at the amplitudes of :data:`EMOTION_AUS`; a mix is the intensity-weighted
sum, clipped to [0, 1]. The result is a (T, 52) offset over the speech's weights; how it is
composed with the speech is :mod:`talkmesh.face.composition`.

A :class:`Performance` is a base mix for the whole clip (``--emotion happy:0.6,surprised:0.2``)
and spans that blend to another mix and back (``--performance FILE``, or ``[happy]`` tags in a
``--text`` transcript) with raised-cosine onsets and offsets.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES

EMOTIONS = ("neutral", "happy", "sad", "angry", "surprised", "fearful", "disgusted")
MAX_INTENSITY = 1.0
ONSET_S = 0.3  # a span's default onset: expressions rise in a few hundred ms
OFFSET_S = 0.5  # ... and fade somewhat slower
MAX_SPANS = 10_000  # a timeline file with more is not a performance
MAX_FILE_BYTES = 4 * 2**20

_BOTH = ("Left", "Right")


def _sides(stem: str, weight: float) -> dict[str, float]:
    return {f"{stem}{side}": weight for side in _BOTH}


# FACS action unit -> ARKit channels at the AU's full intensity.
AU_ARKIT: dict[int, dict[str, float]] = {
    1: {"browInnerUp": 1.0},  # inner brow raiser
    2: _sides("browOuterUp", 1.0),  # outer brow raiser
    4: _sides("browDown", 1.0),  # brow lowerer
    5: _sides("eyeWide", 1.0),  # upper lid raiser
    6: _sides("cheekSquint", 1.0) | _sides("eyeSquint", 0.3),  # cheek raiser
    7: _sides("eyeSquint", 1.0),  # lid tightener
    9: _sides("noseSneer", 1.0),  # nose wrinkler
    12: _sides("mouthSmile", 1.0),  # lip corner puller
    15: _sides("mouthFrown", 1.0),  # lip corner depressor
    16: _sides("mouthLowerDown", 1.0),  # lower lip depressor
    20: _sides("mouthStretch", 1.0),  # lip stretcher
    23: _sides("mouthPress", 1.0),  # lip tightener (no ARKit shape: the presser's)
    26: {"jawOpen": 1.0},  # jaw drop
}

# Emotion -> AU intensities at full emotion (EMFACS prototypes, module docstring).
EMOTION_AUS: dict[str, dict[int, float]] = {
    "neutral": {},
    "happy": {6: 0.6, 12: 0.7},
    "sad": {1: 0.7, 4: 0.35, 15: 0.6},
    "angry": {4: 0.8, 5: 0.3, 7: 0.5, 23: 0.5},
    "surprised": {1: 0.8, 2: 0.8, 5: 0.6, 26: 0.25},
    "fearful": {1: 0.7, 2: 0.5, 4: 0.3, 5: 0.7, 7: 0.2, 20: 0.5, 26: 0.15},
    "disgusted": {9: 0.7, 15: 0.4, 16: 0.3},
}
assert set(EMOTION_AUS) == set(EMOTIONS)

_INDEX = {name: k for k, name in enumerate(ARKIT_NAMES)}


def emotion_vector(emotion: str) -> np.ndarray:
    """(52,) ARKit weights of ``emotion`` at intensity 1: the sum of its AUs' channels."""
    if emotion not in EMOTION_AUS:
        raise TalkmeshError(f"unknown emotion {emotion!r}: use one of {', '.join(EMOTIONS)}")
    out = np.zeros(len(ARKIT_NAMES), np.float32)
    for au, amount in EMOTION_AUS[emotion].items():
        for name, weight in AU_ARKIT[au].items():
            out[_INDEX[name]] += amount * weight
    return np.clip(out, 0.0, 1.0)


# (len(EMOTIONS), 52): every emotion's vector, rows in EMOTIONS order
EMOTION_BASIS = np.stack([emotion_vector(e) for e in EMOTIONS])

Mix = dict[str, float]  # emotion -> intensity in [0, 1]


def check_mix(mix: Mix, where: str) -> Mix:
    """``mix`` with its emotions and intensities checked (one-line errors naming ``where``)."""
    for name, value in mix.items():
        if name not in EMOTION_AUS:
            raise TalkmeshError(
                f"{where}: unknown emotion {name!r}: use one of {', '.join(EMOTIONS)}"
            )
        if not isinstance(value, (int, float)) or not 0.0 <= value <= MAX_INTENSITY:
            raise TalkmeshError(
                f"{where}: the intensity of {name} must be a number from 0 to "
                f"{MAX_INTENSITY:g}, got {value!r}"
            )
    return {k: float(v) for k, v in mix.items()}


def parse_emotion(text: str, where: str = "--emotion") -> Mix:
    """``happy:0.6,surprised:0.2`` -> {"happy": 0.6, "surprised": 0.2}; a bare name is 1."""
    mix: Mix = {}
    for item in text.split(","):
        name, colon, value = item.strip().partition(":")
        name = name.strip().lower()
        if not name:
            raise TalkmeshError(f"{where} {text!r}: give EMOTION[:INTENSITY], e.g. happy:0.6")
        try:
            mix[name] = float(value) if colon else 1.0
        except ValueError:
            raise TalkmeshError(
                f"{where} {text!r}: '{item.strip()}' must look like EMOTION:INTENSITY (happy:0.6)"
            ) from None
    return check_mix(mix, f"{where} {text}")


def mix_vector(mix: Mix) -> np.ndarray:
    """(len(EMOTIONS),) intensities of ``mix`` in EMOTIONS order."""
    return np.array([mix.get(e, 0.0) for e in EMOTIONS], np.float32)


@dataclass(frozen=True)
class Span:
    """From ``start`` to ``end`` (s) the face blends from the base mix to ``mix``: it rises over
    ``onset`` s from ``start`` and falls back over ``offset`` s until ``end`` (raised cosines,
    shortened to fit a short span)."""

    start: float
    end: float
    mix: Mix
    onset: float = ONSET_S
    offset: float = OFFSET_S

    def envelope(self, times: np.ndarray) -> np.ndarray:
        """(T,) in [0, 1]: 0 outside the span, 1 between its onset and offset."""
        length = self.end - self.start
        scale = min(1.0, length / (self.onset + self.offset)) if self.onset + self.offset else 1
        rise, fall = self.onset * scale, self.offset * scale
        up = _ease((times - self.start) / rise) if rise > 0 else (times >= self.start) * 1.0
        down = _ease((self.end - times) / fall) if fall > 0 else (times < self.end) * 1.0
        inside = (times >= self.start) & (times < self.end)
        return np.where(inside, np.minimum(up, down), 0.0)


def _ease(x: np.ndarray) -> np.ndarray:
    """Raised cosine from 0 (x <= 0) to 1 (x >= 1), zero slope at both ends."""
    return 0.5 - 0.5 * np.cos(np.pi * np.clip(x, 0.0, 1.0))


@dataclass(frozen=True)
class Performance:
    """The emotion of a clip: ``base`` throughout, ``spans`` in order (a later span blends from
    what the earlier ones made)."""

    base: Mix = field(default_factory=dict)
    spans: tuple[Span, ...] = ()

    @property
    def is_neutral(self) -> bool:
        """Whether it adds nothing anywhere (every intensity 0 or only ``neutral``)."""
        mixes = [self.base, *(s.mix for s in self.spans)]
        return not any(v > 0 for m in mixes for k, v in m.items() if k != "neutral")

    def intensities(self, times: np.ndarray) -> np.ndarray:
        """(T,) times in s -> (T, len(EMOTIONS)) intensity of each emotion."""
        out = np.repeat(mix_vector(self.base)[None], len(times), axis=0)
        for span in self.spans:
            env = span.envelope(np.asarray(times, np.float64)).astype(np.float32)[:, None]
            out = out * (1 - env) + mix_vector(span.mix)[None] * env
        return out

    def weights(self, times: np.ndarray) -> np.ndarray:
        """(T,) times in s -> (T, 52) ARKit weights of the emotion alone, in [0, 1]."""
        return np.clip(self.intensities(times) @ EMOTION_BASIS, 0.0, 1.0)

    def with_spans(self, spans: list[Span]) -> Performance:
        return Performance(self.base, (*self.spans, *spans))


_SPAN_KEYS = {"start", "end", "emotion", "intensity", "onset", "offset"}


def _number(item: dict, key: str, where: str, default: float | None = None) -> float:
    value = item.get(key, default)
    if value is None:
        raise TalkmeshError(f"{where}: '{key}' is missing (seconds)")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise TalkmeshError(f"{where}: '{key}' must be a number, got {value!r}")
    if value < 0:
        raise TalkmeshError(f"{where}: '{key}' must be 0 or more, got {value!r}")
    return float(value)


def span_from_json(item: object, where: str) -> Span:
    """One timeline entry ``{"start", "end", "emotion", "intensity", "onset", "offset"}`` (the
    last three optional: 1, :data:`ONSET_S`, :data:`OFFSET_S`) as a :class:`Span`."""
    if not isinstance(item, dict):
        raise TalkmeshError(f"{where}: each entry must be an object with start, end and emotion")
    unknown = sorted(set(item) - _SPAN_KEYS)
    if unknown:
        raise TalkmeshError(f"{where}: unknown key '{unknown[0]}' (use {', '.join(_SPAN_KEYS)})")
    start, end = _number(item, "start", where), _number(item, "end", where)
    if end <= start:
        raise TalkmeshError(f"{where}: 'end' ({end:g}) must come after 'start' ({start:g})")
    emotion = item.get("emotion")
    if not isinstance(emotion, str):
        raise TalkmeshError(f"{where}: 'emotion' must be a name or a mix like happy:0.6,sad:0.2")
    mix = parse_emotion(emotion, f"{where}: emotion")
    if "intensity" in item:
        scale = _number(item, "intensity", where)
        if scale > MAX_INTENSITY:
            raise TalkmeshError(f"{where}: 'intensity' must be 0 to {MAX_INTENSITY:g}")
        mix = check_mix({k: v * scale for k, v in mix.items()}, where)
    onset = _number(item, "onset", where, ONSET_S)
    offset = _number(item, "offset", where, OFFSET_S)
    return Span(start, end, mix, onset, offset)


def read_performance(path: str | Path, base: Mix | None = None) -> Performance:
    """A JSON timeline file: a list of span objects (:func:`span_from_json`), or an object
    ``{"emotion": "calm base mix", "spans": [...]}``; ``base`` (``--emotion``) is the base mix
    unless the file names one."""
    path = Path(path)
    try:
        if path.stat().st_size > MAX_FILE_BYTES:
            raise TalkmeshError(f"{path}: larger than {MAX_FILE_BYTES >> 20} MB: not a timeline")
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise TalkmeshError(f"{path}: no such performance file") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise TalkmeshError(
            f"{path}: not a JSON timeline ({e}): see the performance guide"
        ) from None
    except OSError as e:
        raise TalkmeshError(f"{path}: cannot read it ({e.strerror})") from None
    base = dict(base or {})
    if isinstance(data, dict):
        unknown = sorted(set(data) - {"emotion", "spans"})
        if unknown:
            raise TalkmeshError(f"{path}: unknown key '{unknown[0]}' (use emotion, spans)")
        if "emotion" in data:
            if not isinstance(data["emotion"], str):
                raise TalkmeshError(f"{path}: 'emotion' must be a mix like happy:0.6")
            base = parse_emotion(data["emotion"], f"{path}: emotion")
        data = data.get("spans", [])
    if not isinstance(data, list):
        raise TalkmeshError(f"{path}: give a list of spans or an object with 'spans'")
    if len(data) > MAX_SPANS:
        raise TalkmeshError(f"{path}: {len(data)} spans, more than {MAX_SPANS}")
    spans = [span_from_json(item, f"{path}: span {k + 1}") for k, item in enumerate(data)]
    return Performance(check_mix(base, "--emotion"), tuple(spans))


# an inline tag: [happy], [happy:0.6], [happy:0.6,surprised:0.2], [neutral]
_TAG = re.compile(r"\[([^\[\]]*)\]")
_WORD = re.compile(r"[^\W_]+(?:'[^\W_]+)*")


@dataclass(frozen=True)
class Tag:
    """An inline ``[emotion]`` tag: from the ``word``-th word of the transcript on (0-based),
    the face takes ``mix`` (until the next tag)."""

    word: int
    mix: Mix


def split_tags(text: str) -> tuple[str, list[Tag]]:
    """A transcript with ``[happy]`` tags -> the transcript without them and the tags, each at
    the index of the word it precedes (words as the aligner counts them)."""
    if "[" not in text and "]" not in text:
        return text, []
    tags: list[Tag] = []
    plain: list[str] = []
    words = 0
    pos = 0
    for m in _TAG.finditer(text):
        plain.append(text[pos : m.start()])
        words += len(_WORD.findall(text[pos : m.start()].lower().replace("\u2019", "'")))
        tags.append(Tag(words, parse_emotion(m.group(1), f"--text tag [{m.group(1)}]")))
        pos = m.end()
    rest = text[pos:]
    if "[" in rest or "]" in rest or any("]" in p or "[" in p for p in plain):
        raise TalkmeshError(
            f"--text {text!r}: a bracket without its pair: tags look like [happy] or [sad:0.5]"
        )
    return " ".join([*plain, rest]), tags  # a tag between letters still parts two words


def tag_spans(tags: list[Tag], word_starts: list[float], duration: float) -> list[Span]:
    """Tags -> spans: each from its word's start to the next tag's word (the last to the end of
    the clip); a tag after the last word starts at the end of the speech. ``word_starts`` (s)
    are the aligned words' starts, one per transcript word."""
    spans = []
    for k, tag in enumerate(tags):
        start = word_starts[tag.word] if tag.word < len(word_starts) else duration
        nxt = tags[k + 1].word if k + 1 < len(tags) else None
        if nxt is None:
            end, offset = duration, OFFSET_S
        else:  # held until the next tag has risen over it: it blends on from this one
            end = word_starts[nxt] if nxt < len(word_starts) else duration
            end, offset = min(duration, end + ONSET_S), 0.0
        if end > start:
            spans.append(Span(start, end, tag.mix, ONSET_S, offset))
    return spans
