"""The synthetic corpus's motion truth: the procedural animator made right where physics is known.

:func:`talkmesh.face.lipsync.phones_to_weights` blends viseme targets by dominance. Driven by a
synthesiser's short phones, that blend leaves lips apart through /p b m/ and open vowels half open
(the neighbours pull every target towards the middle), and lets the mouth drift in pauses. A
model trained on that truth learns those faults. :func:`teach` applies three rules on top of the
animator, each one measured by the real-speech metrics (``bench/synthetic_lips.py``):

1. Open vowels open as far as their viseme says, scaled by loudness: a raised-cosine jaw gesture
   over the vowel, ``peak = jaw target x speaker's jaw x VOWEL_GAIN x sqrt(loudness)`` (at most
   ``MAX_JAW``), taken where it is wider than the blend; every opening also follows the loudness
   (``LOUDNESS_SHARE``).
2. Pauses of :data:`REST_PAUSE_S` or more return the whole mouth to rest (a gate with
   raised-cosine ramps of :data:`REST_RAMP_S` inside the pause, so it closes and opens in time).
3. The lips meet through the closure of every /p b m/: at each frame inside the phone (at least
   :data:`MIN_CLOSURE_S` centred on it) the mouth channels that part the lips are solved (bounded
   least squares on the head's own blendshapes) so that the inner lips are within
   :data:`CLOSURE_MM` of each other; the change eases in and out over the neighbouring frames.

Before rule 3, the mouth is moved :data:`LEAD_S` ahead of the sound (:func:`lead`): the
jaw and lips move before the acoustics they shape, as the procedural animator's anticipation has
them do (a model trained on a mouth in step with the synthesiser's phones opened a frame late on
real recordings). The mouth closes into a pause that far ahead too, but it leaves a pause's
rest no earlier than :data:`REST_RAMP_S` before the speech. The closures of rule 3 stay where the
sound is stopped: the lips are shut while the /p b m/ is heard.

Rounding (/u o y ø w/) and labiodentals (/f v/) are the animator's own dominance rules; the phone
labels of every language reach them through :func:`talkmesh.audio.languages.sampa_label`.
"""

from __future__ import annotations

import numpy as np

from talkmesh.audio.phonemes import BILABIALS, SILENCE, Phone
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.lipsync import DIPHTHONGS, INDEX, MOUTH_TO_ARKIT, VISEMES

REST_PAUSE_S = 0.15  # pauses this long or longer return the mouth to rest
REST_RAMP_S = 0.06  # inside such a pause, the time to close (and to open again before speech)
CLOSURE_MM = 0.5  # lips closer than this count as met
CLOSURE_TARGET_MM = 0.25  # what the solve aims for (margin under CLOSURE_MM)
# a closure lasts at least this long, centred on a shorter /p b m/: lips cannot meet and part
# faster, and the corpus's 60 fps truth is read at 30 fps (every second frame), where a closure of
# one 60 fps frame falls between frames (6 of the 639 /p b m/ of the benchmark's clips did, 5-32 ms)
MIN_CLOSURE_S = 1 / 30
OPEN_VOWELS = frozenset({"AA", "AE", "AH", "AO", "AW", "AY"})
# open-vowel jaw peak relative to the viseme's jaw target, at full loudness (the square root of
# the loudness scales it below that): the synthesisers' vowels are short (English /@/ 20-30 ms),
# and with 1.3 the truth's open vowels opened 12.8 mm (median of the multilingual test split; the
# procedural animator on real clips: 10.4; English alone 7.2), but a model trained on it opened
# them 9.9 mm there and 10.1 on real clips. With 1.5 the truth opens 13.7 mm, the bundled model
# 11.1 and 11.0 (docs/results/multilingual.md)
VOWEL_GAIN = 1.5
# the mouth moves this far ahead of the sound it shapes. A speech stage trained on a truth in step
# with the phones peaked one 30 fps frame after the loudness on real recordings (loudness r 0.55,
# 0.63 moved a frame earlier; the procedural animator, which anticipates, 0.67 unmoved); trained
# on the truth moved a frame (33 ms) earlier it peaked unmoved (docs/results/multilingual.md)
LEAD_S = 1 / 30
MAX_JAW = 0.45  # no vowel opens the jaw further (about 18 mm of lip opening)
LOUDNESS_RANGE_DB = 24.0
LOUDNESS_SHARE = 0.5  # share of every opening that follows loudness (the rest is articulation)
OPENING_CHANNELS = (
    "jawOpen",
    "mouthLowerDownLeft",
    "mouthLowerDownRight",
    "mouthUpperUpLeft",
    "mouthUpperUpRight",
)  # loudness this far under the utterance's loud vowels gives no opening
# the channels that part or close the lips, solved for /p b m/ closure
CLOSURE_CHANNELS = (
    "jawOpen",
    "mouthClose",
    "mouthPressLeft",
    "mouthPressRight",
    "mouthLowerDownLeft",
    "mouthLowerDownRight",
    "mouthUpperUpLeft",
    "mouthUpperUpRight",
    "mouthFunnel",
    "mouthRollLower",
    "mouthRollUpper",
    "mouthShrugUpper",
)
MOUTH_CHANNELS = tuple(sorted({INDEX[n] for names in MOUTH_TO_ARKIT.values() for n in names}))
# what :func:`lead` moves ahead: every jaw, mouth and tongue channel (the closure's mouthClose too)
LEAD_CHANNELS = tuple(
    i for i, n in enumerate(ARKIT_NAMES) if n.startswith(("jaw", "mouth", "tongue"))
)


