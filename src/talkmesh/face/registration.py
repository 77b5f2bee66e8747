"""Registering the bundled head onto a user's head mesh: rigid + scale, then non-rigid.

1. Rigid + scale (:func:`rigid_fit`): the 24 axis-aligned orientations (so a Z-up or Y-down
   export is found) and the 4 that align the principal axes, each started from the meshes'
   centroids and RMS radii and refined by trimmed, two-way iterative closest points with Umeyama's
   similarity fit (Umeyama 1991, eq. 40-42); the orientation whose fit leaves the smallest residual
   wins. With four or more landmarks, their Umeyama fit is the one start.
2. Non-rigid (:func:`nonrigid_fit`): the registered head's vertices X move to minimise

       stiffness * |L (X - X0)|^2 + LANDMARK_WEIGHT * sum_l |X_l - p_l|^2
       + sum_i w_i (POINT_WEIGHT |X_i - c_i|^2 + (n_i . (X_i - c_i))^2)

   with L the uniform graph Laplacian (a smooth displacement field, as the non-rigid ICP of
   Amberg et al. 2007 regularises its per-vertex transforms), c_i the closest point of the user's
   surface and n_i its normal (trimmed, and only on triangles facing the same way, so closed lips
   do not swap), and p_l the landmarks. The point-to-plane term lets the fit slide along the
   surface where the smoothness term wants it; the point-to-point one keeps it from drifting.
   Each round is one sparse solve (scipy's SuperLU); the stiffness falls from round to round, so
   the fit goes from global to local.
   The first round's closest points c_i are taken from the head pulled by :func:`smoothed_pull`
   (each vertex's offset to its closest target point, Laplacian-smoothed, four times): it gets
   the correspondences of a differently shaped face closer than the rigid fit does (bo's mean
   transfer error 15.1 -> 13.8%, bench/rig_transfer.py).

Everything here is in the user's units and axes after the rigid fit.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

ICP_ITERATIONS = 40
COARSE = 6  # iterations tried from each of the 24 orientations
TRIM = 0.9  # ICP fits the closest 90% of the pairs, so hair and shoulders do not pull
FIT_TRIM = 0.97  # the non-rigid fit drops only the farthest 3% (it starts close)
STIFFNESS = (1e4, 1e4, 3e3, 3e3, 1e3, 1e3, 300.0, 300.0, 100.0, 100.0, 30.0, 30.0, 10.0, 10.0)
POINT_WEIGHT = 1.0  # point-to-point pull beside the point-to-plane one (which lets it slide)
LANDMARK_WEIGHT = 10.0  # a landmark counts as ten closest-point pairs
CANDIDATES = 12  # nearest vertices whose triangles are searched for the closest point
ROUGH_CANDIDATES = 4  # ... while fitting, when the next round corrects a near miss
POINT_BLOCK = 8192  # points searched at a time: memory is their candidate pairs, not all of them
COARSE_POINTS = 1500  # points of each mesh the 28 coarse fits use
FACING = 0.3  # cosine between normals below which a triangle faces away from a point ...
AWAY_PENALTY = 1e3  # ... and is taken only when no triangle facing the point is a candidate
SMOOTH_STEPS = 30  # Laplacian averaging steps of each smoothed_pull round's displacement field


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
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


def nearest_axis_rotation(rotation: np.ndarray, degrees: float = 30.0) -> np.ndarray | None:
    """The axis swap (one of the 24 rotations taking axes onto axes) within ``degrees`` of
    ``rotation``, or None: a Z-up export is a swap, a head turned by a few degrees is not."""
    best = max(_orientations(), key=lambda o: float(np.trace(o.T @ rotation)))
    cos = (float(np.trace(best.T @ rotation)) - 1.0) / 2.0
    return best if cos >= np.cos(np.radians(degrees)) else None


def _principal_orientations(source: np.ndarray, target: np.ndarray) -> list[np.ndarray]:
    """The 4 rotations that align the principal axes of ``source`` with those of ``target``."""
    axes = [np.linalg.eigh(np.cov((x - x.mean(0)).T))[1] for x in (source, target)]
    out = []
    for signs in itertools.product((1, -1), repeat=3):
        r = axes[1] @ np.diag(signs) @ axes[0].T
        if np.linalg.det(r) > 0:
            out.append(r)
    return out


def _icp(source, target, tree, init, steps):
    """Trimmed two-way similarity ICP of ``source`` onto ``target`` from ``init``: a rotation
    (started from the centroids and RMS radii) or a full (s, R, t)."""
    if isinstance(init, tuple):
        scale, rotation, shift = init
    else:
        rms = lambda x: np.sqrt(((x - x.mean(0)) ** 2).sum(1).mean())  # noqa: E731
        scale, rotation = rms(target) / rms(source), init
        shift = target.mean(0) - scale * rotation @ source.mean(0)
    for _ in range(steps):
        moved = scale * source @ rotation.T + shift
        d1, i1 = tree.query(moved)
        d2, i2 = cKDTree(moved).query(target)
        keep1 = d1 <= np.quantile(d1, TRIM)
        keep2 = d2 <= np.quantile(d2, TRIM)
        src = np.concatenate([source[keep1], source[i2[keep2]]])
        dst = np.concatenate([target[i1[keep1]], target[keep2]])
        scale, rotation, shift = similarity(src, dst)
    moved = scale * source @ rotation.T + shift
    residual = float(np.median(tree.query(moved)[0]))
    return scale, rotation, shift, residual


def rigid_fit(
    source: np.ndarray,
    target: np.ndarray,
    pairs: tuple[np.ndarray, np.ndarray] | None = None,
    start: tuple[float, np.ndarray, np.ndarray] | None = None,
) -> tuple[float, np.ndarray, np.ndarray, float]:
    """(scale, rotation, shift, median residual) taking (N, 3) ``source`` onto (M, 3) ``target``.

    ``pairs``: (L, 3) source and target landmark positions; with four or more, their similarity
    fit is the only start. ``start``: a fit (s, R, t) found already (on a sample of ``target``),
    the only start otherwise."""
    tree = cKDTree(target)
    if pairs is not None and len(pairs[0]) >= 4:
        return _icp(source, target, tree, similarity(*pairs), ICP_ITERATIONS)
    if start is not None:
        return _icp(source, target, tree, start, ICP_ITERATIONS)
    # A short fit from every orientation, then a full one from the best two.
    starts = _orientations() + _principal_orientations(source, target)
    rng = np.random.default_rng(0)
    few_source = source[rng.permutation(len(source))[:COARSE_POINTS]]
    few_target = target[rng.permutation(len(target))[:COARSE_POINTS]]
    few_tree = cKDTree(few_target)
    coarse = sorted(starts, key=lambda r: _icp(few_source, few_target, few_tree, r, COARSE)[3])
    fits = [_icp(source, target, tree, r, ICP_ITERATIONS) for r in coarse[:2]]
    return min(fits, key=lambda f: f[3])


def laplacian(faces: np.ndarray, n: int) -> sparse.csr_matrix:
    """Uniform graph Laplacian I - D^-1 A of a triangle mesh with ``n`` vertices, (n, n)."""
    i = faces[:, [0, 1, 2, 1, 2, 0]].ravel()
    j = faces[:, [1, 2, 0, 0, 1, 2]].ravel()
    adj = sparse.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)).tocsr()
    adj.data[:] = 1.0
    degree = np.asarray(adj.sum(1)).ravel()
    degree[degree == 0] = 1.0
    return (sparse.identity(n) - sparse.diags(1.0 / degree) @ adj).tocsr()


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) unit normals (counter-clockwise winding)."""
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) unit area-weighted vertex normals (POINT_BLOCK x 32 faces at a time: the (F, 3, 3)
    corners of a dense mesh's every face would be 170 MB at 2.4M faces)."""
    out = np.zeros_like(vertices, dtype=np.float64)
    step = 32 * POINT_BLOCK
    for a in range(0, len(faces), step):
        part = faces[a : a + step]
        tri = vertices[part]
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        for c in range(3):
            out += np.stack([np.bincount(part[:, c], fn[:, x], len(vertices)) for x in range(3)], 1)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-30)


