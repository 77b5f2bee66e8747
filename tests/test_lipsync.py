import numpy as np
import pytest

from talkmesh.audio.phonemes import Phone
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import lip_opening, load_head
from talkmesh.face.lipsync import SpeakingStyle, phones_to_weights, pitch_accents

FPS = 60
BLINK = ARKIT_NAMES.index("eyeBlinkLeft")
JAW = ARKIT_NAMES.index("jawOpen")
BROW = ARKIT_NAMES.index("browInnerUp")


def timed(spec: str) -> list[Phone]:
    """'SIL .3 P .08 AA .2' -> contiguous phones."""
    tokens = spec.split()
    phones, t = [], 0.0
    for label, dur in zip(tokens[::2], tokens[1::2]):
        phones.append(Phone(label, t, t + float(dur)))
        t += float(dur)
    return phones


SENTENCE = timed("SIL .3 P .08 AA .2 P .08 AA .2 M .1 AY .2 B .07 UW .2 M .08 AE .18 T .06 SIL .4")


def openings(phones, style=None, seed=0):
    head = load_head()
    n = int(round(phones[-1].end * FPS))
    w = phones_to_weights(phones, n, FPS, style=style, seed=seed)
    return w, lip_opening(head.vertices_from_weights(w), head.regions) * 1000  # mm


def at(op, phone):
    return op[int((phone.start + phone.end) / 2 * FPS)]


def test_lips_close_on_bilabials_and_open_on_open_vowels():
    _, op = openings(SENTENCE)
    closed = [at(op, p) for p in SENTENCE if p.label in ("P", "B", "M")]
    opened = [at(op, p) for p in SENTENCE if p.label in ("AA", "AE")]
    assert max(closed) < 3.5, closed  # neutral gap of this mesh is ~1.3 mm
    assert min(opened) > 9.0, opened
    assert min(opened) > 3 * max(closed)


def test_rounding_on_rounded_vowels():
    w, _ = openings(SENTENCE)
    pucker = ARKIT_NAMES.index("mouthPucker")
    uw = next(p for p in SENTENCE if p.label == "UW")
    aa = next(p for p in SENTENCE if p.label == "AA")
    assert w[int((uw.start + uw.end) / 2 * FPS), pucker] > 0.5
    assert w[int((aa.start + aa.end) / 2 * FPS), pucker] < 0.1


def test_coarticulation_anticipates_the_next_vowel():
    # the jaw starts opening before an open vowel begins (anticipation)
    w, _ = openings(timed("SIL .5 AA .3 SIL .5"))
    onset = int(0.5 * FPS)
    assert w[onset - 3, JAW] > 0.05 * w[onset + 9, JAW]
    assert w[onset + 9, JAW] > 0.3


def test_blinks_present_at_a_natural_rate():
    phones = timed("SIL 60")
    w = phones_to_weights(phones, 60 * 30, 30, seed=3, style=SpeakingStyle(blink_rate=15))
    closed = w[:, BLINK] > 0.9
    blinks = np.count_nonzero(closed[1:] & ~closed[:-1])
    assert 7 <= blinks <= 25, blinks
    assert w[:, BLINK].min() == 0.0


def test_deterministic_under_seed_and_seed_only_changes_free_motion():
    a = phones_to_weights(SENTENCE, 120, FPS, seed=7)
    b = phones_to_weights(SENTENCE, 120, FPS, seed=7)
    c = phones_to_weights(SENTENCE, 120, FPS, seed=8)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    mouth = [i for i, n in enumerate(ARKIT_NAMES) if n.startswith(("mouth", "jaw"))]
    assert np.array_equal(a[:, mouth], c[:, mouth])  # lips follow the speech, not the seed


def test_style_scales_articulation():
    loud = SpeakingStyle(articulation=1.3, jaw=1.2)
    soft = SpeakingStyle(articulation=0.7, jaw=0.8)
    wl, _ = openings(SENTENCE, style=loud)
    ws, _ = openings(SENTENCE, style=soft)
    assert wl[:, JAW].max() > 1.5 * ws[:, JAW].max()
    with pytest.raises(TalkmeshError):
        SpeakingStyle(blink_rate=-1)


def test_brow_raises_follow_pitch_accents():
    sr = 16000
    t = np.arange(int(3 * sr)) / sr
    f0 = np.where((t > 1.4) & (t < 1.8), 220.0, 120.0)  # one pitch accent at 1.4-1.8 s
    audio = (0.3 * np.sin(2 * np.pi * np.cumsum(f0) / sr)).astype(np.float32)
    acc = pitch_accents(audio, sr)
    assert len(acc) >= 1 and 1.3 < acc[0, 0] < 1.9
    w = phones_to_weights(
        timed("AH 3"), 90, 30, audio=audio, sr=sr, style=SpeakingStyle(brow_activity=1.0)
    )
    assert w[40:60, BROW].max() > w[:30, BROW].max() + 0.1


def test_long_input_is_fast_and_bounded():
    # ten minutes of phones at 12 phones/s
    labels = ["P", "AA", "T", "IY", "M", "UW", "S", "EH"]
    phones = [Phone(labels[i % 8], i / 12, (i + 1) / 12) for i in range(600 * 12)]
    w = phones_to_weights(phones, 600 * 30, 30)
    assert w.shape == (18000, 52) and w.dtype == np.float32
    assert np.isfinite(w).all() and w[:, JAW].max() > 0.2


def test_arkit_weights_are_recovered_from_vertices():
    from talkmesh.face.arkit import fit_weights
    from talkmesh.face.assets import load_head

    head = load_head()
    rng = np.random.default_rng(0)
    weights = np.clip(rng.uniform(-0.3, 1.0, size=(7, 52)), 0, 1).astype(np.float32)
    offsets = head.vertices_from_weights(weights) - head.template
    np.testing.assert_allclose(fit_weights(offsets, head.blendshapes), weights, atol=1e-3)
    blocks = fit_weights(offsets + head.template, head.blendshapes, head.template, block=3)
    np.testing.assert_allclose(blocks, weights, atol=1e-3)
    pushed = fit_weights(offsets * 3.0, head.blendshapes)  # outside the box: clipped to [0, 1]
    assert pushed.min() >= 0.0 and pushed.max() <= 1.0
    assert fit_weights(offsets[:0], head.blendshapes).shape == (0, 52)


def test_a_models_own_eye_motion_is_replaced_by_procedural_eyes_not_added_to():
    from talkmesh.face.lipsync import BLINK_GAZE, INDEX, blink_gaze_weights, replace_eye_motion

    rng = np.random.default_rng(0)
    basis = rng.standard_normal((52, 30)).astype(np.float32)
    eyes_at = [INDEX[n] for n in BLINK_GAZE]
    own = np.zeros((90, 52), np.float32)
    own[:, eyes_at] = rng.uniform(0, 0.3, (90, len(eyes_at)))  # a model's faint eye motion
    own[:, INDEX["jawOpen"]] = rng.uniform(0, 1, 90)
    offsets = own @ basis
    weights = own.copy()  # as fitted to the offsets
    eyes = blink_gaze_weights(90, 30.0, seed=4)
    assert eyes[:, eyes_at].max() > 0.5  # a blink in these 3 s
    replace_eye_motion(offsets, weights, eyes, basis, block=32)
    expected = own.copy()
    expected[:, eyes_at] = eyes[:, eyes_at]
    np.testing.assert_allclose(weights, expected)
    np.testing.assert_allclose(offsets, expected @ basis, atol=1e-4)  # the jaw untouched
