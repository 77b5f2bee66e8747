"""FaceFormer's released weights (``vocaset.pth`` / ``biwi.pth``, the official trainer's
``torch.save(model.state_dict())``) -> a :class:`~talkmesh.models.faceformer.model.FaceFormer`
whose exact generation computes what the official ``predict`` computes
(:func:`talkmesh.models.official.import_checkpoint` with ``family="faceformer"``)."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from talkmesh.errors import TalkmeshError
from talkmesh.models.checkpoint_io import _fill, _leftover, _take, load_checkpoint
from talkmesh.models.faceformer.model import FaceFormer, FaceFormerConfig
from talkmesh.models.official import (
    FPS,
    MAX_FRAMES,
    SUBJECTS,
    TOKENS_PER_FRAME,
    check_ppe,
    wav2vec2_config,
)
from talkmesh.models.speech import SpeechEncoderConfig

DATASETS = ("vocaset", "biwi")  # the releases' datasets


def import_official(paths: list[Path], dataset: str) -> nn.Module:
    """The one released file -> a :class:`FaceFormer` in eval mode."""
    if len(paths) != 1:
        raise TalkmeshError(
            f"a FaceFormer release is one file (vocaset.pth or biwi.pth), got {len(paths)}"
        )
    return import_faceformer(paths[0], dataset)


def import_faceformer(path: Path, dataset: str) -> nn.Module:
    """FaceFormer's released ``vocaset.pth`` / ``biwi.pth`` -> a :class:`FaceFormer`."""
    state = load_checkpoint(path)
    feature_map = state.get("audio_feature_map.weight")
    vertice_map = state.get("vertice_map.weight")
    styles = state.get("obj_vector.weight")
    if feature_map is None or vertice_map is None or styles is None:
        raise TalkmeshError(
            f"{path}: not a FaceFormer checkpoint (no audio_feature_map, "
            "vertice_map or obj_vector tensors): check --family"
        )
    d, vertex_dims = vertice_map.shape
    names = SUBJECTS[dataset]
    if styles.shape != (d, len(names)):
        raise TalkmeshError(
            f"{path}: obj_vector is {tuple(styles.shape)}, a {dataset} model has "
            f"{len(names)} training subjects ({d}, {len(names)}): is --dataset right?"
        )
    layers = 0
    while f"transformer_decoder.layers.{layers}.linear1.weight" in state:
        layers += 1
    fps, k = FPS[dataset], TOKENS_PER_FRAME[dataset]
    period = int(fps)
    cfg = FaceFormerConfig(
        num_vertices=vertex_dims // 3,
        styles=names,
        motion_fps=fps,
        d_model=d,
        heads=4,  # the official code fixes nhead=4
        ff=state["transformer_decoder.layers.0.linear1.weight"].shape[0] if layers else 2 * d,
        layers=layers,
        period=period,
        audio_tokens_per_frame=k,
        speech=SpeechEncoderConfig(
            kind="wav2vec2",
            frame_rate=fps * k,
            hf_config=wav2vec2_config(state, "audio_encoder.", path),
            resample="cnn",
            normalize=True,
        ),
        attention_window=MAX_FRAMES,
        postnorm=True,
        interleaved_ppe=True,
        frame0_motion_bias=False,
    )
    model = FaceFormer(cfg)
    check_ppe(_take(state, "PPE.pe", path), period, d, dataset, path)
    mapped = {"scale": torch.ones(())}
    for key in list(state):
        if key.startswith("audio_encoder."):
            mapped["speech.model." + key[len("audio_encoder.") :]] = state.pop(key)
        elif key.startswith("transformer_decoder.layers."):
            mapped["blocks." + key[len("transformer_decoder.layers.") :]] = state.pop(key)
    for ours, theirs in (
        ("audio_map", "audio_feature_map"),
        ("motion_map", "vertice_map"),
        ("out", "vertice_map_r"),
    ):
        for p in ("weight", "bias"):
            mapped[f"{ours}.{p}"] = _take(state, f"{theirs}.{p}", path)
    mapped["style.weight"] = _take(state, "obj_vector.weight", path).t().contiguous()
    _leftover(state, path)
    return _fill(model, mapped, path)