def closest_points(
    points: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray | None = None,
    candidates: int = CANDIDATES,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For (P, 3) points: the closest triangle of the mesh, barycentric coordinates (P, 3) of
    the closest point on it, and the distance (P,). Searches the triangles around the
    ``candidates`` nearest vertices (exact for meshes without long thin triangles). With the
    points' (P, 3) ``normals``, triangles facing away are passed over while one facing the same
    way is near: closed lips and eyelids touch, and the lower lip must not take the upper's motion.
    """
    corner_of = faces.ravel()  # vertex -> its faces, as CSR arrays
    order = np.argsort(corner_of, kind="stable")
    starts = np.searchsorted(corner_of[order], np.arange(len(vertices) + 1))
    tree = cKDTree(vertices)
    out = [
        _closest_block(
            points[a : a + POINT_BLOCK],
            vertices,
            faces,
            None if normals is None else normals[a : a + POINT_BLOCK],
            candidates,
            tree,
            order,
            starts,
        )
        for a in range(0, len(points), POINT_BLOCK)
    ]
    if not out:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
    return tuple(np.concatenate(parts) for parts in zip(*out))


def _closest_block(points, vertices, faces, normals, candidates, tree, order, starts):
    """:func:`closest_points` of a block of points (its memory: the block's candidate pairs)."""
    import trimesh

    _, near = tree.query(points, k=min(candidates, len(vertices)))
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
        fn = face_normals(vertices, faces[pairs[:, 1]].reshape(-1, 3))
        facing = (fn * normals[pairs[:, 0]]).sum(1)
        rank = dist + np.where(facing < FACING, AWAY_PENALTY, 0.0)
    order = np.lexsort((rank, pairs[:, 0]))  # per point, nearest first
    first = order[np.r_[True, pairs[order[1:], 0] != pairs[order[:-1], 0]]]
    p = pairs[first, 0]
    best[p], best_face[p], best_point[p] = dist[first], pairs[first, 1], closest[first]
    bary = trimesh.triangles.points_to_barycentric(vertices[faces[best_face]], best_point)
    bary[~np.isfinite(bary).all(1)] = 1 / 3  # a degenerate (zero-area) triangle: its centre
    return best_face, np.clip(bary, 0.0, 1.0), best


def smoothed_pull(
    head: np.ndarray, head_faces: np.ndarray, target: np.ndarray, rounds: int = 4
) -> np.ndarray:
    """(V, 3) ``head`` pulled towards the (M, 3) ``target`` points by a smoothed displacement
    field: ``rounds`` times, each vertex's offset to its closest target point (the farthest
    ``1 - TRIM`` set to zero) is smoothed by ``SMOOTH_STEPS`` steps of uniform Laplacian averaging
    and added (the fit ``talkmesh rig`` used before the sparse solve)."""
    average = sparse.identity(len(head)) - laplacian(head_faces, len(head))
    tree = cKDTree(target)
    out = head.copy()
    for _ in range(rounds):
        d, i = tree.query(out)
        field = target[i] - out
        field[d > np.quantile(d, TRIM)] = 0.0
        for _ in range(SMOOTH_STEPS):
            field = average @ field
        out = out + field
    return out


def _blocks(blocks: np.ndarray) -> sparse.csc_matrix:
    """(3V, 3V) block-diagonal sparse matrix of (V, 3, 3) blocks (x, y, z of a vertex adjacent)."""
    n = len(blocks)
    at = np.arange(3 * n).reshape(n, 3)
    rows = np.repeat(at, 3, axis=1).ravel()
    cols = np.tile(at, (1, 3)).ravel()
    return sparse.csc_matrix((blocks.ravel(), (rows, cols)), shape=(3 * n, 3 * n))


def nonrigid_fit(
    head: np.ndarray,
    head_faces: np.ndarray,
    target: np.ndarray,
    target_faces: np.ndarray,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    start: np.ndarray | None = None,
) -> np.ndarray:
    """(V, 3) ``head`` vertices (already rigidly registered) pulled onto the target surface.

    Args:
        head, head_faces: the registered head, (V, 3) and (F, 3).
        target, target_faces: the user's mesh, (M, 3) and (G, 3).
        landmarks: (L,) head vertex ids and their (L, 3) target positions, or None.
        start: (V, 3) where the first round looks for closest points (default ``head``); the
            smoothness term still measures the displacement from ``head``.

    Returns:
        (V, 3) the head's vertices on the target, its shape kept smooth (see the module doc).
    """
    n = len(head)
    lap = laplacian(head_faces, n)
    smooth = sparse.kron((lap.T @ lap).tocsc(), sparse.identity(3)).tocsc()
    anchor = np.zeros(n)
    anchor_at = np.zeros((n, 3))
    if landmarks is not None and len(landmarks[0]):
        ids, positions = landmarks
        np.add.at(anchor, ids, LANDMARK_WEIGHT)
        np.add.at(anchor_at, ids, LANDMARK_WEIGHT * positions)
    target_normals = face_normals(target, target_faces)
    eye = np.eye(3)
    out = (head if start is None else start).copy()
    for stiffness in STIFFNESS:
        normals = vertex_normals(out, head_faces)
        face, bary, dist = closest_points(out, target, target_faces, normals, ROUGH_CANDIDATES)
        goal = np.einsum("vc,vcx->vx", bary, target[target_faces[face]])
        weight = (dist <= np.quantile(dist, FIT_TRIM)).astype(np.float64)
        # Point-to-plane (n n^T) plus a weaker point-to-point pull, per vertex a 3x3 block.
        plane = target_normals[face, :, None] * target_normals[face, None, :]
        data = weight[:, None, None] * (POINT_WEIGHT * eye + plane)
        system = stiffness * smooth + _blocks(data + anchor[:, None, None] * eye)
        # Solve for the displacement from the rigid fit, so the Laplacian term sees it alone.
        rhs = np.einsum("vxy,vy->vx", data, goal - head) + anchor_at - anchor[:, None] * head
        out = head + splu(system).solve(rhs.ravel()).reshape(n, 3)
    return out
