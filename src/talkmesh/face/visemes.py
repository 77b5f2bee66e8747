"""Viseme curves for avatars and tools that speak in visemes: all 15 Oculus visemes, and the 22
viseme ids of Azure's speech SDK with their times.

The lips and jaw visemes (``PP FF TH aa E I O U``) follow the motion's ARKit weights through the
fixed map of :data:`talkmesh.face.arkit_names.VISEME_FROM_ARKIT`. ARKit weights do not say where
the tongue is, so the tongue visemes (``DD kk nn RR SS CH``) follow the phones where there are
recognised or aligned phones (the procedural animator's, or ``--text``'s forced alignment): each
phone raises its viseme over its span, with ``RAMP`` s raised-cosine ramps either side. Without
phones they are read from the motion as well as it allows: a small jaw opening with the lips
apart (teeth close, a consonant) is ``SS`` when the lips spread, ``CH`` when they round and ``DD``
otherwise; ``kk``, ``nn`` and ``RR`` cannot be told from the lips and stay at rest. ``sil`` is
whatever the mouth is not doing (1 minus the largest other viseme).

Azure's ids (0-21, the Speech SDK's ``VisemeReceived`` events: ``audioOffset`` in 100 ns ticks
and ``visemeId``) come from the phones' ARPAbet labels by Microsoft's documented en-US phoneme
table where there are phones, else from the frame's strongest Oculus viseme.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from talkmesh.face.arkit import ARKIT_NAMES, NUM_ARKIT
from talkmesh.face.arkit_names import VISEMES, visemes_from_arkit

TONGUE = ("DD", "kk", "nn", "RR", "SS", "CH")
RAMP = 0.04  # s: a phone's viseme rises and falls over this either side of its span
NARROW = (0.03, 0.15, 0.35)  # jawOpen: a consonant's small opening starts, peaks and ends
MOTION_SHARE = 0.6  # the most a viseme read from the motion alone reaches (it is a guess)
TICKS_PER_S = 10_000_000  # the Speech SDK's audio offsets are in 100 ns ticks
SPEAKING = 0.1  # without phones, a frame whose visemes all stay under this is silence (id 0)

# ARPAbet (CMU, no stress) -> Oculus viseme (the OVR LipSync reference's phoneme examples).
OCULUS_FROM_PHONE: dict[str, str] = {
    "SIL": "sil",
    "P": "PP", "B": "PP", "M": "PP",
    "F": "FF", "V": "FF",
    "TH": "TH", "DH": "TH",
    "T": "DD", "D": "DD",
    "K": "kk", "G": "kk", "NG": "kk",
    "CH": "CH", "JH": "CH", "SH": "CH", "ZH": "CH",
    "S": "SS", "Z": "SS",
    "N": "nn", "L": "nn",
    "R": "RR", "ER": "RR",
    "AA": "aa", "AE": "aa", "AH": "aa", "AW": "aa", "AY": "aa",
    "EH": "E", "EY": "E",
    "IH": "I", "IY": "I", "Y": "I",
    "AO": "O", "OW": "O", "OY": "O",
    "UH": "U", "UW": "U", "W": "U",
}  # fmt: skip

# ARPAbet -> Azure viseme id (Microsoft's en-US phoneme-to-viseme table; HH is id 12).
AZURE_FROM_PHONE: dict[str, int] = {
    "SIL": 0,
    "AE": 1, "AH": 1,
    "AA": 2,
    "AO": 3,
    "EH": 4, "UH": 4, "EY": 4,
    "ER": 5,
    "Y": 6, "IY": 6, "IH": 6,
    "W": 7, "UW": 7,
    "OW": 8,
    "AW": 9,
    "OY": 10,
    "AY": 11,
    "HH": 12,
    "R": 13,
    "L": 14,
    "S": 15, "Z": 15,
    "SH": 16, "CH": 16, "JH": 16, "ZH": 16,
    "DH": 17,
    "F": 18, "V": 18,
    "D": 19, "T": 19, "N": 19, "TH": 19,
    "K": 20, "G": 20, "NG": 20,
    "P": 21, "B": 21, "M": 21,
}  # fmt: skip

# Oculus viseme -> the Azure id of the same mouth (for frames without phones).
AZURE_FROM_OCULUS: dict[str, int] = {
    "sil": 0, "PP": 21, "FF": 18, "TH": 17, "DD": 19, "kk": 20, "CH": 16, "SS": 15, "nn": 19,
    "RR": 13, "aa": 2, "E": 4, "I": 6, "O": 8, "U": 7,
}  # fmt: skip
assert set(AZURE_FROM_OCULUS) == set(VISEMES) and set(OCULUS_FROM_PHONE) <= {*AZURE_FROM_PHONE}

Phones = Sequence[tuple[str, float, float]]  # (ARPAbet label, start s, end s)
_COLUMN = {v: i for i, v in enumerate(VISEMES)}


def oculus_visemes(weights: np.ndarray, fps: float, phones: Phones | None = None) -> np.ndarray:
    """(T, 52) ARKit weights at ``fps`` (and the clip's timed phones, if any) -> (T, 15) Oculus
    viseme weights in [0, 1], in ``VISEMES`` order."""
    weights = np.asarray(weights, np.float32)
    assert weights.ndim == 2 and weights.shape[1] == NUM_ARKIT, weights.shape
    out = visemes_from_arkit(weights)
    tongue = [_COLUMN[v] for v in TONGUE]
    if phones:
        out[:, tongue] = _phone_curves(phones, len(weights), fps)[:, tongue]
    else:
        out[:, tongue] = _tongue_from_motion(weights)
    out[:, _COLUMN["sil"]] = 1.0 - np.delete(out, _COLUMN["sil"], axis=1).max(axis=1)
    return np.clip(out, 0.0, 1.0)


def _phone_curves(phones: Phones, frames: int, fps: float) -> np.ndarray:
    """(T, 15): each phone's viseme at 1 over its span, raised-cosine ramps of ``RAMP`` s."""
    t = np.arange(frames) / fps
    out = np.zeros((frames, len(VISEMES)), np.float32)
    for label, start, end in phones:
        viseme = OCULUS_FROM_PHONE.get(str(label).upper())
        if viseme is None or viseme == "sil":
            continue
        rise = np.clip((t - (start - RAMP)) / RAMP, 0, 1)
        fall = np.clip(((end + RAMP) - t) / RAMP, 0, 1)
        bump = 0.5 - 0.5 * np.cos(np.pi * np.minimum(rise, fall))
        column = _COLUMN[viseme]
        out[:, column] = np.maximum(out[:, column], bump)
    return out


def _tongue_from_motion(weights: np.ndarray) -> np.ndarray:
    """(T, 52) -> (T, 6) ``TONGUE`` visemes from the lips and jaw alone (see the module doc)."""
    w = {n: weights[:, ARKIT_NAMES.index(n)] for n in ARKIT_NAMES}
    start, peak, end = NARROW
    jaw = w["jawOpen"]
    narrow = np.clip(np.minimum((jaw - start) / (peak - start), (end - jaw) / (end - peak)), 0, 1)
    narrow *= 1.0 - np.clip(
        w["mouthClose"] + 0.5 * (w["mouthPressLeft"] + w["mouthPressRight"]), 0, 1
    )
    spread = np.clip(
        0.5
        * (
            w["mouthStretchLeft"]
            + w["mouthStretchRight"]
            + w["mouthSmileLeft"]
            + w["mouthSmileRight"]
        ),
        0,
        1,
    )
    rounded = np.clip(np.maximum(w["mouthFunnel"], w["mouthPucker"]), 0, 1)
    out = np.zeros((len(weights), len(TONGUE)), np.float32)
    out[:, TONGUE.index("SS")] = narrow * spread
    out[:, TONGUE.index("CH")] = narrow * rounded
    out[:, TONGUE.index("DD")] = narrow * (1.0 - np.maximum(spread, rounded))
    return MOTION_SHARE * out


def azure_events(
    visemes: np.ndarray, fps: float, phones: Phones | None = None, min_frames: int = 2
) -> list[tuple[int, int]]:
    """``(audioOffset in 100 ns ticks, visemeId)`` events as Azure's Speech SDK sends them: one at
    each phone's start (consecutive equal ids merged) where there are ``phones``, else one where
    the frames' strongest Oculus viseme other than ``sil`` (``visemes`` (T, 15); silence where
    all stay under ``SPEAKING``) changes and holds ``min_frames``."""
    events: list[tuple[int, int]] = []

    def add(seconds: float, viseme_id: int) -> None:
        if not events or events[-1][1] != viseme_id:
            events.append((int(round(max(seconds, 0.0) * TICKS_PER_S)), viseme_id))

    if phones:
        for label, start, _ in sorted(phones, key=lambda p: p[1]):
            add(start, AZURE_FROM_PHONE.get(str(label).upper(), 0))
        return events
    visemes = np.asarray(visemes)
    sil = VISEMES.index("sil")
    others = np.delete(visemes, sil, axis=1)  # the mouth's strongest shape, silence if none
    strongest = np.delete(np.arange(len(VISEMES)), sil)[np.argmax(others, axis=1)]
    strongest[others.max(axis=1) < SPEAKING] = sil
    ids = np.array([AZURE_FROM_OCULUS[VISEMES[i]] for i in strongest], np.int64)
    t = 0
    while t < len(ids):
        run = t
        while run < len(ids) and ids[run] == ids[t]:
            run += 1
        if run - t >= min_frames or not events:
            add(t / fps, int(ids[t]))
        t = run
    return events
