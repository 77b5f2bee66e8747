"""CodeTalker's released weights (the stage-1 VQ-VAE ``*_stage1.pth.tar`` and stage 2
``*_stage2.pth.tar``, as the official trainer saves them) -> a
:class:`~talkmesh.models.codetalker.model.CodeTalker` whose exact generation computes what the
official ``predict`` computes (:func:`talkmesh.models.official.import_checkpoint` with
``family="codetalker"``)."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn

from talkmesh.errors import TalkmeshError
from talkmesh.models.checkpoint_io import _fill, _leftover, _take, load_checkpoint
from talkmesh.models.codetalker.model import CodeTalker, CodeTalkerConfig, Stage2Config
from talkmesh.models.codetalker.vq import VQConfig
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
    """The two released files, in any order -> a :class:`CodeTalker` in eval mode."""
    return import_codetalker(paths, dataset)


def _blocks_map(state: dict, theirs: str, ours: str, layers: int, heads: int, path: Path) -> dict:
    """The official stage-1 ``Transformer`` (pre-norm residual blocks, bias-free qkv, scores
    scaled by 1/sqrt(width)) -> talkmesh ``Block`` tensors; the width scaling becomes a factor on
    the query rows, since talkmesh scales by 1/sqrt(head width)."""
    out = {}
    for i in range(layers):
        attn, mlp = f"{theirs}.net.{2 * i}.fn", f"{theirs}.net.{2 * i + 1}.fn"
        qkv = _take(state, f"{attn}.fn.to_qkv.weight", path).clone()
        width = qkv.shape[1]
        qkv[: qkv.shape[0] // 3] *= ((width // heads) / width) ** 0.5
        out[f"{ours}.{i}.attn.qkv.weight"] = qkv
        out[f"{ours}.{i}.attn.qkv.bias"] = torch.zeros(qkv.shape[0])
        for o, t in (
            ("norm1", f"{attn}.norm"),
            ("attn.out", f"{attn}.fn.to_out"),
            ("norm2", f"{mlp}.norm"),
            ("mlp.0", f"{mlp}.fn.l1"),
            ("mlp.2", f"{mlp}.fn.l2"),
        ):
            for p in ("weight", "bias"):
                out[f"{ours}.{i}.{o}.{p}"] = _take(state, f"{t}.{p}", path)
    return out


def _linear(
    state: dict, theirs: str, ours: str, path: Path, extra_bias: Tensor | None = None
) -> dict:
    w = _take(state, f"{theirs}.weight", path)
    b = state.pop(f"{theirs}.bias", None)
    b = torch.zeros(w.shape[0]) if b is None else b
    return {f"{ours}.weight": w, f"{ours}.bias": b if extra_bias is None else b + extra_bias}


def _identity(ours: str, n: int) -> dict:
    return {f"{ours}.weight": torch.eye(n), f"{ours}.bias": torch.zeros(n)}


def _split_codetalker(paths: list[Path]) -> tuple[dict, dict, Path, Path]:
    """Two files -> (stage-1 tensors, stage-2 tensors, their paths), whatever the order."""
    both = (
        "CodeTalker needs both released files, the stage-1 VQ-VAE (e.g. vocaset_stage1.pth.tar) "
        "and stage 2 (vocaset_stage2.pth.tar)"
    )
    if len(paths) not in (1, 2):
        raise TalkmeshError(f"{both}; got {len(paths)} files")
    stage1 = stage2 = None
    for path in paths:
        state = load_checkpoint(path)
        if "quantize.embedding.weight" in state:
            stage1 = (state, path)
        elif "feat_map.weight" in state:
            # a stage-2 file that kept its autoencoder: only stage 2's own tensors are read
            stage2 = ({k: v for k, v in state.items() if not k.startswith("autoencoder.")}, path)
        else:
            raise TalkmeshError(f"{path}: neither a CodeTalker stage-1 nor a stage-2 checkpoint")
    if stage1 is None or stage2 is None:
        missing = "stage-1 (*_stage1.pth.tar)" if stage1 is None else "stage-2 (*_stage2.pth.tar)"
        raise TalkmeshError(f"{both}: the {missing} file is missing")
    return stage1[0], stage2[0], stage1[1], stage2[1]


def _codetalker_vq_config(s1: dict, inp: Tensor, dataset: str, path: Path):
    """The stage-1 VQConfig read off the official tensors' shapes."""
    hidden, vertex_dims = inp.shape
    N, C = s1["quantize.embedding.weight"].shape
    post = s1.get("encoder.encoder_linear_embedding_post.net.weight")
    if (post is not None) != (dataset == "biwi"):
        raise TalkmeshError(
            f"{path}: a {'BIWI' if post is not None else 'VOCASET'} stage-1 "
            f"model, not {dataset}: is --dataset right?"
        )
    H = (post.shape[0] if post is not None else hidden) // C
    layers1 = 0
    while f"encoder.encoder_transformer.net.{2 * layers1}.fn.norm.weight" in s1:
        layers1 += 1
    heads1 = 8  # the released configs' num_attention_heads (shapes do not tell it)
    return VQConfig(
        num_vertices=vertex_dims // 3,
        hidden=hidden,
        layers=layers1,
        heads=heads1,
        ff=s1["encoder.encoder_transformer.net.1.fn.fn.l1.weight"].shape[0] if layers1 else hidden,
        components=H,
        code_dim=C,
        codebook_size=N,
        instance_norm=True,
        gelu_tanh=True,
        final_norm=False,
        frame_positions=False,
    )


