"""Head motion from the speech's prosody: nods on pitch accents, posture shifts at phrase
boundaries, sway that follows the loudness.

Speakers move their heads almost all the time they talk, and the motion follows the prosody:
quick movements fall on stressed syllables and loudness peaks, and the head settles or shifts
posture at the ends of phrases (Hadar, Steiner, Grant & Rose 1983, *Language and Speech* 26:117-129
and *Human Movement Science* 2:35-46); head motion correlates with the voice's F0 and amplitude
(Yehia, Kuratate & Vatikiotis-Bateson 2002, *J. Phonetics* 30:555-568; Munhall et al. 2004,
*Psychological Science* 15:133-137), and nods align with F0 peaks (Esteve-Gibert et al. 2017,
*JASA* 141:4727-4739). This module makes such motion from the audio alone (any language):

* a nod (mostly down, sometimes up) at each pitch accent
  (:func:`talkmesh.face.lipsync.pitch_accents`), as deep as the accent is strong, its apex on
  the loudest voiced syllable nucleus (a peak of the voiced loudness) within ``SNAP_S`` of the
  accent's F0 peak: stress is loudness and length as well as pitch, and F0 peaks often come late
  in the stressed syllable or after it;
* at each phrase boundary (a pause of ``BOUNDARY_S`` or more) a new resting posture (yaw, roll,
  pitch), eased in over ``SHIFT_S``;
* slow sway on every axis, larger while speaking than in pauses, and the head lifted a little and
  leaning forward as the speech gets louder;
* breathing: the head rises a little (``BREATH_M``, ``BREATH_DEG`` back) with each breath in,
  taken at every phrase boundary and, in a silence, every ``BREATH_S`` or so: when the speech
  stops the head does not freeze.

Everything random comes from one seeded generator. The pose is (T, 6): pitch, yaw, roll in
radians (pitch > 0 nods the chin down, yaw > 0 turns the face towards +x, the head's left, roll
> 0 tilts the top of the head towards -x) and a translation in metres; a vertex ``v`` of the
face goes to ``R @ v + t`` with ``R = Ry(yaw) Rx(pitch) Rz(roll)``, the rotation being about the
neck (``PIVOT``), so ``t`` holds the pivot's offset as well as the lean.
"""

from __future__ import annotations

import numpy as np

from talkmesh.constants import SAMPLE_RATE
from talkmesh.errors import TalkmeshError
from talkmesh.face.lipsync import _bump, _smooth_noise, pitch_accents, pitch_track

NATURAL = 0.5  # --head-motion's default: the amplitudes below; 1 is twice as lively, 0 still
POSE_COLUMNS = ("pitch", "yaw", "roll", "tx", "ty", "tz")
PIVOT = np.array([0.0, -0.03, -0.05])  # the bundled head's neck joint (metres, head frame)
_DEG = np.pi / 180
NOD_DEG = 3.0  # a nod on the strongest accent, at NATURAL
NOD_UP_SHARE = 0.2  # the share of accents that raise the head instead
POSTURE_DEG = np.array([1.5, 3.0, 2.0])  # pitch, yaw, roll: spread of resting postures
SWAY_DEG = np.array([0.6, 1.0, 0.7])  # pitch, yaw, roll: sway while speaking
PAUSE_SWAY = 0.35  # share of the sway left in pauses
LIFT_DEG = 1.0  # the head lifts this much at the loudest speech ...
LEAN_M = 0.003  # ... and leans this far forward
BOUNDARY_S = 0.3  # a pause this long ends a phrase
SHIFT_S = 0.6  # a posture shift takes this long
HOP_S = 0.01  # the prosody's frame step
BREATH_M = 0.0008  # the head rises this much (metres) with a breath in ...
BREATH_DEG = 0.3  # ... and tips back this much
BREATH_S = 4.0  # a breath every 4 s in a silence (15 a minute, a resting rate)
SNAP_S = 0.2  # a nod's apex moves to the loudest syllable nucleus this close to its F0 peak


def check_amount(amount: float) -> float:
    if not 0.0 <= amount <= 1.0:  # NaN fails too
        raise TalkmeshError(f"--head-motion {amount:g}: give 0 (still) to 1 (lively)")
    return float(amount)


