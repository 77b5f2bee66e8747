"""The multilingual corpus: reserved voices refused, each phone gets the time the synthesiser gave
it, the teacher's truth holds on what was written."""

import json
import subprocess

import numpy as np
import pytest
import soundfile as sf

from talkmesh.audio.languages import (
    LANGUAGES,
    RESERVED_VOICES,
    check_not_reserved,
    never_trained_languages,
    trained_languages,
)
from talkmesh.audio.phonemes import SILENCE
from talkmesh.audio.voices import _phones_from_pho, mbrola_voice
from talkmesh.datasets.multilingual import (
    make_multilingual_corpus,
    plan_subjects,
    read_phones,
    utterances,
)
from talkmesh.errors import TalkmeshError
from talkmesh.face.assets import lip_opening, load_head


@pytest.mark.parametrize("db,lang", [("de1", "de"), ("en1", "en"), ("tr1", "tr"), ("sw2", "sv")])
def test_reserved_voices_and_languages_are_refused(db, lang):
    with pytest.raises(TalkmeshError, match="reserved"):
        mbrola_voice(db, lang)
    with pytest.raises(TalkmeshError, match="reserved"):
        check_not_reserved("de2", "tr")


def test_the_plan_uses_no_reserved_voice_and_keeps_languages_out():
    plan = plan_subjects()
    dbs = {db for _, _, db in plan}
    assert not dbs & RESERVED_VOICES
    assert not any(db.startswith(("tr", "hu", "ro", "sw", "gr", "cz")) for db in dbs)
    assert len(trained_languages()) >= 15
    assert len(never_trained_languages()) >= 4
    train = {code for split, code, _ in plan if split == "train"}
    test_only = {lang.code for lang in never_trained_languages()}
    assert not train & test_only
    # a held-out voice is never a training voice
    assert not {db for s, _, db in plan if s == "test"} & {db for s, _, db in plan if s != "test"}
    assert len({lang.family for lang in LANGUAGES}) >= 8


def test_utterances_pair_distinct_sentences():
    texts = utterances(("A.", "B.", "C."), 6, np.random.default_rng(0))
    assert len(set(texts)) == 6
    assert all(t.split()[0] != t.split()[1] for t in texts)


def test_each_phone_gets_the_time_the_pho_gives_it():
    pho = "_\t50\ny:\t120\t0 110 100 100\nm\t80\n2:\t95\np\t70\n_\t300\n"
    phones = _phones_from_pho(pho, "de")
    assert [p.label for p in phones] == [SILENCE, "UY", "M", "OE", "P", SILENCE]
    durations = [round((p.end - p.start) * 1000, 6) for p in phones]
    assert durations == [50, 120, 80, 95, 70, 300]
    assert all(a.end == b.start for a, b in zip(phones, phones[1:]))


def test_corpus_phones_match_the_synthesiser_and_the_truth_meets_the_rules(tmp_path):
    info = make_multilingual_corpus(
        tmp_path / "ml", utterances_per_voice=1, languages=["de"], workers=1, progress=False
    )
    assert info.subjects >= 2
    manifest = json.loads((tmp_path / "ml" / "manifest.json").read_text())
    assert manifest["teacher"] and set(manifest["splits"]["test"])
    name, text = next(iter(manifest["sentences"].items()))
    subject = manifest["subjects"][name.rsplit("_", 1)[0]]
    voice = subject["voice"].removeprefix("mb-").split("-")[0]
    spec = mbrola_voice(voice, "de", *map(int, subject["voice"].split("-p")[1].split("-s")))
    pho = subprocess.run(
        ["espeak-ng", "-v", spec.voice, "-p", str(spec.pitch), "-s", str(spec.speed), "-q"]
        + ["--pho", text],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    rows = [line.split() for line in pho.splitlines() if len(line.split()) >= 2]
    phones = read_phones(tmp_path / "ml", name)
    # the pho's phones, silences merged: the speech phones keep their exact durations
    speech = [p for p in phones if p.label != SILENCE]
    pho_speech = [float(r[1]) for r in rows if r[0] != "_"]
    assert np.allclose([(p.end - p.start) * 1000 for p in speech], pho_speech, atol=1e-3)
    audio, sr = sf.read(tmp_path / "ml" / "wav" / f"{name}.wav")
    assert abs(len(audio) / sr - phones[-1].end) < 0.02
    # the written truth closes the lips on every /p b m/ and rests in pauses
    head = load_head(subject["identity"])
    verts = np.load(tmp_path / "ml" / "vertices_npy" / f"{name}.npy")
    verts = verts.reshape(len(verts), -1, 3)
    opening = lip_opening(verts, head.regions) * 1000
    centres = (np.arange(len(verts)) + 0.5) / 60.0
    closures = [p for p in phones if p.label in {"P", "B", "M"}]
    assert closures
    for p in closures:
        inside = (centres >= p.start) & (centres < p.end)
        assert opening[inside].max() <= 0.5


def test_warm_start_copies_every_matching_tensor_but_a_new_style_table():
    """A recipe's warm_start: a model for other speakers starts from a release where shapes
    match; its style table (one row per training voice) and frozen parts keep their own."""
    from dataclasses import replace
    from pathlib import Path

    import torch

    from talkmesh.models.codetalker import CodeTalker
    from talkmesh.models.release import load_model
    from talkmesh.training.trainer import warm_start

    release = Path(__file__).parent / "fixtures" / "old_releases" / "codetalker.safetensors"
    old = load_model(release)
    cfg = replace(old.cfg, stage2=replace(old.cfg.stage2, styles=("x", "y", "z")))
    torch.manual_seed(0)
    net = CodeTalker(cfg)
    style_before = net.style.weight.detach().clone()
    net.vqvae.requires_grad_(False)  # as stage 2 freezes the VQ-VAE from its init
    vq_before = {k: v.clone() for k, v in net.vqvae.state_dict().items()}
    copied, kept = warm_start(net, release)
    assert "style.weight" in kept and copied > 10
    assert torch.equal(net.style.weight, style_before)
    for name, tensor in net.state_dict().items():
        if name.startswith("vqvae."):
            assert torch.equal(tensor, vq_before[name.removeprefix("vqvae.")])
        elif name != "style.weight":
            assert torch.equal(tensor, old.state_dict()[name].to(tensor.dtype)), name
