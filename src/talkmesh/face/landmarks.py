"""Landmarks found from a head mesh's own geometry: the lips, mouth corners, chin and eye corners.

``find_landmarks(vertices, faces, frame, predicted)`` looks for each landmark near where a rigid fit
of the bundled head puts it (``predicted``), in the head's own axes (``frame``: x the face's left,
y up, z forward, metres):

* the lip gap: pairs of vertices whose surfaces face each other across a narrow gap (the closed
  lips touch: the upper lip's underside looks down at the lower lip's top), within ``MOUTH_WINDOW``
  of the predicted mouth. The front-most pair on the midline gives ``upper_lip`` and
  ``lower_lip``, the gap's ends left and right ``mouth_left`` and ``mouth_right``;
* ``chin``: the midline vertex farthest along forward-and-down (``CHIN_DOWN`` below forward) among
  those ``CHIN_BELOW`` under the lower lip;
* eye corners (``eye_inner_left``, ...): the ends, towards and away from the midline, of a boundary
  patch where rays cast from the front at the predicted eye meet no skin first (an eyeball or a
  hole: the eye opening), where the mesh has one;
* ``nose_tip``: the vertex farthest forward near the predicted one.

Each landmark found is checked against the prediction (within ``WINDOW``, on its side of the
midline, the upper lip above the lower) and dropped otherwise: the caller then places it from the
registered head instead. Nothing here raises for a mesh without the feature.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

WINDOW = 0.012  # metres a found landmark may lie from the rigid fit's prediction
NOSE_WINDOW = 0.015  # metres around the predicted nose tip searched for the real one
MOUTH_WINDOW = np.array([0.035, 0.012, 0.025])  # metres (x, y, z) around the predicted mouth
# searched for the lip gap: wide enough for the corners, below the nostrils
GAP = 0.004  # metres across the lip gap at most (the closed lips of the bundled head: 1.3 mm)
CORNER_HEIGHT = 0.015  # metres above or below the lips the mouth corners lie at most
LIP_DEPTH = 0.012  # metres behind the front of the mouth's midline the lips meet at most
FACING = 0.5  # cosine: the two sides of the gap face each other at least this much
MIDLINE = 0.003  # metres either side of the midline (x = 0 of the fitted head)
SIDE = 0.01  # metres from the midline a mouth or eye corner lies at least
CHIN_BELOW = 0.02  # metres below the lower lip the chin lies at least
CHIN_DOWN = np.radians(30)  # the chin is the farthest point along forward turned this far down
EYE_BOX = np.array([0.022, 0.015])  # metres (x, y) either side of the predicted eye searched
EYE_PIXEL = 0.0005  # metres between the rays cast at the eye
EYE_DEPTH = 0.03  # metres behind the predicted eye below which triangles are not cast at
EYE_HOLE = 0.008  # metres behind the predicted eye centre a ray's skin hit is a hole (a socket)


class Frame(NamedTuple):
    """The bundled head's axes in the user's: ``scale * rotation @ p + shift`` takes a point p of
    the bundled head (metres) into the user's frame."""

    scale: float
    rotation: np.ndarray
    shift: np.ndarray

    def to_head(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) user points -> the bundled head's axes and metres."""
        return (points - self.shift) @ self.rotation / self.scale


IDENTITY = Frame(1.0, np.eye(3), np.zeros(3))


def find_landmarks(
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray,
    frame: Frame,
    predicted: dict[str, np.ndarray],
) -> dict[str, int]:
    """Vertex ids of the landmarks found on the mesh and checked.

    Args:
        vertices, faces, normals: the user's mesh, (V, 3), (F, 3) and its (V, 3) vertex normals.
        frame: the rigid fit of the bundled head.
        predicted: landmark name -> (3,) where the rigid fit puts it, in the user's frame.
    """
    whole = frame.to_head(vertices)
    # Only the largest connected part (the skin: not the teeth, eyeballs or tongue) is searched.
    labels = csgraph.connected_components(_adjacency(faces, len(vertices)), directed=False)[1]
    skin = labels == np.argmax(np.bincount(labels))
    local = np.where(skin[:, None], whole, np.inf)
    axes = normals @ frame.rotation  # rotations keep unit normals unit
    at = {k: frame.to_head(p[None])[0] for k, p in predicted.items()}
    found: dict[str, int] = {}
    if "nose_tip" in at:
        window = np.flatnonzero(np.linalg.norm(local - at["nose_tip"], axis=1) < NOSE_WINDOW)
        if len(window):
            found["nose_tip"] = int(window[np.argmax(local[window, 2])])
    if "upper_lip" in at and "lower_lip" in at:
        found.update(_mouth(local, faces, axes, (at["upper_lip"] + at["lower_lip"]) / 2))
    if "chin" in at and "lower_lip" in at:
        lip = local[found["lower_lip"]] if "lower_lip" in found else at["lower_lip"]
        midline = np.flatnonzero(
            (np.abs(local[:, 0]) < MIDLINE) & (local[:, 1] < lip[1] - CHIN_BELOW)
        )
        if len(midline):
            toward = np.array([0.0, -np.sin(CHIN_DOWN), np.cos(CHIN_DOWN)])
            found["chin"] = int(midline[np.argmax(local[midline] @ toward)])
    found.update(_eye_corners(local, faces, at, whole, labels))
    return {k: i for k, i in found.items() if _plausible(k, local[i], at.get(k))}