def _raised_cosine(x: np.ndarray) -> np.ndarray:
    """0 at |x| >= 1, 1 at 0."""
    return np.where(np.abs(x) < 1, 0.5 + 0.5 * np.cos(np.pi * np.clip(x, -1, 1)), 0.0)


def frame_loudness(audio: np.ndarray | None, sr: int, fps: float, n: int) -> np.ndarray:
    """(n,) loudness in [0, 1]: 1 at the utterance's loud speech (95th percentile of frame dB),
    falling linearly to 0 at :data:`LOUDNESS_RANGE_DB` under it. Ones without audio."""
    if audio is None or not len(audio):
        return np.ones(n)
    hop = sr / fps
    db = np.empty(n)
    for t in range(n):
        seg = np.asarray(audio[int(t * hop) : int((t + 1) * hop)], dtype=np.float64)
        db[t] = 10 * np.log10(np.mean(seg**2) + 1e-10) if len(seg) else -100.0
    k = max(1, round(0.05 * fps))  # 50 ms smoothing
    db = np.convolve(db, np.ones(k) / k, mode="same")
    top = np.percentile(db, 95)
    return np.clip(1 + (db - top) / LOUDNESS_RANGE_DB, 0.0, 1.0)


def open_vowels(
    weights: np.ndarray,
    phones: list[Phone],
    fps: float,
    loudness: np.ndarray,
    jaw_scale: float = 1.0,
) -> None:
    """Rule 1, in place: each open vowel's jaw gesture reaches its loudness-scaled peak."""
    times = np.arange(len(weights)) / fps
    jaw, low = INDEX["jawOpen"], [INDEX["mouthLowerDownLeft"], INDEX["mouthLowerDownRight"]]
    for p in phones:
        label = p.label.upper().rstrip("012")
        if label not in OPEN_VOWELS or p.end <= p.start:
            continue
        first = DIPHTHONGS.get(label, (label,))[0]
        half = (p.end - p.start) / 2
        centre = p.start + half
        if label in DIPHTHONGS:  # the open part is the first half
            half /= 2
            centre = p.start + half
        k = int(np.clip(round(centre * fps), 0, len(weights) - 1))
        target = VISEMES[first].get("jaw", 0.0) * jaw_scale * VOWEL_GAIN
        peak = min(MAX_JAW, target * np.sqrt(loudness[k]))
        # a gesture as wide as the vowel plus 40 ms each side, flat over its middle
        bump = _raised_cosine((times - centre) / (half + 0.04))
        bump = np.minimum(1.0, 1.6 * bump)
        weights[:, jaw] = np.maximum(weights[:, jaw], peak * bump)
        for c in low:
            weights[:, c] = np.maximum(weights[:, c], 0.6 * peak * bump)


