"""The synthetic corpus: exact phone timings, VOCASET layout, byte-identical per seed."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from talkmesh.audio.phonemes import ARPABET_PHONES, SILENCE
from talkmesh.audio.voices import VOICES, available_voices, phone_coverage, synthesize
from talkmesh.datasets.reader import open_dataset, safe_load_pickle
from talkmesh.datasets.sentences import generate_sentences
from talkmesh.datasets.synth import augment_audio, make_corpus, split_subjects
from talkmesh.errors import TalkmeshError

needs_voices = pytest.mark.skipif(
    len(available_voices()) < 12 or not shutil.which("festival"),
    reason="mbrola/festival not installed",
)


def digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("corpus") / "c"
    make_corpus(root, subjects=3, sentences=2, seed=7, workers=1, progress=False)
    return root


def test_sentences_distinct_varied_and_seeded():
    s = generate_sentences(600, seed=1)
    assert len(set(s)) == 600
    assert s == generate_sentences(600, seed=1) and s != generate_sentences(600, seed=2)
    words = [len(x.split()) for x in s]
    assert 5 <= min(words) and max(words) <= 20


@needs_voices
def test_twelve_voices_with_exact_timings_cover_every_phone(tmp_path):
    texts = generate_sentences(12, seed=3)
    all_phones = []
    durations = set()
    for k, voice in enumerate(VOICES[:12]):  # the default corpus's voices
        wav = tmp_path / f"{voice.name}.wav"
        ((phones, sr),) = synthesize(voice, [(texts[k], wav)])
        info = sf.info(wav)
        assert phones[0].start == 0 and phones[-1].end == pytest.approx(
            info.frames / info.samplerate
        )
        assert all(a.end == b.start for a, b in zip(phones, phones[1:]))
        assert all(p.label in ARPABET_PHONES or p.label == SILENCE for p in phones)
        durations.add(round(info.frames / info.samplerate, 2))
        all_phones += phones
    assert len(durations) >= 10  # the voices really differ
    big = []
    for k, voice in enumerate(VOICES[:4]):
        ((phones, _),) = synthesize(
            voice, [(" ".join(generate_sentences(40, seed=k)), tmp_path / "x.wav")]
        )
        big += phones
    cover = phone_coverage(all_phones + big)
    missing = set(ARPABET_PHONES) - set(cover)
    assert not missing, missing
    assert cover["P"] + cover["B"] + cover["M"] > 40


@needs_voices
def test_corpus_layout_and_reader(corpus):
    manifest = json.loads((corpus / "manifest.json").read_text())
    assert manifest["fps"] == 60 and manifest["motion_fps"] == 30
    assert (
        len(manifest["subjects"]) == 3
        and len({m["voice"] for m in manifest["subjects"].values()}) == 3
    )
    templates = safe_load_pickle(corpus / "templates.pkl")
    assert set(templates) == set(manifest["subjects"])
    for sub in ("wav", "vertices_npy", "arkit"):
        assert len(list((corpus / sub).iterdir())) == 6
    name = "Synth_01_ada_sentence01"
    motion = np.load(corpus / "vertices_npy" / f"{name}.npy")
    weights = np.load(corpus / "arkit" / f"{name}.npy")
    assert motion.dtype == np.float32 and motion.shape[1] == 4766 * 3
    assert weights.shape == (len(motion), 52)
    info = sf.info(corpus / "wav" / f"{name}.wav")
    assert abs(len(motion) / 60 - info.frames / info.samplerate) < 1 / 60
    ds = open_dataset("synth", corpus, "train")
    assert ds.names[0] == name and ds[0].vertices.shape[0] == (len(motion) + 1) // 2
    assert ds.regions.lve is not None and len(ds.regions.fdd) > 100
    # the lips close and open: ground truth is real lip sync
    from talkmesh.face.assets import lip_opening, load_head

    opening = lip_opening(motion.reshape(len(motion), -1, 3), load_head().regions)
    assert opening.max() - opening.min() > 0.005


@needs_voices
def test_same_seed_same_bytes(corpus, tmp_path):
    again = tmp_path / "again"
    make_corpus(again, subjects=3, sentences=2, seed=7, workers=2, progress=False)
    assert digest(again) == digest(corpus)


def test_refuses_non_empty_output(tmp_path):
    (tmp_path / "keep.txt").write_text("mine")
    with pytest.raises(TalkmeshError, match="not empty"):
        make_corpus(tmp_path, subjects=1, sentences=1, progress=False)
    assert (tmp_path / "keep.txt").read_text() == "mine"


def test_splits_like_vocaset():
    assert split_subjects(12) == (8, 2, 2)
    assert sum(split_subjects(5)) == 5 and min(split_subjects(5)) >= 1


def test_augmentation_is_seeded_and_bounded():
    x = np.sin(np.linspace(0, 200, 16000)).astype(np.float32) * 0.5
    a = augment_audio(x, 16000, np.random.default_rng(0), reverb=1.0)
    b = augment_audio(x, 16000, np.random.default_rng(0), reverb=1.0)
    np.testing.assert_array_equal(a, b)
    assert a.dtype == np.float32 and a.shape == x.shape and np.abs(a).max() <= 1.0
    assert not np.allclose(a, x)
    snr = 10 * np.log10(
        np.mean(x**2)
        / np.mean(
            (augment_audio(x, 16000, np.random.default_rng(1), gain_db=(0, 0), reverb=0) - x) ** 2
        )
    )
    assert 19 < snr < 41


@pytest.mark.skipif(
    not (shutil.which("flite") and shutil.which("pico2wave")), reason="flite/pico not installed"
)
def test_aligned_voices_beyond_the_default_twelve(tmp_path):
    """Voices without their own phone times get the text forced onto their audio; the default
    corpus keeps its twelve voices in their order, the others come after them."""
    from talkmesh.audio.voices import get_voice

    assert [v.engine for v in VOICES[:12]].count("mbrola") == 8
    assert {v.engine for v in VOICES[12:]} >= {"festival", "espeak", "flite", "pico"}
    names = [v.name for v in available_voices()]
    assert names == [v.name for v in VOICES if v.name in names] and "pico-gb" in names
    text = generate_sentences(1, seed=5)[0]
    durations = []
    for name in ("flite-slt", "pico-gb"):
        wav = tmp_path / f"{name}.wav"
        ((phones, sr),) = synthesize(get_voice(name), [(text, wav)])
        info = sf.info(wav)
        assert sr == info.samplerate and phones[0].start == 0
        assert phones[-1].end == pytest.approx(info.frames / info.samplerate)
        assert all(a.end == b.start for a, b in zip(phones, phones[1:]))
        assert sum(p.label in ("P", "B", "M") for p in phones) >= 2
        durations.append([round(p.start, 2) for p in phones])
    assert durations[0] != durations[1]  # two different speakers' timing
    with pytest.raises(TalkmeshError, match="flite-slt: .*pronunciation dictionary"):
        synthesize(get_voice("flite-slt"), [("the qxzvbt", tmp_path / "z.wav")])
