"""Procedural lip sync: timed phones (+ the audio's pitch) -> ARKit-52 weight curves.

This is the linguistics-based baseline that the CodeTalker paper describes (visemes with
coarticulation rules) and talkmesh's ground-truth generator for the synthetic corpus.

Mouth: every phone has a viseme target (ARKit weights) and a per-channel dominance; the weight
curve of a channel is the dominance-weighted mean of the targets (Cohen & Massaro 1993), with
dominance falling off before a phone (anticipation) and after it (carry-over). Bilabials (p b m)
and labiodentals (f v) dominate the lip channels so the lips close or tuck whatever the
neighbours; rounded vowels and /w/ dominate rounding; jaw opening follows vowel openness.

Upper face, partly independent of the audio: blinks at random intervals (a renewal process with a
refractory period), brow raises on pitch accents (peaks of the audio's F0), slow random brow
motion and gaze saccades. A :class:`SpeakingStyle` sets amplitudes, smoothing and rates per
speaker; everything random comes from one seeded generator, so the result is deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from talkmesh.audio.phonemes import Phone
from talkmesh.constants import SAMPLE_RATE
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES

ARKIT = ARKIT_NAMES
INDEX = {name: i for i, name in enumerate(ARKIT)}

# Mouth channels driven by visemes; symmetric pairs share one value.
MOUTH = (
    "jaw",
    "funnel",
    "pucker",
    "stretch",
    "smile",
    "press",
    "rollLower",
    "rollUpper",
    "lowerDown",
    "upperUp",
    "shrugUpper",
    "tongue",
)
MOUTH_TO_ARKIT = {
    "jaw": ("jawOpen",),
    "funnel": ("mouthFunnel",),
    "pucker": ("mouthPucker",),
    "stretch": ("mouthStretchLeft", "mouthStretchRight"),
    "smile": ("mouthSmileLeft", "mouthSmileRight"),
    "press": ("mouthPressLeft", "mouthPressRight"),
    "rollLower": ("mouthRollLower",),
    "rollUpper": ("mouthRollUpper",),
    "lowerDown": ("mouthLowerDownLeft", "mouthLowerDownRight"),
    "upperUp": ("mouthUpperUpLeft", "mouthUpperUpRight"),
    "shrugUpper": ("mouthShrugUpper",),
    "tongue": ("tongueOut",),
}

VOWELS = frozenset("AA AE AH AO AW AY EH ER EY IH IY OW OY UH UW UY OE".split())
# Diphthongs glide between two targets: first half, second half.
DIPHTHONGS = {
    "AW": ("AA", "UH"),
    "AY": ("AA", "IY"),
    "EY": ("EH", "IY"),
    "OW": ("AO", "UW"),
    "OY": ("AO", "IY"),
}

# Viseme targets (mouth channel -> weight). Jaw opening is ordered by vowel openness.
VISEMES: dict[str, dict[str, float]] = {
    "AA": {"jaw": 0.42, "lowerDown": 0.35, "upperUp": 0.1},
    "AE": {"jaw": 0.36, "stretch": 0.3, "lowerDown": 0.35, "upperUp": 0.15},
    "AO": {"jaw": 0.36, "funnel": 0.45, "pucker": 0.1, "lowerDown": 0.2},
    "AH": {"jaw": 0.3, "lowerDown": 0.25},
    "EH": {"jaw": 0.26, "stretch": 0.3, "lowerDown": 0.25, "upperUp": 0.1},
    "ER": {"jaw": 0.16, "funnel": 0.35, "pucker": 0.25},
    "IH": {"jaw": 0.17, "stretch": 0.35, "smile": 0.15, "lowerDown": 0.1},
    "UH": {"jaw": 0.16, "funnel": 0.4, "pucker": 0.35},
    "IY": {"jaw": 0.1, "stretch": 0.5, "smile": 0.3},
    "UW": {"jaw": 0.08, "pucker": 0.85, "funnel": 0.35},
    # rounded front vowels (German ü ö, French u eu, ...): lips rounded, tongue front
    "UY": {"jaw": 0.1, "pucker": 0.75, "funnel": 0.25, "stretch": 0.05},
    "OE": {"jaw": 0.2, "pucker": 0.5, "funnel": 0.4},
    "P": {"press": 0.55, "rollLower": 0.1, "rollUpper": 0.1},
    "F": {"jaw": 0.04, "rollLower": 0.65, "upperUp": 0.15, "shrugUpper": 0.15},
    "TH": {"jaw": 0.1, "tongue": 0.35, "lowerDown": 0.1},
    "S": {"jaw": 0.04, "stretch": 0.3, "smile": 0.15, "upperUp": 0.1},
    "SH": {"jaw": 0.08, "funnel": 0.55, "pucker": 0.3, "upperUp": 0.2},
    "T": {"jaw": 0.1, "lowerDown": 0.1},
    "K": {"jaw": 0.14, "lowerDown": 0.05},
    "R": {"jaw": 0.08, "pucker": 0.45, "funnel": 0.3},
    "W": {"jaw": 0.04, "pucker": 0.9, "funnel": 0.3},
    "Y": {"jaw": 0.08, "stretch": 0.35, "smile": 0.15},
    "HH": {},
    "SIL": {},
}
PHONE_TO_VISEME = {
    "B": "P",
    "M": "P",
    "V": "F",
    "DH": "TH",
    "Z": "S",
    "ZH": "SH",
    "CH": "SH",
    "JH": "SH",
    "D": "T",
    "N": "T",
    "L": "T",
    "G": "K",
    "NG": "K",
}

# Dominance of a viseme over each channel: high means neighbours cannot override it.
_LIP_CLOSURE = {
    "jaw": 8.0,
    "lowerDown": 8.0,
    "upperUp": 8.0,
    "press": 4.0,
    "funnel": 4.0,
    "pucker": 2.0,
    "stretch": 2.0,
    "rollLower": 4.0,
    "rollUpper": 4.0,
    "tongue": 4.0,
}
DOMINANCE: dict[str, dict[str, float]] = {
    "P": _LIP_CLOSURE,
    "F": {**_LIP_CLOSURE, "upperUp": 5.0, "rollLower": 6.0},
    "W": {"pucker": 5.0, "funnel": 3.0, "jaw": 2.0},
    "UW": {"pucker": 3.0, "funnel": 2.0},
    "UY": {"pucker": 3.0, "funnel": 2.0},
    "OE": {"pucker": 2.5, "funnel": 2.0},
    "SH": {"funnel": 3.0, "pucker": 2.0},
    "S": {"jaw": 2.0, "stretch": 1.5},
    "TH": {"tongue": 4.0},
    "T": {ch: 0.35 for ch in MOUTH} | {"jaw": 0.8},
    "K": {ch: 0.3 for ch in MOUTH} | {"jaw": 0.7},
    "HH": {ch: 0.05 for ch in MOUTH},
    "SIL": {ch: 1.2 for ch in MOUTH},
}
DEFAULT_DOMINANCE = 1.0
# How far a viseme's influence spreads, relative to its half-duration: the strong lip gestures are
# also quick (high dominance, fast decay), vowels and weak consonants spread further.
SPREAD = {"P": 0.45, "F": 0.5, "W": 0.7, "T": 0.8, "K": 0.8, "S": 0.7, "SH": 0.8, "TH": 0.7}
DEFAULT_SPREAD = 1.0
MIN_HALF_WIDTH = 0.04  # seconds: even a 10 ms phone spreads its influence this far
MAX_HALF_WIDTH = 0.08  # ... and a long pause no further than this beyond its edges


@dataclass(frozen=True)
class SpeakingStyle:
    """How one speaker moves their face.

    Attributes:
        articulation: scales mouth shapes (1 = the viseme table).
        jaw: extra scale of the jaw opening.
        smoothing: scales coarticulation spread (>1 = lazier, more blended speech).
        anticipation: how much earlier than it is carried over a phone's influence starts.
        blink_rate: blinks per minute (people blink about 10-20 times a minute while talking).
        brow_activity: amplitude of pitch-accent brow raises and random brow motion.
        gaze_activity: amplitude of gaze saccades.
        smile: a constant smile bias.
    """

    articulation: float = 1.0
    jaw: float = 1.0
    smoothing: float = 1.0
    anticipation: float = 1.3
    blink_rate: float = 16.0
    brow_activity: float = 1.0
    gaze_activity: float = 1.0
    smile: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not np.isfinite(value) or value < 0:
                raise TalkmeshError(f"speaking style '{f.name}' must be a finite number >= 0")

    @classmethod
    def random(cls, rng: np.random.Generator) -> SpeakingStyle:
        """A plausible random speaker (used to give each synthetic subject its own style)."""
        return cls(
            articulation=float(rng.uniform(0.7, 1.3)),
            jaw=float(rng.uniform(0.75, 1.25)),
            smoothing=float(rng.uniform(0.7, 1.4)),
            anticipation=float(rng.uniform(1.0, 1.6)),
            blink_rate=float(rng.uniform(8, 26)),
            brow_activity=float(rng.uniform(0.3, 1.6)),
            gaze_activity=float(rng.uniform(0.4, 1.4)),
            smile=float(rng.uniform(0.0, 0.25)),
        )


def frame_times(num_frames: int, fps: float) -> np.ndarray:
    return np.arange(num_frames) / fps


def _expand_phones(phones: list[Phone]) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Phones -> (centres, half widths, starts, viseme names), diphthongs split in two."""
    centres, halves, visemes = [], [], []
    for p in phones:
        label = p.label.upper().rstrip("012")
        parts = DIPHTHONGS.get(label, (label,))
        step = (p.end - p.start) / len(parts)
        for k, part in enumerate(parts):
            start = p.start + k * step
            centres.append(start + step / 2)
            halves.append(step / 2)
            visemes.append(PHONE_TO_VISEME.get(part, part if part in VISEMES else "SIL"))
    return np.array(centres), np.array(halves), np.array(centres) - np.array(halves), visemes


