"""The real-speech benchmark's pieces: clips found with their transcripts, degradations at the
stated SNR, and metrics that tell an open mouth in a pause from a closed one."""

from __future__ import annotations

import numpy as np
import pytest

from talkmesh.audio.phonemes import Phone
from talkmesh.evaluation import real_speech as rs

FPS = 30.0


def _phones():
    # 0-0.5 s pause, 0.5-0.6 s /b/, 0.6-0.9 s /aa/, 0.9-1.5 s pause
    return [
        Phone("SIL", 0.0, 0.5),
        Phone("B", 0.5, 0.6),
        Phone("AA", 0.6, 0.9),
        Phone("SIL", 0.9, 1.5),
    ]


def _wave(seconds=1.5, speech=(0.5, 0.9)):
    t = np.arange(int(seconds * rs.SAMPLE_RATE)) / rs.SAMPLE_RATE
    wave = 0.001 * np.sin(2 * np.pi * 50 * t)
    on = (t >= speech[0]) & (t < speech[1])
    wave[on] = 0.3 * np.sin(2 * np.pi * 220 * t[on])
    return wave.astype(np.float32)


def _opening(pause_mm: float, closes: bool) -> np.ndarray:
    n = int(1.5 * FPS)
    t = (np.arange(n) + 0.5) / FPS
    op = np.full(n, 1.3 + pause_mm)
    op[(t >= 0.5) & (t < 0.6)] = 0.5 if closes else 4.0
    op[(t >= 0.6) & (t < 0.9)] = 12.0
    return op


def test_a_closed_quiet_mouth_scores_well():
    m = rs.score_opening(_opening(0.0, closes=True), 1.3, _phones(), _wave(), FPS)
    assert abs(m["pause_mm"]) < 1e-9
    assert m["bilabial"] == 1.0
    assert m["vowel_mm"] == pytest.approx(12.0 - 1.3)
    assert m["speed_ratio"] > 10
    assert m["loudness_r"] > 0.5
    assert m["pauses"] == 2 and m["bilabials"] == 1


def test_an_open_jittering_mouth_in_pauses_scores_badly():
    op = _opening(3.0, closes=False)
    op[:15] += 0.8 * (np.arange(15) % 2)  # chatter in the first pause
    m = rs.score_opening(op, 1.3, _phones(), _wave(), FPS)
    assert m["pause_mm"] > 2.9
    assert m["bilabial"] == 0.0
    good = rs.score_opening(_opening(0.0, closes=True), 1.3, _phones(), _wave(), FPS)
    assert m["speed_ratio"] < good["speed_ratio"]


def test_short_gaps_are_not_pauses():
    phones = [Phone("AA", 0.0, 0.5), Phone("SIL", 0.5, 0.6), Phone("AA", 0.6, 1.5)]
    m = rs.score_opening(np.full(45, 5.0), 1.3, phones, _wave(), FPS)
    assert m["pauses"] == 0 and np.isnan(m["pause_mm"])


@pytest.mark.parametrize("snr", [20.0, 5.0])
def test_noise_is_added_at_the_stated_snr(snr):
    wave = _wave()
    noise = np.random.default_rng(1).standard_normal(7000).astype(np.float32)
    noisy = rs.add_noise(wave, noise, snr, seed=3)
    added = noisy - wave
    measured = 20 * np.log10(rs._rms(wave) / rs._rms(added))
    assert measured == pytest.approx(snr, abs=0.01)
    assert len(noisy) == len(wave)


def test_unknown_condition_is_a_one_line_error():
    with pytest.raises(rs.TalkmeshError, match="unknown condition"):
        rs.degrade(_wave(), "underwater", None)


def test_builtin_clips_are_real_recordings_with_transcripts():
    clips = rs.builtin_clips()
    names = {c.name for c in clips}
    # make setup installs pocketsphinx-testdata and alsa-utils
    assert {"goforward", "cards-001", "librivox-0880", "alsa-Front_Center"} <= names
    assert all(c.transcript and c.path.is_file() for c in clips)
    go = next(c for c in clips if c.name == "goforward")
    wave = rs.read_clip(go)
    assert 1.0 < len(wave) / rs.SAMPLE_RATE < 10.0 and np.abs(wave).max() <= 1.0


def test_truth_of_a_real_clip_has_its_words_phones_and_the_procedural_mouth_closes_in_pauses():
    """One real clip end to end: forced alignment gives the /m/ of "meters" and pauses; the
    procedural animator keeps the mouth near rest in them."""
    from talkmesh.face.assets import load_head
    from talkmesh.pipeline import animate

    go = next(c for c in rs.builtin_clips() if c.name == "goforward")
    wave = rs.read_clip(go)
    phones = rs.truth_phones(go, wave)
    labels = [p.label for p in phones]
    assert "M" in labels and "F" in labels and "SIL" in labels
    head = load_head()

    vertices = animate(wave, head=head, model="procedural", fps=FPS).vertices
    s = rs.score_clip(go, "procedural", "clean", vertices, head, phones, wave, FPS)
    assert s.pauses >= 1 and s.pause_mm < 1.0 and s.speed_ratio > 2.0


def test_reverb_keeps_length_and_level_and_smears_the_pauses():
    wave = _wave()
    wet = rs.add_reverb(wave, rt60=0.5)
    assert len(wet) == len(wave)
    assert rs._rms(wet) == pytest.approx(rs._rms(wave), rel=1e-3)
    t = np.arange(len(wave)) / rs.SAMPLE_RATE
    after = (t > 0.95) & (t < 1.1)  # just after the speech ends: the room's tail
    assert rs._rms(wet[after]) > 10 * rs._rms(wave[after])


def test_a_transcript_that_does_not_match_is_no_truth():
    go = next(c for c in rs.builtin_clips() if c.name == "goforward")
    wrong = rs.Clip(go.name, go.path, "zyxwvut qqqq", go.source)  # words not in the dictionary
    with pytest.raises(rs.TalkmeshError, match="does not align"):
        rs.truth_phones(wrong, rs.read_clip(go))


def test_pooled_bilabials_count_every_clips_closures():
    def row(clip, method, bilabial, count):
        return rs.ClipScores(
            clip, method, "clean", 0.0, 5.0, bilabial, 10.0, 0.5, 1.0, 1.0, 1, count
        )

    rows = [
        row("a", "m", 1.0, 1),
        row("b", "m", 1.0, 1),
        row("c", "m", 0.5, 10),
        row("d", "m", float("nan"), 0),  # no /p b m/: not scored
        row("a", "n", 0.0, 1),
    ]
    pooled = rs.pooled_bilabials(rows)
    assert pooled == {("m", "clean"): (7, 12), ("n", "clean"): (0, 1)}
    # the median over clips (1.0: two clips of one closure each) is not the share (7 of 12)
    assert rs.medians(rows)[("m", "clean")]["bilabial"] == 1.0
