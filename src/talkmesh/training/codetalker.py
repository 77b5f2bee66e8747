"""How ``talkmesh train`` builds, steps and releases CodeTalker's two stages.

``task: codetalker-stage1`` trains the motion VQ-VAE (L_VQ, Eq. 3); ``task: codetalker-stage2``
trains the speech-driven code query (Eq. 6) with stage 1 frozen, starting from ``init`` (the stage-1
release); ``task: codetalker-finetune`` continues stage 2 of a finished release (``init``: a file or
a bundled name), e.g. on augmented audio, with its model, speech statistics and VQ-VAE as they
are; ``task: codetalker-decoder`` refits the VQ decoder of a finished release on the data (the
encoder, codebook and stage 2 as they are, so the release's code queries stay valid), e.g. with the
lip-gap loss so that the codes of a closure close the lips (``task: codetalker-decoder-speech``:
on the codes the speech stage predicts from the audio instead of the truth's); its model section may say
``head_decoder: true`` to let the decoder hear the head's lips too (``stage2.head_decoder``, for a
release with the style's head term). The model section of the other tasks is
``{preset: small|vocaset|biwi, vq: {...}, stage2: {...}}``; the vertex count and the training
speakers come from the data.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from talkmesh.config import from_dict, merge, to_dict
from talkmesh.errors import TalkmeshError
from talkmesh.models.codetalker.model import (
    CodeTalker,
    CodeTalkerConfig,
    paper_biwi_config,
    paper_vocaset_config,
    small_synth_config,
)
from talkmesh.models.release import load_model, save_model
from talkmesh.training.trainer import DatasetInfo, StepOutput, Task, TorchBatch

STATISTICS_SAMPLES = 64


def build_config(model: dict[str, Any], info: DatasetInfo) -> CodeTalkerConfig:
    model = dict(model)
    preset = model.pop("preset", "small")
    styles = tuple(info.train_subjects)
    if preset == "small":
        base = small_synth_config(styles, info.num_vertices)
    elif preset == "vocaset":
        base = paper_vocaset_config(styles)
    elif preset == "biwi":
        base = paper_biwi_config(styles)
    else:
        raise TalkmeshError(f"model.preset must be small, vocaset or biwi, got {preset!r}")
    data = merge(to_dict(base), model)
    data["vq"]["num_vertices"] = info.num_vertices
    data["stage2"]["styles"] = list(styles)
    data["motion_fps"] = info.motion_fps
    data["stage2"]["speech"]["frame_rate"] = (
        info.motion_fps * data["stage2"]["audio_tokens_per_frame"]
    )
    return from_dict(CodeTalkerConfig, data, "model")


def _build_stage1(model: dict[str, Any], info: DatasetInfo, init: Path | None) -> CodeTalker:
    net = CodeTalker(build_config(model, info))
    if init is not None:  # the motion stage of any release whose VQ-VAE is this recipe's
        _copy_vqvae(net, load_model(init), init)
    return net


def _copy_vqvae(net: CodeTalker, source: CodeTalker, path: Path) -> None:
    if to_dict(net.cfg.vq) != to_dict(source.cfg.vq):
        raise TalkmeshError(f"{path}: its VQ-VAE config differs from this recipe's model.vq")
    net.vqvae.load_state_dict(source.vqvae.state_dict(), strict=True)


def _step_stage1(net: CodeTalker, batch: TorchBatch) -> StepOutput:
    motion = (batch.vertices - batch.templates[:, None]).flatten(2)
    out = net.vqvae(motion, batch.motion_mask, face=net.decoder_face(batch.templates))
    q = net.vqvae.quantizer
    return StepOutput(
        out.loss,
        {
            "reconstruction": float(out.reconstruction.detach()),
            "quantization": float(out.quantization.detach()),
            "perplexity": q.perplexity(),
            "codes_used": float(q.used_codes()),
        },
        out.motion,
    )


def _build_decoder(model: dict[str, Any], info: DatasetInfo, init: Path | None) -> CodeTalker:
    if init is None:
        raise TalkmeshError("task codetalker-decoder needs init: a CodeTalker release to refit")
    model = dict(model)
    head_decoder = model.pop("head_decoder", False)
    if model or not isinstance(head_decoder, bool):
        raise TalkmeshError(
            "task codetalker-decoder takes its model from init: its model section may only say "
            "head_decoder: true (to let the VQ decoder hear the head's lips)"
        )
    net = _release_for(init, info)
    if head_decoder and net.decoder_head is None:
        net = with_decoder_head(net, init)
    net.requires_grad_(False)
    net.vqvae.decoder.requires_grad_(True)
    if net.decoder_head is not None:  # the decoder's input: it learns with the decoder
        net.decoder_head.requires_grad_(True)
    return net


def _decoder_head_parameters(net: CodeTalker) -> Iterator[torch.nn.Parameter]:
    """The parameters of the VQ decoder's head term (``stage2.head_decoder``), if it has one:
    they learn with the VQ decoder."""
    if net.decoder_head is not None:
        yield from net.decoder_head.parameters()


def with_decoder_head(net: CodeTalker, init: Path) -> CodeTalker:
    """``net`` whose VQ decoder hears the head's lips (``stage2.head_decoder``, zero at first: the
    same model), on the lip pairs of its style's head term."""
    if not net.cfg.stage2.head_pairs:
        raise TalkmeshError(
            f"{init}: model.head_decoder reads the lip pairs of the style's head term, which this "
            "release lacks: fine-tune it with model: {head_pairs: 8} first "
            "(configs/codetalker_multilingual_head.yaml)"
        )
    s2 = replace(net.cfg.stage2, head_decoder=True)
    return _grown(net, s2, "the decoder's head term", "decoder_head")


