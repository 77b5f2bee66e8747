"""Safe file handling shared by the exporters and importers in :mod:`talkmesh.output`.

Writes go to a private directory next to the target and are renamed into place (see
:func:`talkmesh.output.formats.save_animation`); reads turn any parse failure into a one-line
:class:`TalkmeshError` that names the file.
"""

from __future__ import annotations

import csv
import os
import struct
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from talkmesh.errors import TalkmeshError


def file_extension(path: Path, format: str | None) -> str:
    """The registry key: ``format`` (``"obj"`` -> ``".obj"``) if given, else ``path``'s suffix."""
    if format:
        return "." + format.lower().lstrip(".")
    return path.suffix.lower()


def move_file(src: Path, dst: Path, overwrite: bool) -> None:
    """Rename ``src`` to ``dst`` atomically; without ``overwrite``, never replace ``dst``."""
    if overwrite:
        os.replace(src, dst)
        return
    try:
        os.link(src, dst)  # fails if dst exists, unlike rename, so a racing writer is not clobbered
    except FileExistsError:
        raise exists_error(dst) from None
    except OSError:  # no hard links on this filesystem
        if dst.exists():
            raise exists_error(dst) from None
        os.replace(src, dst)
    else:
        src.unlink()


def exists_error(path: Path) -> TalkmeshError:
    return TalkmeshError(f"{path} already exists: choose another -o or pass --overwrite")


def check_readable(path: Path) -> None:
    if not path.is_file():
        raise TalkmeshError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise TalkmeshError(f"{path}: the file is empty")


PARSE_ERRORS = (
    OSError,
    ValueError,
    KeyError,
    IndexError,
    TypeError,
    EOFError,
    struct.error,
    zipfile.BadZipFile,
    csv.Error,
    AttributeError,  # JSON of the wrong types (a list where an object belongs)
    RecursionError,  # JSON nested deeper than Python recurses
)


@contextmanager
def reading(path: Path) -> Iterator[None]:
    """Turn any failure to parse ``path`` into a one-line TalkmeshError that names it."""
    try:
        yield
    except TalkmeshError as e:
        msg = one_line(e)
        raise TalkmeshError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
    except PARSE_ERRORS as e:
        raise TalkmeshError(f"{path}: cannot read it ({type(e).__name__}: {one_line(e)})") from None


def one_line(e: BaseException) -> str:
    lines = str(e).strip().splitlines()
    return lines[0] if lines else type(e).__name__


def check_magic(path: Path, magic: bytes, kind: str) -> None:
    with open(path, "rb") as f:
        if f.read(len(magic)) != magic:
            raise TalkmeshError(f"{path}: not a {kind}")


# An .npz whose members expand past this many times its size (and past EXPANSION_FREE bytes) is
# refused before any member is read: talkmesh's float16 motion deflates 2-4 times; a crafted
# archive of zeros, a thousand times (3.9 MB -> 3.4 GB).
MAX_EXPANSION = 100
EXPANSION_FREE = 256 * 2**20


def check_expansion(path: Path) -> None:
    """Refuse a zip archive (.npz) whose members' declared sizes add up to more than
    MAX_EXPANSION times the file (and more than EXPANSION_FREE bytes), before decompressing any,
    and one whose members are bigger than they declare (checked by :mod:`zipfile` as it reads)."""
    with zipfile.ZipFile(path) as z:
        expanded = sum(info.file_size for info in z.infolist())
    size = path.stat().st_size
    if expanded > EXPANSION_FREE and expanded > MAX_EXPANSION * size:
        raise TalkmeshError(
            f"{path}: refused: its members would expand to {expanded / 1e9:.1f} GB from "
            f"{size / 1e6:.1f} MB ({expanded / size:.0f} times): not an animation talkmesh wrote"
        )


def finite(values: np.ndarray, what: str) -> np.ndarray:
    if not np.isfinite(values).all():
        raise TalkmeshError(f"the {what} contain NaN or infinite values")
    return values


def bundled_head():
    """The bundled head (``talkmesh.face.assets.load_head()``), or None where it is unavailable."""
    try:
        from talkmesh.face.assets import load_head
    except ImportError:
        return None
    try:
        return load_head()
    except (TalkmeshError, OSError):
        return None
