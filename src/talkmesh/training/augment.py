"""Audio augmentation of training crops: the recording conditions of real speech, with motion
targets that stay true to the new audio.

Every learned model in talkmesh hears clean synthetic voices with digital silence in the pauses;
real users record in rooms, with noise, at any level and sample rate, through any microphone. Each
training crop (``Sample``: audio (S,) at 16 kHz, vertices (T, V, 3), template (V, 3)) passes, each
step with its own probability, through:

1. speed perturbation (Kaldi's: the audio resampled, tempo and pitch together, x0.9-1.1), the
   motion re-timed to the new length by linear interpolation;
2. silence (leading, trailing or inserted between frames) whose targets are the closed, neutral
   face (``template``), ramped over ``silence_ramp_s`` (100 ms unless a recipe says) from and back
   to the motion around it;
3. room reverberation (pyroomacoustics image-source rooms, a bank of ``rooms`` per seed, applied by
   pedalboard's convolution; the direct-path delay removed so the lips stay in sync);
4. background noise (audiomentations' coloured noise, white to brown) at a random SNR, in the pauses
   and inserted silence as under the speech;
5. band limits: a telephone line (300-3400 Hz, 8 kHz GSM codec, pedalboard) or a random low- or
   high-pass;
6. a round trip through another sample rate (8-48 kHz, pedalboard's resampler);
7. gain of +-20 dB, clipped to [-1, 1] as a recorder would.

``augment(sample, cfg, rng, fps)`` is pure and seeded through ``rng``: the trainer draws it from
(seed, epoch, index), so a resumed run sees the same audio. The libraries are imported on first use
(the ``train`` extra installs them).
"""

from __future__ import annotations

import contextlib
import functools
import random
from dataclasses import dataclass, fields
from fractions import Fraction

import numpy as np

from talkmesh.constants import SAMPLE_RATE
from talkmesh.errors import MissingDependencyError

RAMP_SECONDS = 0.1  # silence targets blend from and back to the face around them over this long
TELEPHONE_BAND_HZ = (300.0, 3400.0)
TELEPHONE_RATE = 8000


@dataclass(frozen=True)
class AugmentConfig:
    """Which augmentations a training crop gets, each with its probability (all 0: off)."""

    speed_p: float = 0.0
    speed: tuple[float, float] = (0.9, 1.1)  # tempo factor range; the targets follow
    silence_p: float = 0.0
    silence_seconds: tuple[float, float] = (0.2, 1.0)  # closed-mouth targets
    # the targets blend from and back to the motion around a silence over this long: each ramp
    # lies inside the silence, so a model learns to hold the mouth open that far into a pause
    # and to open it that far ahead of speech (the teacher's own pause ramp: 60 ms)
    silence_ramp_s: float = RAMP_SECONDS
    reverb_p: float = 0.0
    rt60: tuple[float, float] = (0.2, 0.9)  # seconds
    rooms: int = 16  # room impulse responses in the bank (computed once per process)
    noise_p: float = 0.0
    snr_db: tuple[float, float] = (0.0, 30.0)
    band_p: float = 0.0  # half telephone, half a random low- or high-pass
    resample_p: float = 0.0
    sample_rates: tuple[int, ...] = (8000, 11025, 22050, 32000, 44100, 48000)
    gain_p: float = 0.0
    gain_db: float = 20.0  # +- this many dB

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name.endswith("_p") and not 0.0 <= getattr(self, f.name) <= 1.0:
                raise ValueError(f"data.augment.{f.name} must be in [0, 1]")
        for name in ("speed", "silence_seconds", "rt60", "snr_db"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"data.augment.{name} must be [low, high]")
        if self.speed[0] <= 0 or self.silence_seconds[0] < 0 or self.rt60[0] <= 0:
            raise ValueError("data.augment: speed and rt60 must be positive, silence >= 0")
        if not 0.0 <= self.silence_ramp_s <= 1.0:
            raise ValueError("data.augment.silence_ramp_s must be in [0, 1] seconds")
        if self.rooms < 1 or not self.sample_rates or min(self.sample_rates) < 4000:
            raise ValueError("data.augment: rooms >= 1 and sample rates of 4 kHz or more")

    @property
    def enabled(self) -> bool:
        return any(getattr(self, f.name) > 0 for f in fields(self) if f.name.endswith("_p"))


