"""The bundled head as a plain mesh file (``talkmesh export-head``): something to try
``talkmesh rig`` and ``--template`` on."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from talkmesh.errors import TalkmeshError
from talkmesh.face.assets import Head

HEAD_MESH_SUFFIXES = (".obj", ".npy")


def write_head_mesh(head: Head, path: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``head``'s neutral mesh to ``path``: ``.obj`` (vertices in metres, +y up, and the
    triangles) or ``.npy`` ((V, 3) float32 vertices): a mesh to try ``talkmesh rig`` and
    ``--template`` on. Written beside the target and renamed into place."""
    import os
    import tempfile

    from talkmesh.output.atomic import temp_prefix, writing
    from talkmesh.output.files import move_file

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in HEAD_MESH_SUFFIXES:
        raise TalkmeshError(
            f"{path}: the head mesh is written as {' or '.join(HEAD_MESH_SUFFIXES)}"
        )
    if path.exists() and not overwrite:
        raise TalkmeshError(f"{path} already exists: choose another -o or pass --overwrite")
    with writing(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=temp_prefix(), suffix=suffix)
        try:
            with os.fdopen(fd, "wb") as f:
                if suffix == ".npy":
                    np.save(f, head.template.astype(np.float32))
                else:
                    f.write(_obj_text(head).encode())
            move_file(Path(tmp), path, overwrite)
        finally:
            Path(tmp).unlink(missing_ok=True)
    return path


def _obj_text(head: Head) -> str:
    header = (
        f"# talkmesh bundled head, identity {head.name}: {head.num_vertices} vertices, "
        f"{len(head.faces)} triangles, metres, +y up, +z towards the viewer\n"
    )
    vertices = ("v %.6f %.6f %.6f\n" * head.num_vertices) % tuple(head.template.ravel().tolist())
    faces = ("f %d %d %d\n" * len(head.faces)) % tuple((head.faces + 1).ravel().tolist())
    return header + vertices + faces