def _grown(net: CodeTalker, s2, what: str, *new: str) -> CodeTalker:
    """A model of ``net``'s config with stage 2 ``s2``, holding ``net``'s weights and the modules
    ``new`` as they start (the modules ``s2`` adds); ``what`` names them in the error."""
    grown = CodeTalker(replace(net.cfg, stage2=s2))
    result = grown.load_state_dict(net.state_dict(), strict=False)
    added = sorted(f"{m}.{t}" for m in new for t in ("bias", "weight"))
    if sorted(result.missing_keys) != added or result.unexpected_keys:
        raise TalkmeshError(f"cannot give this model {what}: {result}")
    return grown.train(net.training)


def _release_for(init: Path, info: DatasetInfo) -> CodeTalker:
    """The CodeTalker release at ``init``, checked against the data's vertex count."""
    net = load_model(init, family="codetalker")
    if net.cfg.vq.num_vertices != info.num_vertices:
        raise TalkmeshError(
            f"{init}: a {net.cfg.vq.num_vertices}-vertex model, the data has {info.num_vertices}"
        )
    return net


def _step_decoder(net: CodeTalker, batch: TorchBatch) -> StepOutput:
    net.vqvae.encoder.eval()  # frozen: no codebook usage updates
    net.vqvae.quantizer.eval()
    motion = (batch.vertices - batch.templates[:, None]).flatten(2)
    out = net.vqvae(motion, batch.motion_mask, face=net.decoder_face(batch.templates))
    return StepOutput(
        out.reconstruction, {"reconstruction": float(out.reconstruction.detach())}, out.motion
    )


def _stage2_forward(net: CodeTalker, batch: TorchBatch):
    """The speech stage's teacher-forced pass over a batch (``CodeTalker.forward``)."""
    return net(
        batch.audio,
        batch.audio_lengths,
        batch.vertices,
        batch.templates,
        batch.styles,
        batch.motion_mask,
    )


def _step_decoder_speech(net: CodeTalker, batch: TorchBatch) -> StepOutput:
    """The VQ decoder on the codes the speech stage predicts from the (augmented) audio, fed
    back as in its training (``stage2.self_feedback``), against the true motion: it learns to
    draw the codes the model will give it, not only the truth's. In training the speech stage's
    modules stay in eval mode (no dropout) while the model's own flag keeps the self-feedback."""
    training = net.training
    net.eval()
    if training:
        net.vqvae.decoder.train()
        net.training = True  # the model's self-feedback; its modules stay as set
    out = _stage2_forward(net, batch)
    net.train(training)
    return StepOutput(out.motion_loss, {"motion": float(out.motion_loss.detach())}, out.motion)


