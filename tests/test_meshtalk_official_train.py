"""MeshTalk with every official-exact option (the paper recipes' network: 1 s audio windows,
per-vertex statistics, the official U-Net output, the official prior wiring) trains through
talkmesh's training tasks: both stages step on a fixed batch with finite, falling losses, and
gradients reach every trainable parameter, the official prior's included."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from talkmesh.datasets.reader import Sample
from talkmesh.training.trainer import DatasetInfo, collate_torch, load_recipes, task_spec

ROOT = Path(__file__).resolve().parents[1]
V, FPS, T, SR = 30, 30.0, 10, 16000
TINY_AUDIO = {"width": 16, "out_dim": 16}
TINY_EXPRESSION = {  # sizes only: every architecture option stays the recipe's
    # 4 heads: in the official prior the last layer's head H-1 feeds no classifier head (each
    # head reads heads < h), so with 2 heads that layer's masked map would get no gradient
    "num_heads": 4,
    "num_classes": 8,
    "expression_widths": [32, 16],
    "expression_output": 16,
    "fusion_width": 32,
    "decoder_widths": [32, 16, 16],
}


class TinyData:
    """Two speakers' sequences on one 30-vertex topology, motion that follows the audio's
    loudness."""

    def __init__(self) -> None:
        g = np.random.default_rng(0)
        templates = g.normal(size=(2, V, 3)).astype(np.float32)
        pattern = g.normal(size=(V, 3)).astype(np.float32)
        self.samples = []
        for i, template in enumerate(templates):
            t = np.arange(T, dtype=np.float32)
            level = 0.5 + 0.5 * np.sin(0.6 * t + i)  # (T,)
            audio = g.normal(size=int(T * SR / FPS)).astype(np.float32)
            audio *= np.repeat(level, math.ceil(len(audio) / T))[: len(audio)] * 0.1
            vertices = template + 0.05 * level[:, None, None] * pattern
            self.samples.append(Sample(f"s{i}", "a", f"{i}", audio, vertices, template, 0))

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, i: int) -> Sample:
        return self.samples[i]


def recipe_models() -> tuple[dict, dict]:
    """The released recipe's two model sections at a tiny size."""
    stages = dict(load_recipes(ROOT / "configs" / "meshtalk_released.yaml"))
    expression = dict(stages["expression"].model, **TINY_EXPRESSION)
    expression["audio"] = dict(expression["audio"], **TINY_AUDIO)
    prior = dict(stages["prior"].model, width=8)
    prior["audio"] = dict(prior["audio"], **TINY_AUDIO)
    return expression, prior


def run_steps(task, system, batch, steps: int, lr: float) -> tuple[list[float], set[str]]:
    """Adam steps on one batch -> the losses and the trainable parameters without a gradient
    at the first step."""
    trained = {id(p) for p in task.parameters(system)}
    params = {n: p for n, p in system.named_parameters() if p.requires_grad and id(p) in trained}
    optimizer = torch.optim.Adam(params.values(), lr=lr)
    losses, silent = [], set()
    for step in range(steps):
        torch.manual_seed(step)  # the expression space's Gumbel noise
        optimizer.zero_grad()
        loss = task.step(system, batch).loss
        loss.backward()
        if step == 0:
            silent = {n for n, p in params.items() if p.grad is None or not p.grad.abs().sum() > 0}
        optimizer.step()
        losses.append(float(loss.detach()))
    return losses, silent


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Tiny layers: a second thread only waits on the first (seconds per step on a busy machine)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def trained(tmp_path_factory, one_thread):
    """The expression stage trained a few steps and released, as ``talkmesh train`` does."""
    torch.manual_seed(0)
    data = TinyData()
    info = DatasetInfo(V, FPS, ("a",))
    expression, prior = recipe_models()
    task = task_spec("meshtalk")
    system = task.build(expression, info, None)
    task.prepare(system, data)
    system.train()
    losses, silent = run_steps(task, system, collate_torch(data.samples), 20, 3e-3)
    path = tmp_path_factory.mktemp("official") / "expression.safetensors"
    task.save(system, path)
    return data, info, prior, path, losses, silent, system


def test_the_recipe_network_is_the_official_one(trained):
    system = trained[-1]
    cfg = system.model.config
    assert cfg.audio.windows and cfg.audio.gain == 0.01 and not cfg.audio.mel_statistics
    assert cfg.vertex_norm == "per_vertex" and cfg.official_decoder and cfg.expression_output
    # no per-bin mel statistics: the encoder reads the log-mels as they are
    enc = system.model.audio_encoder
    assert torch.equal(enc.mel_mean, torch.zeros(80)) and torch.equal(enc.mel_std, torch.ones(80))
    assert system.model.template_scale.shape == (V, 3)  # per-coordinate statistics


def test_expression_space_trains(trained):
    losses, silent = trained[4], trained[5]
    assert all(math.isfinite(x) for x in losses)
    assert min(losses[-5:]) < 0.7 * losses[0], losses
    assert not silent, f"no gradient reaches {sorted(silent)}"


def test_official_prior_trains_and_samples(trained):
    data, info, prior, path = trained[:4]
    task = task_spec("meshtalk-prior")
    system = task.build(prior, info, path)
    assert system.cfg.prior.layout == "official" and system.cfg.sampling.gumbel
    task.prepare(system, data)
    system.train()
    batch = collate_torch(data.samples)
    losses, silent = run_steps(task, system, batch, 20, 1e-2)
    assert {n for n, _ in system.prior.named_parameters()}, "the prior has parameters"
    assert not silent, f"no gradient reaches {sorted(silent)}"
    assert all(math.isfinite(x) for x in losses)
    assert min(losses[-5:]) < 0.7 * losses[0], losses
    frozen = [n for n, p in system.model.named_parameters() if p.requires_grad]
    assert not frozen, "the expression space stays frozen"
    system.eval()
    out = system.generate(batch.audio[:1], batch.templates[:1], seed=0)
    assert out.shape[2:] == (V, 3) and torch.isfinite(out).all()
    again = system.generate(batch.audio[:1], batch.templates[:1], seed=0)
    assert torch.equal(out, again)
