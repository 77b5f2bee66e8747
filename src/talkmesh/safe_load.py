"""``torch.load`` of files nobody vouches for: training checkpoints and the papers' weights.

Every read is ``torch.load(weights_only=True)``: only tensors and plain containers come out and
nothing in the file runs. What this adds is the answer when a file is refused: one line that says
what the file is (a zip checkpoint, a legacy one, a plain pickle, something else) and, when it
holds code, what it tried to load (``builtins.exec``, ``os.system``...), and that none of it ran,
instead of torch's multi-paragraph advice to turn the check off. torch's warning about pickle
protocols, printed before the refusal of a plain pickle, is not shown.
"""

from __future__ import annotations

import pickle
import re
import warnings
import zipfile
from pathlib import Path
from typing import Any

from talkmesh.errors import TalkmeshError, os_error_message

NOTHING_RAN = "nothing from it ran"


def load_weights_only(path: Path, *, mmap: bool = False, kind: str = "checkpoint") -> Any:
    """``torch.load(path, weights_only=True)`` on the CPU; a refused or unreadable file is a
    one-line :class:`TalkmeshError` naming ``path`` and saying what the file is. ``mmap`` is used
    for zip checkpoints only (torch's legacy format cannot be mapped)."""
    import torch

    try:
        zipped = zipfile.is_zipfile(path)
    except OSError:
        zipped = False
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Detected pickle protocol")
            return torch.load(path, map_location="cpu", weights_only=True, mmap=mmap and zipped)
    except OSError as e:
        raise TalkmeshError(os_error_message(e, path, action="read")) from None
    except pickle.UnpicklingError as e:
        raise TalkmeshError(
            f"{path}: refused: {refusal(str(e), zipped)}: delete it or use one you trust"
        ) from None
    except (RuntimeError, EOFError, ValueError, AttributeError, IndexError, KeyError) as e:
        if "Invalid magic number" in str(e) or "invalid load key" in str(e):
            raise TalkmeshError(
                f"{path}: not a PyTorch {kind} (torch.save did not write it)"
            ) from None
        raise TalkmeshError(
            f"{path}: truncated or corrupt {kind} ({type(e).__name__}): delete it or use another"
        ) from None


def refusal(message: str, zipped: bool) -> str:
    """What torch's safe unpickler refused, in words, from its (multi-paragraph) message."""
    found = re.search(r"Unsupported global: GLOBAL ([\w.]+)", message)
    if found:
        return f"the file tries to load {found.group(1)}, which is code, not weights; {NOTHING_RAN}"
    if re.search(r"Unsupported operand \d+", message) and not zipped:
        return (
            "a plain Python pickle, not a file torch.save wrote: it may hold code and is not "
            f"unpickled; {NOTHING_RAN}"
        )
    detail = message.split("WeightsUnpickler error:")[-1].strip().splitlines()
    reason = detail[0].rstrip(".")[:100] if detail and "WeightsUnpickler" in message else ""
    return f"it holds more than tensors and plain data ({reason or 'unsupported'}); {NOTHING_RAN}"
