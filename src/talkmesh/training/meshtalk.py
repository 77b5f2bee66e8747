"""How ``talkmesh train`` builds, steps and releases MeshTalk (expression space, then prior).

Recipes: ``task: meshtalk`` trains the expression space (encoders, fusion, decoder); ``task:
meshtalk-prior`` trains the autoregressive prior on the codes of a trained expression space given
by ``init``. The model section is ``{preset: small|released|paper, ...MeshTalkConfig overrides}``
(the prior stage: ``...PriorConfig overrides`` and ``sampling``, the release's
:class:`SamplingConfig`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from talkmesh.config import from_dict, to_dict
from talkmesh.errors import TalkmeshError
from talkmesh.models.meshtalk.model import (
    MeshTalkConfig,
    MeshTalkModel,
    MeshTalkModelConfig,
    SamplingConfig,
    meshtalk_config,
)
from talkmesh.models.meshtalk.prior import PriorConfig, prior_config
from talkmesh.models.release import load_model, save_model
from talkmesh.training.trainer import DatasetInfo, StepOutput, Task, TorchBatch


def _config(cls, preset_fn, model: dict[str, Any], *args):
    model = dict(model)
    preset = model.pop("preset", "small")
    base = to_dict(preset_fn(preset, *args))
    base.update(model)
    return from_dict(cls, base, "model")


def region_maps(
    info: DatasetInfo,
) -> tuple[torch.Tensor | None, torch.Tensor | None, torch.Tensor | None]:
    """Mouth / upper-face maps and eyelid ids for the training topology.

    The bundled head ships soft maps; VOCASET (FLAME_masks.pkl) and BIWI (CodeTalker's region
    files) get binary maps from the dataset's regions (:mod:`talkmesh.datasets.regions`);
    anything else falls back to uniform maps with a warning.
    """
    from talkmesh.datasets.regions import region_masks
    from talkmesh.face.assets import load_head

    head = load_head()
    if info.num_vertices == head.num_vertices:
        r = head.regions
        return (
            torch.as_tensor(r.mouth_weight, dtype=torch.float32),
            torch.as_tensor(r.upper_weight, dtype=torch.float32),
            torch.as_tensor(r.eyelids, dtype=torch.long),
        )
    masks = region_masks(info.regions, info.num_vertices)
    return tuple(None if m is None else torch.as_tensor(m) for m in masks)


def load_system(path: str | Path) -> MeshTalkModel:
    """A released MeshTalk (``talkmesh.models.release`` format, family meshtalk)."""
    system = load_model(path)
    if not isinstance(system, MeshTalkModel):
        raise TalkmeshError(f"{path}: a {system.family} model, not MeshTalk")
    return system


def _build_expression(model: dict[str, Any], info: DatasetInfo, init: Path | None) -> MeshTalkModel:
    config = _config(MeshTalkConfig, meshtalk_config, model, info.num_vertices, info.motion_fps)
    system = MeshTalkModel(MeshTalkModelConfig(config), region_maps(info))
    if init is not None:
        system.load_state_dict(load_system(init).state_dict(), strict=False)
    return system


def _step_expression(system: MeshTalkModel, batch: TorchBatch) -> StepOutput:
    out = system.model(batch.vertices, batch.templates, batch.audio, batch.audio_lengths)
    loss = system.model.loss(out, batch.vertices, batch.motion_mask)
    return StepOutput(
        loss.total,
        {
            "reconstruction": float(loss.reconstruction.detach()),
            "mouth": float(loss.mouth.detach()),
            "upper": float(loss.upper.detach()),
            "eyelid": float(loss.eyelid.detach()),
            # mean largest class probability: near 1 = saturated softmax, no Gumbel gradient
            "confidence": float(out.quantized.logits.detach().softmax(-1).amax(-1).mean()),
        },
    )


def _build_prior(model: dict[str, Any], info: DatasetInfo, init: Path | None) -> MeshTalkModel:
    if init is None:
        raise TalkmeshError(
            "task meshtalk-prior needs init: the trained expression space (.safetensors)"
        )
    trained = load_system(init)
    cfg = trained.model.config
    model = {"num_heads": cfg.num_heads, "num_classes": cfg.num_classes, **model}
    # the release's generation defaults (e.g. the official Gumbel draw) travel with the prior
    sampling = from_dict(SamplingConfig, model.pop("sampling", {}), "model.sampling")
    prior = _config(PriorConfig, prior_config, model, info.motion_fps)
    if (prior.num_heads, prior.num_classes) != (cfg.num_heads, cfg.num_classes):
        raise TalkmeshError(
            "model.num_heads/num_classes of the prior must match the expression space"
        )
    system = MeshTalkModel(MeshTalkModelConfig(cfg, prior, sampling))
    system.model.load_state_dict(trained.model.state_dict(), strict=True)
    system.model.requires_grad_(False)
    return system


def _step_prior(system: MeshTalkModel, batch: TorchBatch) -> StepOutput:
    system.model.eval()  # frozen: argmax codes, no Gumbel noise
    with torch.no_grad():
        codes = system.model.encode(
            batch.vertices, batch.templates, batch.audio, batch.audio_lengths, sample=False
        ).codes
    features = system.audio_features(batch.audio, batch.audio_lengths, codes.shape[1])
    out = system.prior.loss(codes, features, batch.motion_mask)
    return StepOutput(
        out.loss, {"perplexity": float(out.perplexity), "accuracy": float(out.accuracy)}
    )


STATISTICS_SAMPLES = 64  # training sequences used for the normalisation statistics


def _prepare_expression(system: MeshTalkModel, dataset) -> None:
    """Template and offset scales (buffers) and the mel normalisation from training data."""
    step = max(1, len(dataset) // STATISTICS_SAMPLES)
    samples = [dataset[i] for i in range(0, len(dataset), step)][:STATISTICS_SAMPLES]
    templates = torch.stack([torch.from_numpy(s.template) for s in samples])
    offsets = torch.cat([torch.from_numpy(s.vertices - s.template[None]) for s in samples])
    system.model.set_statistics(templates, offsets)
    audio = torch.cat([torch.from_numpy(s.audio) for s in samples])[None]
    system.model.audio_encoder.set_statistics(audio)


def _prepare_prior(system: MeshTalkModel, dataset) -> None:
    samples = [
        dataset[i] for i in range(0, len(dataset), max(1, len(dataset) // STATISTICS_SAMPLES))
    ]
    audio = torch.cat([torch.from_numpy(s.audio) for s in samples[:STATISTICS_SAMPLES]])[None]
    encoder = getattr(system.prior, "audio_encoder", None)
    if encoder is not None and hasattr(encoder, "set_statistics"):
        encoder.set_statistics(audio)


EXPRESSION = Task(
    name="meshtalk",
    build=_build_expression,
    step=_step_expression,
    parameters=lambda system: system.model.parameters(),
    save=save_model,
    prepare=_prepare_expression,
)

PRIOR = Task(
    name="meshtalk-prior",
    build=_build_prior,
    step=_step_prior,
    parameters=lambda system: system.prior.parameters(),
    save=save_model,
    prepare=_prepare_prior,
)
