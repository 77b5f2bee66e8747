"""Recognising ARKit blendshapes (and Oculus visemes) among an avatar's morph target names.

Exporters spell the 52 ARKit shapes many ways: ``jawOpen`` (Apple, Ready Player Me, VRoid perfect
sync), ``JawOpen`` (Live Link, Unreal), ``jaw_open`` / ``Jaw-Open``, ``blendShape1.jawOpen`` (Maya
blendShape nodes exported through FBX), ``Head|jawOpen`` or ``mesh:jawOpen`` (scene paths), and
``eyeBlink_L`` for ``eyeBlinkLeft``. :func:`arkit_channel` maps all of these to the index into
``ARKIT_NAMES``: it keeps the part after the last ``.``, ``|``, ``:`` or ``/``, splits it into
words (separators and camelCase), reads ``L``/``R`` as ``Left``/``Right`` and compares the words
case-insensitively; a name that only *ends* with an ARKit name (``ARKit_jawOpen``,
``CC_Base_jawOpen``) matches the longest such name.

Avatars without ARKit mouth shapes often have the 15 Oculus (OVR LipSync) visemes instead
(``viseme_sil``, ``viseme_PP``, ... ``viseme_U``: Ready Player Me's default export).
:data:`VISEME_FROM_ARKIT` drives them from ARKit weights, a fixed linear map that is an
approximation: ARKit weights say what the lips and jaw do, not where the tongue is, so the
tongue-only visemes (``DD``, ``kk``, ``nn``, ``RR``, ``SS``, ``CH``, ``sil``) stay at rest and
the lips and jaw carry the speech. Each row is clipped to [0, 1].
"""

from __future__ import annotations

import re

import numpy as np

from talkmesh.face.arkit import ARKIT_NAMES, NUM_ARKIT

# The Oculus / OVR LipSync viseme set, in its documented order.
VISEMES: tuple[str, ...] = (
    "sil",
    "PP",
    "FF",
    "TH",
    "DD",
    "kk",
    "CH",
    "SS",
    "nn",
    "RR",
    "aa",
    "E",
    "I",
    "O",
    "U",
)

# viseme -> {ARKit name: coefficient}; weight = clip(sum(coefficient * ARKit weight), 0, 1).
VISEME_FROM_ARKIT: dict[str, dict[str, float]] = {
    "PP": {"mouthClose": 1.0, "mouthPressLeft": 0.5, "mouthPressRight": 0.5},  # lips pressed
    "FF": {"mouthRollLower": 1.0},  # lower lip under the upper teeth
    "TH": {"tongueOut": 1.0},
    "aa": {"jawOpen": 1.0},  # open jaw
    "E": {"mouthStretchLeft": 0.5, "mouthStretchRight": 0.5},  # wide lips
    "I": {"mouthSmileLeft": 0.5, "mouthSmileRight": 0.5},  # spread lips
    "O": {"mouthFunnel": 1.0},  # rounded, open lips
    "U": {"mouthPucker": 1.0},  # rounded, pursed lips
}

# The channels that make speech visible: an avatar with none of them gets the viseme fallback.
MOUTH_CHANNELS: tuple[str, ...] = tuple(
    n for n in ARKIT_NAMES if n.startswith(("jaw", "mouth", "tongue"))
)

_PREFIX_SPLIT = re.compile(r"[.|:/\\]")
_WORDS = re.compile(r"[A-Z]+(?![a-z])|[A-Z]?[a-z]+|[0-9]+")
_SIDES = {"l": "left", "r": "right", "lt": "left", "rt": "right"}


def _key(name: str) -> str:
    """``blendShape1.eyeBlink_L`` -> ``eyeblinkleft``: the last path segment's words, lowercased,
    with single-letter sides spelled out."""
    segment = _PREFIX_SPLIT.split(name.strip())[-1]
    words = [w.lower() for w in _WORDS.findall(segment)]
    if words and words[-1] in _SIDES:
        words[-1] = _SIDES[words[-1]]
    return "".join(words)


_ARKIT_KEYS = {_key(n): i for i, n in enumerate(ARKIT_NAMES)}
assert len(_ARKIT_KEYS) == NUM_ARKIT
# Longest first, so ``...mouthLeft`` is not taken for a shorter name it ends with.
_ARKIT_BY_LENGTH = sorted(_ARKIT_KEYS, key=len, reverse=True)
_VISEME_KEYS = {v.lower(): i for i, v in enumerate(VISEMES)}


def arkit_channel(name: str) -> int:
    """Index into ``ARKIT_NAMES`` of a morph target name as exporters write it; -1 if none."""
    key = _key(name)
    if key in _ARKIT_KEYS:
        return _ARKIT_KEYS[key]
    for k in _ARKIT_BY_LENGTH:
        if key.endswith(k):
            return _ARKIT_KEYS[k]
    return -1


def viseme_channel(name: str) -> int:
    """Index into ``VISEMES`` of an Oculus viseme target name (``viseme_aa``, ``V_PP``...); -1 if
    none. Only names with a ``viseme``/``v`` prefix count, so a shape called ``E`` is not one."""
    segment = _PREFIX_SPLIT.split(name.strip())[-1]
    match = re.fullmatch(r"(?i)(?:viseme|v)[ _-]?([a-z]+)", segment)
    if match is None:
        return -1
    return _VISEME_KEYS.get(match.group(1).lower(), -1)


def viseme_matrix() -> np.ndarray:
    """(52, 15) float32 M with viseme weights = clip(arkit_weights @ M, 0, 1)."""
    m = np.zeros((NUM_ARKIT, len(VISEMES)), np.float32)
    for viseme, terms in VISEME_FROM_ARKIT.items():
        for arkit, coefficient in terms.items():
            m[ARKIT_NAMES.index(arkit), VISEMES.index(viseme)] = coefficient
    return m


def visemes_from_arkit(weights: np.ndarray) -> np.ndarray:
    """(T, 52) ARKit weights -> (T, 15) Oculus viseme weights in ``VISEMES`` order."""
    weights = np.asarray(weights, np.float32)
    assert weights.ndim == 2 and weights.shape[1] == NUM_ARKIT, weights.shape
    return np.clip(weights @ viseme_matrix(), 0.0, 1.0)