def _require(module: str):
    try:
        return __import__(module)
    except ImportError:
        raise MissingDependencyError(module, "train", "training-time audio augmentation") from None


@contextlib.contextmanager
def _seeded(seed: int):
    """audiomentations draws from the global generators: seed them, then put them back, so the
    training loop's own random state is untouched."""
    np_state, py_state = np.random.get_state(), random.getstate()
    np.random.seed(seed)
    random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(np_state)
        random.setstate(py_state)


# ---------------------------------------------------------------------------------------------
# Steps that change the timing (audio and motion together)


def speed_perturb(
    audio: np.ndarray, vertices: np.ndarray, factor: float, fps: float
) -> tuple[np.ndarray, np.ndarray]:
    """Play ``audio`` ``factor`` times faster (resampled: tempo and pitch together) and re-time
    ``vertices`` (T, V, 3) to match: frame j of the result is the motion at time j * factor / fps.

    Returns audio (S',) float32 and vertices (T', V, 3) with T' = round(T / factor) and
    S' = round(T' * 16000 / fps).
    """
    from scipy.signal import resample_poly

    ratio = Fraction(1.0 / factor).limit_denominator(200)
    out = resample_poly(audio.astype(np.float64), ratio.numerator, ratio.denominator)
    t_new = max(1, int(round(len(vertices) / factor)))
    src = np.minimum(np.arange(t_new) * factor, len(vertices) - 1)
    lo = np.floor(src).astype(int)
    hi = np.minimum(lo + 1, len(vertices) - 1)
    w = (src - lo)[:, None, None]
    moved = (1 - w) * vertices[lo] + w * vertices[hi]
    n = int(round(t_new * SAMPLE_RATE / fps))
    out = np.pad(out[:n], (0, max(0, n - len(out))))
    return out.astype(np.float32), moved.astype(np.float32)


