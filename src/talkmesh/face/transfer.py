"""Deformation transfer: blendshapes carried from one mesh to another of different topology.

Sumner and Popovic (2004) transfer a source deformation through the per-triangle deformation
gradients: each source triangle's 3x3 gradient Q = V' V^-1 (its two edges and a scaled normal as
the columns of V, eq. 1-3) is applied to the corresponding target triangle, and the target's
vertices are the least-squares solution that best matches the transferred gradients. We write the
match over triangle edges, as the gradient-domain formulation does (Botsch et al. 2006):

    min_d  sum_t sum_(i, j) in t |(x_j + d_j - x_i - d_i) - Q_c(t) (x_j - x_i)|^2
           + ANCHOR * sum_i |d_i - o_i|^2

with x the target's neutral vertices, d their offsets and o a first guess of them (the closest-point
offsets). The anchor term fixes the translation that gradients alone leave open and ties the low
frequencies to the registration; it is weak (a vertex has about 6 edge rows of weight 1), so the
local shape of each offset comes from the gradients. One sparse factorisation (SuperLU) serves all
52 shapes and 3 axes.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import splu

ANCHOR = 0.2  # weight of the first-guess offsets against the edge rows (weight 1 each)
# Barycentric sample points of a triangle: its corners, edge midpoints and centroid (last).
THIRD = 1 / 3
SAMPLES = np.array(
    [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0], [0, 0.5, 0.5], [0.5, 0, 0.5], [THIRD] * 3]
)
CORNER_WEIGHT = 4.0  # the corners count four times in the fit (the offsets the vertices get)


def frames(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(..., F, 3, 3) Sumner-Popovic frames [v2 - v1, v3 - v1, n / sqrt|n|] as columns, for
    (..., V, 3) vertices."""
    tri = vertices[..., faces, :]
    e1, e2 = tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :]
    n = np.cross(e1, e2)
    n = n / np.sqrt(np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30))
    return np.stack([e1, e2, n], axis=-1)


def deformation_gradients(
    vertices: np.ndarray, faces: np.ndarray, offsets: np.ndarray
) -> np.ndarray:
    """(K, F, 3, 3) gradients Q = V' V^-1 of (K, V, 3) ``offsets`` on the (V, 3) neutral mesh."""
    rest = frames(vertices, faces)
    inverse = np.linalg.inv(rest + 1e-12 * np.eye(3))  # degenerate triangles: near identity
    return frames(vertices[None] + offsets, faces) @ inverse[None]


def fitted_gradients(vertices: np.ndarray, faces: np.ndarray, sampled: np.ndarray) -> np.ndarray:
    """(K, F, 3, 3) gradients of the affine maps that best fit (K, F, len(SAMPLES), 3) offsets
    ``sampled`` at each triangle's ``SAMPLES`` (least squares, corners weighted ``CORNER_WEIGHT``):
    the area-averaged gradient of a displacement field over a triangle, for a triangle larger
    than the features of the field. Only the in-plane part matters to :func:`transfer` (it moves
    edges), so the normal column of the displacement gradient is zero."""
    weight = np.sqrt(np.where(np.arange(len(SAMPLES)) < 3, CORNER_WEIGHT, 1.0))
    fit = np.linalg.pinv(SAMPLES * weight[:, None]) * weight[None]  # (3 corners, samples)
    corner = np.einsum("cs,kfsx->kfcx", fit, sampled)  # the fitted offsets at the corners
    d1, d2 = corner[:, :, 1] - corner[:, :, 0], corner[:, :, 2] - corner[:, :, 0]
    change = np.stack([d1, d2, np.zeros_like(d1)], axis=-1)  # columns: edge 1, edge 2, normal
    inverse = np.linalg.inv(frames(vertices, faces) + 1e-12 * np.eye(3))
    return np.eye(3) + change @ inverse[None]


def edge_operator(faces: np.ndarray, num_vertices: int) -> sparse.csr_matrix:
    """(3F, V) sparse: rows x_j - x_i for the edges (0, 1), (1, 2), (2, 0) of every face."""
    i = faces[:, [0, 1, 2]].ravel()
    j = faces[:, [1, 2, 0]].ravel()
    rows = np.arange(len(i))
    data = np.concatenate([-np.ones(len(i)), np.ones(len(j))])
    return sparse.csr_matrix(
        (data, (np.concatenate([rows, rows]), np.concatenate([i, j]))),
        shape=(len(i), num_vertices),
    )


def transfer(
    vertices: np.ndarray,
    faces: np.ndarray,
    gradients: np.ndarray,
    guess: np.ndarray,
    anchor: float = ANCHOR,
) -> np.ndarray:
    """Offsets of the (V, 3) target whose (F, 3) triangles best follow the gradients.

    Args:
        vertices, faces: the target's neutral mesh.
        gradients: (K, F, 3, 3) a gradient per target triangle and shape (in the target's axes).
        guess: (K, V, 3) first-guess offsets (the anchor term's o).
        anchor: weight of the anchor term.

    Returns:
        (K, V, 3) float64 offsets.
    """
    num_shapes, num_faces = gradients.shape[:2]
    assert faces.shape == (num_faces, 3) and guess.shape == (num_shapes, len(vertices), 3)
    edges = edge_operator(faces, len(vertices))
    rest = (edges @ vertices).reshape(num_faces, 3, 3)  # (F, edge, xyz)
    solver = splu((edges.T @ edges + anchor * sparse.identity(len(vertices))).tocsc())
    out = np.empty(guess.shape)
    for k in range(num_shapes):
        # Q e for every edge e of every face, minus the rest edge: the edge's wanted change.
        change = np.einsum("fxy,fey->fex", gradients[k], rest) - rest
        out[k] = solver.solve(edges.T @ change.reshape(-1, 3) + anchor * guess[k])
    return out


def rigid_follow(points: np.ndarray, part: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(K, P, 3) offsets that move (P, 3) ``points`` as the (N, 3) ``part`` moves rigidly under
    each of its (K, N, 3) ``offsets``: the part's best rotation (Kabsch) about its centroid,
    applied about the points' centroid, plus the part centroid's shift. Eyeballs and teeth of a
    user's head follow the bundled ones this way."""
    centre, own = part.mean(0), points.mean(0)
    a = part - centre
    out = np.empty((len(offsets), len(points), 3))
    for k, off in enumerate(offsets):
        moved = part + off
        b = moved - moved.mean(0)
        u, _, vt = np.linalg.svd(b.T @ a)
        sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
        rotation = u @ sign @ vt
        out[k] = (points - own) @ rotation.T + own + (moved.mean(0) - centre) - points
    return out
