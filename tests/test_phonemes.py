import re
import shutil
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

from talkmesh.audio import phonemes
from talkmesh.audio.loading import SAMPLE_RATE, load_audio, resample
from talkmesh.audio.phonemes import (
    ARPABET_PHONES,
    SILENCE,
    Phone,
    recognize_phones,
    transcript_words,
)
from talkmesh.audio.tts import synthesize_speech
from talkmesh.errors import TalkmeshError, TalkmeshWarning

pytest.importorskip("pocketsphinx")

# LibriVox recordings with transcripts, from Debian's pocketsphinx-testdata.
LIBRIVOX = Path("/usr/share/pocketsphinx/test/data/librivox")
CLIP = LIBRIVOX / "sense_and_sensibility_01_austen_64kb-0870.wav"  # 7.1 s
TEXT = (
    "And Mister John Dashwood had then leisure to consider how much there might be "
    "prudently in his power to do for them."
)
# m(ister) m(uch) m(ight) b(e) p(rudently) p(ower) (the)m
BILABIALS = ["M", "M", "M", "B", "P", "P", "M"]
SHORT_CLIP = LIBRIVOX / "sense_and_sensibility_01_austen_64kb-0880.wav"  # 3.0 s
SHORT_TEXT = "he was not an ill disposed young man"
VOWELS = {p for p in ARPABET_PHONES if p[0] in "AEIOU"}

pytestmark = pytest.mark.skipif(not CLIP.exists(), reason="pocketsphinx-testdata not installed")


def assert_covers(phones: list[Phone], duration: float) -> None:
    assert phones, "no phones"
    assert phones[0].start == 0.0
    assert phones[-1].end == pytest.approx(duration, abs=1e-9)
    for a, b in pairwise(phones):
        assert a.end == b.start, (a, b)
    assert all(p.end > p.start for p in phones)
    assert all(p.label in ARPABET_PHONES or p.label == SILENCE for p in phones)
    assert not any(a.label == b.label == SILENCE for a, b in pairwise(phones))


@pytest.fixture(scope="module")
def clip() -> np.ndarray:
    return load_audio(CLIP)


@pytest.fixture(scope="module")
def aligned(clip) -> list[Phone]:
    return recognize_phones(clip, text=TEXT)


@pytest.fixture(scope="module")
def recognised(clip) -> list[Phone]:
    return recognize_phones(clip)


def test_transcript_matches_the_testdata():
    line = next(ln for ln in (LIBRIVOX / "transcription").open() if CLIP.stem in ln)
    assert transcript_words(TEXT) == re.sub(r"<s>|</s>|\(.*\)", "", line).split()


def test_forced_alignment(clip, aligned):
    duration = len(clip) / SAMPLE_RATE
    assert_covers(aligned, duration)
    assert [p.label for p in aligned if p.label in {"P", "B", "M"}] == BILABIALS
    speech = [p for p in aligned if p.label != SILENCE]
    # Speech starts after the leading pause and ends before the trailing one.
    assert 0.05 < speech[0].start < 0.5 and duration - 0.6 < speech[-1].end < duration
    # Phones last 10 ms to half a second.
    assert all(0.01 <= p.end - p.start <= 0.5 for p in speech)


def test_phone_recognition_without_text(clip, recognised):
    assert_covers(recognised, len(clip) / SAMPLE_RATE)
    labels = [p.label for p in recognised]
    assert sum(label in VOWELS for label in labels) >= 15  # about 25 syllables are spoken
    assert {"P", "B", "M"} & set(labels)
    silent = sum(p.end - p.start for p in recognised if p.label == SILENCE)
    assert silent < 0.3 * len(clip) / SAMPLE_RATE


def test_recognition_agrees_with_alignment_on_timing(aligned, recognised):
    """Frames the aligner calls speech are mostly speech for the recogniser too."""
    t = np.arange(0, aligned[-1].end, 0.01)

    def is_speech(phones):
        return np.array(
            [any(p.start <= x < p.end and p.label != SILENCE for p in phones) for x in t]
        )

    assert np.mean(is_speech(aligned) == is_speech(recognised)) > 0.85


def test_other_sample_rate_gives_the_same_timeline(clip):
    clip48 = resample(clip, SAMPLE_RATE, 48_000)
    phones = recognize_phones(clip48, sr=48_000, text=TEXT)
    assert_covers(phones, len(clip48) / 48_000)
    assert [p.label for p in phones if p.label in {"P", "B", "M"}] == BILABIALS


def test_deterministic_and_independent_of_previous_calls():
    x = load_audio(SHORT_CLIP)
    first = recognize_phones(x, text=SHORT_TEXT)
    recognize_phones(load_audio(CLIP), text=TEXT)
    assert recognize_phones(x, text=SHORT_TEXT) == first


def test_long_audio_is_aligned_in_windows(monkeypatch):
    """The long-audio route (streamed decoding, word-level pass, phone alignment per window),
    exercised on 10 s of speech by shrinking the limits."""
    x = np.concatenate([load_audio(SHORT_CLIP), load_audio(CLIP)])
    monkeypatch.setattr(phonemes, "FULL_UTT_MAX_S", 2.0)
    monkeypatch.setattr(phonemes, "ALIGN_WINDOW_S", 2.0)
    monkeypatch.setattr(phonemes, "MAX_ALIGN_WINDOW_S", 5.0)
    phones = recognize_phones(x, text=f"{SHORT_TEXT} {TEXT}")
    assert_covers(phones, len(x) / SAMPLE_RATE)
    assert [p.label for p in phones if p.label in {"P", "B", "M"}] == ["P", "M", *BILABIALS]