def pause_gate(phones: list[Phone], fps: float, n: int, closing: bool = True) -> np.ndarray:
    """(n,) 1 in speech, 0 at rest in pauses of :data:`REST_PAUSE_S` or more (ramps inside them).
    ``closing`` False: only the rest before speech, and the ramp that leaves it (the gate that
    holds a pause's rest against the mouth's lead)."""
    times = np.arange(n) / fps
    gate = np.ones(n)
    for i, p in enumerate(phones):
        if p.label != SILENCE or p.end - p.start < REST_PAUSE_S:
            continue
        if not closing and i == len(phones) - 1:  # no speech after it to leave rest for
            continue
        ramp = min(REST_RAMP_S, (p.end - p.start) / 2)
        into = np.clip((times - p.start) / ramp, 0, 1)  # 0 at the pause's start, 1 ramp later
        out_of = np.clip((p.end - times) / ramp, 0, 1)
        edge = np.minimum(into, out_of) if closing else out_of  # 1 inside, 0 at its edges
        rest = 0.5 - 0.5 * np.cos(np.pi * edge)
        inside = (times >= p.start) & (times <= p.end)
        gate = np.where(inside, np.minimum(gate, 1 - rest), gate)
    if phones and phones[0].label == SILENCE:  # before the first word: at rest until it starts
        gate[times < phones[0].end - REST_RAMP_S] = 0.0
    if closing and phones and phones[-1].label == SILENCE:
        gate[times > phones[-1].start + REST_RAMP_S] = 0.0
    return gate


def lip_gap_model(head) -> tuple[np.ndarray, np.ndarray]:
    """The inner-lip gap as a linear function of the 52 weights: (g0 (3,), D (52, 3)) so that
    the gap vector of weights ``w`` is ``g0 + w @ D`` (metres)."""
    upper, lower = head.regions.lip_pair
    g0 = head.template[upper] - head.template[lower]
    shapes = head.blendshapes.reshape(len(head.blendshape_names), -1, 3)
    return g0.astype(np.float64), (shapes[:, upper] - shapes[:, lower]).astype(np.float64)


def close_lips(
    weights: np.ndarray, phones: list[Phone], fps: float, head, ease_frames: int = 2
) -> np.ndarray:
    """Rule 3, in place: lips within :data:`CLOSURE_MM` through every /p b m/. Returns the (n,)
    bool mask of the closure frames."""
    n = len(weights)
    g0, D = lip_gap_model(head)
    cols = np.array([INDEX[c] for c in CLOSURE_CHANNELS])
    Dc = D[cols]  # (C, 3)
    centres = (np.arange(n) + 0.5) / fps
    mask = np.zeros(n, bool)
    for p in phones:
        if p.label.upper().rstrip("012") not in BILABIALS:
            continue
        start, end = p.start, p.end
        if end - start < MIN_CLOSURE_S:  # too short to see: the shortest closure, centred
            middle = (start + end) / 2
            start, end = middle - MIN_CLOSURE_S / 2, middle + MIN_CLOSURE_S / 2
        inside = (centres >= start) & (centres < end)
        if not inside.any():  # at a lower frame rate: the frame nearest its middle
            inside[int(np.clip((p.start + p.end) / 2 * fps, 0, n - 1))] = True
        mask |= inside
    delta = np.zeros((n, len(cols)))
    target = CLOSURE_TARGET_MM / 1000
    for t in np.flatnonzero(mask):
        gap = g0 + weights[t] @ D
        if np.linalg.norm(gap) <= target:
            continue
        w = weights[t, cols].astype(np.float64)
        for reg in (1e-5, 1e-6, 1e-7, 1e-8):
            # min |gap + d @ Dc|^2 + reg |d|^2, with 0 <= w + d <= 1
            A = np.vstack([Dc.T, np.sqrt(reg) * np.eye(len(cols))])
            b = np.concatenate([-gap, np.zeros(len(cols))])
            d = bounded_lstsq(A, b, -w, 1 - w)
            if np.linalg.norm(gap + d @ Dc) <= target:
                break
        delta[t] = d
    # ease in and out: neighbours of a closure take part of its change
    eased = delta.copy()
    for k in range(1, ease_frames + 1):
        share = 1 - k / (ease_frames + 1)
        for shift in (k, -k):
            moved = np.roll(delta, shift, axis=0) * share
            if shift > 0:
                moved[:shift] = 0
            else:
                moved[shift:] = 0
            take = ~mask & (np.abs(moved).sum(1) > np.abs(eased).sum(1))
            eased[take] = moved[take]
    weights[:, cols] = np.clip(weights[:, cols] + eased, 0.0, 1.0)
    return mask


