"""talkmesh's cache folder: work done once per machine and read back on later runs (saved
registrations of users' heads, the bundled models' ONNX graphs). ``$TALKMESH_CACHE``, else
``$XDG_CACHE_HOME/talkmesh``, else ``~/.cache/talkmesh``. Everything in it is derived: deleting
it costs time, never data."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

CACHE_ENV = "TALKMESH_CACHE"


def cache_dir() -> Path:
    """Where derived files are saved: $TALKMESH_CACHE, else the user's cache folder."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "talkmesh"


def file_digest(path: str | Path) -> str:
    """SHA-256 of a file's bytes (hex), read in blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
