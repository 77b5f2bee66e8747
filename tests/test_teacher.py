"""The teacher's rules on small cases: lips met through /p b m/, rest in pauses, rounding, open
vowels by loudness; and the phone labels of other languages' SAMPA."""

import numpy as np
import pytest

from talkmesh.audio.languages import sampa_label
from talkmesh.audio.phonemes import SILENCE, Phone
from talkmesh.face.assets import lip_opening, load_head
from talkmesh.face.lipsync import INDEX, SpeakingStyle, phones_to_weights
from talkmesh.face.teacher import (
    CLOSURE_MM,
    LEAD_CHANNELS,
    LEAD_S,
    MOUTH_CHANNELS,
    REST_RAMP_S,
    close_lips,
    lead,
    pause_gate,
    teach,
)

FPS = 60.0


def _phones(spec):
    out, t = [], 0.0
    for label, dur in spec:
        out.append(Phone(label, t, t + dur))
        t += dur
    return out, t


def _animate(spec, head, audio=None, style=None, lead_s=0.0):
    """The rules in step with the phones (``lead_s`` 0), unless a lead is asked for."""
    phones, total = _phones(spec)
    n = int(round(total * FPS))
    w = phones_to_weights(phones, n, FPS, style=style or SpeakingStyle(), seed=0)
    raw = w.copy()
    teach(w, phones, FPS, head, audio=audio, sr=16_000, lead_s=lead_s)
    return phones, raw, w


@pytest.fixture(scope="module")
def head():
    return load_head()


def _opening_mm(head, w):
    return lip_opening(head.vertices_from_weights(w), head.regions) * 1000


@pytest.mark.parametrize("lead_s", [0.0, LEAD_S])
def test_lips_meet_through_every_bilabial(head, lead_s):
    spec = [(SILENCE, 0.3), ("AA", 0.12), ("P", 0.06), ("AA", 0.12), ("M", 0.05), ("IY", 0.1)]
    spec += [("B", 0.04), ("AE", 0.15), (SILENCE, 0.3)]
    phones, raw, w = _animate(spec, head, lead_s=lead_s)
    centres = (np.arange(len(w)) + 0.5) / FPS
    before, after = _opening_mm(head, raw), _opening_mm(head, w)
    for p in phones:
        if p.label in {"P", "B", "M"}:
            inside = (centres >= p.start) & (centres < p.end)
            assert inside.any()
            assert before[inside].max() > CLOSURE_MM  # the animator alone leaves them apart
            # the mouth leads the sound, but the lips are shut while the sound is stopped
            assert after[inside].max() <= CLOSURE_MM, (p, after[inside])


@pytest.mark.parametrize("offset", [0.0, 0.004, 0.008, 0.012])
@pytest.mark.parametrize("duration", [0.005, 0.01, 0.029])
def test_a_short_bilabial_closes_in_the_frames_a_model_reads(head, duration, offset):
    """A /b/ shorter than a 30 fps frame (a synthesiser's sliver) still closes the lips in the
    truth as it is read for training and scoring: every second 60 fps frame."""
    from talkmesh.evaluation.real_speech import phone_window

    spec = [(SILENCE, 0.3 + offset), ("AA", 0.12), ("B", duration), ("AA", 0.12), (SILENCE, 0.3)]
    phones, _, w = _animate(spec, head, lead_s=LEAD_S)
    at_30 = _opening_mm(head, w)[::2]
    lo, hi = phone_window(phones[2], FPS / 2, len(at_30))
    assert at_30[lo:hi].min() <= CLOSURE_MM, at_30[lo:hi]
    assert at_30[lo:hi].max() > 3 * CLOSURE_MM  # a closure between open vowels, not a shut mouth


