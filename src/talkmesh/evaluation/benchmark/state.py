"""State on disk: file digests, the JSON records each step writes, and what each step would do
(skip, resume, train, retrain) given what is already there."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Literal

from talkmesh.config import to_dict
from talkmesh.evaluation.benchmark.config import DONE_FILE, TIMING_FILE, StagePlan

_DIGESTS: dict[tuple[str, int, int], str] = {}


def file_digest(path: str | Path) -> str:
    """sha256 of a file, memoised on (path, size, mtime)."""
    p = Path(path)
    st = p.stat()
    key = (str(p.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _DIGESTS:
        h = hashlib.sha256()
        with p.open("rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        _DIGESTS[key] = h.hexdigest()
    return _DIGESTS[key]


def read_json(path: Path) -> dict[str, Any] | None:
    """A JSON record, or None when it is missing or half-written."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def write_json(path: Path, data: Any) -> None:
    """Write a JSON record atomically (a killed run never leaves half a record)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
    tmp.replace(path)


StageState = Literal["done", "resume", "train", "stale", "waiting"]


def stage_state(plan: StagePlan) -> StageState:
    """done (skip), resume (last.ckpt, no model), train (nothing yet), stale (its recipe or its
    init changed since it was trained: retrain) or waiting (its init does not exist yet)."""
    init = plan.recipe.init
    if init and not Path(init).is_file():
        return "waiting"
    record = read_json(plan.out_dir / TIMING_FILE)
    if record is not None and init and record.get("init_digest") != file_digest(init):
        return "stale"
    trained = read_json(plan.out_dir / "recipe.json")  # written by train()
    if trained is not None and trained != json.loads(json.dumps(to_dict(plan.recipe))):
        return "stale"
    if plan.release.is_file():
        return "done"
    return "resume" if (plan.out_dir / "last.ckpt").is_file() else "train"


def predictions_done(pred_dir: Path, release: Path | None) -> bool:
    """Whether ``pred_dir`` is complete (for a model: from this very release)."""
    record = read_json(pred_dir / DONE_FILE)
    if record is None:
        return False
    if release is None:
        return True
    return release.is_file() and record.get("model_digest") == file_digest(release)