def insert_silence(
    audio: np.ndarray,
    vertices: np.ndarray,
    template: np.ndarray,
    at_frame: int,
    num_frames: int,
    fps: float,
    ramp_s: float = RAMP_SECONDS,
) -> tuple[np.ndarray, np.ndarray]:
    """``num_frames`` of digital silence before frame ``at_frame`` (0: leading, T: trailing) whose
    targets are the neutral face ``template``: the mouth closed. Over the first and last
    ``ramp_s`` seconds (at most a third of the gap each) the targets blend from the frame before and
    back to the frame after with a raised cosine, so the motion has no jump.

    audio (S,), vertices (T, V, 3) -> audio (S + n,), vertices (T + num_frames, V, 3).
    """
    per_frame = SAMPLE_RATE / fps
    gap = np.repeat(template[None].astype(np.float32), num_frames, axis=0)
    ramp = min(int(round(ramp_s * fps)), num_frames // 3)
    if ramp > 0:
        rise = 0.5 - 0.5 * np.cos(np.pi * (np.arange(ramp) + 1) / (ramp + 1))
        w = rise[:, None, None].astype(np.float32)
        if at_frame > 0:
            gap[:ramp] = (1 - w) * vertices[at_frame - 1] + w * template
        if at_frame < len(vertices):
            gap[num_frames - ramp :] = w[::-1] * template + (1 - w[::-1]) * vertices[at_frame]
    a = int(round(at_frame * per_frame))
    n = int(round((at_frame + num_frames) * per_frame)) - a
    audio = np.concatenate([audio[:a], np.zeros(n, np.float32), audio[a:]])
    vertices = np.concatenate([vertices[:at_frame], gap, vertices[at_frame:]])
    return audio.astype(np.float32), vertices


# ---------------------------------------------------------------------------------------------
# Steps on the audio alone


@functools.lru_cache(maxsize=4)
def room_impulse_responses(rooms: int, rt60: tuple[float, float], seed: int) -> tuple:
    """``rooms`` impulse responses (each (L,) float32 at 16 kHz, direct path first, unit energy)
    of random shoebox rooms (3-10 m x 3-8 m x 2.4-4 m) with RT60 drawn from ``rt60``, source and
    microphone 0.5-3 m apart; pyroomacoustics' image-source method, as the benchmark's reverb."""
    pra = _require("pyroomacoustics")
    rng = np.random.default_rng([seed, 0x5EB])
    out = []
    for _ in range(rooms):
        dim = np.array([rng.uniform(3, 10), rng.uniform(3, 8), rng.uniform(2.4, 4.0)])
        t60 = rng.uniform(*rt60)
        absorption, max_order = pra.inverse_sabine(t60, dim)
        room = pra.ShoeBox(
            dim, fs=SAMPLE_RATE, materials=pra.Material(absorption), max_order=min(max_order, 17)
        )
        mic = dim * rng.uniform(0.25, 0.75, 3)
        direction = rng.normal(size=3)
        src = mic + direction / np.linalg.norm(direction) * rng.uniform(0.5, 3.0)
        src = np.clip(src, 0.2, dim - 0.2)
        room.add_source(src)
        room.add_microphone(mic)
        room.compute_rir()
        rir = np.asarray(room.rir[0][0], np.float64)
        rir = rir[max(0, int(np.argmax(np.abs(rir))) - 8) :]  # keep the lips in sync
        out.append((rir / np.sqrt((rir**2).sum())).astype(np.float32))
    return tuple(out)


def reverberate(audio: np.ndarray, rir: np.ndarray) -> np.ndarray:
    """``audio`` (S,) convolved with ``rir`` (pedalboard), same length and RMS."""
    pedalboard = _require("pedalboard")
    wet = pedalboard.Convolution(rir, mix=1.0, sample_rate=SAMPLE_RATE)(audio, SAMPLE_RATE)
    wet = np.asarray(wet, np.float32).reshape(-1)[: len(audio)]
    scale = np.sqrt(np.mean(audio**2) / max(float(np.mean(wet**2)), 1e-20))
    return (wet * scale).astype(np.float32)


def add_noise(audio: np.ndarray, snr_db: float, f_decay: float, seed: int) -> np.ndarray:
    """Coloured noise (``f_decay`` dB per octave: 0 white, -3 pink, -6 brown) at ``snr_db`` below
    the clip's RMS, everywhere: in the pauses as under the speech (audiomentations)."""
    am = _require("audiomentations")
    noise = am.AddColorNoise(
        min_snr_db=snr_db, max_snr_db=snr_db, min_f_decay=f_decay, max_f_decay=f_decay, p=1.0
    )
    with _seeded(seed):
        return noise(audio.astype(np.float32), SAMPLE_RATE).astype(np.float32)


def telephone(audio: np.ndarray) -> np.ndarray:
    """A telephone line: 300-3400 Hz, 8 kHz, the GSM full-rate codec (pedalboard)."""
    pb = _require("pedalboard")
    chain = pb.Pedalboard(
        [
            pb.HighpassFilter(TELEPHONE_BAND_HZ[0]),
            pb.LowpassFilter(TELEPHONE_BAND_HZ[1]),
            pb.GSMFullRateCompressor(),
        ]
    )
    return np.asarray(chain(audio, SAMPLE_RATE), np.float32).reshape(-1)[: len(audio)]


def band_limit(audio: np.ndarray, kind: str, cutoff_hz: float) -> np.ndarray:
    """A low-pass (``kind="low"``) or high-pass (``"high"``) filter at ``cutoff_hz`` (pedalboard)."""
    pb = _require("pedalboard")
    f = pb.LowpassFilter(cutoff_hz) if kind == "low" else pb.HighpassFilter(cutoff_hz)
    return np.asarray(f(audio, SAMPLE_RATE), np.float32).reshape(-1)[: len(audio)]


def resample_round_trip(audio: np.ndarray, rate: int) -> np.ndarray:
    """``audio`` as if recorded at ``rate`` Hz and resampled to 16 kHz (pedalboard)."""
    pb = _require("pedalboard")
    out = pb.Resample(float(rate))(audio, SAMPLE_RATE)
    return np.asarray(out, np.float32).reshape(-1)[: len(audio)]


def apply_gain(audio: np.ndarray, gain_db: float) -> np.ndarray:
    """``audio`` louder or quieter by ``gain_db``, clipped to [-1, 1] as a recorder would."""
    return np.clip(audio * np.float32(10 ** (gain_db / 20)), -1.0, 1.0).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# The pipeline


def _timing(sample, cfg: AugmentConfig, rng: np.random.Generator, fps: float):
    """Steps 1-2: speed perturbation and silence, audio and motion together."""
    audio, vertices = sample.audio, sample.vertices
    if rng.random() < cfg.speed_p:
        audio, vertices = speed_perturb(audio, vertices, rng.uniform(*cfg.speed), fps)
    if rng.random() < cfg.silence_p and len(vertices) > 1:
        where = rng.choice(["leading", "trailing", "inserted"])
        at = {"leading": 0, "trailing": len(vertices)}.get(
            where, int(rng.integers(1, len(vertices)))
        )
        n = max(1, int(round(rng.uniform(*cfg.silence_seconds) * fps)))
        audio, vertices = insert_silence(
            audio, vertices, sample.template, at, n, fps, cfg.silence_ramp_s
        )
    return audio, vertices


def _conditions(audio: np.ndarray, cfg: AugmentConfig, rng: np.random.Generator, seed: int):
    """Steps 3-7: the room, the noise, the line, the converter and the level."""
    if rng.random() < cfg.reverb_p:
        bank = room_impulse_responses(cfg.rooms, tuple(cfg.rt60), seed)
        audio = reverberate(audio, bank[int(rng.integers(len(bank)))])
    if rng.random() < cfg.noise_p:
        snr, decay = rng.uniform(*cfg.snr_db), rng.uniform(-6.0, 0.0)
        audio = add_noise(audio, snr, decay, int(rng.integers(2**31)))
    if rng.random() < cfg.band_p:
        if rng.random() < 0.5:
            audio = telephone(audio)
        elif rng.random() < 0.5:
            audio = band_limit(audio, "low", rng.uniform(2000.0, 7000.0))
        else:
            audio = band_limit(audio, "high", rng.uniform(100.0, 500.0))
    if rng.random() < cfg.resample_p:
        audio = resample_round_trip(audio, int(rng.choice(cfg.sample_rates)))
    if rng.random() < cfg.gain_p:
        audio = apply_gain(audio, rng.uniform(-cfg.gain_db, cfg.gain_db))
    return audio


def augment(sample, cfg: AugmentConfig, rng: np.random.Generator, fps: float, seed: int = 0):
    """One training crop under random recording conditions (see the module docstring).

    sample: a ``talkmesh.datasets.reader.Sample`` (audio (S,) at 16 kHz, vertices (T, V, 3),
    template (V, 3)); returns the same kind, audio (S',) and vertices (T', V, 3) re-timed together.
    ``seed`` picks the room bank; everything else is drawn from ``rng``.
    """
    if not cfg.enabled:
        return sample
    audio, vertices = _timing(sample, cfg, rng, fps)
    audio = _conditions(np.asarray(audio, np.float32), cfg, rng, seed)
    assert audio.ndim == 1 and vertices.ndim == 3, (audio.shape, vertices.shape)
    return sample._replace(audio=audio, vertices=vertices)
