"""Emotion: the FACS tables in ARKit channels, the timeline, tags, and the speech kept in charge
of the lips when an emotion is composed with it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from talkmesh.audio.phonemes import Phone
from talkmesh.cli import main
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import lip_opening, load_head
from talkmesh.face.composition import (
    GAP_TOLERANCE_M,
    GAP_TOLERANCE_SHARE,
    compose,
    compose_vertices,
    lip_basis,
    rest_gap,
)
from talkmesh.face.performance import (
    AU_ARKIT,
    EMOTION_AUS,
    EMOTIONS,
    Performance,
    Span,
    Tag,
    parse_emotion,
    read_performance,
    split_tags,
    tag_spans,
)
from talkmesh.pipeline import animate

# /h eh l ow p ah p/ with pauses either side: a bilabial in the middle of speech
PHONES = [
    Phone("SIL", 0.0, 0.3),
    *(
        Phone(label, 0.3 + 0.1 * k, 0.4 + 0.1 * k)
        for k, label in enumerate(["HH", "EH", "L", "OW", "P", "AA", "P", "AA", "M"])
    ),
    Phone("SIL", 1.2, 1.6),
]
WAVE = np.zeros(int(1.6 * 16000), np.float32)


def _animate(**kwargs):
    return animate(WAVE, phones=PHONES, model="procedural", **kwargs)


@pytest.mark.parametrize("emotion", EMOTIONS)
def test_each_emotion_moves_the_channels_of_its_action_units(emotion):
    weights = Performance({emotion: 1.0}).weights(np.zeros(1))[0]
    expected = np.zeros(len(ARKIT_NAMES))
    for au, amount in EMOTION_AUS[emotion].items():
        for name, w in AU_ARKIT[au].items():
            expected[ARKIT_NAMES.index(name)] += amount * w
    np.testing.assert_allclose(weights, np.clip(expected, 0, 1), atol=1e-6)
    moved = {ARKIT_NAMES[k] for k in np.flatnonzero(weights)}
    named = {n for au in EMOTION_AUS[emotion] for n in AU_ARKIT[au]}
    assert moved == named


def test_the_prototypes_are_the_emfacs_ones():
    # Friesen & Ekman's EMFACS prototypes (the module docstring): the AUs, not the amounts
    assert {e: set(aus) for e, aus in EMOTION_AUS.items()} == {
        "neutral": set(),
        "happy": {6, 12},
        "sad": {1, 4, 15},
        "angry": {4, 5, 7, 23},
        "surprised": {1, 2, 5, 26},
        "fearful": {1, 2, 4, 5, 7, 20, 26},
        "disgusted": {9, 15, 16},
    }
    happy = Performance({"happy": 1.0}).weights(np.zeros(1))[0]
    assert happy[ARKIT_NAMES.index("mouthSmileLeft")] > 0.5
    assert happy[ARKIT_NAMES.index("browDownLeft")] == 0


def test_mixes_add_and_intensity_scales():
    t = np.zeros(1)
    half = Performance({"happy": 0.5}).weights(t)
    full = Performance({"happy": 1.0}).weights(t)
    np.testing.assert_allclose(half * 2, full, atol=1e-6)
    mix = Performance(parse_emotion("happy:0.6,surprised:0.2")).weights(t)
    parts = Performance({"happy": 0.6}).weights(t) + Performance({"surprised": 0.2}).weights(t)
    np.testing.assert_allclose(mix, np.clip(parts, 0, 1), atol=1e-6)


@pytest.mark.parametrize("emotion", ["neutral", "happy:0", "angry:0,sad:0.0"])
def test_intensity_zero_is_the_neutral_output_bit_for_bit(emotion):
    plain = _animate()
    same = _animate(performance=Performance(parse_emotion(emotion)))
    assert np.array_equal(plain.vertices, same.vertices)
    assert np.array_equal(plain.weights, same.weights)


@pytest.mark.parametrize("emotion", [e for e in EMOTIONS if e != "neutral"])
def test_speech_keeps_the_lip_opening_under_every_emotion(emotion):
    head = load_head()
    plain = _animate(head=head)
    moved = _animate(head=head, performance=Performance({emotion: 1.0}))
    assert not np.array_equal(plain.weights, moved.weights)
    gap0 = lip_opening(plain.vertices, head.regions)
    gap = lip_opening(moved.vertices, head.regions)
    rest = rest_gap(head.template, head.regions.lip_pair)
    tol = np.maximum(GAP_TOLERANCE_M, GAP_TOLERANCE_SHARE * (gap0 - rest))
    assert np.all(np.abs(gap - gap0) <= tol + 1e-5), np.abs(gap - gap0).max()


def test_without_the_speech_in_charge_the_emotion_would_move_the_lips():
    # the guard is needed: the emotions added plainly open a /p/ or close a vowel
    head = load_head()
    plain = _animate(head=head)
    basis = lip_basis(head.blendshapes, head.regions.lip_pair)
    worst = 0.0
    for emotion in ("happy", "surprised", "disgusted"):
        emo = Performance({emotion: 1.0}).weights(np.arange(plain.num_frames) / plain.fps)
        naive = np.clip(plain.weights + emo, 0, 1)
        gap0 = lip_opening(plain.vertices, head.regions)
        gap = lip_opening(head.vertices_from_weights(naive), head.regions)
        worst = max(worst, float(np.abs(gap - gap0).max()))
    assert worst > 1e-3  # a millimetre and more (a surprised jaw drop: about 9 mm)
    assert basis.shape == (52, 3)


def test_compose_on_vertices_equals_compose_on_weights():
    head = load_head()
    plain = _animate(head=head)
    emo = Performance({"surprised": 1.0}).weights(np.arange(plain.num_frames) / plain.fps)
    vertices = plain.vertices.copy()
    rest = rest_gap(head.template, head.regions.lip_pair)
    weights = compose_vertices(
        vertices, plain.weights, emo, head.blendshapes, head.regions.lip_pair, rest
    )
    np.testing.assert_allclose(vertices, head.vertices_from_weights(weights), atol=1e-5)
    upper, lower = head.regions.lip_pair
    lips = plain.vertices[:, upper] - plain.vertices[:, lower]
    basis = lip_basis(head.blendshapes, head.regions.lip_pair)
    again = compose(plain.weights, emo, lips, basis, rest)
    np.testing.assert_allclose(weights, again, atol=1e-6)


def test_span_eases_in_and_out():
    span = Span(1.0, 3.0, {"happy": 1.0}, onset=0.4, offset=0.5)
    t = np.linspace(0, 4, 401)
    env = span.envelope(t)
    assert env[t < 1.0].max() == 0 and env[t >= 3.0].max() == 0
    assert np.allclose(env[(t > 1.4) & (t < 2.5)], 1.0)
    rise = env[(t >= 1.0) & (t <= 1.4)]
    assert np.all(np.diff(rise) >= 0) and rise[0] < 0.01
    assert np.abs(np.diff(env)).max() < 0.05  # no jumps at 10 ms steps


def test_timeline_file_blends_from_the_base(tmp_path):
    path = tmp_path / "p.json"
    spans = [{"start": 0.5, "end": 1.5, "emotion": "angry", "intensity": 0.5}]
    path.write_text(json.dumps({"emotion": "happy:0.4", "spans": spans}))
    perf = read_performance(path)
    got = perf.intensities(np.array([0.0, 1.0]))
    happy, angry = EMOTIONS.index("happy"), EMOTIONS.index("angry")
    assert got[0, happy] == pytest.approx(0.4) and got[0, angry] == 0
    assert got[1, happy] == pytest.approx(0.0) and got[1, angry] == pytest.approx(0.5)


def test_tags_split_from_the_transcript_and_timed_at_their_words():
    text, tags = split_tags("[happy] go forward [sad:0.5]ten meters")
    assert text.split() == ["go", "forward", "ten", "meters"]
    assert tags == [Tag(0, {"happy": 1.0}), Tag(2, {"sad": 0.5})]
    spans = tag_spans(tags, [0.1, 0.4, 0.9, 1.2], 2.0)
    assert [(s.start, s.mix) for s in spans] == [(0.1, {"happy": 1.0}), (0.9, {"sad": 0.5})]
    assert spans[0].end > spans[1].start  # held until the next has risen: no dip between
    assert spans[1].end == 2.0
    assert split_tags("no tags here") == ("no tags here", [])


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("joyful", "unknown emotion 'joyful'"),
        ("happy:1.5", "from 0 to 1"),
        ("happy:-0.2", "from 0 to 1"),
        ("happy:nan", "from 0 to 1"),
        ("happy:lots", "EMOTION:INTENSITY"),
        ("happy,,sad", "EMOTION[:INTENSITY]"),
    ],
)
def test_bad_emotions_are_one_line(text, fragment):
    with pytest.raises(TalkmeshError, match=fragment.replace("[", r"\[")) as e:
        parse_emotion(text)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("[joyful] hello", "unknown emotion 'joyful'"),
        ("[happy:2] hello", "from 0 to 1"),
        ("[happy hello", "a bracket without its pair"),
        ("hello] there", "a bracket without its pair"),
        ("[] hello", "EMOTION[:INTENSITY]"),
    ],
)
def test_bad_tags_are_one_line(text, fragment):
    with pytest.raises(TalkmeshError, match=fragment.replace("[", r"\[")) as e:
        split_tags(text)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize(
    "content, fragment",
    [
        (None, "no such performance file"),
        ("{not json", "not a JSON timeline"),
        ('{"spans": 3}', "give a list of spans"),
        ('[{"start": 1, "end": 0.5, "emotion": "happy"}]', "must come after"),
        ('[{"start": 0, "end": 1, "emotion": "happy", "mood": 1}]', "unknown key 'mood'"),
        ('[{"start": 0, "end": 1, "emotion": "glee"}]', "unknown emotion 'glee'"),
        ('[{"start": 0, "end": 1, "emotion": "sad", "intensity": 3}]', "intensity"),
        ('[{"start": "0", "end": 1, "emotion": "sad"}]', "'start' must be a number"),
        ('[{"end": 1, "emotion": "sad"}]', "'start' is missing"),
    ],
)
def test_bad_timeline_files_are_one_line(tmp_path, content, fragment):
    path = tmp_path / "p.json"
    if content is not None:
        path.write_text(content)
    with pytest.raises(TalkmeshError, match=fragment) as e:
        read_performance(path)
    assert "\n" not in str(e.value) and str(path) in str(e.value)


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--emotion", "joyful"], "unknown emotion"),
        (["--emotion", "sad:7"], "from 0 to 1"),
        (["--text", "[sad hello", "--model", "procedural"], "bracket"),
    ],
)
def test_cli_refuses_bad_emotions_in_one_line_before_any_work(tmp_path, capsys, args, fragment):
    speech = tmp_path / "a.wav"
    speech.write_bytes(b"")  # never read: the option is refused first
    out = tmp_path / "a.npz"
    assert main(["animate", str(speech), "-o", str(out), *args]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("talkmesh: error:") and fragment in err[0]
    assert not out.exists()


def test_cli_writes_the_emotion_into_the_weights(tmp_path):
    clip = Path("/usr/share/pocketsphinx/test/data/librivox")
    clip = clip / "sense_and_sensibility_01_austen_64kb-0880.wav"
    if not clip.exists():
        pytest.skip("pocketsphinx-testdata not installed")
    wav = tmp_path / "a.wav"
    wav.write_bytes(clip.read_bytes())
    outs = {}
    for name, extra in (("plain", []), ("sad", ["--emotion", "sad"])):
        outs[name] = tmp_path / f"{name}.npz"
        argv = ["animate", str(wav), "--model", "procedural", "-o", str(outs[name]), "-q"]
        assert main(argv + extra) == 0
    plain, sad = np.load(outs["plain"]), np.load(outs["sad"])
    inner = ARKIT_NAMES.index("browInnerUp")
    assert sad["weights"][:, inner].mean() > plain["weights"][:, inner].mean() + 0.4