def test_the_mouth_leads_the_sound_and_the_upper_face_does_not(head):
    spec = [(SILENCE, 0.3), ("AA", 0.2), ("S", 0.08), ("AA", 0.2), (SILENCE, 0.3)]
    _, _, in_step = _animate(spec, head)
    _, _, ahead = _animate(spec, head, lead_s=LEAD_S)
    k = round(LEAD_S * FPS)
    assert k == 2  # a 30 fps frame: two of the corpus's 60 fps frames
    mouth = list(LEAD_CHANNELS)
    assert set(MOUTH_CHANNELS) < set(mouth) and INDEX["mouthClose"] in mouth
    t = np.arange(len(ahead)) / FPS
    # from the speech on (its closing into the last pause too), as heard LEAD_S later
    speech = (t >= 0.3) & (np.arange(len(t)) < len(t) - k)
    np.testing.assert_allclose(
        ahead[speech][:, mouth], in_step[k:][speech[:-k]][:, mouth], atol=1e-6
    )
    # the rest is not cut short by the lead: the mouth leaves rest REST_RAMP_S before the speech
    rest = t <= 0.3 - REST_RAMP_S
    assert np.abs(ahead[rest][:, MOUTH_CHANNELS]).max() == 0.0
    assert np.abs(ahead[(t > 0.3 - REST_RAMP_S) & (t < 0.3)][:, MOUTH_CHANNELS]).max() > 0.0
    assert np.abs(ahead[t >= 0.78 + REST_RAMP_S - LEAD_S][:, MOUTH_CHANNELS]).max() == 0.0
    assert np.abs(in_step[t < 0.78 + REST_RAMP_S - LEAD_S][-1, MOUTH_CHANNELS]).max() > 0.0
    upper = [c for c in range(52) if c not in set(mouth)]
    np.testing.assert_array_equal(ahead[:, upper], in_step[:, upper])
    # half a 60 fps frame ahead lies halfway between the frames
    w = np.zeros((4, 52), np.float32)
    w[:, INDEX["jawOpen"]] = [0.0, 0.2, 0.4, 0.4]
    lead(w, FPS, 0.5 / FPS)
    np.testing.assert_allclose(w[:, INDEX["jawOpen"]], [0.1, 0.3, 0.4, 0.4])


def test_closure_solve_reaches_the_target_from_a_wide_open_frame(head):
    w = np.zeros((3, 52), np.float32)
    w[:, INDEX["jawOpen"]] = 0.4
    w[:, INDEX["mouthFunnel"]] = 0.3
    mask = close_lips(w, [Phone("M", 0.0, 3 / FPS)], FPS, head)
    assert mask.all()
    assert _opening_mm(head, w).max() <= CLOSURE_MM
    assert ((w >= 0) & (w <= 1)).all()


def test_mouth_rests_in_long_pauses_not_in_short_ones(head):
    spec = [("AA", 0.2), (SILENCE, 0.4), ("AA", 0.2), (SILENCE, 0.1), ("AE", 0.2)]
    phones, raw, w = _animate(spec, head)
    t = np.arange(len(w)) / FPS
    long_pause = (t > 0.2 + REST_RAMP_S + 1e-6) & (t < 0.6 - REST_RAMP_S - 1e-6)
    assert np.abs(w[long_pause][:, MOUTH_CHANNELS]).max() == 0.0
    assert np.abs(raw[long_pause][:, MOUTH_CHANNELS]).max() > 0.01  # the animator drifts there
    short = (t > 0.82) & (t < 0.88)
    assert w[short][:, INDEX["jawOpen"]].max() > 0.0  # a 100 ms gap is no rest
    gate = pause_gate(phones, FPS, len(w))
    assert gate.min() == 0.0 and gate.max() == 1.0


def test_rounded_vowels_of_every_language_round_the_lips(head):
    for label in ("UY", "OE", "UW", "OW"):
        _, _, w = _animate([(SILENCE, 0.2), (label, 0.2), (SILENCE, 0.2)], head)
        mid = int(0.3 * FPS)
        assert w[mid, INDEX["mouthPucker"]] > 0.3, label
    _, _, spread = _animate([(SILENCE, 0.2), ("IY", 0.2), (SILENCE, 0.2)], head)
    assert spread[int(0.3 * FPS), INDEX["mouthPucker"]] < 0.05


