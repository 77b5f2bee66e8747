"""How ``talkmesh train`` builds, steps and releases MeshTalk (expression space, then prior).

Recipes: ``task: meshtalk`` trains the expression space (encoders, fusion, decoder); ``task:
meshtalk-prior`` trains the autoregressive prior on the codes of a trained expression space given
by ``init``. The model section is ``{preset: small|released|paper, ...MeshTalkConfig overrides}``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from torch import nn

from talkmesh.config import from_dict, to_dict
from talkmesh.errors import TalkmeshError
from talkmesh.models.meshtalk import (
    AutoregressivePrior,
    MeshTalk,
    MeshTalkConfig,
    PriorConfig,
    meshtalk_config,
    prior_config,
)
from talkmesh.train import DatasetInfo, StepOutput, Task, TorchBatch

FORMAT = "talkmesh-meshtalk"
FORMAT_VERSION = 1


def _config(cls, preset_fn, model: dict[str, Any], *args):
    model = dict(model)
    preset = model.pop("preset", "small")
    base = to_dict(preset_fn(preset, *args))
    base.update(model)
    return from_dict(cls, base, "model")


def region_maps(
    info: DatasetInfo,
) -> tuple[torch.Tensor | None, torch.Tensor | None, torch.Tensor | None]:
    """Soft mouth / upper-face maps and eyelid ids for the training topology.

    The bundled head ships soft maps; other topologies fall back to uniform maps (the
    cross-modality loss then weighs every vertex alike).
    """
    from talkmesh.assets import load_head

    head = load_head()
    if info.num_vertices != head.num_vertices:
        return None, None, None
    r = head.regions
    return (
        torch.as_tensor(r.mouth_weight, dtype=torch.float32),
        torch.as_tensor(r.upper_weight, dtype=torch.float32),
        torch.as_tensor(r.eyelids, dtype=torch.long),
    )


class MeshTalkSystem(nn.Module):
    """The expression space plus (for the prior stage) the prior: one module to save and load."""

    def __init__(self, config: MeshTalkConfig, prior: PriorConfig | None, maps=(None, None, None)):
        super().__init__()
        self.model = MeshTalk(config, *maps)
        self.prior = AutoregressivePrior(prior) if prior is not None else None


def save_system(system: MeshTalkSystem, path: Path) -> None:
    from safetensors.torch import save_file

    meta = {
        "format": FORMAT,
        "format_version": str(FORMAT_VERSION),
        "config": json.dumps(to_dict(system.model.config)),
        "prior": json.dumps(to_dict(system.prior.config) if system.prior is not None else None),
    }
    state = {k: v.detach().contiguous().cpu() for k, v in system.state_dict().items()}
    save_file(state, str(path), metadata=meta)


def load_system(path: str | Path) -> MeshTalkSystem:
    """A released MeshTalk (``strict=True``; no pickle)."""
    from safetensors import safe_open
    from safetensors.torch import load_file

    path = Path(path)
    if not path.is_file():
        raise TalkmeshError(f"model file not found: {path}")
    try:
        with safe_open(str(path), "pt") as f:
            meta = f.metadata() or {}
    except Exception as e:  # safetensors raises its own types for corrupt headers
        raise TalkmeshError(f"{path}: not a safetensors model file ({e})") from None
    if meta.get("format") != FORMAT:
        raise TalkmeshError(
            f"{path}: not a talkmesh MeshTalk release (format {meta.get('format')!r})"
        )
    config = from_dict(MeshTalkConfig, json.loads(meta["config"]))
    prior = json.loads(meta["prior"])
    system = MeshTalkSystem(config, from_dict(PriorConfig, prior) if prior else None)
    system.load_state_dict(load_file(str(path)), strict=True)
    return system.eval()


def _build_expression(
    model: dict[str, Any], info: DatasetInfo, init: Path | None
) -> MeshTalkSystem:
    config = _config(MeshTalkConfig, meshtalk_config, model, info.num_vertices, info.motion_fps)
    system = MeshTalkSystem(config, None, region_maps(info))
    if init is not None:
        system.load_state_dict(load_system(init).state_dict(), strict=False)
    return system


def _step_expression(system: MeshTalkSystem, batch: TorchBatch) -> StepOutput:
    out = system.model(batch.vertices, batch.templates, batch.audio, batch.audio_lengths)
    loss = system.model.loss(out, batch.vertices, batch.motion_mask)
    return StepOutput(
        loss.total,
        {
            "reconstruction": float(loss.reconstruction.detach()),
            "mouth": float(loss.mouth.detach()),
            "upper": float(loss.upper.detach()),
            "eyelid": float(loss.eyelid.detach()),
        },
    )


def _build_prior(model: dict[str, Any], info: DatasetInfo, init: Path | None) -> MeshTalkSystem:
    if init is None:
        raise TalkmeshError(
            "task meshtalk-prior needs init: the trained expression space (.safetensors)"
        )
    trained = load_system(init)
    cfg = trained.model.config
    model = {"num_heads": cfg.num_heads, "num_classes": cfg.num_classes, **model}
    prior = _config(PriorConfig, prior_config, model, info.motion_fps)
    if (prior.num_heads, prior.num_classes) != (cfg.num_heads, cfg.num_classes):
        raise TalkmeshError(
            "model.num_heads/num_classes of the prior must match the expression space"
        )
    system = MeshTalkSystem(cfg, prior)
    system.model.load_state_dict(trained.model.state_dict(), strict=True)
    system.model.requires_grad_(False)
    return system


def _step_prior(system: MeshTalkSystem, batch: TorchBatch) -> StepOutput:
    system.model.eval()  # frozen: argmax codes, no Gumbel noise
    with torch.no_grad():
        codes = system.model.encode(
            batch.vertices, batch.templates, batch.audio, batch.audio_lengths, sample=False
        ).codes
    features = system.prior.audio_features(batch.audio, batch.audio_lengths, codes.shape[1])
    out = system.prior.loss(codes, features, batch.motion_mask)
    return StepOutput(
        out.loss, {"perplexity": float(out.perplexity), "accuracy": float(out.accuracy)}
    )


STATISTICS_SAMPLES = 64  # training sequences used for the normalisation statistics


def _prepare_expression(system: MeshTalkSystem, dataset) -> None:
    """Template and offset scales (buffers) and the mel normalisation from training data."""
    step = max(1, len(dataset) // STATISTICS_SAMPLES)
    samples = [dataset[i] for i in range(0, len(dataset), step)][:STATISTICS_SAMPLES]
    templates = torch.stack([torch.from_numpy(s.template) for s in samples])
    offsets = torch.cat([torch.from_numpy(s.vertices - s.template[None]) for s in samples])
    system.model.set_statistics(templates, offsets)
    audio = torch.cat([torch.from_numpy(s.audio) for s in samples])[None]
    system.model.audio_encoder.set_statistics(audio)


def _prepare_prior(system: MeshTalkSystem, dataset) -> None:
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
    save=save_system,
    prepare=_prepare_expression,
)

PRIOR = Task(
    name="meshtalk-prior",
    build=_build_prior,
    step=_step_prior,
    parameters=lambda system: system.prior.parameters(),
    save=save_system,
    prepare=_prepare_prior,
)
