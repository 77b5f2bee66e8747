"""Rigging a plain head mesh: the bundled 52 ARKit blendshapes carried onto any head.

``rig_head(vertices, faces)`` registers the bundled head onto the user's mesh and gives every user
vertex the blendshape offsets of the closest point of the registered head's surface:

1. Rigid + scale registration: the 24 axis-aligned orientations (so a Z-up or Y-down export is
   found), each started from the meshes' centroids and RMS radii, refined by trimmed, two-way
   iterative closest points with Umeyama's similarity fit (Umeyama 1991, eq. 40-42); the
   orientation whose fit leaves the smallest residual wins.
2. Non-rigid refinement: the registered head is pulled towards the user's surface by a displacement
   field smoothed over the head's mesh (uniform Laplacian smoothing of the closest-point
   displacements, a few rounds), so a wider jaw or fuller lips still land on their counterpart.
3. Transfer: each user vertex takes the barycentric blend of the offsets at its closest point on
   the registered head, rotated and scaled into the user's frame; vertices farther than
   ``FALLOFF`` (relative to the head's size) from the head fade to no motion (hair, shoulders).

Units (mm, cm, m: the scale of the fit) and up-axis (the orientation) are detected, and the offsets
come out in the user's units and axes. This is closest-point transfer, not Sumner and Popovic's
deformation-gradient transfer: it keeps the shapes' magnitudes exactly where the heads agree, and
smooths them where the user's mesh is much finer than the bundled one.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from talkmesh.animation import Animation
from talkmesh.constants import MOTION_FPS
from talkmesh.errors import MissingDependencyError, TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import Head, load_head

ICP_ITERATIONS = 40
COARSE = 6  # iterations tried from each of the 24 orientations
TRIM = 0.9  # ICP fits the closest 90% of the pairs, so hair and shoulders do not pull
NONRIGID_ROUNDS = 8
SMOOTHING = 15  # Laplacian smoothing iterations of each round's displacement field
FALLOFF = (0.02, 0.06)  # fraction of the head's RMS radius: full motion within, none beyond
MIN_VERTICES = 100
CANDIDATES = 12  # nearest head vertices whose triangles are searched for the closest point
FACING = 0.3  # cosine between normals below which a triangle faces away from a point ...
AWAY_PENALTY = 1e3  # ... and is taken only when no triangle facing the point is a candidate


@dataclass(frozen=True)
class Rig:
    """The bundled blendshapes on a user's head.

    Attributes:
        vertices: (V, 3) float32 the user's neutral vertices, as given.
        faces: (F, 3) int32 the user's triangles.
        blendshapes: (52, V, 3) float32 offsets in the user's units and axes.
        scale: user units per metre of the bundled head (1000: millimetres).
        rotation: (3, 3) the bundled head's axes in the user's frame (columns: x, y up, z front).
        translation: (3,) so that ``scale * rotation @ p + translation`` takes a point p of the
            bundled head (metres) into the user's frame.
        residual: median distance (user units) from the registered head to the user's surface.
    """

    vertices: np.ndarray
    faces: np.ndarray
    blendshapes: np.ndarray
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    residual: float

    @property
    def units(self) -> str:
        """The unit the fitted scale is closest to (by decades): mm, cm or m."""
        decade = int(np.clip(np.round(np.log10(self.scale)), 0, 3))
        return {0: "m", 1: "dm", 2: "cm", 3: "mm"}[decade]

    def neutral_animation(self) -> Animation:
        """One neutral frame with the 52 blendshapes as its ``basis`` (all weights zero): saved as
        .glb it is the rigged head, one ARKit-named morph target per blendshape."""
        return Animation(
            vertices=self.vertices[None],
            faces=self.faces,
            fps=MOTION_FPS,
            weights=np.zeros((1, len(ARKIT_NAMES)), np.float32),
            weight_names=list(ARKIT_NAMES),
            template=self.vertices,
            basis=self.blendshapes,
        )

    @property
    def up_axis(self) -> str:
        """The user's axis the head's up (+y) maps to: '+y', '-z', ..."""
        up = self.rotation[:, 1]
        k = int(np.argmax(np.abs(up)))
        return ("+" if up[k] > 0 else "-") + "xyz"[k]


def _similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama: s, R, t minimising sum |s R src + t - dst|^2 over (N, 3) pairs."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, d, vt = np.linalg.svd(b.T @ a / len(src))
    sign = np.ones(3)
    sign[2] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rotation = u @ np.diag(sign) @ vt
    scale = float((d * sign).sum() / (a**2).sum(1).mean())
    return scale, rotation, mu_d - scale * rotation @ mu_s


def _orientations() -> list[np.ndarray]:
    """The 24 rotations that map coordinate axes onto coordinate axes."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            r = np.zeros((3, 3))
            r[list(perm), [0, 1, 2]] = signs
            if np.linalg.det(r) > 0:
                out.append(r)
    return out


