"""Lip sync on real recordings: what a user who records their own voice sees.

The synthetic corpus has ground-truth motion; real recordings have none. What they do have is a
transcript, so the timing truth comes from forcing the transcript onto the clean audio
(:func:`talkmesh.audio.phonemes.recognize_phones` with ``text``): where the pauses are, where each
/p b m/ and each open vowel is. Every method animates the audio alone, as a user would run it, and
is scored on the lip opening (inner lips at the midline, :func:`talkmesh.face.assets.lip_opening`):

* ``pause_mm``: mean opening above rest in pauses of ``MIN_PAUSE_S`` or more, less
  ``PAUSE_MARGIN_S`` at each end where the mouth closes and opens (want about 0);
* ``speed_ratio``: mean lip speed in speech / in pauses (a mouth that moves when nobody speaks
  scores near 1; pause speeds under ``SPEED_FLOOR_MM_S`` count as that floor);
* ``bilabial``: share of /p b m/ whose lips come within ``CLOSED_MM`` of closed during the phone;
* ``vowel_mm``: mean peak opening above rest on open vowels;
* ``loudness_r``: correlation of the opening with the smoothed log loudness.

The same clips are scored again under real recorded noise (alsa-utils' ``Noise.wav``) at several
SNRs and under room reverberation (a pyroomacoustics image-source room), with the clean clip's
timing truth. ``bench/real_speech.py`` runs it and writes the table and plot in docs/results.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from talkmesh.audio.loading import SAMPLE_RATE, load_audio
from talkmesh.audio.phonemes import BILABIALS, SILENCE, Phone, recognize_phones
from talkmesh.errors import MissingDependencyError, TalkmeshError
from talkmesh.face.assets import Head, lip_opening

POCKETSPHINX_DATA = Path("/usr/share/pocketsphinx/test/data")
ALSA_SOUNDS = Path("/usr/share/sounds/alsa")
NOISE_FILE = ALSA_SOUNDS / "Noise.wav"

MIN_PAUSE_S = 0.2  # shorter gaps are within-phrase closures, not pauses
PAUSE_MARGIN_S = 0.05  # the first and last 50 ms of a pause are the mouth closing and opening
CLOSED_MM = 1.5  # lips this close count as closed for /p b m/
OPEN_VOWELS = frozenset({"AA", "AE", "AH", "AO", "AW", "AY"})
LOUDNESS_SMOOTH_S = 0.1  # moving-average window of the log loudness
SPEED_FLOOR_MM_S = 1.0  # lips moving slower than this in pauses count as still (no inf ratios)
SNRS_DB = (20, 10, 5)
CONDITIONS = ("clean", *(f"snr{s}" for s in SNRS_DB), "reverb")
METRICS = ("pause_mm", "speed_ratio", "bilabial", "vowel_mm", "loudness_r")
# better direction of each metric: +1 higher is better, -1 lower is better
BETTER = {"pause_mm": -1, "speed_ratio": 1, "bilabial": 1, "vowel_mm": 1, "loudness_r": 1}

# alsa-utils' voice prompts say their file names
_ALSA_PROMPTS = (
    "Front_Center",
    "Front_Left",
    "Front_Right",
    "Rear_Center",
    "Rear_Left",
    "Rear_Right",
    "Side_Left",
    "Side_Right",
)
# pocketsphinx-testdata's raw clips (16 kHz 16-bit mono) with the words its tests expect
_RAW_CLIPS = {"goforward": "go forward ten meters"}


@dataclass(frozen=True)
class Clip:
    """A real recording with its transcript."""

    name: str
    path: Path
    transcript: str
    source: str


def _transcriptions(path: Path) -> dict[str, str]:
    """Sphinx ``.transcription`` lines ``<s> words </s> (id)`` -> {id: words}."""
    out = {}
    for line in path.read_text().splitlines():
        if "(" not in line:
            continue
        words, _, rest = line.rpartition("(")
        words = words.replace("<s>", "").replace("</s>", "").strip()
        out[rest.rstrip(") ").strip()] = words
    return out


def builtin_clips() -> list[Clip]:
    """Every real recording with a transcript that Debian packages put on this machine."""
    clips = []
    cards = POCKETSPHINX_DATA / "cards"
    if (cards / "cards.transcription").is_file():
        for key, words in _transcriptions(cards / "cards.transcription").items():
            if (cards / f"{key}.wav").is_file():
                clips.append(
                    Clip(f"cards-{key}", cards / f"{key}.wav", words, "pocketsphinx-testdata")
                )
    librivox = POCKETSPHINX_DATA / "librivox"
    if (librivox / "transcription").is_file():
        for key, words in _transcriptions(librivox / "transcription").items():
            path = librivox / f"{key}.wav"
            if path.is_file():
                short = "librivox-" + key.rsplit("-", 1)[-1]
                clips.append(Clip(short, path, words, "pocketsphinx-testdata (LibriVox)"))
    for key, words in _RAW_CLIPS.items():
        if (POCKETSPHINX_DATA / f"{key}.raw").is_file():
            clips.append(
                Clip(key, POCKETSPHINX_DATA / f"{key}.raw", words, "pocketsphinx-testdata")
            )
    for key in _ALSA_PROMPTS:
        if (ALSA_SOUNDS / f"{key}.wav").is_file():
            words = key.replace("_", " ").lower()
            clips.append(Clip(f"alsa-{key}", ALSA_SOUNDS / f"{key}.wav", words, "alsa-utils"))
    return clips


def read_clip(clip: Clip) -> np.ndarray:
    """(S,) float32 at 16 kHz; ``.raw`` files are headerless 16-bit little-endian mono at 16 kHz."""
    if clip.path.suffix == ".raw":
        return (np.fromfile(clip.path, dtype="<i2").astype(np.float32) / 32768.0).copy()
    return load_audio(clip.path)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x, dtype=np.float64)) + 1e-20))


def add_noise(wave: np.ndarray, noise: np.ndarray, snr_db: float, seed: int = 0) -> np.ndarray:
    """``wave`` plus ``noise`` (looped from a random offset) at ``snr_db`` over the speech's RMS."""
    rng = np.random.default_rng(seed)
    reps = math.ceil(len(wave) / len(noise)) + 1
    looped = np.tile(noise, reps)
    start = int(rng.integers(0, len(noise)))
    piece = looped[start : start + len(wave)]
    gain = _rms(wave) / (_rms(piece) * 10 ** (snr_db / 20))
    return (wave + gain * piece).astype(np.float32)