def _plausible(name: str, point: np.ndarray, predicted: np.ndarray | None) -> bool:
    """A found landmark near its prediction and on its side of the midline."""
    if predicted is None or np.linalg.norm(point - predicted) > WINDOW:
        return False
    if name.endswith("_left"):
        return point[0] > SIDE
    if name.endswith("_right"):
        return point[0] < -SIDE
    return True


def _mouth(local: np.ndarray, faces: np.ndarray, axes: np.ndarray, centre: np.ndarray):
    """Lips and mouth corners from the pairs of vertices facing each other across the lip gap."""
    window = np.flatnonzero((np.abs(local - centre) < MOUTH_WINDOW).all(1))
    if len(window) < 4:
        return {}
    near = faces[np.isin(faces[:, 0], window)]
    spacing = float(np.median(np.linalg.norm(local[near[:, 1:]] - local[near[:, :1]], axis=2)))
    reach = max(GAP, 1.5 * spacing)  # a coarse mesh's lips are a few edges apart
    pairs = np.array(sorted(cKDTree(local[window]).query_pairs(reach)), np.int64).reshape(-1, 2)
    i, j = window[pairs[:, 0]], window[pairs[:, 1]]
    # i above j: the upper side looks down at the lower side, which looks up at it.
    swap = local[i, 1] < local[j, 1]
    i, j = np.where(swap, j, i), np.where(swap, i, j)
    # (Not "j straight along i's normal": the upper lip of many faces overhangs the lower.)
    facing = ((axes[i] * axes[j]).sum(1) < -FACING) & (axes[i, 1] < 0) & (axes[j, 1] > 0)
    i, j = i[facing], j[facing]
    out = {}
    if not len(i):
        return out
    mid = np.flatnonzero(
        np.maximum(np.abs(local[i, 0]), np.abs(local[j, 0])) < max(MIDLINE, spacing)
    )
    midline = window[np.abs(local[window, 0]) < max(MIDLINE, spacing)]
    if len(mid):
        front = mid[np.argmax(local[i[mid], 2] + local[j[mid], 2])]
        # the lips are the front of the mouth (sealed lips leave only pairs deep in the mouth)
        if (local[i[front], 2] + local[j[front], 2]) / 2 > local[midline, 2].max() - LIP_DEPTH:
            out["upper_lip"], out["lower_lip"] = int(i[front]), int(j[front])
    if "upper_lip" in out:  # the corners: the ends of the gap at the lips' height
        gap = np.concatenate([i, j])
        lips = local[[out["upper_lip"], out["lower_lip"]], 1].mean()
        gap = gap[np.abs(local[gap, 1] - lips) < CORNER_HEIGHT]
        out["mouth_left"] = int(gap[np.argmax(local[gap, 0])])
        out["mouth_right"] = int(gap[np.argmin(local[gap, 0])])
    return out


def _eye_corners(local, faces, at, whole, labels) -> dict[str, int]:
    """Eye corners: the inner and outer ends of each eye opening, seen from the front."""
    out: dict[str, int] = {}
    names = [f"eye_{end}_{side}" for side in ("left", "right") for end in ("inner", "outer")]
    if not all(k in at for k in names):
        return out
    skin = np.isfinite(local[:, 0])
    for side, sign in (("left", 1.0), ("right", -1.0)):
        inner, outer = at[f"eye_inner_{side}"], at[f"eye_outer_{side}"]
        ends = eye_opening(whole, faces, skin[faces].all(1), (inner + outer) / 2)
        if ends is None:
            continue
        ok = np.flatnonzero(skin)
        tree = cKDTree(whole[ok])
        a, b = (int(ok[tree.query(p)[1]]) for p in ends)  # a: the end at smaller x
        out[f"eye_inner_{side}"], out[f"eye_outer_{side}"] = (a, b) if sign > 0 else (b, a)
    return out