def _principal_orientations(source: np.ndarray, target: np.ndarray) -> list[np.ndarray]:
    """The 4 rotations that align the principal axes of ``source`` with those of ``target``."""
    axes = [np.linalg.eigh(np.cov((x - x.mean(0)).T))[1] for x in (source, target)]
    out = []
    for signs in itertools.product((1, -1), repeat=3):
        r = axes[1] @ np.diag(signs) @ axes[0].T
        if np.linalg.det(r) > 0:
            out.append(r)
    return out


def _icp(source: np.ndarray, target: np.ndarray, tree: cKDTree, init: np.ndarray, steps: int):
    """Trimmed two-way similarity ICP of ``source`` onto ``target`` from rotation ``init``."""
    rms = lambda x: np.sqrt(((x - x.mean(0)) ** 2).sum(1).mean())  # noqa: E731
    scale = rms(target) / rms(source)
    rotation = init
    shift = target.mean(0) - scale * rotation @ source.mean(0)
    source_tree = None
    for _ in range(steps):
        moved = scale * source @ rotation.T + shift
        d1, i1 = tree.query(moved)
        source_tree = cKDTree(moved)
        d2, i2 = source_tree.query(target)
        keep1 = d1 <= np.quantile(d1, TRIM)
        keep2 = d2 <= np.quantile(d2, TRIM)
        src = np.concatenate([source[keep1], source[i2[keep2]]])
        dst = np.concatenate([target[i1[keep1]], target[keep2]])
        scale, rotation, shift = _similarity(src, dst)
    moved = scale * source @ rotation.T + shift
    residual = float(np.median(tree.query(moved)[0]))
    return scale, rotation, shift, residual


def _laplacian(faces: np.ndarray, n: int) -> sparse.csr_matrix:
    """Row-normalised adjacency (uniform Laplacian smoothing operator) of a triangle mesh."""
    i = faces[:, [0, 1, 2, 1, 2, 0]].ravel()
    j = faces[:, [1, 2, 0, 0, 1, 2]].ravel()
    adj = sparse.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)).tocsr()
    adj.data[:] = 1.0
    degree = np.asarray(adj.sum(1)).ravel()
    degree[degree == 0] = 1.0
    return sparse.diags(1.0 / degree) @ adj


def _nonrigid(head: np.ndarray, faces: np.ndarray, target: np.ndarray, tree: cKDTree) -> np.ndarray:
    """Pull ``head`` (V, 3) towards ``target`` points with a smooth displacement field."""
    smooth = _laplacian(faces, len(head))
    out = head.copy()
    for _ in range(NONRIGID_ROUNDS):
        d, i = tree.query(out)
        field = target[i] - out
        field[d > np.quantile(d, TRIM)] = 0.0
        for _ in range(SMOOTHING):
            field = smooth @ field
        out = out + field
    return out


