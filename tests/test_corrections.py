"""The recogniser's corrections of a learned model's mouth: each one does its job and turns off."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from talkmesh.audio.phonemes import Phone
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import lip_opening, load_head
from talkmesh.face.corrections import (
    NEAR_CLOSED_MM,
    NONE,
    Corrections,
    bilabial_frames,
    correct_mouth,
    correct_mouth_chunks,
    loudness_curve,
    near_closures,
)
from talkmesh.face.lipsync import phones_to_weights
from talkmesh.face.pauses import TAIL_MAX_S, speech_gate, tail_pauses

FPS = 30.0
SR = 16_000
PHONES = [
    Phone("SIL", 0.0, 0.3),
    Phone("AA", 0.3, 0.6),
    Phone("M", 0.6, 0.7),
    Phone("AA", 0.7, 1.0),
    Phone("SIL", 1.0, 1.5),
    Phone("AA", 1.5, 2.0),
]
T = 60
t = (np.arange(T) + 0.5) / FPS
# the pause gate on the pauses of PHONES (the tests' waves are tones, not speech)
RECOGNISED = Corrections(mix=0.0, gain=0.0, lip_closure=False, pauses="recognizer")


def _open_mouth(head):
    """A 'model' that holds the jaw half open all the time: (T, V, 3)."""
    w = np.zeros((T, len(ARKIT_NAMES)), np.float32)
    w[:, ARKIT_NAMES.index("jawOpen")] = 0.5
    return head.vertices_from_weights(w)


def _wave():
    """Speech-loud noise where PHONES speak, silence in their pauses."""
    rng = np.random.default_rng(0)
    wave = np.zeros(int(2.0 * SR), np.float32)
    for p in PHONES:
        if p.label != "SIL":
            wave[int(p.start * SR) : int(p.end * SR)] = rng.normal(
                0, 0.1, int(p.end * SR) - int(p.start * SR)
            )
    return wave


def _mm(head, vertices):
    return lip_opening(vertices, head.regions) * 1000


def test_near_closures_are_minima_close_to_rest_only():
    opening = np.array([5.0, 2.0, 4.0, 8.0, 6.0, 7.0, 1.0, 1.0, 3.0])
    found = near_closures(opening, rest=1.0, within=3.0)
    # 2.0 is a minimum 1 above rest, 1.0 one at rest; 6.0 is a minimum but far open
    np.testing.assert_array_equal(np.flatnonzero(found), [1, 6, 7])


def test_only_dips_are_closures_not_lips_resting_in_a_pause():
    opening = np.array([5.0, 2.0, 4.0, 8.0, 6.0, 7.0, 1.0, 1.0, 3.0])
    # the flat minimum's first frame does not open the next frame; its second does
    found = near_closures(opening, rest=1.0, within=3.0, reopen=0.5)
    np.testing.assert_array_equal(np.flatnonzero(found), [1, 7])
    closing_into_a_pause = np.array([6.0, 4.0, 1.2, 1.0, 1.0, 1.1, 1.0, 1.0])
    assert not near_closures(closing_into_a_pause, 1.0, 3.0, reopen=0.5).any()
    out_of_a_pause = np.array([1.0, 1.0, 1.1, 1.0, 1.0, 3.0, 6.0])
    assert not near_closures(out_of_a_pause, 1.0, 3.0, reopen=0.5).any()
    # a closure reopens within the frames before it: four frames back is too far
    assert near_closures(np.array([6.0, 1.0, 1.0, 1.0, 4.0]), 1.0, 3.0, 0.5).tolist() == [
        False, False, False, True, False
    ]  # fmt: skip
    assert not near_closures(np.array([6.0, 1.0, 1.0, 1.0, 1.0, 4.0]), 1.0, 3.0, 0.5).any()


def test_the_lip_closure_shuts_dips_not_lips_that_rest_near_closed():
    """Lips that come to rest near closed three frames before the pause gate closes the mouth
    (voice activity and the speech disagree at a pause's edge), or that the model leaves at rest
    through a /m/, stay as they are: shut wherever noise makes a minimum, they moved in a pause.
    A dip shuts."""
    head = load_head()
    w = np.zeros((T, len(ARKIT_NAMES)), np.float32)
    w[:, ARKIT_NAMES.index("jawOpen")] = 0.5
    w[16:21, ARKIT_NAMES.index("jawOpen")] = 0.03  # an M left at rest (frames 16-20)
    w[27:, ARKIT_NAMES.index("jawOpen")] = 0.03  # at rest from frame 27; the pause from 30
    w[27:, ARKIT_NAMES.index("jawOpen")] += 0.002 * (np.arange(T - 27) % 2)  # noise
    w[52:55, ARKIT_NAMES.index("jawOpen")] = [0.2, 0.04, 0.2]  # a dip in the last word
    verts = head.vertices_from_weights(w)
    for gate in (False, True):
        closure = replace(RECOGNISED, pause_gate=gate, lip_closure=True, met_lips=True)
        bare = _mm(head, verts)
        fixed = _mm(head, correct_mouth(verts.copy(), head, PHONES, _wave(), FPS, closure))
        np.testing.assert_allclose(fixed[15:30], bare[15:30], rtol=1e-6)  # still: as it was
        assert fixed[53] <= 0.5 < bare[53]  # the dip: shut


def test_no_corrections_leave_the_model_alone_and_mix_is_checked():
    head = load_head()
    verts = _open_mouth(head)
    before = verts.copy()
    correct_mouth(verts, head, PHONES, _wave(), FPS, NONE)
    np.testing.assert_array_equal(verts, before)
    with pytest.raises(TalkmeshError, match="procedural-mix"):
        Corrections(mix=1.5)
    with pytest.raises(TalkmeshError, match="loudness-gain"):
        Corrections(gain=-0.1)


def _dipping(head):
    """A 'model' whose jaw is half open but nearly closes (a minimum) at frame 20: (T, V, 3)."""
    w = np.zeros((T, len(ARKIT_NAMES)), np.float32)
    w[:, ARKIT_NAMES.index("jawOpen")] = 0.5
    w[19:22, ARKIT_NAMES.index("jawOpen")] = [0.2, 0.04, 0.2]
    return head.vertices_from_weights(w)


def test_lip_closure_shuts_the_models_near_closure_and_only_with_its_switch():
    head = load_head()
    rest = float(_mm(head, head.template[None])[0])
    bare = _mm(head, _dipping(head))
    assert bare[20] - rest > 0.5 and bare[20] - rest < NEAR_CLOSED_MM  # nearly closed
    closure = Corrections(pause_gate=False, lip_closure=True, mix=0.0, gain=0.0, met_lips=False)
    closed = _mm(head, correct_mouth(_dipping(head), head, PHONES, _wave(), FPS, closure))
    assert abs(closed[20] - rest) < 0.05  # shut at the minimum
    np.testing.assert_allclose(np.delete(closed, 20), np.delete(bare, 20), rtol=1e-6)
    off = _mm(head, correct_mouth(_dipping(head), head, PHONES, _wave(), FPS, NONE))
    np.testing.assert_allclose(off, bare)


def test_bilabial_closure_shuts_near_closures_by_a_recognised_p_b_m_only():
    head = load_head()
    rest = float(_mm(head, head.template[None])[0])
    near = bilabial_frames(PHONES, T, FPS)
    np.testing.assert_array_equal(np.flatnonzero(near), np.arange(16, 23))  # M: 0.6-0.7 s, +-2
    verts = _dipping(head)
    w = np.zeros((T, len(ARKIT_NAMES)), np.float32)
    w[:, ARKIT_NAMES.index("jawOpen")] = 0.5
    w[49:52, ARKIT_NAMES.index("jawOpen")] = [0.2, 0.04, 0.2]  # a second dip, in an AA
    verts[45:] = head.vertices_from_weights(w)[45:]
    bare = _mm(head, verts)
    assert bare[50] - rest > 0.5 and bare[50] - rest < NEAR_CLOSED_MM
    fix = Corrections(
        pause_gate=False, lip_closure=False, mix=0.0, gain=0.0, met_lips=False, bilabial=True
    )
    shut = _mm(head, correct_mouth(verts.copy(), head, PHONES, _wave(), FPS, fix))
    assert abs(shut[20] - rest) < 0.05  # by the M: shut
    np.testing.assert_allclose(np.delete(shut, 20), np.delete(bare, 20), rtol=1e-6)  # not at 50
    every = Corrections(
        pause_gate=False, mix=0.0, gain=0.0, bilabial=True, lip_closure=True, met_lips=False
    )
    both = _mm(head, correct_mouth(verts.copy(), head, PHONES, _wave(), FPS, every))
    assert abs(both[50] - rest) < 0.05 and abs(both[20] - rest) < 0.05


def test_mix_moves_toward_procedural_but_keeps_the_models_closures():
    head = load_head()
    bare = _mm(head, _dipping(head))
    mixed = _mm(
        head,
        correct_mouth(
            _dipping(head),
            head,
            PHONES,
            _wave(),
            FPS,
            Corrections(False, False, 0.5, 0.0, bilabial=False),
        ),
    )
    procedural = _mm(
        head, head.vertices_from_weights(phones_to_weights(PHONES, T, FPS, audio=_wave()))
    )
    far = np.abs(procedural - bare) > 1.0
    far[18:23] = False
    assert far.sum() > 10
    np.testing.assert_allclose(mixed[far], 0.5 * (bare[far] + procedural[far]), atol=0.3)
    np.testing.assert_allclose(mixed[19:22], bare[19:22], rtol=1e-6)  # the closure is kept


def test_loudness_curve_follows_the_speech_and_is_zero_in_silence():
    loud = loudness_curve(_wave(), T, FPS)
    assert loud.shape == (T,) and loud.dtype == np.float32
    assert np.all(loud[(t > 0.4) & (t < 0.9)] > 0.9)  # speech at the clip's level
    assert np.all(loud[(t > 1.1) & (t < 1.4)] == 0.0)  # digital silence
    assert np.all(loudness_curve(np.zeros(0, np.float32), 5, FPS) == 0.0)


def test_gain_opens_the_mouth_further_in_loud_speech_but_keeps_closures():
    head = load_head()
    rest = float(_mm(head, head.template[None])[0])
    bare = _mm(head, _dipping(head))
    gain = Corrections(pause_gate=False, lip_closure=False, mix=0.0, gain=0.5, bilabial=False)
    louder = _mm(head, correct_mouth(_dipping(head), head, PHONES, _wave(), FPS, gain))
    speech = (t > 0.4) & (t < 0.55)  # loud, far from the closure at frame 20
    # the lips' displacement from the closed mouth grows by half
    np.testing.assert_allclose(louder[speech] - rest, 1.5 * (bare[speech] - rest), rtol=0.05)
    silent = (t > 1.1) & (t < 1.4)
    np.testing.assert_allclose(louder[silent], bare[silent], rtol=1e-6)  # no sound, no gain
    np.testing.assert_allclose(louder[19:22], bare[19:22], rtol=1e-6)  # the closure is kept


def test_the_gain_fades_with_the_pause_gate():
    """On the gate's ramps the gain's extra opening is scaled by the gate (then the gate scales
    the whole opening again): no gained opening pops out as the mouth closes for a pause."""
    head = load_head()
    gate = speech_gate(tail_pauses(PHONES, _wave()), T, FPS)
    ramp = (gate > 0) & (gate < 1)
    assert ramp.sum() >= 2  # the gate closes and opens over a few frames

    def opening(pause_gate: bool, gain: float) -> np.ndarray:
        fix = Corrections(
            pause_gate=pause_gate,
            lip_closure=False,
            mix=0.0,
            gain=gain,
            bilabial=False,
            pauses="recognizer",
        )
        return _mm(head, correct_mouth(_open_mouth(head), head, PHONES, _wave(), FPS, fix))

    extra_gated = opening(True, 0.7) - opening(True, 0.0)
    extra_free = opening(False, 0.7) - opening(False, 0.0)
    loud = ramp & (extra_free > 1.0)  # ramp frames where the gain would open the mouth further
    assert loud.sum() >= 2
    np.testing.assert_allclose(extra_gated[ramp], gate[ramp] ** 2 * extra_free[ramp], atol=0.1)
    speech = gate == 1
    np.testing.assert_allclose(extra_gated[speech], extra_free[speech], atol=1e-4)


@pytest.mark.parametrize("size", [1, 2, 3, 19, 20, 21, 22, 59])
def test_chunks_are_corrected_as_the_whole_clip(size):
    """Chunk edges next to the near-closure at frame 20: the look-ahead must see its neighbours."""
    head = load_head()
    every = Corrections(
        pause_gate=True, lip_closure=True, mix=0.5, gain=0.3, pauses="recognizer", met_lips=False
    )
    whole = correct_mouth(_dipping(head), head, PHONES, _wave(), FPS, every)
    verts = _dipping(head)
    chunks = (verts[i : i + size] for i in range(0, T, size))
    got = list(correct_mouth_chunks(chunks, T, head, PHONES, _wave(), FPS, every))
    assert [len(c) for c in got] == [len(verts[i : i + size]) for i in range(0, T, size)]
    np.testing.assert_allclose(np.concatenate(got), whole, rtol=0, atol=1e-7)
    bare = _mm(head, _dipping(head))
    assert abs(_mm(head, whole)[20] - _mm(head, head.template[None])[0]) < 0.05
    np.testing.assert_allclose(_mm(head, whole)[19:22:2], bare[19:22:2], rtol=1e-6)  # kept


def test_pause_gate_shuts_the_mouth_in_pauses():
    head = load_head()
    rest = float(_mm(head, head.template[None])[0])
    gated = _mm(head, correct_mouth(_open_mouth(head), head, PHONES, _wave(), FPS, RECOGNISED))
    assert np.all(np.abs(gated[(t >= 1.15) & (t < 1.35)] - rest) < 0.1)
    mixed = _mm(
        head,
        correct_mouth(
            _open_mouth(head), head, PHONES, _wave(), FPS, Corrections(False, False, 0.5)
        ),
    )
    bare = _mm(head, _open_mouth(head))
    assert np.all(mixed[(t >= 1.15) & (t < 1.35)] < bare[(t >= 1.15) & (t < 1.35)] - 1.0)


def test_tail_pauses_moves_a_pause_back_over_an_echo_but_not_over_speech():
    rng = np.random.default_rng(1)
    speech = rng.normal(0, 0.1, SR // 2).astype(np.float32)  # 0.5 s of loud sound
    decay = np.exp(-np.arange(SR // 2) / SR * 3 * np.log(10) / 0.5)  # RT60 0.5 s: 60 dB in 0.5 s
    tail = (rng.normal(0, 0.1, SR // 2) * decay).astype(np.float32)
    wave = np.concatenate([speech, tail])
    late = [Phone("AA", 0.0, 0.75), Phone("SIL", 0.75, 1.0)]  # the recogniser hears the echo
    moved = tail_pauses(late, wave)
    # the echo is 25 dB down after 0.21 s: the pause now starts there, not later than 0.75 - max
    assert 0.75 - TAIL_MAX_S - 1e-6 <= moved[1].start < 0.75
    assert moved[0].end == moved[1].start and moved[1].end == 1.0
    loud = np.concatenate([speech, speech])
    assert tail_pauses(late, loud) == late  # no quiet frames: nothing moves


@pytest.mark.slow  # runs the bundled model on a real recording
def test_default_corrections_shut_a_reverberant_pause_the_bare_model_leaves_open():
    from talkmesh.audio.phonemes import recognize_phones
    from talkmesh.evaluation import real_speech as rs
    from talkmesh.pipeline import animate

    clip = next(c for c in rs.builtin_clips() if c.name == "alsa-Front_Right")
    clean = rs.read_clip(clip)
    truth = rs.truth_phones(clip, clean)
    wave = rs.degrade(clean, "reverb", None)
    head = load_head()
    bare = animate(
        wave,
        head=head,
        model="codetalker-synth",
        fps=FPS,
        pause_gate=False,
        procedural_mix=0.0,
        loudness_gain=0.0,
        bilabial_closure=False,
    ).vertices
    fixed = correct_mouth(bare.copy(), head, recognize_phones(wave), wave, FPS)
    rest = float(_mm(head, head.template[None])[0])

    def pause_mm(vertices):
        return rs.score_opening(_mm(head, vertices), rest, truth, wave, FPS)["pause_mm"]

    # the echo hides most of the pause from the recogniser; the bare model stays ~8 mm open
    assert pause_mm(bare) > 3.0 and pause_mm(fixed) < 1.0


def test_voice_activity_finds_pauses_in_real_speech_and_in_other_languages(tmp_path):
    """The default pause gate needs no English: voice activity finds the pause between the
    demo recording's two sentences, and between two German sentences; the gate shuts the mouth
    there."""
    import subprocess

    from talkmesh.audio.loading import load_audio
    from talkmesh.audio.vad import speech_pauses

    demo = load_audio("examples/librivox-sense-and-sensibility.flac")
    pauses = [p for p in speech_pauses(demo) if p.label == "SIL" and p.end - p.start >= 0.2]
    assert any(2.7 < (p.start + p.end) / 2 < 3.4 for p in pauses), pauses
    parts = []
    for k, text in enumerate(["Mein Bruder baut ein Boot.", "Bitte bring mir Brot."]):
        wav = tmp_path / f"de{k}.wav"
        subprocess.run(["espeak-ng", "-v", "de", "-w", str(wav), text], check=True)
        parts.append(load_audio(wav))
    german = np.concatenate([parts[0], np.zeros(int(0.5 * SR), np.float32), parts[1]])
    segments = speech_pauses(german)
    assert sum(p.label == "SPEECH" for p in segments) >= 2
    inner = [p for p in segments[1:-1] if p.label == "SIL"]
    assert inner and max(p.end - p.start for p in inner) >= 0.4
    assert segments[0].start == 0 and abs(segments[-1].end - len(german) / SR) < 1e-6
    head = load_head()
    n = int(len(german) / SR * FPS)
    w = np.zeros((n, len(ARKIT_NAMES)), np.float32)
    w[:, ARKIT_NAMES.index("jawOpen")] = 0.3
    wide = head.vertices_from_weights(w)
    gated = _mm(
        head, correct_mouth(wide, head, [], german, FPS, Corrections(mix=0.0, bilabial=False))
    )
    gap = max(inner, key=lambda p: p.end - p.start)
    mid = int((gap.start + gap.end) / 2 * FPS)
    rest = float(_mm(head, head.template[None])[0])
    assert abs(gated[mid] - rest) < 0.1
    first_word = next(p for p in segments if p.label == "SPEECH")
    assert gated[int((first_word.start + first_word.end) / 2 * FPS)] > rest + 3  # speech: open


def test_met_lips_shut_near_closures_to_closed_lips_not_to_the_rest_face():
    """With met_lips a shut near-closure has its lips met (the teacher's closure), below the rest
    face's small gap; without, it goes to the rest face."""
    from talkmesh.face.corrections import closed_lips

    head = load_head()
    rest = float(_mm(head, head.template[None])[0])
    assert float(_mm(head, closed_lips(head)[None])[0]) <= 0.5 < rest
    plain = Corrections(
        pause_gate=False, lip_closure=True, mix=0.0, gain=0.0, bilabial=False, met_lips=False
    )
    met = Corrections(
        pause_gate=False, lip_closure=True, mix=0.0, gain=0.0, bilabial=False, met_lips=True
    )
    to_rest = _mm(head, correct_mouth(_dipping(head), head, PHONES, _wave(), FPS, plain))
    to_met = _mm(head, correct_mouth(_dipping(head), head, PHONES, _wave(), FPS, met))
    assert abs(to_rest[20] - rest) < 0.05
    assert to_met[20] <= 0.5
    np.testing.assert_allclose(to_met[:18], to_rest[:18], rtol=1e-6)  # elsewhere the same
