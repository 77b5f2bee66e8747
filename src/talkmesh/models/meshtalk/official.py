"""Import MeshTalk's released model (facebookresearch/meshtalk, ``pretrained_models.zip``) into a
:class:`talkmesh.models.meshtalk.model.MeshTalkModel` (``talkmesh import-checkpoint --family meshtalk``).

The release is three files written by the official ``Net.save`` (``torch.save(state_dict())``):
``encoder.pkl`` (MultimodalEncoder: mel audio encoder, expression encoder, fusion MLP),
``context_model.pkl`` (the autoregressive ContextModel) and ``vertex_unet.pkl`` (the decoder).
They are told apart by their tensors, read with ``torch.load(weights_only=True)`` only
(:func:`talkmesh.models.checkpoint_io.load_checkpoint`), and every tensor is mapped onto one talkmesh
key or checked against what talkmesh computes (the mel filterbank, window and head masks);
the ``unmasked_linear`` of the prior's embedding and classifier, which the official code builds
but never reads, are shape-checked and dropped. Optional text files from the official
``assets/`` folder (same names) add the demo's smoothing masks (``forehead_mask.txt``,
``neck_mask.txt``) and the training region maps (``weighted_mouth_mask.txt``,
``weighted_eye_mask.txt``, ``eye_keypoints.txt``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from talkmesh.errors import TalkmeshError

HIDDEN = 64  # the official ContextModel's width per head (hard-coded there)
AUDIO_DILATIONS = (2, 4, 6, 2, 4, 6)  # the official AudioEncoder: 2 * (i % 3 + 1)
CONTEXT_DILATIONS = (1, 2, 4, 8)
SMOOTHING = ("forehead_mask.txt", "neck_mask.txt")  # animate_face.py's order
REGIONS = ("weighted_mouth_mask.txt", "weighted_eye_mask.txt", "eye_keypoints.txt")
PARTS = {  # a tensor only that file has -> its name in the release
    "audio_encoder.code.weight": "encoder.pkl",
    "embedding.masked_linear.weight": "context_model.pkl",
    "vertex_bias": "vertex_unet.pkl",
}


def _files(paths: list[Path]) -> tuple[dict[str, dict[str, Tensor]], dict[str, np.ndarray], Path]:
    """The release's three state dicts (by part) and the asset masks (by file name); a folder
    stands for the files in it."""
    from talkmesh.models.checkpoint_io import load_checkpoint

    files = []
    for path in paths:
        if path.is_dir():
            files += sorted(p for p in path.iterdir() if p.suffix in (".pkl", ".txt"))
        else:
            files.append(path)
    parts, masks = {}, {}
    for path in files:
        if path.suffix == ".txt":
            if path.name not in SMOOTHING + REGIONS:
                raise TalkmeshError(
                    f"{path}: not one of MeshTalk's asset masks ({', '.join(SMOOTHING + REGIONS)})"
                )
            try:
                masks[path.name] = np.loadtxt(path, dtype=np.float32).reshape(-1)
            except ValueError:
                raise TalkmeshError(f"{path}: not a column of numbers") from None
            continue
        state = load_checkpoint(path)
        part = next((name for key, name in PARTS.items() if key in state), None)
        if part is None:
            raise TalkmeshError(
                f"{path}: not one of MeshTalk's encoder.pkl, context_model.pkl, vertex_unet.pkl"
            )
        if part in parts:
            raise TalkmeshError(f"{path}: a second {part} (pass each file once)")
        parts[part] = state
    missing = [p for p in PARTS.values() if p not in parts]
    if missing:
        raise TalkmeshError(
            f"a MeshTalk release is encoder.pkl, context_model.pkl and vertex_unet.pkl: "
            f"{', '.join(missing)} missing (the files of pretrained_models.zip, or its folder)"
        )
    return parts, masks, files[0]


def _configs(parts: dict, fps: float, smoothing: int, path: Path):
    from talkmesh.models.mel import MelConfig
    from talkmesh.models.meshtalk.model import MeshTalkConfig, MeshTalkModelConfig, SamplingConfig
    from talkmesh.models.meshtalk.prior import PriorConfig

    enc, ctx, unet = parts["encoder.pkl"], parts["context_model.pkl"], parts["vertex_unet.pkl"]
    try:
        V = unet["mean"].shape[-2]
        HC = enc["fusion_model.mlp.4.weight"].shape[0]
        H = ctx["embedding.masked_linear.weight"].shape[0] // HIDDEN
        audio_dim = enc["audio_encoder.code.weight"].shape[0]
        expression_dim = enc["expression_encoder.code.weight"].shape[0]
    except (KeyError, IndexError):
        raise TalkmeshError(
            f"{path}: not a MeshTalk release (a tensor it needs is missing)"
        ) from None
    if H < 1 or HC % H or ctx["embedding.masked_linear.weight"].shape[1] != HC:
        raise TalkmeshError(f"{path}: the prior's heads do not match the encoder's {HC} logits")
    audio = MelConfig(
        width=128,
        kernel_size=5,
        dilations=AUDIO_DILATIONS,
        input_kernel=5,
        lookahead_ms=500.0,  # the window's half after the frame
        out_dim=audio_dim,
        log_floor=1e-10,
        windows=True,
        gain=0.01,
        mel_statistics=False,
    )
    model = MeshTalkConfig(
        V,
        fps,
        num_heads=H,
        num_classes=HC // H,
        audio=audio,
        expression_widths=(256, 128),
        expression_output=expression_dim,
        fusion_width=256,
        decoder_widths=(512, 256, 128),
        decoder_lstm_layers=2,
        vertex_norm="per_vertex",
        official_decoder=True,
    )
    prior = PriorConfig(
        num_heads=H,
        num_classes=HC // H,
        width=HIDDEN,
        dilations=CONTEXT_DILATIONS,
        kernel_size=2,
        audio=audio,
        fps=fps,
        audio_source="expression",
        layout="official",
    )
    return MeshTalkModelConfig(model, prior, SamplingConfig(gumbel=True), smoothing)


def _lstm(state: dict, theirs: str, ours: str, layers: int, path: Path) -> dict:
    from talkmesh.models.checkpoint_io import _take

    out = {}
    for layer in range(layers):
        for kind in ("weight_ih", "weight_hh", "bias_ih", "bias_hh"):
            out[f"{ours}.{kind}_l{layer}"] = _take(state, f"{theirs}.{kind}_l{layer}", path)
    return out


def _check_fixed(name: str, got: Tensor, want: Tensor, path: Path) -> None:
    """A tensor the official code computes (filterbank, window, masks) against talkmesh's."""
    if got.shape != want.shape or not torch.allclose(got.float(), want, atol=1e-4, rtol=1e-4):
        raise TalkmeshError(
            f"{path}: '{name}' is not the official code's fixed tensor: is this a MeshTalk release?"
        )


