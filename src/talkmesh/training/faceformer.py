"""How ``talkmesh train`` builds, steps and releases FaceFormer (``task: faceformer``).

The model section is ``{preset: small|vocaset|biwi, ...FaceFormerConfig overrides}``; the vertex
count, the frame rate (and with it the speech encoder's token rate) and the training speakers come
from the data. ``init`` (optional) warm-starts from an earlier FaceFormer release of the same size.
``teacher_forcing: false`` in the model section trains on the model's own predictions with the
official loop (:func:`own_predictions`); otherwise a step is the teacher-forced ``forward``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from talkmesh.config import from_dict, merge, to_dict
from talkmesh.errors import TalkmeshError
from talkmesh.models.faceformer.model import (
    FaceFormer,
    FaceFormerConfig,
    biwi_config,
    decoder_bias,
    masked_mse,
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


def own_predictions(net: FaceFormer, batch: TorchBatch) -> tuple[Tensor, Tensor]:
    """The official training loop (``teacher_forcing: false``), as the paper trains: frame 0 reads
    the style alone, and at step t the whole decoder runs over the t + 1 inputs so far, its last
    frame's motion is fed back (motion encoder + style, with gradients through the whole chain)
    and the last pass's motion of every frame is the prediction. T passes per sequence, so the
    cost grows with length squared, as the official loop's does.

    Returns (B, T, V*3) predicted offsets (in units of the motion scale) and the masked MSE."""
    cfg = net.cfg
    B, T = batch.vertices.shape[:2]
    net._check(batch.audio, batch.templates, "templates")
    motion = (batch.vertices - batch.templates[:, None]).flatten(2) / net.scale
    seen = net.style(batch.styles.clamp(min=0))
    style = torch.where((batch.styles >= 0)[:, None], seen, net.style.weight.mean(0)[None])
    cross = net.cross_terms(net.audio_tokens(batch.audio, batch.audio_lengths, T))
    bias = decoder_bias(cfg.heads, T, T, cfg.period, cfg.attention_window, motion.device)[None]
    inputs = [net.first_input(style)[:, None]]
    for t in range(T):
        x = torch.cat(inputs, dim=1)
        x = net.dropout(x + net.ppe(t + 1, x.device))  # the official PPE's dropout, every pass
        h = net.hidden_states(x, [c[:, : t + 1] for c in cross], bias[..., : t + 1, : t + 1])
        if t + 1 < T:  # the motion decoder on the last frame only: the fed-back one
            inputs.append((net.motion_map(net.out(h[:, -1])) + style)[:, None])
    pred = net.out(h)
    return pred, masked_mse(pred, motion, batch.motion_mask)


def _step(net: FaceFormer, batch: TorchBatch) -> StepOutput:
    if not net.cfg.teacher_forcing:
        return StepOutput(own_predictions(net, batch)[1], {})
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