def import_codetalker(paths: list[Path], dataset: str) -> nn.Module:
    """CodeTalker's released stage-1 + stage-2 files -> a :class:`CodeTalker`."""
    s1, s2, p1, p2 = _split_codetalker(paths)
    inp = _take(s1, "encoder.vertice_mapping.0.weight", p1)
    vq = _codetalker_vq_config(s1, inp, dataset, p1)
    names = SUBJECTS[dataset]
    style = s2.get("learnable_style_emb.weight")
    if style is None or style.shape[0] != len(names):
        raise TalkmeshError(
            f"{p2}: a {dataset} stage 2 has {len(names)} training subjects "
            "(learnable_style_emb): is --dataset right?"
        )
    d = style.shape[1]
    layers2 = 0
    while f"transformer_decoder.layers.{layers2}.linear1.weight" in s2:
        layers2 += 1
    fps, k = FPS[dataset], TOKENS_PER_FRAME[dataset]
    stage2 = Stage2Config(
        d_model=d,
        heads=4,
        layers=layers2,
        period=int(fps),
        audio_tokens_per_frame=k,
        ff=s2["transformer_decoder.layers.0.linear1.weight"].shape[0] if layers2 else 2 * d,
        styles=names,
        attention_window=MAX_FRAMES,
        postnorm=True,
        interleaved_ppe=True,
        speech=SpeechEncoderConfig(
            kind="wav2vec2",
            frame_rate=fps * k,
            resample="cnn",
            normalize=True,
            hf_config=wav2vec2_config(s2, "audio_encoder.", p2),
        ),
    )
    model = CodeTalker(CodeTalkerConfig(vq=vq, stage2=stage2, motion_fps=fps))
    mapped = _vq_map(s1, vq, inp, p1)
    check_ppe(_take(s2, "PPE.pe", p2), int(fps), d, dataset, p2)
    for key in list(s2):
        if key.startswith("audio_encoder."):
            mapped["speech.model." + key[len("audio_encoder.") :]] = s2.pop(key)
        elif key.startswith("transformer_decoder.layers."):
            mapped["blocks." + key[len("transformer_decoder.layers.") :]] = s2.pop(key)
    mapped.update(_linear(s2, "audio_feature_map", "audio_map", p2))
    mapped.update(_linear(s2, "vertice_map", "motion_map", p2))
    mapped.update(_linear(s2, "feat_map", "feat_map", p2))  # bias-free officially
    mapped["style.weight"] = _take(s2, "learnable_style_emb.weight", p2)
    _leftover(s1, p1)
    _leftover(s2, p2)
    return _fill(model, mapped, p2)


def _vq_map(s1: dict, vq, inp: Tensor, path: Path) -> dict:
    """Stage-1 tensors -> ``vqvae.*``; the official positional encoding adds one vector (that of
    position 0) to every frame: it becomes part of the embedding's bias."""
    out = {
        "vqvae.encoder.inp.weight": inp,
        "vqvae.encoder.inp.bias": _take(s1, "encoder.vertice_mapping.0.bias", path),
    }
    HC = vq.components * vq.code_dim
    for side in ("encoder", "decoder"):
        pe = _take(s1, f"{side}.{side}_pos_embedding.pe", path)
        if pe.ndim != 3 or pe.shape[1:] != (1, vq.hidden):
            raise TalkmeshError(f"{path}: {side}_pos_embedding.pe has shape {tuple(pe.shape)}")
        conv = f"{side}.squasher.0.0" if side == "encoder" else f"{side}.expander.0.0"
        out.update(_linear(s1, conv, f"vqvae.{side}.conv.conv", path))
        out.update(
            _linear(
                s1,
                f"{side}.{side}_linear_embedding.net",
                f"vqvae.{side}.mid",
                path,
                extra_bias=pe[0, 0],
            )
        )
        out.update(
            _blocks_map(
                s1, f"{side}.{side}_transformer", f"vqvae.{side}.blocks", vq.layers, vq.heads, path
            )
        )
        out[f"vqvae.{side}.scale"] = torch.ones(vq.num_vertices * 3)
    if "encoder.encoder_linear_embedding_post.net.weight" in s1:  # BIWI: hidden <-> H x C maps
        out.update(
            _linear(s1, "encoder.encoder_linear_embedding_post.net", "vqvae.encoder.out", path)
        )
        out.update(
            _linear(s1, "decoder.decoder_linear_embedding_pre.net", "vqvae.decoder.inp", path)
        )
    else:  # VOCASET: hidden = H x C, no maps
        out.update(_identity("vqvae.encoder.out", HC))
        out.update(_identity("vqvae.decoder.inp", HC))
    out.update(_linear(s1, "decoder.vertice_map_reverse", "vqvae.decoder.out", path))
    out["vqvae.quantizer.codebook"] = _take(s1, "quantize.embedding.weight", path)
    out["vqvae.quantizer.usage"] = torch.zeros(vq.codebook_size)
    out["vqvae.quantizer.initialised"] = torch.tensor(True)
    return out
