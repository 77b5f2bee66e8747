"""CodeTalker's head term (``stage2.head_pairs``): the style hears how far the head's lips stand
apart at rest, in PyTorch, in ONNX Runtime and when a release is fine-tuned to learn it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import build_tiny_codetalker
from fixtures import TINY_WHISPER

from talkmesh.errors import TalkmeshError
from talkmesh.models.codetalker.model import HEAD_SCALE, CodeTalker, Stage2Config
from talkmesh.models.speech import SpeechEncoderConfig

PAIRS = (0, 1, 2, 3)  # two vertex pairs of the tiny mesh


def with_head(model: CodeTalker, weight: float) -> CodeTalker:
    """``model``'s weights with a head term on PAIRS, its map filled with ``weight``-scaled noise."""
    s2 = replace(model.cfg.stage2, head_pairs=PAIRS, head_mean=(0.1, 0.2), head_std=(0.05, 0.1))
    grown = CodeTalker(replace(model.cfg, stage2=s2)).eval()
    missing = grown.load_state_dict(model.state_dict(), strict=False).missing_keys
    assert sorted(missing) == ["head_map.bias", "head_map.weight"]
    torch.manual_seed(5)
    with torch.no_grad():
        grown.head_map.weight.copy_(torch.randn_like(grown.head_map.weight) * weight)
        grown.head_map.bias.copy_(torch.randn_like(grown.head_map.bias) * weight)
    return grown


def apart(template: torch.Tensor, gap: float) -> torch.Tensor:
    """``template`` (1, V, 3) with vertex 1 ``gap`` below vertex 0 (the first pair's distance)."""
    out = template.clone()
    out[0, 1] = out[0, 0] - torch.tensor([0.0, gap, 0.0])
    return out


def test_the_head_term_starts_at_zero_and_reads_the_lips_of_the_template():
    base = build_tiny_codetalker(causal=True)
    audio = torch.randn(1, 16000) * 0.1
    template = torch.randn(1, base.num_vertices, 3) * 0.1
    weights = torch.tensor([[0.5, 0.5]])
    fresh = with_head(base, 0.0)  # as a fine-tune begins: the same model
    assert torch.equal(
        fresh.generate(audio, template, style_weights=weights),
        base.generate(audio, template, style_weights=weights),
    )
    learned = with_head(base, 0.5)
    near, far = apart(template, 0.05), apart(template, 0.3)
    style_near = learned.style_vector(None, weights, near)
    style_far = learned.style_vector(None, weights, far)
    plain = base.style_vector(None, weights)
    assert not torch.allclose(style_near, style_far)
    # the term is linear in the standardised distances: (0.3 - 0.05) / 0.05 along pair 0's column
    step = (style_far - style_near)[0]
    want = learned.head_map.weight[:, 0] * (0.25 / 0.05) * HEAD_SCALE
    assert torch.allclose(step, want, atol=1e-4)
    # no template: the training templates' average head (standardised distances 0)
    no_head = learned.style_vector(None, weights)
    assert torch.allclose(no_head, plain + learned.head_map.bias, atol=1e-6)
    moved = learned.generate(audio, far, style_weights=weights) - far[:, None]
    still = learned.generate(audio, near, style_weights=weights) - near[:, None]
    assert not torch.allclose(moved, still)  # the head changes the motion, not just the offset


def test_head_pairs_need_a_mean_and_std_each():
    with pytest.raises(ValueError, match="head_pairs"):
        Stage2Config(styles=("a",), head_pairs=(0, 1, 2), head_mean=(0.0,), head_std=(1.0,))
    with pytest.raises(ValueError, match="head_pairs"):
        Stage2Config(styles=("a",), head_pairs=(0, 1), head_mean=(), head_std=())


def test_onnx_runtime_adds_the_head_term_as_pytorch_does(tmp_path):
    pytest.importorskip("onnxruntime")
    from talkmesh.models.onnx import export_onnx
    from talkmesh.models.release import load_model

    speech = SpeechEncoderConfig(kind="whisper", dim=16, hf_config=TINY_WHISPER)
    model = with_head(build_tiny_codetalker(speech=speech, causal=True, attention_window=7), 0.5)
    path = tmp_path / "head.onnx"
    export_onnx(model, path)
    runtime = load_model(path)
    template = apart(torch.randn(1, model.num_vertices, 3) * 0.1, 0.2)
    weights = torch.tensor([[0.7, 0.3]])
    with torch.no_grad():
        want = model.style_vector(None, weights, template).numpy()
    got = runtime.style(weights.numpy(), template.numpy()[0])
    assert np.abs(got - want).max() <= 1e-5
    assert np.abs(got - runtime.style(weights.numpy())).max() > 1e-3  # the template counts
    audio = torch.randn(1, 16000) * 0.1
    gen = model.generate(audio, template, style_weights=weights)
    onnx_gen = runtime.generate(audio, template, style_weights=weights)
    scale = (gen - template[:, None]).abs().max()
    assert (onnx_gen - gen).abs().max() <= 1e-4 * scale