def _build_stage2(model: dict[str, Any], info: DatasetInfo, init: Path | None) -> CodeTalker:
    if init is None:
        raise TalkmeshError("task codetalker-stage2 needs init: the stage-1 release (.safetensors)")
    model = dict(model)
    head_pairs = _head_pairs(model.pop("head_pairs", 0))
    net = CodeTalker(build_config(model, info))
    source = load_model(init)
    _copy_vqvae(net, source, init)
    if source.decoder_head is not None:  # a motion stage refitted with the face needs it
        net = with_source_face(net, source, init)
    elif head_pairs:
        net = with_head(net, info, head_pairs)
    _freeze_motion_stage(net)
    return net


def with_source_face(net: CodeTalker, source: CodeTalker, init: Path) -> CodeTalker:
    """``net`` with the face term of ``source``'s VQ decoder (``stage2.head_decoder``) on its lip
    pairs: a decoder refitted with the face decodes its codes right only with that term. The
    style's head term on the same pairs starts at zero (the model as it was)."""
    s = source.cfg.stage2
    s2 = replace(
        net.cfg.stage2,
        head_pairs=s.head_pairs,
        head_mean=s.head_mean,
        head_std=s.head_std,
        head_decoder=True,
    )
    grown = _grown(net, s2, f"the face term of {init}'s decoder", "head_map", "decoder_head")
    grown.decoder_head.load_state_dict(source.decoder_head.state_dict())
    print(f"the VQ decoder's face term from {init} ({len(s.head_mean)} lip pairs)")
    return grown


def _freeze_motion_stage(net: CodeTalker) -> None:
    """Stage 2 learns with the motion stage fixed: the VQ-VAE and the decoder's head term."""
    net.vqvae.requires_grad_(False)
    if net.decoder_head is not None:
        net.decoder_head.requires_grad_(False)


def _head_pairs(value: Any) -> int:
    """A recipe's ``model.head_pairs``: how many lip pairs the style's head term reads."""
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise TalkmeshError(
            f"model.head_pairs must be a count of lip pairs (0: none), got {value!r}"
        )
    return value


def _build_finetune(model: dict[str, Any], info: DatasetInfo, init: Path | None) -> CodeTalker:
    if init is None:
        raise TalkmeshError("task codetalker-finetune needs init: a CodeTalker release to continue")
    model = dict(model)
    head_pairs = _head_pairs(model.pop("head_pairs", 0))
    if model:
        raise TalkmeshError(
            "task codetalker-finetune takes its model from init: its model section may only "
            "say head_pairs: N (a count, to give the style the head's lips)"
        )
    net = _release_for(init, info)
    if not set(net.cfg.stage2.styles) <= set(info.train_subjects):
        missing = sorted(set(net.cfg.stage2.styles) - set(info.train_subjects))
        raise TalkmeshError(
            f"{init}: trained on the speakers {', '.join(net.cfg.stage2.styles)}; this dataset's "
            f"training speakers lack {', '.join(missing)}: continue it on data that keeps them"
        )
    net = with_styles(net, tuple(info.train_subjects))
    if head_pairs and not net.cfg.stage2.head_pairs:
        net = with_head(net, info, head_pairs)
    _freeze_motion_stage(net)
    return net.train()


def with_head(net: CodeTalker, info: DatasetInfo, count: int) -> CodeTalker:
    """``net`` with a head term in its style (``stage2.head_pairs``, zero at first: the same
    model) on the ``count`` lip pairs of the training data that part the most, standardised by
    the training speakers' templates."""
    from talkmesh.training.lip_gap import lip_width, widest_lip_pairs

    dataset, lips = info.dataset, getattr(info.regions, "lve", None)
    if dataset is None:
        raise TalkmeshError("model.head_pairs needs the training data")
    pairs = widest_lip_pairs(dataset, lips, count)
    templates = np.stack([dataset.templates[s] for s in info.train_subjects])
    dist = np.linalg.norm(templates[:, pairs[:, 0]] - templates[:, pairs[:, 1]], axis=-1)
    floor = 0.01 * lip_width(templates[0], np.asarray(lips, np.int64))
    s2 = replace(
        net.cfg.stage2,
        head_pairs=tuple(int(v) for v in pairs.reshape(-1)),
        head_mean=tuple(float(v) for v in dist.mean(0)),
        head_std=tuple(float(max(v, floor)) for v in dist.std(0)),
    )
    grown = _grown(net, s2, "the head term", "head_map")
    print(f"head term on {len(pairs)} lip pairs (stage2.head_pairs)")
    return grown


