"""``task: codetalker-decoder``: a release's VQ decoder refitted on data (with the lip-gap loss),
everything else as it was, so the release's code queries stay valid; and stage 1 takes the
lip-gap loss too."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import decoder_recipe

from talkmesh.errors import TalkmeshError
from talkmesh.models.codetalker.model import CodeTalker


def _tiny_release(root, path):
    """(the tiny corpus's training split, a tiny CodeTalker saved as a release at ``path``)."""
    pytest.importorskip("lightning")
    from talkmesh.datasets.reader import open_dataset
    from talkmesh.models.release import save_model

    data = open_dataset("synth", root, "train")
    torch.manual_seed(0)
    base = CodeTalker(CodeTalker.tiny_config(data.spec.num_vertices, data.spec.train_subjects))
    save_model(base, path)
    return data, base


def _refit(recipe):
    """The release a recipe trains."""
    from talkmesh.models.release import load_model
    from talkmesh.training.trainer import load_recipe, train

    return load_model(train(load_recipe(recipe), progress=False))


def test_refit_changes_the_vq_decoder_alone(tiny_corpus, tmp_path):
    _, base = _tiny_release(tiny_corpus, tmp_path / "base.safetensors")
    decoder_recipe(
        tmp_path / "r.yaml", tmp_path / "base.safetensors", tiny_corpus, tmp_path / "run"
    )
    refit = _refit(tmp_path / "r.yaml")
    before, after = base.state_dict(), refit.state_dict()
    assert before.keys() == after.keys()
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    assert changed and all(k.startswith("vqvae.decoder.") for k in changed), changed
    assert "vqvae.decoder.out.weight" in changed  # the lip-gap loss reaches the output map
    assert torch.equal(refit.vqvae.quantizer.codebook, base.vqvae.quantizer.codebook)
    assert refit.cfg == base.cfg


def test_refit_refuses_a_model_section_no_init_and_other_vertex_counts(tiny_corpus, tmp_path):
    pytest.importorskip("lightning")
    from talkmesh.datasets.reader import open_dataset
    from talkmesh.models.release import save_model
    from talkmesh.training.trainer import load_recipe, train

    data = open_dataset("synth", tiny_corpus, "train")
    base = CodeTalker(CodeTalker.tiny_config(data.spec.num_vertices, data.spec.train_subjects))
    save_model(base, tmp_path / "base.safetensors")
    other = CodeTalker(CodeTalker.tiny_config(data.spec.num_vertices + 3, ("a",)))
    save_model(other, tmp_path / "other.safetensors")
    recipe = tmp_path / "r.yaml"
    decoder_recipe(
        recipe, tmp_path / "base.safetensors", tiny_corpus, tmp_path / "a", "model: {x: 1}\n"
    )
    with pytest.raises(TalkmeshError, match="takes its model from init"):
        train(load_recipe(recipe), progress=False)
    decoder_recipe(recipe, tmp_path / "other.safetensors", tiny_corpus, tmp_path / "b")
    with pytest.raises(TalkmeshError, match="vertex model, the data has"):
        train(load_recipe(recipe), progress=False)
    decoder_recipe(recipe, "null", tiny_corpus, tmp_path / "c")
    with pytest.raises(TalkmeshError, match="needs init"):
        train(load_recipe(recipe), progress=False)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_stage1_takes_the_lip_gap_loss(tiny_corpus, tmp_path):
    pytest.importorskip("lightning")
    import csv

    from talkmesh.training.trainer import load_recipe, train

    recipe = tmp_path / "s1.yaml"
    recipe.write_text(
        "task: codetalker-stage1\n"
        "model: {preset: small, vq: {hidden: 32, layers: 1, heads: 2, ff: 64, components: 2, "
        "code_dim: 8, codebook_size: 16}}\n"
        f"data: {{kind: synth, root: {tiny_corpus}, batch_size: 2, max_seconds: 1.0, val_split: ''}}\n"
        "train: {lr: 1.0e-3, epochs: 1, max_steps: 2, log_every: 1, accelerator: cpu, "
        f"lip_gap_weight: 0.5, out_dir: {tmp_path}/s1}}\n"
    )
    train(load_recipe(recipe), progress=False)
    rows = list(csv.DictReader((tmp_path / "s1" / "logs" / "metrics.csv").open()))
    gaps = [float(r["train/lip_gap"]) for r in rows if r.get("train/lip_gap")]
    assert gaps and all(g > 0 for g in gaps)


def test_the_refit_recipe_refits_the_bundled_models_decoder_with_the_lip_gap_loss():
    pytest.importorskip("yaml")
    from pathlib import Path

    from talkmesh.training.trainer import _init_path, load_recipe, task_spec

    recipe = load_recipe(Path(__file__).parents[1] / "configs" / "codetalker_decoder_refit.yaml")
    assert recipe.task == "codetalker-decoder" and recipe.model == {}
    assert recipe.train.lip_gap_weight > 0 and recipe.train.code_ce_weight == 0
    assert _init_path(recipe.init).name == "codetalker-synth.safetensors"
    assert task_spec(recipe.task).name == "codetalker-decoder"


def test_stage1_starts_from_the_motion_stage_of_any_release_with_its_vq(tmp_path):
    from dataclasses import replace

    from talkmesh.models.release import save_model
    from talkmesh.training.codetalker import _build_stage1
    from talkmesh.training.trainer import DatasetInfo

    torch.manual_seed(0)
    other = CodeTalker(CodeTalker.tiny_config(12, ("x",)))  # other speakers than the data's
    save_model(other, tmp_path / "other.safetensors")
    info = DatasetInfo(num_vertices=12, motion_fps=30.0, train_subjects=("a", "b"))
    model = {"vq": dict(other.cfg.vq.__dict__), "stage2": {"d_model": 32, "heads": 2, "ff": 64}}
    net = _build_stage1(model, info, tmp_path / "other.safetensors")
    assert net.cfg.stage2.styles == ("a", "b")
    for key, value in other.vqvae.state_dict().items():
        assert torch.equal(net.vqvae.state_dict()[key], value), key
    bigger = {
        **model,
        "vq": dict(replace(other.cfg.vq, code_dim=other.cfg.vq.code_dim * 2).__dict__),
    }
    with pytest.raises(TalkmeshError, match="VQ-VAE config differs"):
        _build_stage1(bigger, info, tmp_path / "other.safetensors")


def test_refit_on_the_speech_stages_codes_changes_the_vq_decoder_alone(tiny_corpus, tmp_path):
    """``task: codetalker-decoder-speech``: the decoder learns from the codes the speech stage
    predicts; every other weight stays, and the decoder moves towards the truth on those codes."""
    data, base = _tiny_release(tiny_corpus, tmp_path / "base.safetensors")
    recipe = tmp_path / "r.yaml"
    decoder_recipe(recipe, tmp_path / "base.safetensors", tiny_corpus, tmp_path / "run")
    recipe.write_text(recipe.read_text().replace("codetalker-decoder", "codetalker-decoder-speech"))
    refit = _refit(recipe)
    before, after = base.state_dict(), refit.state_dict()
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    assert changed and all(k.startswith("vqvae.decoder.") for k in changed), changed
    assert refit.cfg == base.cfg
    # its loss is the decoder's on the predicted codes, which the refit lowered
    sample = data[0]
    audio = torch.tensor(np.asarray(sample.audio))[None]
    verts = torch.tensor(np.asarray(sample.vertices)).float().view(1, len(sample.vertices), -1, 3)
    template = torch.tensor(np.asarray(sample.template)).float()[None]
    styles = torch.tensor([data.spec.train_subjects.index(sample.subject)])

    def loss(net: CodeTalker) -> float:
        net.eval()
        with torch.no_grad():
            return float(net(audio, None, verts, template, styles).motion_loss)

    assert loss(refit) < loss(base)


def test_train_trainable_changes_the_named_parameters_alone(tiny_corpus, tmp_path):
    """``train.trainable``: of what the task trains, only the parameters so named learn; a name
    that matches none of them is one line before any training."""
    data, base = _tiny_release(tiny_corpus, tmp_path / "base.safetensors")
    recipe = tmp_path / "r.yaml"
    decoder_recipe(recipe, tmp_path / "base.safetensors", tiny_corpus, tmp_path / "run")
    recipe.write_text(
        recipe.read_text().replace("lip_gap_weight: 0.5,", "trainable: [vqvae.decoder.out],")
    )
    refit = _refit(recipe)
    before, after = base.state_dict(), refit.state_dict()
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    assert changed == {"vqvae.decoder.out.weight", "vqvae.decoder.out.bias"}, changed
    decoder_recipe(recipe, tmp_path / "base.safetensors", tiny_corpus, tmp_path / "none")
    recipe.write_text(recipe.read_text().replace("lip_gap_weight: 0.5,", "trainable: [style],"))
    with pytest.raises(TalkmeshError, match="names none of the parameters"):
        _refit(recipe)