def test_tiny_clip_is_valid(clip):
    x = clip[SAMPLE_RATE : SAMPLE_RATE + SAMPLE_RATE // 10]
    assert_covers(recognize_phones(x), 0.1)
    assert_covers(recognize_phones(x[:100]), 100 / SAMPLE_RATE)


def test_silence_is_sil_only():
    assert recognize_phones(np.zeros(SAMPLE_RATE, np.float32)) == [Phone(SILENCE, 0.0, 1.0)]
    hiss = np.random.default_rng(0).normal(0, 1e-4, 2 * SAMPLE_RATE).astype(np.float32)
    assert recognize_phones(hiss, text="hello") == [Phone(SILENCE, 0.0, 2.0)]


def test_digital_silence_inside_speech_is_sil(clip):
    gap = np.zeros(SAMPLE_RATE, np.float32)
    phones = recognize_phones(np.concatenate([clip[: 2 * SAMPLE_RATE], gap]))
    assert phones[-1].label == SILENCE and phones[-1].start <= 2.05


def test_unknown_word_falls_back_to_recognition(clip):
    with pytest.warns(TalkmeshWarning, match="not in the pronunciation dictionary.*zxqv"):
        phones = recognize_phones(clip, text=TEXT + " zxqv")
    assert_covers(phones, len(clip) / SAMPLE_RATE)


def test_mismatched_transcript_falls_back_to_recognition(clip):
    x = clip[: SAMPLE_RATE // 2]
    with pytest.warns(TalkmeshWarning, match="could not be aligned"):
        phones = recognize_phones(x, text=TEXT)
    assert_covers(phones, 0.5)


def test_edge_inputs():
    assert recognize_phones(np.zeros(0, np.float32)) == []
    with pytest.raises(TalkmeshError, match="mono"):
        recognize_phones(np.zeros((2, 100), np.float32))


def test_transcript_words():
    text = "Mr. Dashwood\u2019s well-being, 'quoted' -- 3 times!"
    assert transcript_words(text) == ["mr", "dashwood's", "well", "being", "quoted", "3", "times"]


def test_arpabet_phones():
    assert len(ARPABET_PHONES) == len(set(ARPABET_PHONES)) == 39


FOUR_SENTENCES = (
    "Can you hear me clearly now? The train leaves from platform four. Remember to buy some "
    "bread and milk. Thank you very much for your help."
)


@pytest.mark.skipif(shutil.which("espeak-ng") is None, reason="espeak-ng is not installed")
def test_four_espeak_sentences_align_to_their_exact_transcript(tmp_path):
    """espeak-ng's British "remember" is not the dictionary's: PocketSphinx's default beam lost
    the whole transcript; the wide-beam retry aligns it, and no warning is given."""
    import subprocess
    import warnings

    wav = tmp_path / "four.wav"
    subprocess.run(["espeak-ng", "-v", "en-gb", "-w", str(wav), FOUR_SENTENCES], check=True)
    audio = load_audio(wav)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # "could not be aligned" would fail the test
        phones = recognize_phones(audio, text=FOUR_SENTENCES)
    assert_covers(phones, len(audio) / SAMPLE_RATE)
    # m(e) (fro)m p(latfor)m (re)m(e)mb(er) b(uy) (so)m(e) b(read) m(ilk) m(uch) (hel)p
    labels = [p.label for p in phones if p.label in {"P", "B", "M"}]
    assert labels == ["M", "M", "P", "M", "M", "M", "B", "B", "M", "B", "M", "M", "P"]


@pytest.mark.skipif(shutil.which("espeak-ng") is None, reason="espeak-ng is not installed")
def test_synthesize_speech(tmp_path):
    path = tmp_path / "bob.wav"
    phones = synthesize_speech("Bob made a map.", path)
    duration = len(load_audio(path)) / SAMPLE_RATE
    assert_covers(phones, duration)
    assert [p.label for p in phones if p.label in {"P", "B", "M"}] == ["B", "B", "M", "M", "P"]
    with pytest.raises(TalkmeshError, match="voice 'nosuchvoice'"):
        synthesize_speech("hello", tmp_path / "x.wav", voice="nosuchvoice")


def test_phone_tidier_resumed_equals_tidying_from_scratch():
    """The streaming recogniser's incremental tidying (PhoneTidier) gives _tidy's phones after
    every chunk while the best path's tail is revised and the last frame's RMS changes."""
    from talkmesh.audio.phonemes import Phone, PhoneTidier, _tidy

    rng = np.random.default_rng(0)
    labels = ["AA", "B", "SIL", "M", "+NSN+", "IY1", "S"]
    loudness = rng.uniform(0, 0.05, 3000).astype(np.float32)
    loudness[rng.random(3000) < 0.3] = 0.0  # silent frames turn phones into SIL
    tidier, segments, resumed = PhoneTidier(), [], 0
    for step in range(1, 300):
        segments = segments[: max(0, len(segments) - int(rng.integers(0, 4)))]  # revised tail
        t, n = (segments[-1][2] if segments else 0), 10 * step
        while t < n:  # gaps and a last segment past the audio's end
            start = t + int(rng.integers(0, 2))
            t = start + int(rng.integers(1, 12))
            segments.append((str(rng.choice(labels)), start, t))
        rms = loudness[:n].copy()
        rms[-1] = rng.uniform(0, 0.05)  # the zero-padded last frame
        samples, offset, after = 160 * n - int(rng.integers(0, 160)), 2.5, rng.uniform(0, n / 100)
        resumed += bool(tidier.segments)
        got = tidier.phones(list(segments), rms, n - 1, samples, offset, after)
        want = [
            Phone(p.label, p.start + offset, p.end + offset)
            for p in _tidy(segments, rms, samples)
            if p.end + offset > after
        ]
        assert got == want, step
        assert len(tidier.states) == len(segments)
    assert resumed > 250
