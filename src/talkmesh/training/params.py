"""Which parameters a training run changes, and how: the subset that learns
(``train.trainable``) and the weight-decay groups (``train.weight_decay_modules``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from talkmesh.errors import TalkmeshError

if TYPE_CHECKING:
    import torch


def trainable(model, parameters, names: tuple[str, ...]) -> list:
    """The parameters that learn: the task's ``parameters`` that need gradients, and with
    ``names`` only those whose name starts with one of them."""
    params = [p for p in parameters if p.requires_grad]
    if not names:
        return params
    chosen = {id(p) for n, p in model.named_parameters() if n.startswith(tuple(names))}
    params = [p for p in params if id(p) in chosen]
    if not params:
        raise TalkmeshError(
            f"train.trainable {list(names)} names none of the parameters this task trains: "
            "use parameter names of the model (e.g. head_map.weight)"
        )
    return params


def decay_groups(
    net: torch.nn.Module, params: list, weight_decay: float, modules: tuple[str, ...]
) -> list[dict]:
    """Optimizer parameter groups: weight decay on the parameters under ``modules`` (dotted
    sub-module names of ``net``; empty: all of them), none on the others."""
    if not modules:
        return [{"params": params, "weight_decay": weight_decay}]
    names = {id(p): n for n, p in net.named_parameters()}
    for m in modules:
        if not any(n.startswith(m + ".") for n in names.values()):
            raise TalkmeshError(
                f"train.weight_decay_modules: {m!r} names no parameters of the trained network "
                f"(its sub-modules: {', '.join(sorted({n.split('.')[0] for n in names.values()}))})"
            )
    decayed = [p for p in params if any(names[id(p)].startswith(m + ".") for m in modules)]
    chosen = {id(p) for p in decayed}
    rest = [p for p in params if id(p) not in chosen]
    return [
        {"params": decayed, "weight_decay": weight_decay},
        {"params": rest, "weight_decay": 0.0},
    ]
