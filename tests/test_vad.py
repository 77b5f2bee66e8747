"""Voice activity through ONNX Runtime (talkmesh.audio.vad) against the silero-vad package
itself: the same probabilities as the package's ONNX wrapper, the same speech segments as its
``get_speech_timestamps`` with the gate's settings, on real recordings, synthetic speech in two
languages, noise and silence; and a run that never imports torch."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from talkmesh.audio.loading import load_audio
from talkmesh.audio.vad import (
    MIN_SILENCE_MS,
    SPEECH_PAD_MS,
    THRESHOLD,
    speech_pauses,
    speech_probabilities,
    speech_segments,
)
from talkmesh.constants import SAMPLE_RATE as SR

ROOT = Path(__file__).parents[1]
LIBRIVOX = Path("/usr/share/pocketsphinx/test/data/librivox")  # real recordings
REAL = [ROOT / "examples" / "librivox-sense-and-sensibility.flac"] + sorted(
    LIBRIVOX.glob("sense_and_sensibility_01_austen_64kb-08*.wav")
)[:2]


def _espeak(tmp_path: Path, voice: str, texts: list[str], gap_s: float) -> np.ndarray:
    parts = []
    for k, text in enumerate(texts):
        wav = tmp_path / f"{voice}{k}.wav"
        subprocess.run(["espeak-ng", "-v", voice, "-w", str(wav), text], check=True)
        parts += [load_audio(wav), np.zeros(int(gap_s * SR), np.float32)]
    return np.concatenate(parts)


def _clips(tmp_path: Path) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    clips = {p.name: load_audio(p) for p in REAL}
    clips["german"] = _espeak(tmp_path, "de", ["Mein Bruder baut ein Boot.", "Bitte Brot."], 0.5)
    clips["french"] = _espeak(tmp_path, "fr", ["Le petit bateau part.", "Merci beaucoup."], 0.3)
    clips["noise"] = (0.05 * rng.standard_normal(3 * SR)).astype(np.float32)
    clips["silence"] = np.zeros(SR, np.float32)
    clips["short"] = clips["german"][:700]
    return clips


def test_the_same_probabilities_and_segments_as_the_silero_package(tmp_path):
    torch = pytest.importorskip("torch")
    from silero_vad import get_speech_timestamps, load_silero_vad

    package = load_silero_vad(onnx=True)
    found_speech = 0
    for name, wave in _clips(tmp_path).items():
        ours = speech_probabilities(wave)
        package.reset_states()
        padded = np.zeros(len(ours) * 512, np.float32)
        padded[: len(wave)] = wave
        theirs = [
            package(torch.from_numpy(padded[i : i + 512]), SR).item()
            for i in range(0, len(padded), 512)
        ]
        np.testing.assert_allclose(ours, theirs, atol=1e-6, err_msg=name)
        want = get_speech_timestamps(
            torch.from_numpy(wave), package, sampling_rate=SR, threshold=THRESHOLD,
            min_silence_duration_ms=MIN_SILENCE_MS, speech_pad_ms=SPEECH_PAD_MS,
        )  # fmt: skip
        got = speech_segments(ours, len(wave))
        assert got == [(s["start"], s["end"]) for s in want], name
        found_speech += len(got)
    assert found_speech >= 6  # the speech clips have segments: the comparison is not all-empty


def test_pauses_cover_the_clip_and_find_the_gap_between_sentences(tmp_path):
    german = _espeak(tmp_path, "de", ["Mein Bruder baut ein Boot.", "Bitte bring mir Brot."], 0.6)
    parts = speech_pauses(german)
    assert parts[0].start == 0 and abs(parts[-1].end - len(german) / SR) < 1e-9
    assert all(a.end == b.start for a, b in zip(parts, parts[1:]))
    inner = [p for p in parts[1:-1] if p.label == "SIL"]
    assert inner and max(p.end - p.start for p in inner) >= 0.45
    assert speech_pauses(np.zeros(0, np.float32)) == []
    assert [p.label for p in speech_pauses(np.zeros(SR, np.float32))] == ["SIL"]


def test_segment_rules_on_made_up_probabilities():
    """The rules by hand: a 3-window dip is within speech (under 100 ms), a long one ends it;
    a segment under 250 ms is dropped; pads split a short gap evenly."""
    p = np.array([0, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1] + [0] * 10 + [1, 1]
                 + [0] * 10, np.float32)  # fmt: skip
    n = len(p) * 512
    got = speech_segments(p, n, pad_ms=0)
    assert got == [(512, 20 * 512)]  # the 96 ms dip stays inside; the last 64 ms burst drops
    padded = speech_segments(p, n, pad_ms=10)
    assert padded == [(512 - 160, 20 * 512 + 160)]
    two = np.array([1] * 10 + [0] * 4 + [1] * 10, np.float32)
    a, b = speech_segments(two, len(two) * 512, min_silence_ms=50, pad_ms=100)
    assert a[1] == b[0] and a[1] - 10 * 512 == (4 * 512) // 2  # a 128 ms gap under two pads


def test_voice_activity_runs_without_torch():
    code = (
        "import sys, numpy as np\n"
        "from talkmesh.audio.vad import speech_pauses\n"
        "t = np.arange(32000) / 16000\n"
        "speech_pauses((0.3 * np.sin(2 * np.pi * 220 * t)).astype(np.float32))\n"
        "print('torch' in sys.modules)\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert res.stdout.strip() == "False"
