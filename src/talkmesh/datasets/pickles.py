"""The safe unpickler for the pickles datasets ship (templates.pkl, VOCASET's index and audio,
FLAME's vertex masks): only dicts, lists, strings, numbers and numpy arrays can come out of
them, so no code in a file can run while it is read."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from talkmesh.errors import TalkmeshError


class _SafeUnpickler(pickle.Unpickler):
    """Only what dicts of numpy arrays need: no code can run while loading a template file."""

    ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("copyreg", "_reconstructor"),
        ("builtins", "object"),
        ("__builtin__", "object"),
        ("collections", "OrderedDict"),
        ("_codecs", "encode"),  # how Python 3 writes bytes (array data) into protocol-2 pickles
    }

    def find_class(self, module: str, name: str):
        if (module, name) in self.ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}")


def safe_load_pickle(path: str | Path) -> object:
    """Load a (Python 2 or 3) pickle that may only hold dicts, lists, strings, numbers and arrays."""
    path = Path(path)
    if not path.is_file():
        raise TalkmeshError(f"{path} is missing")
    try:
        with path.open("rb") as f:
            obj = _SafeUnpickler(f, encoding="latin1").load()
    except pickle.UnpicklingError as e:
        raise TalkmeshError(
            f"{path}: unsafe or corrupt pickle ({e}); templates may hold only arrays"
        ) from None
    except (EOFError, ValueError, TypeError, AttributeError, ImportError, IndexError) as e:
        raise TalkmeshError(f"{path}: corrupt pickle ({type(e).__name__})") from None
    _check_plain(obj, path)
    return obj


def _check_plain(obj: object, path: Path) -> None:
    if isinstance(obj, dict):
        for k, v in obj.items():
            _check_plain(k, path)
            _check_plain(v, path)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            _check_plain(v, path)
    elif not isinstance(obj, (str, bytes, int, float, bool, np.ndarray, np.generic, type(None))):
        raise TalkmeshError(f"{path}: unexpected {type(obj).__name__} in a template pickle")