def closest_points(
    points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For (P, 3) points: the closest triangle of the mesh, barycentric coordinates (P, 3) of
    the closest point on it, and the distance (P,). Searches the triangles around the
    ``CANDIDATES`` nearest vertices (exact for meshes without long thin triangles). With the
    points' (P, 3) ``normals``, triangles facing away are passed over while one facing the same
    way is near: closed lips and eyelids touch, and the lower lip must not take the upper's motion.
    """
    import trimesh

    corner_of = faces.ravel()  # vertex -> its faces, as CSR arrays
    order = np.argsort(corner_of, kind="stable")
    starts = np.searchsorted(corner_of[order], np.arange(len(vertices) + 1))
    _, near = cKDTree(vertices).query(points, k=min(CANDIDATES, len(vertices)))
    near = near.reshape(len(points), -1)
    counts = starts[near + 1] - starts[near]  # faces around each candidate vertex
    point_ids = np.repeat(np.repeat(np.arange(len(points)), near.shape[1]), counts.ravel())
    offsets = np.arange(counts.sum()) - np.repeat(
        np.cumsum(counts.ravel()) - counts.ravel(), counts.ravel()
    )
    face_ids = order[np.repeat(starts[near.ravel()], counts.ravel()) + offsets] // 3
    pairs = np.unique(np.stack([point_ids, face_ids], 1), axis=0)
    best = np.full(len(points), np.inf)
    best_face = np.zeros(len(points), np.int64)
    best_point = np.zeros((len(points), 3))
    tri = vertices[faces[pairs[:, 1]]]
    closest = trimesh.triangles.closest_point(tri, points[pairs[:, 0]])
    dist = np.linalg.norm(closest - points[pairs[:, 0]], axis=1)
    rank = dist
    if normals is not None:
        face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        face_normals /= np.maximum(np.linalg.norm(face_normals, axis=1, keepdims=True), 1e-30)
        facing = (face_normals * normals[pairs[:, 0]]).sum(1)
        rank = dist + np.where(facing < FACING, AWAY_PENALTY, 0.0)
    order = np.lexsort((rank, pairs[:, 0]))  # per point, nearest first
    first = order[np.r_[True, pairs[order[1:], 0] != pairs[order[:-1], 0]]]
    p = pairs[first, 0]
    best[p], best_face[p], best_point[p] = dist[first], pairs[first, 1], closest[first]
    bary = trimesh.triangles.points_to_barycentric(vertices[faces[best_face]], best_point)
    return best_face, np.clip(bary, 0.0, 1.0), best


MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
NOT_A_HEAD = 0.08  # median registration distance over RMS radius beyond which it is no head


def load_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) vertices and (F, 3) triangles of a mesh file (all its meshes merged, in the file's
    units and axes); one-line TalkmeshErrors for missing, unreadable or empty files."""
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
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many kinds on bad files
        raise TalkmeshError(f"{path}: cannot read the mesh ({type(e).__name__}: {e})") from None
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))))
    if not len(faces):
        raise TalkmeshError(f"{path}: no triangles in the file")
    return np.asarray(mesh.vertices, np.float64), faces.astype(np.int64)


def rig_head(vertices: np.ndarray, faces: np.ndarray, head: Head | None = None) -> Rig:
    """The bundled head's 52 blendshapes carried onto the mesh (V, 3) vertices, (F, 3) faces."""
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < MIN_VERTICES:
        raise TalkmeshError(
            f"a head mesh needs at least {MIN_VERTICES} vertices, got {len(vertices)}"
        )
    if faces.ndim != 2 or faces.shape[1] != 3 or not len(faces):
        raise TalkmeshError("the mesh has no triangles: give a surface mesh (OBJ, PLY, glTF)")
    if not np.isfinite(vertices).all():
        raise TalkmeshError("the mesh's vertices contain NaN or infinite values")
    head = head or load_head()
    source = head.template.astype(np.float64)
    tree = cKDTree(vertices)
    # A short fit from every orientation, then a full one from the best two.
    starts = _orientations() + _principal_orientations(source, vertices)
    coarse = sorted(starts, key=lambda r: _icp(source, vertices, tree, r, COARSE)[3])
    fits = [_icp(source, vertices, tree, r, ICP_ITERATIONS) for r in coarse[:2]]
    scale, rotation, shift, _ = min(fits, key=lambda f: f[3])
    registered = _nonrigid(scale * source @ rotation.T + shift, head.faces, vertices, tree)
    radius = np.sqrt(((vertices - vertices.mean(0)) ** 2).sum(1).mean())
    fit = float(np.median(tree.query(scale * source @ rotation.T + shift)[0]))
    if fit > NOT_A_HEAD * radius:
        raise TalkmeshError(
            f"the mesh does not look like a head: the bundled head fits it no closer than "
            f"{100 * fit / radius:.0f}% of its size (give a head, face forward, mouth included)"
        )
    import trimesh

    normals = trimesh.Trimesh(vertices, faces, process=False).vertex_normals
    face, bary, dist = closest_points(vertices, registered, head.faces.astype(np.int64), normals)
    corners = head.faces[face]  # (V, 3) head vertices around each closest point
    offsets = np.einsum("vc,kvcx->kvx", bary, head.blendshapes[:, corners].astype(np.float64))
    near, far = FALLOFF[0] * radius, FALLOFF[1] * radius
    fade = np.clip((far - dist) / (far - near), 0.0, 1.0)
    blendshapes = scale * offsets @ rotation.T * fade[None, :, None]
    return Rig(
        vertices=vertices.astype(np.float32),
        faces=faces.astype(np.int32),
        blendshapes=blendshapes.astype(np.float32),
        scale=scale,
        rotation=rotation,
        translation=shift,
        residual=float(np.median(cKDTree(vertices).query(registered)[0])),
    )
