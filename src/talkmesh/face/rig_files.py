"""Rigs and meshes on disk: a head mesh read for rigging, a rig registered once and read back
from the user cache (:mod:`talkmesh.face.rig_cache`) by ``talkmesh animate --head``."""

from __future__ import annotations

import hashlib
from functools import lru_cache
from pathlib import Path

import numpy as np

from talkmesh.errors import MissingDependencyError, TalkmeshError
from talkmesh.face import rig_cache
from talkmesh.face.assets import Head, load_head
from talkmesh.face.rig import CARRY_BLOCK, MESH_SUFFIXES, Rig, rig_head
from talkmesh.face.rig_dense import closest_shapes


def load_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) vertices and (F, 3) triangles of a mesh file (all its meshes merged, in the file's
    units and axes); one-line TalkmeshErrors for missing, unreadable or empty files. A file of
    one mesh is taken as trimesh reads it (``force="mesh"`` copied a 1.2M-vertex .ply three
    times: 590 MB and 4.5 s instead of 240 MB and 0.2 s)."""
    path = Path(path)
    if not path.is_file():
        raise TalkmeshError(f"{path}: no such file")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise TalkmeshError(f"{path}: give a head mesh as {', '.join(MESH_SUFFIXES)}")
    try:
        import trimesh
    except ImportError:
        raise MissingDependencyError("trimesh", "rig", "talkmesh rig") from None
    try:
        mesh = trimesh.load(path, process=False)
        if isinstance(mesh, trimesh.Scene):  # several meshes (.glb, .obj groups): merged
            mesh = mesh.to_mesh()
    except Exception as e:  # trimesh raises many kinds on bad files
        raise TalkmeshError(f"{path}: cannot read the mesh ({type(e).__name__}: {e})") from None
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))))
    if not len(faces):
        raise TalkmeshError(f"{path}: no triangles in the file")
    return np.asarray(mesh.vertices, np.float64), faces.astype(np.int64)


def load_rig(path: str | Path) -> Rig:
    """The head mesh at ``path`` registered to the bundled head (the closest-point shapes: what
    :meth:`Rig.carry` needs), once per file and process (a CLI check and the workers forked
    after it share it), and across runs through the saved registration of the same file bytes
    (:mod:`talkmesh.face.rig_cache`). One-line TalkmeshErrors for a file that is no head mesh."""
    path = Path(path)
    if not path.is_file():
        raise TalkmeshError(f"{path}: no such file")
    return _rig_file(str(path.resolve()), path.stat().st_mtime)


@lru_cache(maxsize=2)
def _rig_file(path: str, mtime: float) -> Rig:
    vertices, faces = load_mesh(path)
    return _registered(vertices, faces, rig_cache.file_digest(path), path)


def rig_mesh(vertices: np.ndarray, faces: np.ndarray) -> Rig:
    """:func:`load_rig` for a mesh given as arrays (a learned model's template, which may come
    from no mesh file of its own): saved by the SHA-256 of its vertices' and triangles' bytes."""
    vertices = np.ascontiguousarray(vertices, np.float32)
    faces = np.ascontiguousarray(faces, np.int64)
    digest = hashlib.sha256(b"mesh" + vertices.tobytes() + faces.tobytes()).hexdigest()
    return _rig_arrays(digest, vertices.tobytes(), faces.tobytes(), len(vertices))


@lru_cache(maxsize=2)
def _rig_arrays(digest: str, vertices: bytes, faces: bytes, count: int) -> Rig:
    v = np.frombuffer(vertices, np.float32).reshape(count, 3).astype(np.float64)
    return _registered(v, np.frombuffer(faces, np.int64).reshape(-1, 3), digest, "")


def _registered(vertices: np.ndarray, faces: np.ndarray, digest: str, path: str) -> Rig:
    """The closest-point Rig of a mesh: its saved registration read back, or registered now and
    saved under ``digest``."""
    head = load_head()
    head_id = _head_id(head)
    saved = rig_cache.load(digest, head_id, len(vertices), head.num_vertices)
    if saved is not None:
        arrays, landmarks = saved
        return _closest_rig(vertices, faces, head, landmarks=landmarks, **arrays)
    try:
        rig = rig_head(vertices, faces, head, method="closest")
    except TalkmeshError as e:
        message = str(e)
        raise TalkmeshError(
            message if not path or path in message else f"{path}: {message}"
        ) from None
    rig_cache.save(digest, head_id, _correspondence(rig), rig.landmarks)
    return rig


def save_registration(path: str | Path, rig: Rig) -> None:
    """Save ``rig``'s registration of the mesh file at ``path`` (``talkmesh rig``) for
    :func:`load_rig` (``animate --head``) to read back instead of registering the file again."""
    rig_cache.save(
        rig_cache.file_digest(path), _head_id(load_head()), _correspondence(rig), rig.landmarks
    )


def _head_id(head: Head) -> str:
    return rig_cache.head_fingerprint(head.template.tobytes(), head.faces.tobytes())


def _correspondence(rig: Rig) -> dict[str, np.ndarray]:
    """The arrays a saved registration keeps (``rig_cache.FIELDS``)."""
    return {
        "scale": np.float64(rig.scale),
        "rotation": rig.rotation,
        "translation": rig.translation,
        "residual": np.float64(rig.residual),
        "corners": rig.corners,
        "weights": rig.weights,
    }


def _closest_rig(
    vertices, faces, head, *, scale, rotation, translation, residual, corners, weights, landmarks
) -> Rig:
    """The closest-point Rig (``method="closest"``) from a correspondence: every vertex takes the
    bundled offsets at its corresponding point (``weights`` over the ``corners``)."""
    scale, residual = float(scale), float(residual)
    return Rig(
        vertices=np.asarray(vertices, np.float32),
        faces=np.asarray(faces, np.int32),
        blendshapes=closest_shapes(head, corners, weights, scale, rotation, CARRY_BLOCK).astype(
            np.float32
        ),
        scale=scale,
        rotation=rotation,
        translation=translation,
        residual=residual,
        landmarks=landmarks,
        corners=corners,
        weights=weights,
    )
