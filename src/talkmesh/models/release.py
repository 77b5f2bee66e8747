"""Released models: one self-describing ``.safetensors`` file (weights + JSON config + format
version in the metadata), loaded with ``strict=True`` and no pickle.

    model = talkmesh.load_model("runs/ct2/model.safetensors")   # or a bundled name

Every learned family implements :class:`talkmesh.models.base.MotionModel` and is listed in
:data:`talkmesh.models.registry.FAMILIES`; a release stores the family's name and its ``cfg``
(never a module or class path, so files outlive moves of the code), so ``load_model`` rebuilds it
as ``cls(cfg)`` from the file alone.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import torch
from torch import nn

from talkmesh.config import from_dict, to_dict
from talkmesh.errors import MissingDependencyError, TalkmeshError
from talkmesh.models.base import MotionModel
from talkmesh.models.bundled import MODELS_DIR, resolve
from talkmesh.models.registry import FAMILIES

FORMAT_VERSION = 1
MAX_CONFIG_CHARS = 1_000_000  # a config is a few kB of JSON; more is not one talkmesh wrote
__all__ = ["MODELS_DIR", "load_model", "resolve", "save_model"]


def save_model(model: MotionModel, path: str | Path, *, dtype: torch.dtype | None = None) -> Path:
    """Write ``model`` (its ``cfg`` travels in the metadata); ``dtype`` e.g. torch.float16 to ship."""
    try:
        from safetensors.torch import save_file
    except ImportError:
        raise MissingDependencyError("safetensors", "models", "saving models") from None
    family = getattr(model, "family", None)
    if family not in FAMILIES or not isinstance(model, FAMILIES[family]):
        raise TalkmeshError(f"cannot release a {type(model).__name__}")
    state = {}
    for k, v in model.state_dict().items():
        v = v.detach().cpu().contiguous()
        state[k] = v.to(dtype) if dtype is not None and v.is_floating_point() else v
    meta = {
        "format": "talkmesh-model",
        "format_version": str(FORMAT_VERSION),
        "family": family,
        "config": json.dumps(to_dict(model.cfg)),
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    save_file(state, str(tmp), metadata=meta)
    tmp.replace(path)
    return path


def load_model(
    name_or_path: str | Path, *, dtype: torch.dtype = torch.float32, family: str | None = None
) -> MotionModel:
    """Rebuild a released model offline from its file alone (``strict=True``), in eval mode.

    ``family`` (e.g. ``"meshtalk"``), when given, is required of the file. A ``.onnx`` file of
    ``talkmesh export-onnx`` is run by ONNX Runtime (:class:`talkmesh.models.onnx.OnnxModel`).
    """
    if str(name_or_path).lower().endswith(".onnx") and family is None:
        from talkmesh.models.onnx import OnnxModel

        return OnnxModel(name_or_path)  # type: ignore[return-value]  # a MotionModel's surface
    try:
        from safetensors import safe_open
        from safetensors.torch import load_file
    except ImportError:
        raise MissingDependencyError("safetensors", "models", "loading models") from None
    path = resolve(name_or_path)
    try:
        with safe_open(str(path), "pt") as f:
            meta = f.metadata() or {}
        state = load_file(str(path))
    except Exception as e:  # safetensors raises its own error types on corrupt files
        raise TalkmeshError(
            f"{path}: not a readable .safetensors model ({type(e).__name__})"
        ) from None
    if meta.get("format") != "talkmesh-model":
        raise TalkmeshError(f"{path}: not a talkmesh model release")
    version, config = meta.get("format_version", "0"), meta.get("config", "")
    if not version.isdigit() or len(config) > MAX_CONFIG_CHARS:
        raise TalkmeshError(f"{path}: a malformed talkmesh model release (its metadata)")
    if int(version) > FORMAT_VERSION:
        raise TalkmeshError(
            f"{path}: written by a newer talkmesh (format {meta['format_version']}): upgrade"
        )
    if meta.get("family") not in FAMILIES:
        raise TalkmeshError(
            f"{path}: unknown model family {meta.get('family')!r}: upgrade talkmesh"
        )
    if family is not None and meta["family"] != family:
        raise TalkmeshError(f"{path}: a {meta['family']} model, not {family}")
    cls = FAMILIES[meta["family"]]
    try:
        stored = json.loads(config)
    except (ValueError, RecursionError) as e:  # RecursionError: JSON nested thousands deep
        raise TalkmeshError(
            f"{path}: a malformed talkmesh model release (its config: {type(e).__name__})"
        ) from None
    if not isinstance(stored, dict):
        raise TalkmeshError(f"{path}: a malformed talkmesh model release (its config)")
    with no_random_init():  # strict=True below replaces every parameter the init would draw
        model = cls(from_dict(cls.config_class, stored))
    # assign: the loaded tensors become the parameters, with no random init before them. Each is
    # a fresh copy (copy=True; the conversion itself for float16 files), not a view into the
    # file's buffer, whose alignment changed the last bits of some models' products
    model.load_state_dict(
        {k: v.to(dtype if v.is_floating_point() else v.dtype, copy=True) for k, v in state.items()},
        strict=True,
        assign=True,
    )
    return model.to(dtype).eval()


RANDOM_INITS = (
    "uniform_",
    "normal_",
    "trunc_normal_",
    "kaiming_uniform_",
    "kaiming_normal_",
    "xavier_uniform_",
    "xavier_normal_",
    "orthogonal_",
)


@contextmanager
def no_random_init() -> Iterator[None]:
    """Build a module whose weights are then loaded: ``torch.nn.init``'s random draws leave their
    tensors as they are meanwhile (as transformers' ``no_init_weights`` does). The draws were
    0.15-0.5 s of loading the bundled CodeTalker, for numbers overwritten at once; buffers that
    are computed (windows, masks) and zeros/ones are made as usual."""
    saved = {name: getattr(nn.init, name) for name in RANDOM_INITS}

    def keep(tensor, *args, **kwargs):
        return tensor

    for name in RANDOM_INITS:
        setattr(nn.init, name, keep)
    try:
        yield
    finally:
        for name, init in saved.items():
            setattr(nn.init, name, init)