# Per viseme (rows in _VISEME_INDEX order): mouth-channel targets and dominances
# (len(VISEMES), len(MOUTH)) and spread (len(VISEMES),); looked up for every phone many times a
# second by a streaming session, so built once.
_VISEME_INDEX = {v: k for k, v in enumerate(VISEMES)}
_VISEME_TARGETS = np.array([[VISEMES[v].get(ch, 0.0) for ch in MOUTH] for v in VISEMES])
_VISEME_DOMINANCE = np.array(
    [[DOMINANCE.get(v, {}).get(ch, DEFAULT_DOMINANCE) for ch in MOUTH] for v in VISEMES]
)
_VISEME_SPREAD = np.array([SPREAD.get(v, DEFAULT_SPREAD) for v in VISEMES], float)


def mouth_curves(phones: list[Phone], times: np.ndarray, style: SpeakingStyle) -> np.ndarray:
    """Timed phones -> (T, len(MOUTH)) mouth channel curves by dominance blending."""
    out = np.zeros((len(times), len(MOUTH)), dtype=np.float32)
    if not phones or not len(times):
        return out
    centres, halves, _, visemes = _expand_phones(phones)
    rows = [_VISEME_INDEX[v] for v in visemes]
    targets, alpha, spread = _VISEME_TARGETS[rows], _VISEME_DOMINANCE[rows], _VISEME_SPREAD[rows]
    width = np.clip(halves, MIN_HALF_WIDTH, MAX_HALF_WIDTH) * spread * style.smoothing
    reach = 6 * width.max() * max(style.anticipation, 1.0)
    # Process in blocks of frames against the phones near them: bounded memory for any length
    # (a block's (t, n, K) dominance arrays are about 100 MB at 512 frames).
    block = 512
    for b0 in range(0, len(times), block):
        t = times[b0 : b0 + block]
        near = np.flatnonzero((centres > t[0] - reach) & (centres < t[-1] + reach))
        if not len(near):
            continue
        dt = t[:, None] - centres[None, near]  # (t, n): > 0 after the phone centre
        w = np.where(dt < 0, width[near] * style.anticipation, width[near])
        # Flat top inside the phone, then fall-off (Cohen-Massaro dominance function, c = 1.5).
        d = np.exp(-((np.maximum(np.abs(dt) - halves[near], 0) / w) ** 1.5))
        dom = d[:, :, None] * alpha[None, near]  # (t, n, K)
        out[b0 : b0 + block] = (dom * targets[None, near]).sum(1) / (dom.sum(1) + 1e-8)
    return out


