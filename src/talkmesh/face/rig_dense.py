"""Rigging dense meshes with bounded memory (:mod:`talkmesh.face.rig`): the registration runs on a
decimated copy and the shapes are carried back to every vertex, ``rig.CARRY_BLOCK`` vertices at
a time (docs/results/rigging.md, "Dense meshes")."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from talkmesh.errors import MissingDependencyError
from talkmesh.face.registration import closest_points, vertex_normals
from talkmesh.forked import in_child


def closest_shapes(head, corners, weights, scale, rotation, block: int) -> np.ndarray:
    """(52, V, 3) float64 the bundled shapes at each vertex's corresponding point, user axes;
    rig.CARRY_BLOCK vertices at a time (the (52, V, 3, 3) gather is 3.7 GB at a million)."""
    out = np.empty((len(head.blendshapes), len(corners), 3))
    for a in range(0, len(corners), block):
        b = slice(a, a + block)
        gathered = head.blendshapes[:, corners[b]]
        out[:, b] = scale * np.einsum("vc,kvcx->kvx", weights[b], gathered) @ rotation.T
    return out


def reduce_mesh(vertices: np.ndarray, faces: np.ndarray, count: int) -> tuple[np.ndarray, ...]:
    """(V', 3) vertices and (F', 3) faces of the mesh decimated to about ``count`` vertices by
    quadric edge collapse (fast-simplification): edges collapse, separate surfaces never merge,
    so lips that touch stay two lips. Where the OS forks, in a child process: fast-simplification
    keeps its working arrays in C++ globals that never give their memory back (600 MB for the
    rest of the run at 2.4M faces)."""
    try:
        import fast_simplification  # noqa: F401  (here, so a missing one is a one-line error)
    except ImportError:
        raise MissingDependencyError(
            "fast-simplification", "all", f"rigging meshes of over {count} vertices"
        ) from None
    target = int(len(faces) * min(1.0, 2 * count / len(faces)))  # F ~ 2V on a closed surface
    small_v, small_f = _in_child(_simplify, vertices, faces, target)
    tri = small_v[small_f]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    small_f = small_f[area > 1e-8 * np.median(area)]  # slivers: no closest point is on them
    used = np.unique(small_f)  # vertices no face uses (collapsed away) are dropped
    remap = np.full(len(small_v), -1, np.int64)
    remap[used] = np.arange(len(used))
    return small_v[used], remap[small_f]


def _simplify(vertices: np.ndarray, faces: np.ndarray, target: int) -> tuple[np.ndarray, ...]:
    import fast_simplification

    return fast_simplification.simplify(
        vertices.astype(np.float64), faces.astype(np.int32), target_count=target
    )


def _in_child(fn, *args) -> tuple[np.ndarray, ...]:
    """``fn(*args)`` (a tuple of plain arrays) run in a forked child, its memory given back when
    it exits; in this process where there is no fork or the child failed (it then raises here)."""
    out = in_child(fn, *args)
    return fn(*args) if out is None else out


def carry_back(vertices, faces, small_v, small_f, small, landmarks, block: int):
    """The shapes of ``small`` (a Rig of the decimated copy ``small_v``, ``small_f``) at every
    vertex of the full mesh: each takes them at its closest point on the copy (facing the same
    way: the lower lip does not take the upper's), ``block`` vertices at a time. Returns (52, V,
    3) float32 shapes, (V, 3) corners and weights of the correspondence, and the landmarks on
    the full mesh (the user's ``landmarks`` as given, the found ones at their nearest vertex).
    Memory: the shapes (624 bytes a vertex) and a block's work."""
    normals = vertex_normals(vertices, faces)
    shapes = np.empty((len(small.blendshapes), len(vertices), 3), np.float32)
    corners = np.empty((len(vertices), 3), np.int64)
    weights = np.empty((len(vertices), 3))
    for a in range(0, len(vertices), block):
        b = slice(a, a + block)
        face, bary, _ = closest_points(vertices[b], small_v, small_f, normals[b])
        tri = small_f[face]
        shapes[:, b] = np.einsum("vc,kvcx->kvx", bary, small.blendshapes[:, tri])
        nearest = tri[np.arange(len(tri)), np.argmax(bary, axis=1)]
        corners[b], weights[b] = small.corners[nearest], small.weights[nearest]
    tree = cKDTree(vertices)
    found = {n: int(tree.query(small_v[i])[1]) for n, i in small.landmarks.items()}
    found.update({n: int(i) for n, i in (landmarks or {}).items()})  # the user's ids, as given
    return shapes, corners, weights, found
