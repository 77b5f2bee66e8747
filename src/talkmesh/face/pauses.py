"""Closing the mouth in pauses: a learned model's lower face gated by where speech is.

Models trained on clean synthetic speech keep the mouth a few millimetres open through noisy
pauses of real recordings (docs/results/real-speech.md). The phone recogniser finds those pauses
reliably, so the mouth region (``Regions.mouth_weight``) is blended back to the neutral face there,
with short ramps so the lips close and open as they would; the upper face is left to the model.
"""

from __future__ import annotations

import numpy as np

from talkmesh.audio.phonemes import SILENCE, Phone

MIN_PAUSE_S = 0.3  # shorter gaps are left to the model: the mouth need not close in them
# The mouth closes over the first 100 ms of a pause and opens over its last 150 ms: lips part
# before the sound starts. On the synthetic unseen-speaker test split (bundled model, LVE 3.635 mm
# ungated) gating pauses from 200 ms with 80 ms ramps cost 4.6% LVE (3.801): the synthetic truth
# keeps the mouth open through short pauses; from 300 ms with 100/150 ms ramps, 2.1% (3.712).
CLOSE_S = 0.1
OPEN_S = 0.15


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
