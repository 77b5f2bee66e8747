"""Saved registrations: a head mesh is registered to the bundled head once, not on every run.

``talkmesh rig my_head.obj`` and the first ``talkmesh animate --head my_head.obj`` save the
correspondence they found (rigid scale, rotation and shift, each user vertex's bundled triangle
and barycentric weights, the landmarks) as a plain ``.npz`` (no pickle) named by the SHA-256 of the
mesh file's bytes, under ``$TALKMESH_CACHE`` (default ``$XDG_CACHE_HOME/talkmesh`` or
``~/.cache/talkmesh``), in ``rigs/``. A later run on the same bytes reads it back instead of
registering; an edited mesh has another name, so it is registered again. A saved file that cannot
be read, was written by another format version or for another bundled head, or does not fit the
mesh, is one warning and the mesh is registered again (and saved over it).

Everything here is plain arrays: :func:`talkmesh.face.rig_files.load_rig` turns them into a ``Rig``.
"""

from __future__ import annotations

import hashlib
import io
import os
import tempfile
import warnings
from functools import lru_cache
from pathlib import Path

import numpy as np

from talkmesh.cache import CACHE_ENV, cache_dir
from talkmesh.cache import file_digest as file_digest  # the saved files are named by it
from talkmesh.errors import TalkmeshWarning

FORMAT = 1  # bump when the saved fields or their meaning change
FIELDS = ("scale", "rotation", "translation", "residual", "corners", "weights")


def saved_path(digest: str) -> Path:
    return cache_dir() / "rigs" / f"{digest}.npz"


@lru_cache(maxsize=4)
def head_fingerprint(template_bytes: bytes, faces_bytes: bytes) -> str:
    """SHA-256 of the bundled head's neutral vertices and triangles: the correspondence indexes
    them, so a saved one is only good for the head it was made on."""
    return hashlib.sha256(template_bytes + faces_bytes).hexdigest()


def save(digest: str, head_id: str, arrays: dict[str, np.ndarray], landmarks: dict[str, int]):
    """Write the correspondence (``FIELDS``) and landmarks for the mesh file with ``digest``;
    written to a temporary file and renamed, so a reader never sees half a file. A folder that
    cannot be written is one warning (the run goes on, unsaved)."""
    path = saved_path(digest)
    names = sorted(landmarks)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".tmp", delete=False) as f:
            np.savez(
                f,
                format=np.int64(FORMAT),
                mesh=np.str_(digest),
                head=np.str_(head_id),
                landmark_names=np.array(names, dtype=np.str_),
                landmark_ids=np.array([landmarks[k] for k in names], np.int64),
                **{k: np.asarray(arrays[k]) for k in FIELDS},
            )
        os.replace(f.name, path)
    except OSError as e:
        warnings.warn(
            f"cannot save the registration to {path} ({e.strerror or e}): the next run registers "
            f"again (set {CACHE_ENV} to a writable folder)",
            TalkmeshWarning,
            stacklevel=2,
        )


def load(digest: str, head_id: str, num_vertices: int, num_head_vertices: int):
    """The saved correspondence for the mesh file with ``digest`` as (arrays by ``FIELDS``,
    landmarks), or None when there is none; a file that is unreadable, of another format or head,
    or that does not fit a mesh of ``num_vertices`` is one warning and None."""
    path = saved_path(digest)
    if not path.is_file():
        return None
    try:
        # read whole (a few hundred kB): np.load leaves the file open when the zip is damaged
        data = np.load(io.BytesIO(path.read_bytes()), allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ValueError("not an .npz archive")
        saved = {k: data[k] for k in data.files}
        arrays = {k: saved[k] for k in FIELDS}
        landmarks = dict(zip(saved["landmark_names"].tolist(), saved["landmark_ids"].tolist()))
        why = _mismatch(saved, arrays, digest, head_id, num_vertices, num_head_vertices)
    except Exception as e:  # a damaged file raises many kinds (zip, format, key, value errors)
        detail = (str(e).splitlines() or [""])[0][:120]
        why = f"cannot read it ({type(e).__name__}: {detail})"
    if why:
        warnings.warn(
            f"ignoring the saved registration {path}: {why}; registering again",
            TalkmeshWarning,
            stacklevel=2,
        )
        return None
    return arrays, {str(k): int(v) for k, v in landmarks.items()}


def _mismatch(saved, arrays, digest, head_id, num_vertices, num_head_vertices) -> str:
    """Why a saved correspondence cannot be used ('' when it can)."""
    if int(saved["format"]) != FORMAT:
        return f"format {int(saved['format'])}, this talkmesh reads {FORMAT}"
    if str(saved["mesh"]) != digest:
        return "made for another mesh file"
    if str(saved["head"]) != head_id:
        return "made for another bundled head (talkmesh was updated)"
    corners = arrays["corners"]
    shapes = {
        "corners": (num_vertices, 3),
        "weights": (num_vertices, 3),
        "rotation": (3, 3),
        "translation": (3,),
        "scale": (),
        "residual": (),
    }
    for name, shape in shapes.items():
        if arrays[name].shape != shape:
            return f"{name} has shape {arrays[name].shape}, the mesh needs {shape}"
    if corners.dtype.kind not in "iu" or corners.min() < 0 or corners.max() >= num_head_vertices:
        return "its triangle corners are not vertices of the bundled head"
    floats = [arrays[k] for k in FIELDS if k != "corners"]
    if not all(a.dtype.kind == "f" and np.isfinite(a).all() for a in floats):
        return "it holds NaN, infinite or non-numeric values"
    if float(arrays["scale"]) <= 0:
        return "its scale is not positive"
    ids = saved["landmark_ids"]
    if ids.dtype.kind not in "iu" or (len(ids) and (ids.min() < 0 or ids.max() >= num_vertices)):
        return "its landmarks are not vertices of the mesh"
    return ""