def add_reverb(wave: np.ndarray, rt60: float = 0.5, seed: int = 0) -> np.ndarray:
    """``wave`` in a 6 x 5 x 3 m room with the given reverberation time (pyroomacoustics)."""
    try:
        import pyroomacoustics as pra
    except ImportError:
        raise MissingDependencyError("pyroomacoustics", "benchmark", "reverb") from None
    room_dim = [6.0, 5.0, 3.0]
    absorption, max_order = pra.inverse_sabine(rt60, room_dim)
    room = pra.ShoeBox(
        room_dim, fs=SAMPLE_RATE, materials=pra.Material(absorption), max_order=min(max_order, 17)
    )
    rng = np.random.default_rng(seed)
    room.add_source([1.5 + rng.uniform(0, 0.5), 2.0, 1.6], signal=wave)
    room.add_microphone([4.0, 3.0, 1.2])
    room.simulate()
    out = room.mic_array.signals[0][: len(wave)]
    return (out * (_rms(wave) / _rms(out))).astype(np.float32)


def degrade(
    wave: np.ndarray, condition: str, noise: np.ndarray | None, seed: int = 0
) -> np.ndarray:
    """The clip under one of :data:`CONDITIONS`."""
    if condition == "clean":
        return wave
    if condition == "reverb":
        return add_reverb(wave, seed=seed)
    if condition.startswith("snr"):
        if noise is None:
            raise TalkmeshError(
                f"{NOISE_FILE} is missing: install alsa-utils for the noise conditions"
            )
        return add_noise(wave, noise, float(condition[3:]), seed=seed)
    raise TalkmeshError(f"unknown condition {condition!r}: use one of {', '.join(CONDITIONS)}")


def _frames(
    phones: list[Phone], labels: Callable[[Phone], bool], fps: float, n: int, margin: float = 0.0
) -> np.ndarray:
    """(n,) bool: frames whose centre lies in a phone that ``labels`` selects, ``margin`` s in."""
    mask = np.zeros(n, bool)
    centres = (np.arange(n) + 0.5) / fps
    for p in phones:
        if labels(p):
            mask |= (centres >= p.start + margin) & (centres < p.end - margin)
    return mask


def log_loudness(wave: np.ndarray, fps: float, n: int) -> np.ndarray:
    """(n,) smoothed log RMS (dB) of ``wave`` in windows of one frame."""
    hop = SAMPLE_RATE / fps
    db = np.empty(n)
    for t in range(n):
        seg = wave[int(t * hop) : int((t + 1) * hop)]
        db[t] = 20 * np.log10(_rms(seg) + 1e-5) if len(seg) else -100.0
    k = max(1, round(LOUDNESS_SMOOTH_S * fps))
    return np.convolve(db, np.ones(k) / k, mode="same")


@dataclass(frozen=True)
class ClipScores:
    clip: str
    method: str
    condition: str
    pause_mm: float
    speed_ratio: float
    bilabial: float
    vowel_mm: float
    loudness_r: float
    speech_speed: float  # mm/s
    pause_speed: float  # mm/s
    pauses: int
    bilabials: int


def phone_window(phone: Phone, fps: float, frames: int) -> tuple[int, int]:
    """The frames [lo, hi) that a phone's metrics read: its own, and one either side."""
    return max(0, int(phone.start * fps) - 1), min(frames, int(math.ceil(phone.end * fps)) + 1)