def _encoder_map(enc: dict, net, path: Path) -> dict:
    """encoder.pkl -> ``model.*`` (the mel encoder, expression encoder, fusion MLP)."""
    from talkmesh.models.checkpoint_io import _take

    audio = net.model.audio_encoder
    _check_fixed(
        "audio_encoder.melspec.mel_scale.fb",
        _take(enc, "audio_encoder.melspec.mel_scale.fb", path),
        audio.filterbank,
        path,
    )
    _check_fixed(
        "audio_encoder.melspec.spectrogram.window",
        _take(enc, "audio_encoder.melspec.spectrogram.window", path),
        audio.window,
        path,
    )
    m = {
        "model.audio_encoder.mel_mean": torch.zeros(80),
        "model.audio_encoder.mel_std": torch.ones(80),
    }
    pairs = [("audio_encoder.convert_dimensions", "model.audio_encoder.input")]
    pairs += [(f"audio_encoder.convs.{i}", f"model.audio_encoder.convs.{i}") for i in range(6)]
    pairs += [("audio_encoder.code", "model.audio_encoder.output")]
    pairs += [
        (f"expression_encoder.layers.{i}", f"model.expression_encoder.layers.{i}") for i in (0, 1)
    ]
    pairs += [("expression_encoder.code", "model.expression_encoder.code")]
    pairs += [(f"fusion_model.mlp.{a}", f"model.fusion.layers.{b}") for a, b in ((2, 1), (4, 2))]
    for theirs, ours in pairs:
        for kind in ("weight", "bias"):
            m[f"{ours}.{kind}"] = _take(enc, f"{theirs}.{kind}", path)
    m.update(_lstm(enc, "expression_encoder.lstm", "model.expression_encoder.lstm", 1, path))
    # the official fusion reads [expression, audio]; talkmesh's reads [audio, expression]
    w = _take(enc, "fusion_model.mlp.0.weight", path)
    e = net.cfg.model.expression_output
    m["model.fusion.layers.0.weight"] = torch.cat([w[:, e:], w[:, :e]], dim=1)
    m["model.fusion.layers.0.bias"] = _take(enc, "fusion_model.mlp.0.bias", path)
    for name in ("mean", "stddev"):  # the same statistics as the decoder's (checked there)
        m[f"expression.{name}"] = _take(enc, f"expression_encoder.{name}", path)
    return m


def _unet_map(unet: dict, path: Path) -> dict:
    """vertex_unet.pkl -> ``model.decoder.*`` and the per-vertex statistics."""
    from talkmesh.models.checkpoint_io import _take

    m = {}
    pairs = [(f"encoder.{i}", f"model.decoder.encoder.{i}") for i in range(3)]
    pairs += [("fusion", "model.decoder.bottleneck")]
    pairs += [(f"decoder.{i}", f"model.decoder.decoder.{i}") for i in (0, 1)]
    pairs += [("decoder.2", "model.decoder.output")]
    for theirs, ours in pairs:
        for kind in ("weight", "bias"):
            m[f"{ours}.{kind}"] = _take(unet, f"{theirs}.{kind}", path)
    m.update(_lstm(unet, "temporal", "model.decoder.lstm", 2, path))
    m["model.decoder.vertex_bias"] = _take(unet, "vertex_bias", path)
    mean, std = _take(unet, "mean", path), _take(unet, "stddev", path)
    m["model.template_mean"] = mean.reshape(-1, 3)
    m["model.template_scale"] = std.reshape(-1, 3)
    m["model.offset_scale"] = std.reshape(-1, 3)
    return m