# frames of the pitch track at once: its spectra are about 65 kB a frame (complex128, 2048-point)
PITCH_BLOCK = 256


def pitch_track(audio: np.ndarray, sr: int, hop: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Autocorrelation F0 (Hz, 0 where unvoiced) and RMS energy every ``hop`` seconds.

    Returns:
        f0: (N,) pitch in Hz, 0 for unvoiced frames.
        energy: (N,) frame RMS.
    """
    win, step = int(0.04 * sr), int(hop * sr)
    if len(audio) < win:
        return np.zeros(0), np.zeros(0)
    n = 1 + (len(audio) - win) // step
    lo, hi = int(sr / 400), int(sr / 70)  # 70-400 Hz covers adult speech
    f0, energy = np.zeros(n), np.zeros(n)
    nfft = 1 << (2 * win - 1).bit_length()
    block = PITCH_BLOCK
    for b0 in range(0, n, block):
        b1 = min(n, b0 + block)
        piece = np.asarray(audio[b0 * step : (b1 - 1) * step + win])  # a Waveform: one read
        idx = np.arange(b1 - b0)[:, None] * step + np.arange(win)[None]
        frames = piece[idx].astype(np.float32)
        frames -= frames.mean(1, keepdims=True)
        energy[b0 : b0 + len(frames)] = np.sqrt((frames**2).mean(1))
        spec = np.fft.rfft(frames * np.hanning(win), nfft)
        ac = np.fft.irfft(np.abs(spec) ** 2, nfft)[:, : hi + 1].copy()  # not a view: the
        del spec  # block's (n, nfft) spectra go before the next block's are made
        lag = lo + np.argmax(ac[:, lo : hi + 1], axis=1)
        strength = ac[np.arange(len(ac)), lag] / (ac[:, 0] + 1e-9)
        voiced = strength > 0.45
        f0[b0 : b0 + len(frames)] = np.where(voiced, sr / lag, 0.0)
    loud = energy > 0.1 * np.percentile(energy, 95) if n else energy > 0
    return np.where(loud, f0, 0.0), energy


def pitch_accents(audio: np.ndarray | None, sr: int, min_gap: float = 0.7) -> np.ndarray:
    """Times (s) and strengths of pitch accents: F0 peaks well above the speaker's median.

    Returns:
        (A, 2) array of (time, strength in [0, 1]).
    """
    if audio is None or len(audio) < sr * 0.1:
        return np.zeros((0, 2))
    hop = 0.01
    f0, _ = pitch_track(audio, sr, hop)
    voiced = f0 > 0
    if voiced.sum() < 10:
        return np.zeros((0, 2))
    semitones = np.zeros_like(f0)
    semitones[voiced] = 12 * np.log2(f0[voiced] / np.median(f0[voiced]))
    kernel = np.hanning(9) / np.hanning(9).sum()
    smooth = np.convolve(np.where(voiced, semitones, 0), kernel, mode="same")
    peaks = np.flatnonzero((smooth[1:-1] > smooth[:-2]) & (smooth[1:-1] >= smooth[2:])) + 1
    peaks = peaks[smooth[peaks] > 1.5]  # at least 1.5 semitones above the median
    chosen: list[tuple[float, float]] = []
    for p in peaks[np.argsort(-smooth[peaks])]:  # strongest first, then enforce spacing
        t = p * hop + 0.02
        if all(abs(t - c) >= min_gap for c, _ in chosen):
            chosen.append((t, float(np.clip(smooth[p] / 6, 0.25, 1.0))))
    return np.array(sorted(chosen)).reshape(-1, 2)


def _bump(times: np.ndarray, start: float, rise: float, hold: float, fall: float) -> np.ndarray:
    """A smooth 0 -> 1 -> 0 pulse (raised-cosine edges)."""
    x = times - start
    up = 0.5 - 0.5 * np.cos(np.pi * np.clip(x / rise, 0, 1))
    down = 0.5 + 0.5 * np.cos(np.pi * np.clip((x - rise - hold) / fall, 0, 1))
    return np.where(x < rise + hold, up, down) * ((x > 0) & (x < rise + hold + fall))


def _smooth_noise(rng: np.random.Generator, times: np.ndarray, period: float) -> np.ndarray:
    """Zero-mean band-limited noise with unit-ish amplitude and features about ``period`` s long."""
    if not len(times):
        return np.zeros(0)
    knots = np.arange(-1, times[-1] / period + 3) * period
    values = rng.standard_normal(len(knots))
    return np.interp(times, knots, values) * 0.6


def upper_face_curves(
    times: np.ndarray,
    rng: np.random.Generator,
    style: SpeakingStyle,
    accents: np.ndarray,
) -> np.ndarray:
    """Blinks, brows and gaze -> (T, 52) ARKit weights (mouth channels left at 0)."""
    w = np.zeros((len(times), len(ARKIT)), dtype=np.float32)
    duration = times[-1] if len(times) else 0.0
    # Blinks: gamma-distributed intervals (more regular than Poisson) with a 1 s refractory period.
    blink = np.zeros(len(times))
    if style.blink_rate > 0:
        mean_gap = 60.0 / style.blink_rate
        t = rng.uniform(0.2, min(mean_gap, 3.0))
        while t < duration:
            depth = 1.0 if rng.random() > 0.1 else rng.uniform(0.5, 0.8)  # some half blinks
            blink = np.maximum(blink, depth * _bump(times, t, 0.07, 0.03, 0.15))
            t += 1.0 + rng.gamma(3.0, max(mean_gap - 1.0, 0.1) / 3.0)
    w[:, INDEX["eyeBlinkLeft"]] = blink
    w[:, INDEX["eyeBlinkRight"]] = blink * rng.uniform(0.9, 1.0)

    # Brows: raises on pitch accents, plus slow random motion.
    raise_ = np.zeros(len(times))
    for t, strength in accents:
        amp = strength * rng.uniform(0.6, 1.0)
        raise_ = np.maximum(raise_, amp * _bump(times, t - 0.12, 0.15, 0.15, 0.35))
    drift = _smooth_noise(rng, times, 1.5)
    b = style.brow_activity
    inner = np.clip(b * (0.55 * raise_ + 0.12 * np.clip(drift, 0, None)), 0, 1)
    outer = np.clip(b * (0.45 * raise_ + 0.08 * np.clip(drift, 0, None)), 0, 1)
    down = np.clip(b * 0.15 * np.clip(-drift, 0, None), 0, 1)
    w[:, INDEX["browInnerUp"]] = inner
    for side in ("Left", "Right"):
        w[:, INDEX[f"browOuterUp{side}"]] = outer
        w[:, INDEX[f"browDown{side}"]] = down
    # Gaze: saccades between fixations held 0.5-2.5 s, quick 50 ms transitions.
    g = style.gaze_activity
    gx, gy = np.zeros(len(times)), np.zeros(len(times))
    t, prev = 0.0, np.zeros(2)
    while t < duration + 1:
        target = rng.normal(0, 0.12, size=2) * g
        ramp = np.clip((times - t) / 0.05, 0, 1)
        gx += (target[0] - prev[0]) * ramp
        gy += (target[1] - prev[1]) * ramp
        prev = target
        t += rng.uniform(0.5, 2.5)
    for side, inward in (("Left", 1.0), ("Right", -1.0)):
        x = gx * inward
        w[:, INDEX[f"eyeLookIn{side}"]] = np.clip(x, 0, 1)
        w[:, INDEX[f"eyeLookOut{side}"]] = np.clip(-x, 0, 1)
        w[:, INDEX[f"eyeLookUp{side}"]] = np.clip(gy, 0, 1)
        w[:, INDEX[f"eyeLookDown{side}"]] = np.clip(-gy, 0, 1)
        w[:, INDEX[f"eyeSquint{side}"]] = np.clip(0.1 * b * np.clip(drift, 0, None), 0, 1)
    return w


BLINK_GAZE = tuple(n for n in ARKIT if n.startswith(("eyeBlink", "eyeLook")))


def blink_gaze_weights(
    num_frames: int, fps: float, *, seed: int = 0, style: SpeakingStyle | None = None
) -> np.ndarray:
    """Only the audio-independent eye motion (blinks and gaze saccades) -> (T, 52) ARKit weights,
    every other channel 0: what a speech-driven model cannot predict, to add to its output."""
    times = frame_times(num_frames, fps)
    full = upper_face_curves(times, np.random.default_rng(seed), style or SpeakingStyle(), [])
    out = np.zeros_like(full)
    keep = [INDEX[n] for n in BLINK_GAZE]
    out[:, keep] = full[:, keep]
    return out


def replace_eye_motion(
    offsets: np.ndarray,
    weights: np.ndarray,
    eyes: np.ndarray,
    basis: np.ndarray,
    block: int = 2048,
) -> None:
    """Swaps a learned model's own eye motion for procedural eyes, in place.

    ``offsets`` (T, ...) the model's vertices or vertex offsets, ``weights`` (T, 52) the ARKit
    weights fitted to them, ``eyes`` (T, 52) procedural blinks and gaze
    (:func:`blink_gaze_weights`), ``basis`` (52, V*3) the blendshapes. The fitted blink and gaze
    channels are taken out of the motion and the procedural ones put in (and into ``weights``), so
    the fit's residual is unchanged. A speech-driven model cannot time blinks; what it makes of
    them is a faint average, and procedural blinks added on top of it overshoot the upper face's
    dynamics (FDD; docs/results/codetalker.md). Blocks of ``block`` frames keep memory bounded.
    """
    keep = np.array([INDEX[n] for n in BLINK_GAZE])
    delta = eyes[:, keep] - weights[:, keep]
    part = basis[keep]
    for i in range(0, len(offsets), block):
        rows = offsets[i : i + block]
        rows += (delta[i : i + block] @ part).reshape(rows.shape).astype(rows.dtype, copy=False)
    weights[:, keep] = eyes[:, keep]


def phones_to_weights(
    phones: list[Phone],
    num_frames: int,
    fps: float,
    *,
    audio: np.ndarray | None = None,
    sr: int = SAMPLE_RATE,
    style: SpeakingStyle | None = None,
    seed: int = 0,
) -> np.ndarray:
    """Timed phones (and optionally the audio, for pitch accents) -> (T, 52) ARKit weights.

    Args:
        phones: contiguous phones with start/end in seconds.
        num_frames: T, the number of output frames.
        fps: output frame rate.
        audio: (S,) mono waveform; brow raises follow its pitch accents when given.
        sr: sample rate of ``audio``.
        style: the speaker's style (default :class:`SpeakingStyle`).
        seed: seed of the audio-independent motion (blinks, drift, gaze).
    """
    if fps <= 0:
        raise TalkmeshError(f"fps must be positive, got {fps}")
    style = style or SpeakingStyle()
    rng = np.random.default_rng(seed)
    times = frame_times(num_frames, fps)
    weights = upper_face_curves(times, rng, style, pitch_accents(audio, sr))
    return add_mouth(weights, mouth_curves(phones, times, style), style)


def add_mouth(weights: np.ndarray, mouth: np.ndarray, style: SpeakingStyle) -> np.ndarray:
    """Upper-face ARKit weights (T, 52) and mouth curves (T, len(MOUTH)) -> all (T, 52) weights,
    clipped to [0, 1] (``weights`` is changed in place)."""
    scale = np.full(len(MOUTH), style.articulation)
    scale[MOUTH.index("jaw")] *= style.jaw
    mouth = mouth * scale
    for k, ch in enumerate(MOUTH):
        for name in MOUTH_TO_ARKIT[ch]:
            weights[:, INDEX[name]] = mouth[:, k]
    for side in ("Left", "Right"):
        weights[:, INDEX[f"mouthSmile{side}"]] += style.smile
    return np.clip(weights, 0.0, 1.0, out=weights)