def teach(
    weights: np.ndarray,
    phones: list[Phone],
    fps: float,
    head,
    *,
    audio: np.ndarray | None = None,
    sr: int = 16_000,
    jaw_scale: float = 1.0,
    lead_s: float = LEAD_S,
) -> np.ndarray:
    """The three rules on the animator's (T, 52) ARKit ``weights`` (changed in place and
    returned): open vowels by loudness, rest in pauses, the mouth moved ``lead_s`` ahead of the
    sound (0: in step with the phones) but not out of a pause's rest earlier than
    :data:`REST_RAMP_S` before the speech, then lips met through /p b m/ where they are heard."""
    assert weights.ndim == 2 and weights.shape[1] == len(ARKIT_NAMES), weights.shape
    n = len(weights)
    loudness = frame_loudness(audio, sr, fps, n)
    # louder speech opens wider: the opening channels follow the loudness everywhere
    opening = [INDEX[c] for c in OPENING_CHANNELS]
    weights[:, opening] *= (1 - LOUDNESS_SHARE + LOUDNESS_SHARE * loudness)[:, None].astype(
        weights.dtype
    )
    open_vowels(weights, phones, fps, loudness, jaw_scale)
    gate = pause_gate(phones, fps, n)
    weights[:, MOUTH_CHANNELS] *= gate[:, None].astype(weights.dtype)
    lead(weights, fps, lead_s)  # the mouth closes into a pause ahead of the sound, as it moves
    # but the rest holds against the lead: after a pause the mouth leaves rest REST_RAMP_S before
    # the speech, not REST_RAMP_S + lead_s (a model trained on a truth without this opened the
    # first word 100-130 ms early on a reverberant real clip)
    weights[:, MOUTH_CHANNELS] *= pause_gate(phones, fps, n, closing=False)[:, None].astype(
        weights.dtype
    )
    close_lips(weights, phones, fps, head)
    return weights


def lead(weights: np.ndarray, fps: float, seconds: float = LEAD_S) -> np.ndarray:
    """In place: the jaw, mouth and tongue channels read ``seconds`` later, so the mouth moves
    that far ahead of the sound (linear between frames; the last frame held). The upper face
    stays as it is."""
    n = len(weights)
    if seconds <= 0 or n < 2:
        return weights
    src = np.minimum(np.round(np.arange(n) + seconds * fps, 9), n - 1)
    lo = np.floor(src).astype(int)
    hi = np.minimum(lo + 1, n - 1)
    frac = (src - lo)[:, None].astype(weights.dtype)
    cols = list(LEAD_CHANNELS)
    mouth = weights[:, cols]
    weights[:, cols] = mouth[lo] * (1 - frac) + mouth[hi] * frac
    return weights


def bounded_lstsq(
    a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray, max_steps: int = 200
) -> np.ndarray:
    """min |a @ x - b|^2 subject to lo <= x <= hi, for a few variables: (M, N) ``a`` of full
    column rank, (M,) ``b``, (N,) bounds -> (N,) x, exact to rounding.

    An active-set method (Lawson and Hanson's NNLS with two bounds a variable, as BVLS does):
    the free variables are solved by least squares with the others at their bounds, moving no
    further than the first bound met; a bound whose gradient pulls the solution inwards frees its
    variable. Used instead of ``scipy.optimize.lsq_linear``, whose package takes longer to import
    (0.3-1.4 s) than every solve of a run together; ``tests/test_teacher.py`` checks it against it.
    """
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    x = np.clip(np.linalg.lstsq(a, b, rcond=None)[0], lo, hi)
    free = (x > lo) & (x < hi)
    tol = 1e-12 * max(1.0, float(np.abs(a.T @ b).max()))
    for _ in range(max_steps):
        while free.any():  # the free variables' least squares, as far as the box allows
            rest = b - a[:, ~free] @ x[~free]
            z = np.linalg.lstsq(a[:, free], rest, rcond=None)[0]
            low, high = z < lo[free], z > hi[free]
            if not (low.any() or high.any()):
                x[free] = z
                break
            start, move = x[free], z - x[free]
            bound = np.where(low, lo[free], hi[free])
            out = low | high
            step = np.ones_like(z)
            step[out] = (bound[out] - start[out]) / move[out]
            k = int(np.argmin(step))
            x[free] = start + step[k] * move
            index = np.flatnonzero(free)[k]
            x[index] = lo[index] if low[k] else hi[index]  # exactly on the bound it met
            free[index] = False
        grad = a.T @ (a @ x - b)
        # at a lower bound the cost must not fall inwards (grad >= 0), at an upper one (grad <= 0)
        pull = np.where(~free & (x <= lo), -grad, 0.0) + np.where(~free & (x >= hi), grad, 0.0)
        if pull.max(initial=0.0) <= tol:
            return x
        free[int(np.argmax(pull))] = True
    return x