def with_styles(net: CodeTalker, styles: tuple[str, ...]) -> CodeTalker:
    """``net`` with the style rows of ``styles``, in that order: a speaker it knows keeps its
    learned style, a new one starts at the mean of the known styles (the style an unseen speaker
    gets when generating), so a release can go on learning on a corpus with more speakers."""
    if tuple(net.cfg.stage2.styles) == styles:
        return net
    cfg = replace(net.cfg, stage2=replace(net.cfg.stage2, styles=styles))
    grown = CodeTalker(cfg)
    state = {k: v for k, v in net.state_dict().items() if k != "style.weight"}
    result = grown.load_state_dict(state, strict=False)
    if result.missing_keys != ["style.weight"] or result.unexpected_keys:
        raise TalkmeshError(f"cannot add speakers to this model: {result}")
    old = net.style.weight.detach()
    known = {name: n for n, name in enumerate(net.cfg.stage2.styles)}
    with torch.no_grad():
        for n, name in enumerate(styles):
            grown.style.weight[n] = old[known[name]] if name in known else old.mean(0)
    return grown


def _step_stage2(net: CodeTalker, batch: TorchBatch) -> StepOutput:
    net.vqvae.eval()  # frozen: no codebook usage updates
    out = _stage2_forward(net, batch)
    return StepOutput(
        out.loss,
        {"feature": float(out.feature_loss.detach()), "motion": float(out.motion_loss.detach())},
        out.motion,
        (out.features, out.target_codes, net.vqvae.quantizer.codebook),
    )


def prepare_speech_statistics(net, dataset) -> None:
    """A model's speech-encoder normalisation (``net.speech``, a buffer) from training audio
    (shared by the families whose speech encoder is ``net.speech``)."""
    if not hasattr(net.speech, "set_statistics"):
        return
    step = max(1, len(dataset) // STATISTICS_SAMPLES)
    audio = torch.cat([torch.from_numpy(dataset[i].audio) for i in range(0, len(dataset), step)])
    net.speech.set_statistics(audio[None])


def _prepare_stage1(net: CodeTalker, dataset) -> None:
    step = max(1, len(dataset) // STATISTICS_SAMPLES)
    motion = torch.cat(
        [
            torch.from_numpy(dataset[i].vertices - dataset[i].template).flatten(1)
            for i in range(0, len(dataset), step)
        ]
    )
    net.vqvae.set_scale(motion)


STAGE1 = Task(
    name="codetalker-stage1",
    build=_build_stage1,
    step=_step_stage1,
    parameters=lambda net: itertools.chain(net.vqvae.parameters(), _decoder_head_parameters(net)),
    save=save_model,
    prepare=_prepare_stage1,
)
STAGE2 = Task(
    name="codetalker-stage2",
    build=_build_stage2,
    step=_step_stage2,
    parameters=lambda net: (
        p for n, p in net.named_parameters() if not n.startswith(("vqvae.", "decoder_head."))
    ),
    save=save_model,
    prepare=prepare_speech_statistics,
)
DECODER = Task(
    name="codetalker-decoder",
    build=_build_decoder,
    step=_step_decoder,
    parameters=lambda net: itertools.chain(
        net.vqvae.decoder.parameters(), _decoder_head_parameters(net)
    ),
    save=save_model,
    prepare=None,
)
DECODER_SPEECH = Task(
    name="codetalker-decoder-speech",
    build=_build_decoder,
    step=_step_decoder_speech,
    parameters=DECODER.parameters,
    save=save_model,
    prepare=None,
)
FINETUNE = Task(
    name="codetalker-finetune",
    build=_build_finetune,
    step=_step_stage2,
    parameters=STAGE2.parameters,
    save=save_model,
    prepare=None,  # the release's speech statistics are part of what it learned
)
