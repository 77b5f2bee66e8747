"""Fixtures shared by several test files: the tiny CodeTalker that the model, streaming, batching,
serving and long-audio tests build (one configuration, so that they test the same model), and a
tiny synthetic corpus the fine-tuning tests read."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from fixtures import TINY_WAV2VEC2

from talkmesh.models.codetalker.model import CodeTalker, CodeTalkerConfig, Stage2Config
from talkmesh.models.codetalker.vq import VQConfig
from talkmesh.models.speech import SpeechEncoderConfig

TINY_V = 20  # vertices of the tiny model's face
# the streaming tests' speech encoder: mel features, look-ahead chosen at run time up to 200 ms
STREAM_SPEECH = SpeechEncoderConfig(kind="mel", dim=16, lookahead_ms=0.0, lookahead_max_ms=200.0)


def build_tiny_codetalker(
    *,
    vq_layers: int = 1,
    speech: str | SpeechEncoderConfig = "mel",
    causal: bool = False,
    attention_window: int | None = None,
    num_vertices: int = TINY_V,
) -> CodeTalker:
    """A seeded tiny CodeTalker in eval mode. ``speech``: a kind (mel, wav2vec2: tiny encoders of
    width 16) or a whole config; ``attention_window`` None keeps Stage2Config's default. The
    zero-initialised output map (and look-ahead embedding) are randomised: else every frame is
    alike and equality tests would pass on anything."""
    if isinstance(speech, str):
        hf = TINY_WAV2VEC2 if speech == "wav2vec2" else {}
        speech = SpeechEncoderConfig(kind=speech, dim=16, hf_config=hf)
    window = {} if attention_window is None else {"attention_window": attention_window}
    torch.manual_seed(0)
    cfg = CodeTalkerConfig(
        vq=VQConfig(
            num_vertices=num_vertices,
            hidden=32,
            layers=vq_layers,
            heads=2,
            ff=64,
            components=4,
            code_dim=8,
            codebook_size=16,
            causal=causal,
            causal_window=6,
        ),
        stage2=Stage2Config(
            d_model=32,
            heads=2,
            ff=64,
            layers=2,
            period=5,
            styles=("a", "b"),
            speech=speech,
            **window,
        ),
    )
    model = CodeTalker(cfg)
    for p in model.feat_map.parameters():
        torch.nn.init.normal_(p, std=0.5)
    if hasattr(model.speech, "shift_embedding"):
        torch.nn.init.normal_(model.speech.shift_embedding.weight, std=0.5)
    return model.eval()


@pytest.fixture
def tiny_codetalker() -> Callable[..., CodeTalker]:
    """:func:`build_tiny_codetalker`, called with the options a test needs."""
    return build_tiny_codetalker


@pytest.fixture
def tiny_stream_model(tmp_path) -> Callable[..., Path]:
    """``tiny_stream_model(causal=True, num_vertices=TINY_V)``: the release file of a tiny
    streaming CodeTalker (causal VQ decoder, 7-frame attention window, run-time look-ahead)."""
    count = iter(range(1_000))

    def make(causal: bool = True, num_vertices: int = TINY_V) -> Path:
        from talkmesh.models.release import save_model

        model = build_tiny_codetalker(
            causal=causal, attention_window=7, speech=STREAM_SPEECH, num_vertices=num_vertices
        )
        return save_model(model, tmp_path / f"stream{next(count)}.safetensors")

    return make


@pytest.fixture(autouse=True, scope="session")
def _own_cache(tmp_path_factory):
    """Registrations saved by `talkmesh rig` and `animate --head` (talkmesh.face.rig_cache) go to
    a folder of this test run, never the user's cache."""
    os.environ["TALKMESH_CACHE"] = str(tmp_path_factory.mktemp("cache"))


@pytest.fixture(scope="session")
def tiny_corpus(tmp_path_factory) -> Path:
    """A 3-speaker, 2-sentence synthetic corpus (MBROLA voices), built once; tests only read it."""
    if not shutil.which("mbrola"):
        pytest.skip("mbrola not installed")
    from talkmesh.datasets.synth import make_corpus

    root = tmp_path_factory.mktemp("tiny_corpus") / "c"
    make_corpus(root, subjects=3, sentences=2, seed=3, workers=1, progress=False)
    return root


def decoder_recipe(path: Path, init, root, out, extra: str = "") -> None:
    """Write a 3-step ``codetalker-decoder`` recipe to ``path`` (``extra``: more YAML lines, e.g.
    a model section) refitting ``init`` on the corpus at ``root`` into ``out``."""
    path.write_text(
        "task: codetalker-decoder\n"
        f"init: {init}\n{extra}"
        f"data: {{kind: synth, root: {root}, batch_size: 2, max_seconds: 1.0, val_split: ''}}\n"
        "train: {lr: 1.0e-2, epochs: 1, max_steps: 3, accelerator: cpu, lip_gap_weight: 0.5, "
        f"out_dir: {out}}}\n"
    )