def test_finetune_gives_a_release_the_head_term_of_its_training_heads(tiny_corpus, tmp_path):
    pytest.importorskip("lightning")
    from talkmesh.datasets.reader import open_dataset
    from talkmesh.models.release import load_model, save_model
    from talkmesh.training.trainer import load_recipe, train

    data = open_dataset("synth", tiny_corpus, "train")
    subjects = tuple(data.spec.train_subjects)
    torch.manual_seed(0)
    base = CodeTalker(CodeTalker.tiny_config(data.spec.num_vertices, subjects))
    save_model(base, tmp_path / "base.safetensors")
    recipe_file = tmp_path / "head.yaml"
    recipe_file.write_text(
        "task: codetalker-finetune\n"
        f"init: {tmp_path / 'base.safetensors'}\n"
        "model: {head_pairs: 3}\n"
        f"data: {{kind: synth, root: {tiny_corpus}, batch_size: 1, max_seconds: 1.0, val_split: ''}}\n"
        f"train: {{lr: 1.0e-3, epochs: 1, max_steps: 2, accelerator: cpu, out_dir: {tmp_path}/r}}\n"
    )
    tuned = load_model(train(load_recipe(recipe_file), progress=False))
    s2 = tuned.cfg.stage2
    pairs = np.asarray(s2.head_pairs).reshape(-1, 2)
    assert pairs.shape == (3, 2) and set(pairs.ravel()) <= set(data.regions.lve.tolist())
    templates = np.stack([data.templates[s] for s in subjects])
    dist = np.linalg.norm(templates[:, pairs[:, 0]] - templates[:, pairs[:, 1]], axis=-1)
    assert np.allclose(s2.head_mean, dist.mean(0), atol=1e-7)
    assert tuned.head_map.weight.abs().max() > 0  # it learned, from zero
    for bad in ("-1", "x", "true"):
        with pytest.raises(TalkmeshError, match="head_pairs must be a count"):
            train(
                load_recipe(recipe_file, [f"model.head_pairs={bad}", f"train.out_dir={tmp_path}/b"])
            )
    with pytest.raises(TalkmeshError, match="may only say head_pairs"):
        train(load_recipe(recipe_file, ["model.preset=small", f"train.out_dir={tmp_path}/c"]))


def test_stage2_from_a_motion_stage_can_start_with_the_head_term(tiny_corpus, tmp_path):
    from talkmesh.datasets.reader import open_dataset
    from talkmesh.models.release import save_model
    from talkmesh.training.codetalker import _build_stage2
    from talkmesh.training.trainer import dataset_info

    data = open_dataset("synth", tiny_corpus, "train")
    info = dataset_info(data)
    stage1 = CodeTalker(CodeTalker.tiny_config(data.spec.num_vertices, info.train_subjects))
    save_model(stage1, tmp_path / "stage1.safetensors")
    small = {
        "vq": dict(stage1.cfg.vq.__dict__),
        "stage2": {"d_model": 32, "heads": 2, "ff": 64, "layers": 1, "speech": {"kind": "mel"}},
        "head_pairs": 2,
    }
    net = _build_stage2(small, info, tmp_path / "stage1.safetensors")
    assert len(net.cfg.stage2.head_pairs) == 4 and net.head_map.weight.abs().max() == 0
    assert torch.equal(net.vqvae.quantizer.codebook, stage1.vqvae.quantizer.codebook)
    with pytest.raises(TalkmeshError, match="head_pairs must be a count"):
        _build_stage2({**small, "head_pairs": 1.5}, info, tmp_path / "stage1.safetensors")


def test_the_head_recipe_continues_the_bundled_model_with_eight_pairs():
    pytest.importorskip("yaml")
    from pathlib import Path

    from talkmesh.training.trainer import _init_path, load_recipe

    recipe = load_recipe(
        Path(__file__).parents[1] / "configs" / "codetalker_multilingual_head.yaml"
    )
    assert recipe.task == "codetalker-finetune" and recipe.model == {"head_pairs": 8}
    assert recipe.train.lip_gap_weight > 0 and recipe.data.augment.enabled
    assert _init_path(recipe.init).name == "codetalker-synth.safetensors"