def head_pose(
    audio: np.ndarray, num_frames: int, fps: float, *, amount: float = NATURAL, seed: int = 0
) -> np.ndarray:
    """(S,) speech at 16 kHz -> (T, 6) head pose (module docstring), all zero for ``amount`` 0.

    Args:
        audio: (S,) mono waveform at 16 kHz (or a :class:`~talkmesh.audio.waveform.Waveform`).
        num_frames: T.
        fps: frames per second.
        amount: 0 (still) to 1; ``NATURAL`` is the measured default.
        seed: seed of the random part (nod directions, postures, sway).
    """
    scale = check_amount(amount) / NATURAL
    pose = np.zeros((num_frames, 6), np.float32)
    if scale == 0 or num_frames == 0:
        return pose
    rng = np.random.default_rng([seed, 0x4EAD])  # not the blinks' stream of the same seed
    times = np.arange(num_frames) / fps
    f0, energy = pitch_track(audio, SAMPLE_RATE, HOP_S)
    loud = _loudness(energy, times)
    speaking = _speaking(energy, times)
    angles = np.zeros((num_frames, 3))  # pitch, yaw, roll (radians)
    accents = snap_to_nuclei(pitch_accents(audio, SAMPLE_RATE), f0, energy)
    angles[:, 0] += _nods(accents, times, rng)
    angles += _postures(speaking, times, rng)
    level = PAUSE_SWAY + (1 - PAUSE_SWAY) * _smooth(speaking.astype(float), fps, 0.3)
    for k in range(3):
        angles[:, k] += SWAY_DEG[k] * _DEG * level * _smooth_noise(rng, times, 1.3 + 0.4 * k)
    angles[:, 0] -= LIFT_DEG * _DEG * loud
    breath = breathing(speaking, times, rng)
    angles[:, 0] -= BREATH_DEG * _DEG * breath
    angles *= scale
    pose[:, :3] = angles
    pose[:, 3:] = pivot_offset(angles)
    pose[:, 5] += scale * LEAN_M * loud
    pose[:, 4] += scale * BREATH_M * breath
    return pose


def rotations(angles: np.ndarray) -> np.ndarray:
    """(T, 3) pitch, yaw, roll -> (T, 3, 3) rotation matrices ``Ry(yaw) Rx(pitch) Rz(roll)``."""
    p, y, r = (np.asarray(angles, np.float64)[:, k] for k in range(3))
    cp, sp, cy, sy, cr, sr = np.cos(p), np.sin(p), np.cos(y), np.sin(y), np.cos(r), np.sin(r)
    one, zero = np.ones_like(p), np.zeros_like(p)
    rx = np.stack([one, zero, zero, zero, cp, -sp, zero, sp, cp], -1).reshape(-1, 3, 3)
    ry = np.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy], -1).reshape(-1, 3, 3)
    rz = np.stack([cr, -sr, zero, sr, cr, zero, zero, zero, one], -1).reshape(-1, 3, 3)
    return ry @ rx @ rz


def quaternions(angles: np.ndarray) -> np.ndarray:
    """(T, 3) pitch, yaw, roll -> (T, 4) unit quaternions (x, y, z, w), glTF's order."""
    p, y, r = (np.asarray(angles, np.float64)[:, k] / 2 for k in range(3))
    qx = np.stack([np.sin(p), 0 * p, 0 * p, np.cos(p)], -1)
    qy = np.stack([0 * y, np.sin(y), 0 * y, np.cos(y)], -1)
    qz = np.stack([0 * r, 0 * r, np.sin(r), np.cos(r)], -1)
    return qmul(qmul(qy, qx), qz)


def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products of (..., 4) quaternions (x, y, z, w)."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        -1,
    )


def pivot_offset(angles: np.ndarray) -> np.ndarray:
    """(T, 3) angles -> (T, 3) the translation that makes the rotation turn about ``PIVOT``."""
    return PIVOT[None] - rotations(angles) @ PIVOT


def pose_vertices(
    vertices: np.ndarray, pose: np.ndarray, frame: np.ndarray | None = None
) -> np.ndarray:
    """(T, V, 3) face-frame vertices and a (T, 6) pose -> (T, V, 3) posed vertices. ``frame``:
    the (4, 4) similarity ``F`` placing the pose's frame in the vertices' (a user's head in its
    own units and axes, :attr:`talkmesh.animation.Animation.pose_frame`): ``u -> F (R F^-1 u +
    t)``, the same rigid motion of the head wherever its vertices are kept."""
    vertices = np.asarray(vertices, np.float32)
    if frame is not None:
        linear, shift = np.asarray(frame, np.float64)[:3, :3], np.asarray(frame)[:3, 3]
        inner = ((vertices - shift) @ np.linalg.inv(linear).T).astype(np.float32)
        return (pose_vertices(inner, pose) @ linear.T + shift).astype(np.float32)
    rot = rotations(pose[:, :3]).astype(np.float32)
    return np.einsum("tij,tvj->tvi", rot, vertices) + pose[:, None, 3:].astype(np.float32)


