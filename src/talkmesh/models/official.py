"""Import the papers' released checkpoints into talkmesh models (``talkmesh import-checkpoint``).

    model = import_checkpoint(["vocaset.pth"], family="faceformer", dataset="vocaset")
    save_model(model, "faceformer_vocaset.safetensors")

This module holds what the importers share (the datasets' facts, the wav2vec 2.0 encoder's
config, the positional-encoding check) and the dispatcher; each family's mapping of the official
tensors lives in its folder, ``talkmesh/models/<family>/official.py``, as
``import_official(paths, dataset)`` with the ``DATASETS`` it accepts.

The files are read as the official trainers write them (FaceFormer: ``torch.save(model.state_dict())``)
with ``torch.load(weights_only=True)`` only, so a checkpoint can never run code; tensors saved
from a GPU load on the CPU; a ``module.`` prefix (DataParallel) and torch 1.x weight-norm names
(``weight_g``/``weight_v``) are accepted. Every official tensor is mapped onto one talkmesh
state-dict key (or, for fixed buffers such as the positional encoding, checked against what
talkmesh computes), shapes are checked and nothing is left over or missing: a one-line error
names what does not fit. The model's config switches on the official-exact options
(post-norm layers, CNN-feature resampling, the processor's audio normalisation...), so its exact
generation computes what the official ``predict`` computes.
"""

from __future__ import annotations

import importlib
from pathlib import Path

import torch
from torch import Tensor, nn

from talkmesh.constants import BIWI_TRAIN_SUBJECTS, VOCASET_TRAIN_SUBJECTS
from talkmesh.errors import TalkmeshError
from talkmesh.models.checkpoint_io import load_checkpoint
from talkmesh.models.registry import family_package, official_families

__all__ = ["check_ppe", "import_checkpoint", "load_checkpoint", "wav2vec2_config"]

DATASETS = ("vocaset", "biwi", "meshtalk")  # meshtalk: the released MeshTalk's own face mesh

# the official training subjects, in one-hot order (the columns of the style matrix)
SUBJECTS = {"vocaset": VOCASET_TRAIN_SUBJECTS, "biwi": BIWI_TRAIN_SUBJECTS}
FPS = {"vocaset": 30.0, "biwi": 25.0, "meshtalk": 30.0}
TOKENS_PER_FRAME = {"vocaset": 1, "biwi": 2}  # wav2vec2 features (50 Hz) per motion frame
VERTICES = {"vocaset": 5023, "biwi": 23370}  # the datasets' meshes (MeshTalk's own: any count)
MAX_FRAMES = 600  # the official positional encoding and temporal bias length


def wav2vec2_config(state: dict[str, Tensor], prefix: str, path: Path) -> dict:
    """The Wav2Vec2Config of the encoder whose tensors are under ``prefix`` (read from shapes;
    what shapes cannot tell is wav2vec 2.0 base's, the encoder the official models fine-tune)."""
    from transformers import Wav2Vec2Config

    def shape(key: str) -> tuple[int, ...] | None:
        t = state.get(prefix + key)
        return None if t is None else tuple(t.shape)

    convs = []
    while shape(f"feature_extractor.conv_layers.{len(convs)}.conv.weight"):
        convs.append(shape(f"feature_extractor.conv_layers.{len(convs)}.conv.weight"))
    pos = shape("encoder.pos_conv_embed.conv.parametrizations.weight.original1")
    proj = shape("feature_projection.projection.weight")
    if len(convs) != 7 or pos is None or proj is None:
        raise TalkmeshError(f"{path}: its speech encoder is not a wav2vec 2.0 model")
    layers = 0
    while shape(f"encoder.layers.{layers}.attention.q_proj.weight"):
        layers += 1
    hidden = proj[0]
    ff = shape("encoder.layers.0.feed_forward.intermediate_dense.weight")
    all_norm = shape("feature_extractor.conv_layers.1.layer_norm.weight") is not None
    cfg = Wav2Vec2Config(
        hidden_size=hidden,
        num_hidden_layers=layers,
        num_attention_heads=max(1, hidden // 64),
        intermediate_size=ff[0] if ff else 4 * hidden,
        conv_dim=tuple(c[0] for c in convs),
        conv_kernel=tuple(c[2] for c in convs),
        conv_bias=shape("feature_extractor.conv_layers.0.conv.bias") is not None,
        feat_extract_norm="layer" if all_norm else "group",
        do_stable_layer_norm=all_norm,
        num_conv_pos_embeddings=pos[2],
        num_conv_pos_embedding_groups=hidden // pos[1],
    )
    return cfg.to_dict()


def check_ppe(pe: Tensor, period: int, d: int, dataset: str, path: Path) -> None:
    """The official periodic positional encoding ``pe`` (1, rows, D) must be the one talkmesh
    computes for ``period`` (it is not a weight: a different one means another dataset)."""
    from talkmesh.models.postnorm import interleaved_encoding

    rows = period * (MAX_FRAMES // period + 1)
    if pe.shape != (1, rows, d) or not torch.allclose(
        pe[0], interleaved_encoding(rows, d, period), atol=1e-5
    ):
        raise TalkmeshError(
            f"{path}: its positional encoding is not the period-{period} one of a {dataset} "
            "model: is --dataset right?"
        )


def import_checkpoint(files: list[str | Path], family: str, dataset: str) -> nn.Module:
    """The released file(s) of ``family`` trained on ``dataset`` -> a talkmesh model (eval mode)."""
    families = official_families()
    if family not in families:
        raise TalkmeshError(f"unknown family '{family}': use one of {', '.join(families)}")
    dataset = dataset.lower()
    if dataset not in DATASETS:
        raise TalkmeshError(f"unknown dataset '{dataset}': use vocaset, biwi or meshtalk")
    importer = importlib.import_module(family_package(family) + ".official")
    if dataset not in importer.DATASETS:
        what = "MeshTalk's own mesh" if dataset == "meshtalk" else "not what its weights fit"
        raise TalkmeshError(
            f"--dataset {dataset} is {what}: {family} uses {' or '.join(importer.DATASETS)}"
        )
    return importer.import_official([Path(f) for f in files], dataset)
