"""The safe unpickler for the pickles datasets ship (templates.pkl, VOCASET's index and audio,
FLAME's vertex masks): only dicts, lists, strings, numbers and numpy arrays can come out of
them, so no code in a file can run while it is read."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from talkmesh.errors import TalkmeshError

MAX_DEPTH = 32  # VOCASET's deepest (index: subject -> sentence -> frame -> id) is 3
# Containers and values visited, a shared one each time it is met: a file of a few hundred bytes
# can nest the same list in itself 60 times over (2**60 items to visit); VOCASET's largest
# (the frame index) has under a million.
MAX_ITEMS = 5_000_000


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
    except (RecursionError, MemoryError) as e:
        raise TalkmeshError(
            f"{path}: refused: the pickle is too large ({type(e).__name__})"
        ) from None
    _check_plain(obj, path)
    return obj


PLAIN = (str, bytes, int, float, bool, np.ndarray, np.generic, type(None))


def _check_plain(obj: object, path: Path) -> None:
    """Refuse anything but plain data, nesting deeper than MAX_DEPTH and more than MAX_ITEMS
    items (shared containers counted each time they are met, as a reader would walk them):
    iterative, so neither depth nor sharing can exhaust the stack or the time."""
    check_bounded(obj, path, leaves=PLAIN, what="in a template pickle")


def check_bounded(
    obj: object,
    path: Path,
    *,
    leaves: tuple[type, ...] | None = None,
    what: str = "",
    max_depth: int = MAX_DEPTH,
    max_items: int = MAX_ITEMS,
) -> None:
    """Refuse ``obj`` (read from ``path``) when its dicts, lists and tuples nest deeper than
    ``max_depth``, contain themselves, or hold more than ``max_items`` items in all, a shared
    container counted each time it is met (as a reader walking it would meet it: a list holding
    the same list twice, 60 levels deep, is 2**60 items), or when it holds anything but
    ``leaves`` (None: anything). One-line TalkmeshErrors. Each container is visited once (its
    expanded size is summed from its children's) and without recursion, so neither depth nor
    sharing can exhaust the stack or the time."""
    expanded: dict[int, int] = {}  # id of a finished container -> the items it expands to
    ancestors: set[int] = set()  # the containers being walked: the path from obj down
    stack: list[tuple[object, bool]] = [(obj, False)]
    while stack:
        item, finished = stack.pop()
        if not isinstance(item, (dict, list, tuple)):
            if leaves is not None and not isinstance(item, leaves):
                raise TalkmeshError(f"{path}: unexpected {type(item).__name__} {what}".rstrip())
            continue
        key = id(item)
        children = [x for kv in item.items() for x in kv] if isinstance(item, dict) else item
        if finished:
            ancestors.discard(key)
            expanded[key] = len(children) + sum(expanded.get(id(c), 0) for c in children)
            if expanded[key] > max_items:
                raise TalkmeshError(
                    f"{path}: refused: it expands to over {max_items:,} items (containers "
                    "nested in each other)"
                )
            continue
        if key in expanded:
            continue
        if key in ancestors:
            raise TalkmeshError(f"{path}: refused: a container holds itself")
        if len(ancestors) >= max_depth:
            raise TalkmeshError(f"{path}: refused: containers nested over {max_depth} levels")
        ancestors.add(key)
        stack.append((item, True))
        stack.extend((c, False) for c in children)
