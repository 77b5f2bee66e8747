"""Closing the mouth in pauses: a learned model's lower face gated by where speech is.

Models trained on clean synthetic speech keep the mouth a few millimetres open through noisy
pauses of real recordings (docs/results/real-speech.md). The phone recogniser finds those pauses
reliably, so the mouth region (``Regions.mouth_weight``) is blended back to the neutral face there,
with short ramps so the lips close and open as they would; the upper face is left to the model.

In a reverberant room the recogniser hears the room's echo of the last word as speech, so a
pause is recognised late and short; :func:`tail_pauses` moves its start back over that tail,
the frames quieter than the clip's speech level by ``TAIL_DB`` or more.
"""

from __future__ import annotations

import numpy as np

from talkmesh.audio.phonemes import SILENCE, Phone
from talkmesh.constants import SAMPLE_RATE

MIN_PAUSE_S = 0.25  # shorter gaps are left to the model: the mouth need not close in them
# The mouth closes over the first 50 ms of a pause and opens over its last 80 ms: lips part
# before the sound starts. On the synthetic unseen-speaker test split (bundled model, LVE 3.635 mm
# without corrections) pauses from 300 ms with 100/150 ms ramps cost 2.1% LVE (3.712): the
# synthetic truth keeps the mouth open through short pauses. From 250 ms with 50/80 ms ramps and
# the pause starts moved back over the echo they cost more, but with the procedural mix
# (talkmesh.face.corrections) all together cost 1.4%, and no real clip's pause stays open.
CLOSE_S = 0.05
OPEN_S = 0.08
TAIL_DB = 25.0  # a frame this far under the speech level is echo or silence, not a word
TAIL_MAX_S = 0.15  # a pause moves back at most this far (RT60 0.5 s: the echo falls 18 dB)
SPEECH_LEVEL_PERCENTILE = 95  # of the 10 ms frame energies: the clip's speech level
HOP_S = 0.01
DB_BLOCK = 4096  # frames of frame_db at once (5 MB of float64 at 16 kHz)


def speech_gate(
    phones: list[Phone],
    num_frames: int,
    fps: float,
    *,
    min_pause_s: float = MIN_PAUSE_S,
    close_s: float = CLOSE_S,
    open_s: float = OPEN_S,
) -> np.ndarray:
    """(T,) float32 in [0, 1]: 1 where speech is, 0 inside pauses of ``min_pause_s`` or more,
    raised-cosine ramps over a pause's first ``close_s`` and last ``open_s`` seconds (a pause at
    the clip's start or end has no ramp on that side)."""
    gate = np.ones(num_frames, np.float32)
    t = (np.arange(num_frames) + 0.5) / fps
    duration = num_frames / fps
    for p in phones:
        if p.label != SILENCE or p.end - p.start < min_pause_s:
            continue
        inside = (t >= p.start) & (t < p.end)
        closing = np.clip((t - p.start) / close_s, 0, 1) if p.start > 0 else np.ones_like(t)
        opening = (
            np.clip((p.end - t) / open_s, 0, 1) if p.end < duration - 1e-6 else np.ones_like(t)
        )
        depth = np.minimum(closing, opening)  # 0 at the pause's ends, 1 inside
        shut = 0.5 - 0.5 * np.cos(np.pi * depth)
        gate[inside] = np.minimum(gate[inside], 1.0 - shut[inside])
    return gate


def gate_mouth(
    vertices: np.ndarray, template: np.ndarray, mouth_weight: np.ndarray, gate: np.ndarray
) -> np.ndarray:
    """(T, V, 3) vertices with the mouth region pulled to ``template`` by ``1 - gate`` (T,),
    weighted per vertex by ``mouth_weight`` (V,) in [0, 1]. In place; returns ``vertices``."""
    T, V, _ = vertices.shape
    assert template.shape == (V, 3) and mouth_weight.shape == (V,) and gate.shape == (T,)
    pull = (1.0 - gate).astype(np.float32)
    for t in np.flatnonzero(pull > 0):  # frames in pauses only: cheap on long clips
        w = (pull[t] * mouth_weight).astype(np.float32)[:, None]
        vertices[t] -= w * (vertices[t] - template)
    return vertices


def frame_db(wave: np.ndarray, hop_s: float = HOP_S, block: int = DB_BLOCK) -> np.ndarray:
    """(S,) waveform at 16 kHz -> (N,) energy in dB of consecutive ``hop_s`` frames, computed
    ``block`` frames at a time (a float64 copy of an hour's audio would be 460 MB; each frame's
    mean is its own, so the blocks give the whole clip's numbers)."""
    hop = int(round(hop_s * SAMPLE_RATE))
    n = len(wave) // hop
    out = np.empty(n, np.float64)
    for f0 in range(0, n, block):
        f1 = min(n, f0 + block)
        x = np.asarray(wave[f0 * hop : f1 * hop], np.float64).reshape(f1 - f0, hop)
        out[f0:f1] = np.mean(x**2, axis=1)
    return 10.0 * np.log10(out + 1e-12)


def tail_pauses(
    phones: list[Phone], wave: np.ndarray, below_db: float = TAIL_DB, max_s: float = TAIL_MAX_S
) -> list[Phone]:
    """``phones`` with each pause's start moved back over the quiet frames before it (at most
    ``max_s``, keeping 30 ms of the phone before): frames ``below_db`` or more under the clip's
    speech level are the room's echo of the last word, which the recogniser counts as speech."""
    db = frame_db(wave)
    if not len(db):
        return list(phones)
    quiet = db < np.percentile(db, SPEECH_LEVEL_PERCENTILE) - below_db
    out = list(phones)
    for i in range(1, len(out)):
        prev, p = out[i - 1], out[i]
        if p.label != SILENCE or prev.label == SILENCE:
            continue
        f = int(round(p.start / HOP_S))
        lo = max(int(round((p.start - max_s) / HOP_S)), int(round(prev.start / HOP_S)) + 3)
        while lo <= f - 1 < len(quiet) and quiet[f - 1]:
            f -= 1
        if f * HOP_S < p.start:
            out[i - 1] = Phone(prev.label, prev.start, f * HOP_S)
            out[i] = Phone(p.label, f * HOP_S, p.end)
    return out