def _loudness(energy: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(T,) loudness in [0, 1]: the smoothed level from 30 dB under the speech's peak up to it."""
    if not len(energy):
        return np.zeros(len(times))
    db = 20 * np.log10(energy + 1e-6)
    top = np.percentile(db, 95)
    level = np.clip((db - (top - 30)) / 30, 0, 1)
    level = np.convolve(level, np.ones(15) / 15, mode="same")  # 150 ms
    return np.interp(times, np.arange(len(level)) * HOP_S + 0.02, level)


def _speaking(energy: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(T,) bool: speech (energy over a tenth of its 95th percentile) rather than a pause."""
    if not len(energy):
        return np.zeros(len(times), bool)
    active = energy > 0.1 * np.percentile(energy, 95)
    return np.interp(times, np.arange(len(active)) * HOP_S + 0.02, active.astype(float)) > 0.5


def _smooth(x: np.ndarray, fps: float, seconds: float) -> np.ndarray:
    k = max(1, int(round(seconds * fps)))
    return np.convolve(np.pad(x, (k, k), mode="edge"), np.ones(k) / k, mode="same")[k:-k]


def snap_to_nuclei(accents: np.ndarray, f0: np.ndarray, energy: np.ndarray) -> np.ndarray:
    """(A, 2) accents (time, strength) with each time moved to the loudest syllable nucleus
    (a local peak of the voiced frames' smoothed loudness) within ``SNAP_S``, if any."""
    if not len(accents) or not len(energy):
        return accents
    loud = np.convolve(np.where(f0 > 0, energy, 0.0), np.hanning(7) / np.hanning(7).sum(), "same")
    peaks = np.flatnonzero((loud[1:-1] > loud[:-2]) & (loud[1:-1] >= loud[2:])) + 1
    times = peaks * HOP_S + 0.02  # the centre of the 40 ms analysis frame
    out = accents.copy()
    for k, (t, _) in enumerate(accents):
        near = np.flatnonzero(np.abs(times - t) <= SNAP_S)
        if len(near):
            out[k, 0] = times[near[np.argmax(loud[peaks[near]])]]
    return out


def _nods(accents: np.ndarray, times: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(T,) pitch (radians): a nod peaking at every accent, down or (sometimes) up."""
    out = np.zeros(len(times))
    for t, strength in accents:
        sign = -1.0 if rng.random() < NOD_UP_SHARE else 1.0
        depth = NOD_DEG * _DEG * strength * rng.uniform(0.7, 1.0)
        out += sign * depth * _bump(times, t - 0.15, 0.15, 0.0, 0.3)
    return out


def phrase_ends(speaking: np.ndarray, times: np.ndarray) -> list[float]:
    """Times (s) where speech stops for ``BOUNDARY_S`` or more (the ends of phrases)."""
    if not len(times):
        return []
    step = times[1] - times[0] if len(times) > 1 else 1.0
    ends, k = [], 0
    while k < len(speaking):
        if not speaking[k] and k > 0 and speaking[k - 1]:
            j = k
            while j < len(speaking) and not speaking[j]:
                j += 1
            if (j - k) * step >= BOUNDARY_S or j == len(speaking):
                ends.append(float(times[k]))
            k = j
        else:
            k += 1
    return ends


def breathing(speaking: np.ndarray, times: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(T,) in [0, 1]: breaths in (a rise over up to 1.2 s) and out (2 s), one at the start of
    every pause of ``BOUNDARY_S`` or more and one about every ``BREATH_S`` while it lasts."""
    out = np.zeros(len(times))
    if len(times) < 2:
        return out
    step = times[1] - times[0]
    starts = np.flatnonzero(~speaking & np.r_[True, speaking[:-1]])
    for k in starts:
        end = k + int(np.argmax(speaking[k:])) if speaking[k:].any() else len(times)
        length = (end - k) * step
        if length < BOUNDARY_S and end < len(times):
            continue
        t = times[k] + 0.05
        while t < times[k] + max(length, 0.1):
            rise = min(1.2, max(length - (t - times[k]), 0.3))
            out = np.maximum(out, rng.uniform(0.7, 1.0) * _bump(times, t, rise, 0.1, 2.0))
            t += BREATH_S * rng.uniform(0.8, 1.2)
    return out


def _postures(speaking: np.ndarray, times: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(T, 3) angles: a resting posture, shifting to a new one at each phrase end."""
    current = rng.normal(0, 0.5, 3) * POSTURE_DEG * _DEG
    out = np.repeat(current[None], len(times), axis=0)
    for t in phrase_ends(speaking, times):
        target = rng.normal(0, 1, 3) * POSTURE_DEG * _DEG
        ease = 0.5 - 0.5 * np.cos(np.pi * np.clip((times - t) / SHIFT_S, 0, 1))
        out += (target - current)[None] * ease[:, None]
        current = target
    return out
