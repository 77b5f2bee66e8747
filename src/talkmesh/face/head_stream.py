"""Head motion as the speech streams in: the causal counterpart of
:func:`talkmesh.face.head_motion.head_pose`, for live sessions.

The offline head motion reads the whole clip (its loudest level, its pitch accents with the
audio after them). A live session has only the audio so far, so the same parts are made from it
as it arrives, in 10 ms hops, each decided by the hops before it:

* the level: a running peak of the hops' loudness (rising at once, falling ``PEAK_FALL_DB`` a
  second) stands for the clip's 95th percentile; a hop is speech above a tenth of it;
* a nod on each stressed syllable: a peak of the smoothed loudness at least ``NOD_PROMINENCE``
  above the trough before it, ``NOD_GAP_S`` or more after the last nod; it starts when the peak
  is seen, so its apex comes 0.15 s after the syllable's (the offline nods centre on it);
* at each phrase end (``BOUNDARY_S`` of silence after speech) a new resting posture eased in over
  ``SHIFT_S``, and a breath;
* breaths every ``BREATH_S`` or so while the silence lasts (and from the start, before any
  speech): when the speech stops or has not begun, the head does not freeze;
* slow sway on every axis, its knots drawn per axis and knot index from the seed (larger while
  speaking than in pauses), and the head lifted and leaning forward with the loudness.

A frame's pose depends only on the audio up to its time, never on how the audio was cut into
chunks (``tests/test_head_stream.py``); state stays bounded however long the stream runs.
"""

from __future__ import annotations

import math

import numpy as np

from talkmesh.constants import SAMPLE_RATE
from talkmesh.face.head_motion import (
    BOUNDARY_S,
    BREATH_DEG,
    BREATH_M,
    BREATH_S,
    HOP_S,
    LEAN_M,
    LIFT_DEG,
    NATURAL,
    NOD_DEG,
    NOD_UP_SHARE,
    PAUSE_SWAY,
    POSTURE_DEG,
    SHIFT_S,
    SWAY_DEG,
    check_amount,
    pivot_offset,
)
from talkmesh.face.lipsync import _bump

HOP = int(round(HOP_S * SAMPLE_RATE))  # samples per hop (160)
PEAK_FALL_DB = 1.0  # the running peak level falls this much per second of quieter audio
QUIET_DB = -50.0  # the running peak never falls below this: silence is never speech
NOD_PROMINENCE = 0.2  # a nod's loudness peak stands this far above the trough before it
NOD_GAP_S = (
    0.9  # nods at most this often (the clip of tests/test_head_stream.py: 7 pitch accents in 8.3 s)
)
LOUD_S = 0.15  # the loudness that lifts the head, smoothed over this long
KEEP_HOPS = 2048  # hops of loudness kept (20 s): frames may be asked this late (a server's backlog)
_DEG = math.pi / 180
_SWAY_PERIODS = (1.3, 1.7, 2.1)  # pitch, yaw, roll: as head_motion's sway