def test_labiodentals_tuck_the_lower_lip(head):
    _, _, w = _animate([("AA", 0.15), ("F", 0.1), ("AA", 0.15)], head)
    assert w[int(0.2 * FPS), INDEX["mouthRollLower"]] > 0.4


def test_open_vowels_open_with_loudness(head):
    spec = [(SILENCE, 0.2), ("AA", 0.1), (SILENCE, 0.3), ("AA", 0.1), (SILENCE, 0.2)]
    sr = 16_000
    t = np.arange(int(0.9 * sr)) / sr
    tone = np.sin(2 * np.pi * 150 * t)
    audio = np.zeros_like(t)
    loud, soft = (t >= 0.2) & (t < 0.3), (t >= 0.6) & (t < 0.7)
    audio[loud] = 0.8 * tone[loud]
    audio[soft] = 0.1 * tone[soft]  # 18 dB softer
    phones, raw, w = _animate(spec, head, audio=audio.astype(np.float32))
    op = _opening_mm(head, w)
    a, b = op[int(0.2 * FPS) : int(0.3 * FPS)].max(), op[int(0.6 * FPS) : int(0.7 * FPS)].max()
    assert a > 1.3 * b  # the loud one at MAX_JAW, the soft one at about half its target
    assert a > _opening_mm(head, raw)[int(0.2 * FPS) : int(0.3 * FPS)].max()


@pytest.mark.parametrize(
    "symbol,label",
    [
        ("y", "UY"), ("y:", "UY"), ("Y", "UY"), ("2:", "OE"), ("9", "OE"), ("9~", "OE"),
        ("u:", "UW"), ("o", "OW"), ("O", "AO"), ("a:", "AA"), ("a~", "AA"), ("p", "P"),
        ("b", "B"), ("m", "M"), ("f", "F"), ("v", "V"), ("pf", "F"), ("_", SILENCE),
        ("p_h", "P"), ("bh", "B"), ("R", "G"), ("w", "W"), ("H", "W"), ("zz!", "Z"),
    ],
)  # fmt: skip
def test_sampa_of_any_voice_maps_to_the_animator_labels(symbol, label):
    assert sampa_label(symbol) == label


def test_an_unknown_symbol_is_speech_not_silence():
    assert sampa_label("QQQ") not in (SILENCE, "")


def test_bounded_lstsq_finds_what_scipy_finds():
    """The closure's bounded least squares (talkmesh's own, to spare importing scipy.optimize)
    reaches the minimum scipy's BVLS reaches, on boxes that bind and boxes that do not."""
    from scipy.optimize import lsq_linear

    from talkmesh.face.teacher import bounded_lstsq

    rng = np.random.default_rng(1)
    bound_somewhere = 0
    for k in range(300):
        n = int(rng.integers(1, 9))
        a = rng.standard_normal((n + int(rng.integers(0, 5)), n)) * 10 ** rng.uniform(-3, 1)
        b = rng.standard_normal(len(a))
        lo, hi = -rng.uniform(0, 1, n) * (k % 3 > 0), rng.uniform(0, 1, n)
        x = bounded_lstsq(a, b, lo, hi)
        want = lsq_linear(a, b, bounds=(lo, hi), method="bvls", tol=1e-14).x
        assert np.all(x >= lo) and np.all(x <= hi)
        cost, best = np.sum((a @ x - b) ** 2), np.sum((a @ want - b) ** 2)
        assert cost <= best * (1 + 1e-9) + 1e-24
        np.testing.assert_allclose(x, want, atol=1e-7)
        bound_somewhere += bool(np.any((x == lo) | (x == hi)))
    assert 50 < bound_somewhere < 300  # both kinds of problem were met
