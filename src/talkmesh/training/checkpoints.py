"""Training checkpoints: read without running code, find the one to resume, check it fits the recipe.

A Lightning checkpoint is a pickle. Every read here goes through ``torch.load(weights_only=True)``,
which rebuilds only tensors and plain containers: a file that asks for anything else (a crafted
``__reduce__``) is refused with one line naming it, and nothing in it runs.

Resume picks the newest *complete* checkpoint of a run folder by the step stored in it, whatever the
file is called (Lightning writes ``last-v1.ckpt``, ``last-v2.ckpt`` ... when ``last.ckpt`` exists
from elsewhere); files that do not load (truncated by a kill, refused) are skipped with a warning.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path
from typing import Any, NamedTuple

from talkmesh.datasets.pickles import check_bounded
from talkmesh.errors import TalkmeshError, TalkmeshWarning
from talkmesh.safe_load import load_weights_only

# Recipe keys that decide the model's tensors (and the optimiser's state): a resume with other
# values cannot load the checkpoint.
FIXED_KEYS = ("task", "model.", "data.kind", "data.regions", "train.optimizer")
# Recipe keys that may change on resume (they only move where the run goes from here).
FREE_KEYS = ("train.out_dir", "train.record_batches", "data.num_workers", "train.accelerator")


class Checkpoint(NamedTuple):
    path: Path
    step: int
    epoch: int
    data: dict[str, Any]


def read_checkpoint(path: str | Path, *, mmap: bool = True) -> dict[str, Any]:
    """A checkpoint's contents, tensors and plain containers only (nothing in the file runs).

    Raises:
        TalkmeshError: one line naming ``path``: missing, truncated/corrupt, or holding objects
            other than tensors and plain data (a pickle that would run code is one of these).
    """
    path = Path(path)
    if not path.is_file():
        raise TalkmeshError(f"checkpoint not found: {path}")
    data = load_weights_only(path, mmap=mmap)
    if not isinstance(data, dict):
        raise TalkmeshError(f"{path}: not a talkmesh training checkpoint ({type(data).__name__})")
    check_bounded(data, path)  # a recipe of dicts shared 34 levels deep would never be compared
    for key in ("global_step", "epoch"):
        value = data.get(key, 0)
        if not isinstance(value, int) or isinstance(value, bool):
            raise TalkmeshError(
                f"{path}: not a talkmesh training checkpoint ({key} is {type(value).__name__} "
                f"{str(value)[:20]!r}, not a whole number)"
            )
    for key in ("state_dict", "talkmesh_recipe"):
        if key in data and not isinstance(data[key], dict):
            raise TalkmeshError(
                f"{path}: not a talkmesh training checkpoint (its {key} is a "
                f"{type(data[key]).__name__}, not a mapping)"
            )
    return data


def checkpoint_files(out: Path) -> list[Path]:
    """The ``*.ckpt`` files directly in a run folder."""
    return sorted(p for p in Path(out).glob("*.ckpt") if p.is_file())


def newest_checkpoint(out: Path) -> Checkpoint:
    """The loadable checkpoint of ``out`` with the highest stored step (then epoch, then mtime).

    Unloadable ones are skipped with a :class:`TalkmeshWarning` each; none loadable is an error.
    """
    files = checkpoint_files(out)
    if not files:
        raise TalkmeshError(
            f"nothing to resume: {out} holds no .ckpt file (drop --resume to start)"
        )
    found: list[Checkpoint] = []
    problems: list[str] = []
    for path in files:
        try:
            data = read_checkpoint(path)
        except TalkmeshError as e:
            problems.append(str(e))
            continue
        found.append(
            Checkpoint(path, int(data.get("global_step", -1)), int(data.get("epoch", -1)), data)
        )
    if not found:
        raise TalkmeshError(f"nothing to resume in {out}: " + "; ".join(problems))
    best = max(found, key=lambda c: (c.step, c.epoch, c.path.stat().st_mtime))
    for problem in problems:
        warnings.warn(
            f"skipped {problem}; resuming from {best.path.name}", TalkmeshWarning, stacklevel=2
        )
    return best


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in d.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[prefix + key] = value
    return out


def recipe_differences(old: dict[str, Any], new: dict[str, Any]) -> dict[str, tuple[Any, Any]]:
    """Dotted recipe keys whose values differ: ``{key: (checkpoint's, recipe's)}``."""
    a, b = _flat(old), _flat(new)
    return {k: (a.get(k), b.get(k)) for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)}


def check_resume(ckpt: Checkpoint, recipe: dict[str, Any]) -> None:
    """Refuse a recipe whose model differs from the checkpoint's; warn about changed settings.

    Raises:
        TalkmeshError: one line listing the differing keys that decide tensor shapes (model,
            task, dataset kind, regions) or the optimiser's state.
    """
    stored = ckpt.data.get("talkmesh_recipe")
    if not isinstance(stored, dict):
        raise TalkmeshError(f"{ckpt.path}: not written by talkmesh train (no recipe inside)")
    diff = recipe_differences(stored, recipe)
    fixed = [k for k in diff if k.startswith(FIXED_KEYS)]
    if fixed:
        listed = ", ".join(f"{k} ({diff[k][0]!r} -> {diff[k][1]!r})" for k in fixed)
        raise TalkmeshError(
            f"cannot resume from {ckpt.path}: the recipe differs from the checkpoint's in what "
            f"shapes the model: {listed}; use the run's recipe or start a new train.out_dir"
        )
    changed = [k for k in diff if not k.startswith(FREE_KEYS)]
    if changed:
        listed = ", ".join(f"{k} {diff[k][0]!r} -> {diff[k][1]!r}" for k in changed)
        warnings.warn(
            f"resuming with changed settings (checkpoint -> recipe): {listed}; the recipe's "
            "values apply from here on",
            TalkmeshWarning,
            stacklevel=2,
        )


def check_state_shapes(ckpt: Checkpoint, model_state: dict[str, Any]) -> None:
    """Refuse a checkpoint whose weights do not fit the model built from the recipe (one line)."""
    stored = ckpt.data.get("state_dict", {})
    ours = {k: tuple(v.shape) for k, v in model_state.items()}
    theirs = {k: tuple(v.shape) for k, v in stored.items() if hasattr(v, "shape")}
    differ = sorted(k for k in set(ours) | set(theirs) if ours.get(k) != theirs.get(k))
    if differ:
        listed = ", ".join(f"{k} {theirs.get(k)} -> {ours.get(k)}" for k in differ[:6])
        more = f" and {len(differ) - 6} more" if len(differ) > 6 else ""
        raise TalkmeshError(
            f"cannot resume from {ckpt.path}: its weights do not fit the model the recipe builds "
            f"({listed}{more}): use the run's recipe and dataset or start a new train.out_dir"
        )


def announce(ckpt: Checkpoint) -> None:
    """Say which checkpoint a resume continues (always: it decides what the run trains)."""
    print(
        f"talkmesh: resuming from {ckpt.path} (epoch {ckpt.epoch + 1} done, step {ckpt.step})",
        file=sys.stderr,
        flush=True,
    )