def score_opening(
    opening_mm: np.ndarray, rest_mm: float, phones: list[Phone], wave: np.ndarray, fps: float
) -> dict[str, float]:
    """The five metrics of one clip from its (T,) lip opening in mm and the timing truth."""
    n = len(opening_mm)

    def is_pause(p: Phone) -> bool:
        return p.label == SILENCE and p.end - p.start >= MIN_PAUSE_S

    pause = _frames(phones, is_pause, fps, n, margin=PAUSE_MARGIN_S)
    speech = _frames(phones, lambda p: p.label != SILENCE, fps, n)
    speed = np.abs(np.diff(opening_mm, prepend=opening_mm[:1])) * fps
    pause_speed = float(speed[pause].mean()) if pause.any() else math.nan
    speech_speed = float(speed[speech].mean()) if speech.any() else math.nan
    closed, peaks = [], []
    for p in phones:
        lo, hi = phone_window(p, fps, n)
        if hi <= lo:
            continue
        if p.label in BILABIALS:
            closed.append(float(opening_mm[lo:hi].min()) <= CLOSED_MM)
        elif p.label in OPEN_VOWELS:
            peaks.append(float(opening_mm[lo:hi].max()) - rest_mm)
    loud = log_loudness(wave, fps, n)
    r = np.corrcoef(opening_mm, loud)[0, 1] if opening_mm.std() > 0 and loud.std() > 0 else math.nan
    return {
        "pause_mm": float(opening_mm[pause].mean() - rest_mm) if pause.any() else math.nan,
        "speed_ratio": speech_speed / max(pause_speed, SPEED_FLOOR_MM_S),
        "speech_speed": speech_speed,
        "pause_speed": pause_speed,
        "bilabial": float(np.mean(closed)) if closed else math.nan,
        "vowel_mm": float(np.mean(peaks)) if peaks else math.nan,
        "loudness_r": float(r),
        "pauses": sum(map(is_pause, phones)),
        "bilabials": len(closed),
    }


def truth_phones(clip: Clip, wave: np.ndarray) -> list[Phone]:
    """Timing truth: the transcript forced onto the clean recording."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UserWarning)
        phones = recognize_phones(wave, SAMPLE_RATE, text=clip.transcript)
    # the recogniser warns when it falls back to recognition: that is no timing truth
    fallback = [w for w in caught if issubclass(w.category, UserWarning)]
    if fallback:
        raise TalkmeshError(f"{clip.name}: the transcript does not align: {fallback[0].message}")
    return phones


def score_clip(
    clip: Clip,
    method: str,
    condition: str,
    vertices: np.ndarray,
    head: Head,
    phones: list[Phone],
    wave: np.ndarray,
    fps: float,
) -> ClipScores:
    """Score (T, V, 3) ``vertices`` animated from ``wave`` (the clip under ``condition``)."""
    opening = lip_opening(vertices, head.regions) * 1000.0
    rest = float(lip_opening(head.template[None], head.regions)[0]) * 1000.0
    m = score_opening(opening, rest, phones, wave, fps)
    return ClipScores(clip.name, method, condition, **m)


def medians(rows: list[ClipScores]) -> dict[tuple[str, str], dict[str, float]]:
    """(method, condition) -> the median of each metric over clips (NaNs left out)."""
    groups: dict[tuple[str, str], list[ClipScores]] = {}
    for r in rows:
        groups.setdefault((r.method, r.condition), []).append(r)
    out = {}
    for key, group in groups.items():
        out[key] = {}
        for m in METRICS:
            vals = [getattr(r, m) for r in group if not math.isnan(getattr(r, m))]
            out[key][m] = float(np.median(vals)) if vals else math.nan
    return out


def closed_of_all(clips) -> tuple[int, int]:
    """(/p b m/ closed, /p b m/ scored) over clips given as (``bilabial`` share, ``bilabials``
    count) pairs; a clip with none is left out."""
    closed = total = 0
    for share, count in clips:
        if count and not math.isnan(share):
            closed, total = closed + round(share * count), total + count
    return closed, total


def pooled_bilabials(rows: list[ClipScores]) -> dict[tuple[str, str], tuple[int, int]]:
    """(method, condition) -> (/p b m/ closed, /p b m/ scored) over all clips together. The real
    clips hold few (35 in 10 clips, one to eleven a clip), so their median moves by a tenth
    when one clip's closure flips; the count says how many closures a change gained or lost."""
    groups: dict[tuple[str, str], list[ClipScores]] = {}
    for r in rows:
        groups.setdefault((r.method, r.condition), []).append(r)
    out = {
        key: closed_of_all((r.bilabial, r.bilabials) for r in group)
        for key, group in groups.items()
    }
    return {key: counts for key, counts in out.items() if counts[1]}


def to_json(rows: list[ClipScores]) -> list[dict]:
    return [asdict(r) for r in rows]
