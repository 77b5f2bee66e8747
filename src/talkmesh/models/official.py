"""Import the papers' released checkpoints into talkmesh models (``talkmesh import-checkpoint``).

    model = import_checkpoint(["vocaset.pth"], family="faceformer", dataset="vocaset")
    save_model(model, "faceformer_vocaset.safetensors")

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

import pickle
from pathlib import Path

import torch
from torch import Tensor, nn

from talkmesh.errors import TalkmeshError

FAMILIES = ("codetalker", "faceformer", "meshtalk")
DATASETS = ("vocaset", "biwi")

# the official training subjects, in one-hot order (the columns of the style matrix)
SUBJECTS = {
    "vocaset": (
        "FaceTalk_170728_03272_TA", "FaceTalk_170904_00128_TA", "FaceTalk_170725_00137_TA",
        "FaceTalk_170915_00223_TA", "FaceTalk_170811_03274_TA", "FaceTalk_170913_03279_TA",
        "FaceTalk_170904_03276_TA", "FaceTalk_170912_03278_TA",
    ),
    "biwi": ("F2", "F3", "F4", "M3", "M4", "M5"),
}  # fmt: skip
FPS = {"vocaset": 30.0, "biwi": 25.0}
TOKENS_PER_FRAME = {"vocaset": 1, "biwi": 2}  # wav2vec2 features (50 Hz) per motion frame
MAX_FRAMES = 600  # the official positional encoding and temporal bias length


def load_checkpoint(path: str | Path) -> dict[str, Tensor]:
    """A released file -> its flat tensor dict, never running code from it.

    Accepts a plain state dict or ``{'state_dict': ...}`` (CodeTalker's trainer), strips a
    ``module.`` prefix and renames torch 1.x weight-norm tensors to today's names.
    """
    path = Path(path)
    if not path.is_file():
        raise TalkmeshError(f"{path}: no such checkpoint file")
    try:
        obj = torch.load(str(path), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:  # torch's safe unpickler met something else
        text = str(e).split("WeightsUnpickler error:")[-1].strip()
        why = text.splitlines()[0][:120] if text else type(e).__name__
        raise TalkmeshError(
            f"{path}: refused: not a plain PyTorch weight file ({why}); talkmesh never "
            "unpickles anything but tensors"
        ) from None
    except Exception as e:  # corrupt or not a torch file at all
        raise TalkmeshError(
            f"{path}: not a readable PyTorch checkpoint ({type(e).__name__})"
        ) from None
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict) or not all(
        isinstance(k, str) and isinstance(v, Tensor) for k, v in obj.items()
    ):
        raise TalkmeshError(f"{path}: not a state dict (a mapping of names to tensors)")
    out = {}
    for key, value in obj.items():
        if key.startswith("module."):
            key = key[len("module.") :]
        key = key.replace(".weight_g", ".parametrizations.weight.original0")
        key = key.replace(".weight_v", ".parametrizations.weight.original1")
        out[key] = value.float() if value.is_floating_point() else value
    return out


def _take(state: dict[str, Tensor], key: str, path: Path) -> Tensor:
    try:
        return state.pop(key)
    except KeyError:
        raise TalkmeshError(
            f"{path}: tensor '{key}' is missing: is this the right file and --family?"
        ) from None


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


def _fill(model: nn.Module, mapped: dict[str, Tensor], path: Path) -> nn.Module:
    """Load ``mapped`` into ``model``: every key present, shapes equal, strict."""
    expected = model.state_dict()
    missing = sorted(set(expected) - set(mapped))
    if missing:
        raise TalkmeshError(
            f"{path}: no tensor for talkmesh's '{missing[0]}' ({len(missing)} missing)"
        )
    for key, value in mapped.items():
        if key not in expected:
            raise TalkmeshError(f"{path}: internal mapping error: unknown key '{key}'")
        if tuple(value.shape) != tuple(expected[key].shape):
            raise TalkmeshError(
                f"{path}: '{key}' has shape {tuple(value.shape)}, this architecture needs "
                f"{tuple(expected[key].shape)}: is --dataset right?"
            )
    model.load_state_dict(mapped, strict=True)
    return model.eval()


def _leftover(state: dict[str, Tensor], path: Path) -> None:
    if state:
        names = sorted(state)
        raise TalkmeshError(
            f"{path}: unexpected tensor '{names[0]}' ({len(names)} not used): "
            "is this the right file and --family?"
        )


def import_faceformer(path: Path, dataset: str) -> nn.Module:
    """FaceFormer's released ``vocaset.pth`` / ``biwi.pth`` -> a :class:`FaceFormer`."""
    from talkmesh.models.faceformer import FaceFormer, FaceFormerConfig
    from talkmesh.models.postnorm import interleaved_encoding
    from talkmesh.models.speech import SpeechEncoderConfig

    state = load_checkpoint(path)
    feature_map = state.get("audio_feature_map.weight")
    vertice_map = state.get("vertice_map.weight")
    styles = state.get("obj_vector.weight")
    if feature_map is None or vertice_map is None or styles is None:
        raise TalkmeshError(f"{path}: not a FaceFormer checkpoint (no audio_feature_map, "
                            "vertice_map or obj_vector tensors): check --family")  # fmt: skip
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
    pe = _take(state, "PPE.pe", path)
    rows = period * (MAX_FRAMES // period + 1)
    if pe.shape != (1, rows, d) or not torch.allclose(
        pe[0], interleaved_encoding(rows, d, period), atol=1e-5
    ):
        raise TalkmeshError(
            f"{path}: its positional encoding is not the period-{period} one of a {dataset} "
            "model: is --dataset right?"
        )
    mapped = {"scale": torch.ones(())}
    for key in list(state):
        if key.startswith("audio_encoder."):
            mapped["speech.model." + key[len("audio_encoder.") :]] = state.pop(key)
        elif key.startswith("transformer_decoder.layers."):
            mapped["blocks." + key[len("transformer_decoder.layers.") :]] = state.pop(key)
    for ours, theirs in (("audio_map", "audio_feature_map"), ("motion_map", "vertice_map"),
                         ("out", "vertice_map_r")):  # fmt: skip
        for p in ("weight", "bias"):
            mapped[f"{ours}.{p}"] = _take(state, f"{theirs}.{p}", path)
    mapped["style.weight"] = _take(state, "obj_vector.weight", path).t().contiguous()
    _leftover(state, path)
    return _fill(model, mapped, path)


def import_checkpoint(files: list[str | Path], family: str, dataset: str) -> nn.Module:
    """The released file(s) of ``family`` trained on ``dataset`` -> a talkmesh model (eval mode)."""
    if family not in FAMILIES:
        raise TalkmeshError(f"unknown family '{family}': use one of {', '.join(FAMILIES)}")
    dataset = dataset.lower()
    if dataset not in DATASETS:
        raise TalkmeshError(f"unknown dataset '{dataset}': use vocaset or biwi")
    paths = [Path(f) for f in files]
    if family == "faceformer":
        if len(paths) != 1:
            raise TalkmeshError(
                f"a FaceFormer release is one file (vocaset.pth or biwi.pth), got {len(paths)}"
            )
        return import_faceformer(paths[0], dataset)
    raise TalkmeshError(
        f"importing {family} checkpoints is not supported yet: only faceformer imports today"
    )
