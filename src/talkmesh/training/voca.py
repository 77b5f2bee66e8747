"""How ``talkmesh train`` builds, steps, prepares and releases VOCA (``task: voca``).

The model section is ``{preset: small|vocaset, ...VOCAConfig overrides}``; the vertex count, the
motion rate and the training speakers (the one-hot order) come from the data. Before training,
:func:`prepare` fits what VOCA takes from the training set: the mel encoder's normalisation (when
the speech encoder is ``mel``), the per-channel statistics of the speech features (the paper's
input normalisation) and the PCA basis that initialises the decoder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from talkmesh.config import from_dict, merge, to_dict
from talkmesh.errors import TalkmeshError
from talkmesh.models.release import save_model
from talkmesh.models.voca.model import VOCA as VOCAModel
from talkmesh.models.voca.model import VOCAConfig, paper_vocaset_config, small_config
from talkmesh.training.codetalker import prepare_speech_statistics
from talkmesh.training.trainer import DatasetInfo, StepOutput, Task, TorchBatch

PCA_SEQUENCES = 64  # training sequences sampled for the PCA basis
PCA_FRAMES = 2048  # frames kept from them (the PCA costs frames^2 x V*3)
FEATURE_SEQUENCES = 16  # training sequences whose speech features set the normalisation
FROM_DATA = ("num_vertices", "styles", "motion_fps")


def build_config(model: dict[str, Any], info: DatasetInfo) -> VOCAConfig:
    """The recipe's model section + the dataset facts -> a validated :class:`VOCAConfig`."""
    model = dict(model)
    preset = model.pop("preset", "small")
    for key in FROM_DATA:
        if key in model:
            raise TalkmeshError(f"model.{key} comes from the training data: remove it")
    styles = tuple(info.train_subjects)
    if preset == "small":
        base = small_config(styles, info.num_vertices, info.motion_fps)
    elif preset == "vocaset":
        base = paper_vocaset_config(styles)
    else:
        raise TalkmeshError(f"model.preset must be small or vocaset, got {preset!r}")
    data = merge(to_dict(base), model)
    data.update(num_vertices=info.num_vertices, styles=list(styles), motion_fps=info.motion_fps)
    return from_dict(VOCAConfig, data, "model")


def _build(model: dict[str, Any], info: DatasetInfo, init: Path | None) -> VOCAModel:
    if init is not None:
        raise TalkmeshError(
            "task voca trains in one stage: drop init (continue a run with --resume)"
        )
    return VOCAModel(build_config(model, info))


def _step(net: VOCAModel, batch: TorchBatch) -> StepOutput:
    out = net(
        batch.audio,
        batch.audio_lengths,
        batch.vertices,
        batch.templates,
        batch.styles,
        batch.motion_mask,
    )
    return StepOutput(
        out.loss,
        {
            "position": float(out.position_loss.detach()),
            "velocity": float(out.velocity_loss.detach()),
        },
    )


def _every(n: int, most: int) -> range:
    return range(0, n, max(1, -(-n // most)))


@torch.no_grad()
def prepare(net: VOCAModel, dataset) -> None:
    """Fit the speech normalisation and the decoder's PCA basis on the training ``dataset``."""
    prepare_speech_statistics(net, dataset)
    was_training = net.training
    net.eval()
    net.feature_mean.zero_()  # raw features first
    net.feature_std.fill_(1.0)
    try:
        feats = []
        for i in _every(len(dataset), FEATURE_SEQUENCES):
            sample = dataset[i]
            audio = torch.from_numpy(sample.audio)[None].to(net.feature_mean.device)
            frames = torch.tensor([len(sample.vertices)], device=audio.device)
            feats.append(net.speech_tokens(audio, None, frames)[0])
        net.set_feature_statistics(torch.cat(feats))
    finally:
        net.train(was_training)
    offsets = torch.cat(
        [
            torch.from_numpy(dataset[i].vertices - dataset[i].template).flatten(1)
            for i in _every(len(dataset), PCA_SEQUENCES)
        ]
    )
    offsets = offsets[:: max(1, -(-len(offsets) // PCA_FRAMES))]
    net.set_basis(offsets.to(net.decoder.weight.device))


VOCA = Task(
    name="voca",
    build=_build,
    step=_step,
    parameters=lambda net: net.parameters(),
    save=save_model,
    prepare=prepare,
)