def _context_map(ctx: dict, H: int, C: int, path: Path) -> dict:
    """context_model.pkl -> ``prior.*``; the head masks are checked, the embedding's and
    classifier's audio maps (built, never read by the official code) dropped."""
    from talkmesh.models.checkpoint_io import _take
    from talkmesh.models.meshtalk.context import head_mask

    m = {}
    stages = [("embedding", "prior.embedding", C, HIDDEN)]
    stages += [(f"context_layers.{i}", f"prior.layers.{i}", HIDDEN, HIDDEN) for i in range(4)]
    stages += [("logits", "prior.classifier", HIDDEN, C)]
    for theirs, ours, d_in, d_out in stages:
        mask = _take(ctx, f"{theirs}.mask", path)
        _check_fixed(f"{theirs}.mask", mask.squeeze(-1), head_mask(H, d_out, d_in), path)
        m[f"{ours}.masked.weight"] = _take(ctx, f"{theirs}.masked_linear.weight", path).squeeze(-1)
        m[f"{ours}.masked.bias"] = _take(ctx, f"{theirs}.masked_linear.bias", path)
        w = _take(ctx, f"{theirs}.unmasked_linear.weight", path).squeeze(-1)
        b = _take(ctx, f"{theirs}.unmasked_linear.bias", path)
        if theirs.startswith("context_layers"):
            m[f"{ours}.audio.weight"], m[f"{ours}.audio.bias"] = w, b
            m[f"{ours}.historic.weight"] = _take(ctx, f"{theirs}.historic.weight", path)
            m[f"{ours}.historic.bias"] = _take(ctx, f"{theirs}.historic.bias", path)
        elif w.shape[0] != H * d_out:
            raise TalkmeshError(
                f"{path}: '{theirs}.unmasked_linear.weight' has shape {tuple(w.shape)}"
            )
    return m


def import_meshtalk(paths: list[Path], fps: float, num_vertices: int | None = None):
    """MeshTalk's released files (+ optional asset masks) -> a :class:`MeshTalkModel`;
    ``num_vertices``: the vertex count ``--dataset`` promises (None: MeshTalk's own mesh)."""
    from talkmesh.models.checkpoint_io import _fill, _leftover
    from talkmesh.models.meshtalk.model import MeshTalkModel

    parts, masks, first = _files(paths)
    smooth = [name for name in SMOOTHING if name in masks]
    if len(smooth) == 1:
        raise TalkmeshError(
            f"the demo smooths with both {' and '.join(SMOOTHING)}: pass both or neither"
        )
    cfg = _configs(parts, fps, len(smooth), first)
    V = cfg.model.num_vertices
    if num_vertices is not None and V != num_vertices:
        raise TalkmeshError(
            f"{first}: a MeshTalk of {V} vertices, the dataset's mesh has {num_vertices}: is "
            "--dataset right? (--dataset meshtalk: the release's own face mesh)"
        )
    for name, values in masks.items():
        if values.shape != (V,):
            raise TalkmeshError(f"{name}: {values.size} values, the model has {V} vertices")
    eyelids = masks.get("eye_keypoints.txt")
    maps = (
        masks.get("weighted_mouth_mask.txt"),
        masks.get("weighted_eye_mask.txt"),
        None if eyelids is None else torch.from_numpy(np.flatnonzero(eyelids > 0)),
    )
    net = MeshTalkModel(cfg, tuple(None if v is None else torch.as_tensor(v) for v in maps))
    enc, ctx, unet = parts["encoder.pkl"], parts["context_model.pkl"], parts["vertex_unet.pkl"]
    mapped = _encoder_map(enc, net, first)
    expression = mapped.pop("expression.mean"), mapped.pop("expression.stddev")
    mapped.update(_unet_map(unet, first))
    if not all(
        torch.equal(a.reshape(-1, 3), mapped[k])
        for a, k in zip(expression, ("model.template_mean", "model.template_scale"))
    ):
        raise TalkmeshError(
            "encoder.pkl and vertex_unet.pkl hold different vertex statistics "
            "(face_mean/face_std): files of two different models?"
        )
    mapped.update(_context_map(ctx, cfg.model.num_heads, cfg.model.num_classes, first))
    for key in ("model.mouth_weight", "model.upper_weight", "model.eyelid_mask"):
        mapped[key] = net.state_dict()[key]  # from the asset masks, or the uniform defaults
    if smooth:
        mapped["smooth_masks"] = torch.stack([torch.from_numpy(masks[n]) for n in smooth])
    for name, state in parts.items():
        _leftover(state, Path(name))
    return _fill(net, mapped, first)


DATASETS = ("meshtalk", "vocaset", "biwi")  # meshtalk: the release's own face mesh


def import_official(paths: list[Path], dataset: str):
    """:func:`import_meshtalk` at ``dataset``'s frame rate, checking its vertex count."""
    from talkmesh.models.official import FPS, VERTICES

    return import_meshtalk(paths, FPS[dataset], VERTICES.get(dataset))