class HeadMotionStream:
    """``receive`` audio as it arrives, then ``poses`` of frames whose audio has come."""

    def __init__(self, fps: float, *, amount: float = NATURAL, seed: int = 0) -> None:
        self.fps = float(fps)
        self.scale = check_amount(amount) / NATURAL
        self.seed = seed
        self.rng = np.random.default_rng([seed, 0x4EAD, 1])  # events, drawn in hop order
        self.tail = np.zeros(0, np.float32)
        self.hops = 0  # complete hops received
        self.peak_db = QUIET_DB
        self.loud = 0.0  # smoothed loudness (150 ms), 0 to 1
        self.fast = 0.0  # loudness smoothed over 30 ms: syllable nuclei
        self.level = 0.0  # the share of recent hops that were speech (0.3 s)
        self.rising, self.trough, self.last_nod = False, 0.0, -math.inf
        self.silent_hops, self.spoke = 0, False
        self.next_breath = 0.05  # a breath at the start: the stream opens in silence
        self.history = np.zeros((KEEP_HOPS, 2))  # (loud, level) of hop h at h % KEEP_HOPS
        self.nods: list[tuple[float, float]] = []  # (start, signed depth in radians)
        self.breaths: list[tuple[float, float]] = []  # (start, depth 0-1)
        posture = self.rng.normal(0, 0.5, 3) * POSTURE_DEG * _DEG
        self.shifts: list[tuple[float, np.ndarray, np.ndarray]] = [(0.0, posture, posture)]
        self.knots: dict[tuple[int, int], float] = {}

    def receive(self, audio: np.ndarray) -> None:
        """(S,) float32 mono audio at 16 kHz, the stream's next samples."""
        tail = np.concatenate([self.tail, np.asarray(audio, np.float32)])
        n = len(tail) // HOP
        for frame in tail[: n * HOP].reshape(n, HOP):
            self._hop(float(np.sqrt(np.mean(np.square(frame, dtype=np.float64)))))
        self.tail = tail[n * HOP :]

    def poses(self, start: int, end: int) -> np.ndarray:
        """(end - start, 6) float32 head poses of frames ``start`` to ``end`` (the module
        docstring of :mod:`talkmesh.face.head_motion` gives the layout)."""
        times = np.arange(start, end) / self.fps
        pose = np.zeros((len(times), 6), np.float32)
        if self.scale == 0 or not len(times):
            return pose
        known = self.hops - 1  # frames past the audio (at its end) take its last hop
        hops = np.clip(np.floor(times / HOP_S).astype(int), max(known - KEEP_HOPS + 1, 0), known)
        loud, level = self.history[hops % KEEP_HOPS].T if known >= 0 else np.zeros((2, len(hops)))
        angles = self._postures(times)
        for start_s, depth in self.nods:
            angles[:, 0] += depth * _bump(times, start_s, 0.15, 0.0, 0.3)
        for k in range(3):
            sway = self._sway(k, times)
            angles[:, k] += SWAY_DEG[k] * _DEG * (PAUSE_SWAY + (1 - PAUSE_SWAY) * level) * sway
        breath = np.zeros(len(times))
        for start_s, depth in self.breaths:
            breath = np.maximum(breath, depth * _bump(times, start_s, 1.2, 0.1, 2.0))
        angles[:, 0] -= LIFT_DEG * _DEG * loud + BREATH_DEG * _DEG * breath
        angles *= self.scale
        pose[:, :3] = angles
        pose[:, 3:] = pivot_offset(angles)
        pose[:, 5] += self.scale * LEAN_M * loud
        pose[:, 4] += self.scale * BREATH_M * breath
        self._forget(times[0])
        return pose

    # -- one 10 ms hop
    def _hop(self, rms: float) -> None:
        t = (self.hops + 0.5) * HOP_S
        db = 20 * math.log10(rms + 1e-6)
        self.peak_db = max(db, self.peak_db - PEAK_FALL_DB * HOP_S, QUIET_DB)
        speaking = db > self.peak_db - 20  # over a tenth of the peak's amplitude
        target = min(max((db - (self.peak_db - 30)) / 30, 0.0), 1.0)
        self.loud += (target - self.loud) * HOP_S / LOUD_S
        before = self.fast
        self.fast += (target - self.fast) * HOP_S / 0.03
        self.level += (float(speaking) - self.level) * HOP_S / 0.15
        self._nod(t, before, speaking)
        self._pauses(t, speaking)
        self.history[self.hops % KEEP_HOPS] = self.loud, self.level
        self.hops += 1

    def _nod(self, t: float, before: float, speaking: bool) -> None:
        if self.fast > before:
            if not self.rising:
                self.trough, self.rising = before, True
            return
        if not self.rising:
            return
        self.rising = False
        if speaking and before - self.trough >= NOD_PROMINENCE and t - self.last_nod >= NOD_GAP_S:
            strength = min(1.0, (before - self.trough) / 0.4)
            sign = -1.0 if self.rng.random() < NOD_UP_SHARE else 1.0
            depth = NOD_DEG * _DEG * strength * self.rng.uniform(0.7, 1.0)
            self.nods.append((t, sign * depth))
            self.last_nod = t

    def _pauses(self, t: float, speaking: bool) -> None:
        if speaking:
            self.silent_hops, self.spoke = 0, True
            self.next_breath = math.inf
            return
        self.silent_hops += 1
        if self.spoke and self.silent_hops * HOP_S >= BOUNDARY_S:  # a phrase ended
            self.spoke = False
            _, _, current = self.shifts[-1]
            target = self.rng.normal(0, 1, 3) * POSTURE_DEG * _DEG
            self.shifts.append((t, current, target))
            self.next_breath = t
        if t >= self.next_breath:
            self.breaths.append((t, self.rng.uniform(0.7, 1.0)))
            self.next_breath = t + BREATH_S * self.rng.uniform(0.8, 1.2)

    # -- the parts of a pose
    def _postures(self, times: np.ndarray) -> np.ndarray:
        out = np.empty((len(times), 3))
        for k, t in enumerate(times):
            at = max(i for i, s in enumerate(self.shifts) if s[0] <= t or i == 0)
            start, old, new = self.shifts[at]
            ease = 0.5 - 0.5 * math.cos(math.pi * min(max((t - start) / SHIFT_S, 0.0), 1.0))
            out[k] = old + (new - old) * ease
        return out

    def _sway(self, axis: int, times: np.ndarray) -> np.ndarray:
        """Band-limited noise (as :func:`talkmesh.face.lipsync._smooth_noise`): knots every
        period, each drawn from the seed, the axis and its index, so any frame can be asked."""
        period = _SWAY_PERIODS[axis]
        x = times / period
        k = np.floor(x).astype(int)
        a = np.array([self._knot(axis, i) for i in k])
        b = np.array([self._knot(axis, i + 1) for i in k])
        return (a + (b - a) * (x - k)) * 0.6

    def _knot(self, axis: int, index: int) -> float:
        key = (axis, index)
        if key not in self.knots:
            if len(self.knots) > 64:
                self.knots.clear()
            rng = np.random.default_rng([self.seed, 0x4EAD, 2, axis, index])
            self.knots[key] = float(rng.standard_normal())
        return self.knots[key]

    def _forget(self, now: float) -> None:
        """Drop the events no frame from ``now`` on can see: state stays bounded."""
        self.nods = [n for n in self.nods if n[0] + 0.45 > now]
        self.breaths = [b for b in self.breaths if b[0] + 3.3 > now]
        current = max(i for i, s in enumerate(self.shifts) if s[0] <= now or i == 0)
        self.shifts = self.shifts[current:]  # a shift alone gives every pose after its start
