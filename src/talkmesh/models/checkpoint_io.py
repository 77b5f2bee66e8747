"""Reading the papers' released checkpoints safely and filling talkmesh models from them: the
helpers that :mod:`talkmesh.models.official` and :mod:`talkmesh.models.meshtalk.official` share.

A checkpoint is untrusted input: it is read with ``torch.load(weights_only=True)`` only, so it can
never run code; what does not fit is named in a one-line error.
"""

from __future__ import annotations

from pathlib import Path

from torch import Tensor, nn

from talkmesh.errors import TalkmeshError
from talkmesh.safe_load import load_weights_only


def load_checkpoint(path: str | Path) -> dict[str, Tensor]:
    """A released file -> its flat tensor dict, never running code from it.

    Accepts a plain state dict or ``{'state_dict': ...}`` (CodeTalker's trainer), strips a
    ``module.`` prefix and renames torch 1.x weight-norm tensors to today's names.
    """
    path = Path(path)
    if not path.is_file():
        raise TalkmeshError(f"{path}: no such checkpoint file")
    obj = load_weights_only(path, kind="weight file")
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