def eye_opening(
    points: np.ndarray, faces: np.ndarray, skin: np.ndarray, centre: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """The two ends (smaller x first), as points on the eyelids' rim, of the eye opening around
    ``centre``: rays cast backwards (-z) on an ``EYE_PIXEL`` grid whose first hit is no skin
    triangle (``skin``: (F,) bool), an eyeball or a hole, or skin ``EYE_HOLE`` behind ``centre``
    (the back of an open socket); the connected patch of them nearest ``centre``. None if no patch.

    ``points``: (V, 3) in the head's axes, metres."""
    from scipy import ndimage

    lo, hi = centre[:2] - EYE_BOX, centre[:2] + EYE_BOX
    xs = np.arange(lo[0], hi[0], EYE_PIXEL)
    ys = np.arange(lo[1], hi[1], EYE_PIXEL)
    tri = points[faces]
    inside = ((tri[..., :2] > lo - 0.005) & (tri[..., :2] < hi + 0.005)).all(2).any(1)
    inside &= tri[..., 2].max(1) > centre[2] - EYE_DEPTH
    tri, skin = tri[inside], skin[inside]
    if not len(tri):
        return None
    rays = np.stack(np.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)
    depth, first_skin = _first_hits(tri, skin, rays)
    opening = ~first_skin | (depth < centre[2] - EYE_HOLE)
    grid = opening.reshape(len(ys), len(xs))
    patches, count = ndimage.label(grid)
    if not count:
        return None
    at = np.argwhere(patches > 0)
    middle = np.array([len(ys), len(xs)]) / 2
    patch = patches[tuple(at[np.argmin(np.linalg.norm(at - middle, axis=1))])]
    rows, cols = np.nonzero(patches == patch)
    if cols.min() == 0 or cols.max() == len(xs) - 1:  # runs out of the box: no eye opening
        return None
    ends = []
    for col, step in ((cols.min(), -1), (cols.max(), 1)):
        row = int(np.round(rows[cols == col].mean()))
        beyond = row * len(xs) + col + step  # the skin just past the end
        z = depth[beyond] if np.isfinite(depth[beyond]) else centre[2]
        ends.append(np.array([xs[col + step], ys[row], z]))
    return ends[0], ends[1]


def _first_hits(tri, skin, rays, chunk: int = 512):
    """For (R, 2) rays (x, y) cast backwards (-z) at (T, 3, 3) triangles: (R,) the depth z of the
    first (frontmost) hit, -inf where none, and (R,) whether that triangle is skin (``skin``:
    (T,) bool)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1 = (b - a)[:, :2], (c - a)[:, :2]
    det = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    det = np.where(np.abs(det) < 1e-18, np.nan, det)  # edge-on triangles are never hit
    depth = np.full(len(rays), -np.inf)
    first = np.zeros(len(rays), bool)
    for start in range(0, len(rays), chunk):
        v2 = rays[start : start + chunk, None, :] - a[None, :, :2]
        u = (v2[..., 0] * v1[:, 1] - v1[:, 0] * v2[..., 1]) / det
        w = (v0[:, 0] * v2[..., 1] - v2[..., 0] * v0[:, 1]) / det
        z = a[:, 2] + u * (b - a)[:, 2] + w * (c - a)[:, 2]
        z = np.where((u >= 0) & (w >= 0) & (u + w <= 1), z, -np.inf)
        best = np.argmax(z, axis=1)
        depth[start : start + chunk] = z[np.arange(len(z)), best]
        first[start : start + chunk] = skin[best] & np.isfinite(depth[start : start + chunk])
    return depth, first


def _adjacency(faces: np.ndarray, n: int) -> sparse.coo_matrix:
    i, j = faces.ravel(), faces[:, [1, 2, 0]].ravel()
    return sparse.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))


def boundary_loops(faces: np.ndarray, n: int) -> list[np.ndarray]:
    """The vertex ids of each connected run of boundary edges (edges of one triangle only)."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    border = unique[counts == 1]
    if not len(border):
        return []
    graph = sparse.coo_matrix((np.ones(len(border)), (border[:, 0], border[:, 1])), shape=(n, n))
    labels = csgraph.connected_components(graph, directed=False)[1]
    on = np.unique(border)
    return [on[labels[on] == label] for label in np.unique(labels[on])]
