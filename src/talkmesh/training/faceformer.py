"""How ``talkmesh train`` builds, steps and releases FaceFormer (``task: faceformer``).

The model section is ``{preset: small|vocaset|biwi, ...FaceFormerConfig overrides}``; the vertex
count, the frame rate (and with it the speech encoder's token rate) and the training speakers come
from the data. ``init`` (optional) warm-starts from an earlier FaceFormer release of the same size.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from talkmesh.config import from_dict, merge, to_dict
from talkmesh.errors import TalkmeshError
from talkmesh.models.faceformer import (
    FaceFormer,
    FaceFormerConfig,
    biwi_config,
    small_synth_config,
    vocaset_config,
)
from talkmesh.models.release import load_model, save_model
from talkmesh.training.trainer import DatasetInfo, StepOutput, Task, TorchBatch

PRESETS = {"small": small_synth_config, "vocaset": vocaset_config, "biwi": biwi_config}
STATISTICS_SAMPLES = 64  # training sequences read to fit the mel statistics and motion scale


def build_config(model: dict[str, Any], info: DatasetInfo) -> FaceFormerConfig:
    """A recipe's model section plus the data's facts -> the validated config."""
    model = dict(model)
    preset = model.pop("preset", "small")
    if preset not in PRESETS:
        raise TalkmeshError(f"model.preset must be {', '.join(PRESETS)}, got {preset!r}")
    styles = tuple(info.train_subjects)
    data = merge(to_dict(PRESETS[preset](styles, info.num_vertices)), model)
    data.update(num_vertices=info.num_vertices, styles=list(styles), motion_fps=info.motion_fps)
    data["speech"]["frame_rate"] = info.motion_fps * data["audio_tokens_per_frame"]
    return from_dict(FaceFormerConfig, data, "model")


def _build(model: dict[str, Any], info: DatasetInfo, init: Path | None) -> FaceFormer:
    net = FaceFormer(build_config(model, info))
    if init is not None:
        start = load_model(init)
        if getattr(start, "family", None) != FaceFormer.family:
            raise TalkmeshError(f"{init}: not a FaceFormer release, cannot warm-start from it")
        try:
            net.load_state_dict(start.state_dict(), strict=True)
        except RuntimeError:
            raise TalkmeshError(
                f"{init}: its FaceFormer differs in size from this recipe's model"
            ) from None
    return net


def _step(net: FaceFormer, batch: TorchBatch) -> StepOutput:
    out = net(
        batch.audio,
        batch.audio_lengths,
        batch.vertices,
        batch.templates,
        batch.styles,
        batch.motion_mask,
    )
    return StepOutput(out.loss, {})


def _prepare(net: FaceFormer, dataset) -> None:
    """The mel encoder's normalisation and the motion scale (buffers) from training sequences."""
    step = max(1, len(dataset) // STATISTICS_SAMPLES)
    samples = [dataset[i] for i in range(0, len(dataset), step)]
    motion = torch.cat([torch.from_numpy(s.vertices - s.template).flatten(1) for s in samples])
    net.set_motion_scale(motion)
    if hasattr(net.speech, "set_statistics"):
        net.speech.set_statistics(torch.cat([torch.from_numpy(s.audio) for s in samples])[None])


FACEFORMER = Task(
    name="faceformer",
    build=_build,
    step=_step,
    parameters=lambda net: net.parameters(),
    save=save_model,
    prepare=_prepare,
)
