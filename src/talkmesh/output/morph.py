"""Morph-target rigs: the named blendshapes (plus residual targets) or a PCA basis that plays an
animation within ``GLB_MAX_ERROR``; the .glb exporter writes them as glTF morph targets."""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np

from talkmesh.animation import Animation
from talkmesh.blas import one_blas_thread

GLB_MAX_ERROR = 1e-4  # metres: PCA morph targets reproduce every vertex to 0.1 mm ...
MAX_PCA_TARGETS = 64  # ... using at most this many targets
PCA_TOLERANCE = GLB_MAX_ERROR / 2  # headroom for rounding the targets to float32
EXACT_SVD_LIMIT = 512  # above this many frames and coordinates, use a randomised SVD
GRAM_COLUMNS = 65536  # coordinates upcast to float64 at a time for the Gram matrix
MIN_SINGULAR = 1e-7  # of the largest singular value: smaller directions are lost to rounding


@dataclass
class MorphRig:
    """A mesh whose vertices are ``base + weights @ targets``, i.e. glTF morph targets.

    Attributes:
        base: (V, 3) float32 positions of the glTF mesh.
        targets: (K, V, 3) float32 morph target offsets.
        weights: (T, K) float32 animated target weights.
        rest_weights: (K,) the mesh's default weights: ``base + rest_weights @ targets`` is the
            neutral face.
        names: the K target names.
    """

    base: np.ndarray
    targets: np.ndarray
    weights: np.ndarray
    rest_weights: np.ndarray
    names: list[str]

    def vertices(self) -> np.ndarray:
        """(T, V, 3) float32 vertices the rig plays."""
        k, v = len(self.targets), len(self.base)
        offsets = self.weights.astype(np.float64) @ self.targets.reshape(k, -1).astype(np.float64)
        return (self.base[None].astype(np.float64) + offsets.reshape(-1, v, 3)).astype(np.float32)

    def neutral(self) -> np.ndarray:
        """(V, 3) float32 neutral face."""
        if not self.rest_weights.any():  # a rig's blendshapes: no float64 copy of them all
            return self.base.astype(np.float32)
        offset = np.tensordot(self.rest_weights.astype(np.float64), self.targets, axes=1)
        return (self.base + offset).astype(np.float32)


BLOCK_FRAMES = 1024  # frames processed at a time when checking long animations


BLEND_VERTICES = 65536  # of a float32 basis upcast at a time (the whole is 1.5 GB at 1M)


def _blend(weights: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """(T, K) weights and (K, V, 3) basis -> (T, V, 3) offsets in float64."""
    weights = weights.astype(np.float64)
    out = np.empty((len(weights), basis.shape[1], 3))
    for a in range(0, basis.shape[1], BLEND_VERTICES):
        part = basis[:, a : a + BLEND_VERTICES].astype(np.float64)
        out[:, a : a + BLEND_VERTICES] = np.tensordot(weights, part, axes=1)
    return out


def _max_over_blocks(fn, num_frames: int) -> float:
    return max(
        float(np.abs(fn(slice(s, s + BLOCK_FRAMES))).max())
        for s in range(0, num_frames, BLOCK_FRAMES)
    )


def _mean_over_blocks(fn, num_frames: int) -> np.ndarray:
    total = sum(
        fn(slice(s, s + BLOCK_FRAMES)).sum(axis=0) for s in range(0, num_frames, BLOCK_FRAMES)
    )
    return total / num_frames


def morph_rig(anim: Animation) -> MorphRig:
    """Morph targets that play ``anim``.

    With ``anim.basis`` and ``anim.weights`` the targets are the named blendshapes (plus up to
    ``MAX_PCA_TARGETS`` ``residual_NNN`` targets when ``template + weights @ basis`` misses the
    vertices by ``GLB_MAX_ERROR`` or more). Otherwise they are ``pca_NNN`` principal components of
    the offsets from the template (or the first frame): the fewest that reproduce every vertex
    within ``GLB_MAX_ERROR``, at most ``MAX_PCA_TARGETS``.
    """
    num_v = anim.num_vertices
    template = anim.template
    if template is not None and template.shape != (num_v, 3):
        template = None
    has_basis = (
        anim.basis is not None
        and anim.weights is not None
        and anim.basis.shape == (anim.weights.shape[1], num_v, 3)
    )
    if has_basis:
        basis = anim.basis  # float32 is upcast a block at a time (_blend)
        if template is None:
            template = _mean_over_blocks(
                lambda b: anim.vertices[b] - _blend(anim.weights[b], basis), anim.num_frames
            )
        reference = template.astype(np.float64)

        def residual_block(b: slice) -> np.ndarray:
            return anim.vertices[b] - reference - _blend(anim.weights[b], basis)

        names, targets = list(anim.weight_names), [basis]
        weights, rest = [anim.weights.astype(np.float64)], [np.zeros(len(basis))]
        prefix = "residual"
    else:
        reference = (template if template is not None else anim.vertices[0]).astype(np.float64)

        def residual_block(b: slice) -> np.ndarray:
            return anim.vertices[b] - reference

        names, targets, weights, rest = [], [], [], []
        prefix = "pca"
    residual = _residual(residual_block, anim.num_frames, checked=has_basis)
    if residual is not None:
        components, coeffs = principal_components(residual, MAX_PCA_TARGETS, PCA_TOLERANCE)
        # Blender clamps shape-key values to [slider_min, slider_max] (0..1 by default) and its
        # glTF importer widens that range from the first keyframe only, so keep weights in [0, 1]:
        # w = (c - lo) / span, target = span * component, and lo @ components moves into the base.
        lo = np.minimum(coeffs.min(axis=0), 0.0)
        span = np.maximum(coeffs.max(axis=0), 0.0) - lo
        span[span <= 1e-12] = 1.0
        reference = reference + np.tensordot(lo, components, axes=1)
        names += [f"{prefix}_{k:03d}" for k in range(len(components))]
        targets.append(components * span[:, None, None])
        weights.append((coeffs - lo) / span)
        rest.append(-lo / span)
    return MorphRig(
        base=reference.astype(np.float32),
        targets=(targets[0] if len(targets) == 1 else np.concatenate(targets)).astype(
            np.float32, copy=False
        ),
        weights=np.concatenate(weights, axis=1).astype(np.float32),
        rest_weights=np.concatenate(rest).astype(np.float32),
        names=names,
    )


def _residual(block, num_frames: int, checked: bool) -> np.ndarray | None:
    """(T, V, 3) float32 residual that ``block(slice)`` gives a block of frames at a time; with
    ``checked``, None when it stays under PCA_TOLERANCE (no PCA targets needed). Long animations
    (10 min is 1 GB of float32 vertices) are checked in blocks and the whole residual is built
    only when needed; a clip of one block is computed once and kept."""
    if num_frames <= BLOCK_FRAMES:
        whole = block(slice(0, num_frames))
        if checked and float(np.abs(whole).max()) < PCA_TOLERANCE:
            return None
        return whole.astype(np.float32)
    if checked and _max_over_blocks(block, num_frames) < PCA_TOLERANCE:
        return None
    first = block(slice(0, BLOCK_FRAMES))
    residual = np.empty((num_frames, *first.shape[1:]), np.float32)  # float32: 10 min is 1 GB
    residual[:BLOCK_FRAMES] = first
    for s in range(BLOCK_FRAMES, num_frames, BLOCK_FRAMES):
        residual[s : s + BLOCK_FRAMES] = block(slice(s, s + BLOCK_FRAMES))
    return residual


def principal_components(
    offsets: np.ndarray, max_components: int, tolerance: float
) -> tuple[np.ndarray, np.ndarray]:
    """(T, V, 3) offsets -> (K, V, 3) orthonormal components and (T, K) coefficients.

    K is the fewest components (at least 1, at most ``max_components``) whose reconstruction
    ``coeffs @ components`` is within ``tolerance`` of every coordinate, or ``max_components``
    when none is.
    """
    num_t, num_v = offsets.shape[:2]
    data = offsets.reshape(num_t, -1)  # float32 stays float32 (no 2 GB copy for 10 minutes)
    if data.dtype not in (np.float32, np.float64):
        data = data.astype(np.float64)
    # a short clip's medium products on one thread (talkmesh.blas); long ones keep the team
    small = min(data.shape) <= EXACT_SVD_LIMIT
    with one_blas_thread() if small else nullcontext():
        return _fewest_components(data, num_v, max_components, tolerance)


def _fewest_components(
    data: np.ndarray, num_v: int, max_components: int, tolerance: float
) -> tuple[np.ndarray, np.ndarray]:
    num_t = len(data)
    basis = _row_space(data, max_components)  # (3V, R), most important first
    coeffs = data @ basis.astype(data.dtype, copy=False)
    # the check in the data's precision: float32 rounds a reconstruction by ~1e-7 of the
    # offsets, far under the tolerance, at half the memory traffic of float64
    check = basis.astype(data.dtype, copy=False)

    def max_error(k: int) -> float:
        err = 0.0
        for start in range(0, num_t, 256):  # in blocks of frames to bound memory
            block = slice(start, start + 256)
            approx = coeffs[block, :k] @ check[:, :k].T
            err = max(err, float(np.abs(data[block] - approx).max()))
        return err

    lo, hi = 1, basis.shape[1]
    if max_error(hi) < tolerance:
        while lo < hi:  # smallest k within tolerance
            mid = (lo + hi) // 2
            if max_error(mid) < tolerance:
                hi = mid
            else:
                lo = mid + 1
    k = hi
    return basis[:, :k].T.reshape(k, num_v, 3), coeffs[:, :k]


def _row_space(data: np.ndarray, max_components: int) -> np.ndarray:
    """(T, D) -> (D, R) orthonormal basis of the top R <= max_components right singular vectors."""
    if min(data.shape) <= EXACT_SVD_LIMIT:
        return _row_space_gram(data, max_components)
    # Randomised SVD with power iterations (Halko et al. 2011, Alg. 4.4); the caller measures the
    # reconstruction error itself, so an approximate subspace only costs extra components.
    # Small factors take the data's dtype: mixing float32 data with float64 factors would make
    # numpy upcast a float64 copy of the whole data (2 GB at 10 minutes) in every product.
    rank = min(max_components + 16, *data.shape)
    rng = np.random.default_rng(0)
    dt = data.dtype

    def orth(x: np.ndarray) -> np.ndarray:
        return np.linalg.qr(x)[0].astype(dt, copy=False)

    q = orth(data.T @ rng.standard_normal((data.shape[0], rank)).astype(dt))
    for _ in range(4):
        q = orth(data.T @ orth(data @ q))
    _, _, vt = np.linalg.svd(data @ q, full_matrices=False)
    return (q @ vt.T.astype(dt))[:, :max_components]


def _row_space_gram(data: np.ndarray, max_components: int) -> np.ndarray:
    """:func:`_row_space` through the eigenvectors of the small Gram matrix (T x T for T frames
    of D coordinates, or D x D), in float64: the SVD's singular subspaces at a fraction of its
    cost (8.3 s of the bundled head's motion, 249 x 14298: 0.1 s instead of 1-4 s). Directions
    whose singular value is below ``MIN_SINGULAR`` of the largest are dropped (the Gram matrix
    squares the spread, so rounding decides them); the caller measures the reconstruction
    error, so the basis needs to be orthonormal, not exactly the SVD's."""
    num_t, dim = data.shape
    if num_t <= dim:
        gram = np.zeros((num_t, num_t))
        for a in range(0, dim, GRAM_COLUMNS):
            block = data[:, a : a + GRAM_COLUMNS].astype(np.float64)
            gram += block @ block.T
    else:
        gram = np.zeros((dim, dim))
        for a in range(0, num_t, GRAM_COLUMNS):
            block = data[a : a + GRAM_COLUMNS].astype(np.float64)
            gram += block.T @ block
    values, vectors = np.linalg.eigh(gram)  # ascending
    order = np.argsort(values)[::-1][:max_components]
    values, vectors = np.maximum(values[order], 0.0), vectors[:, order]
    keep = values > (MIN_SINGULAR**2) * max(float(values[0]), np.finfo(float).tiny)
    values, vectors = values[keep], vectors[:, keep]
    if not len(values):  # no motion at all: any unit direction reproduces it
        basis = np.zeros((dim, 1))
        basis[0] = 1.0
        return basis
    if num_t > dim:
        return vectors
    # right singular vectors v = X^T u / s, orthonormalised again (QR keeps their order)
    right = np.empty((dim, len(values)))
    for a in range(0, dim, GRAM_COLUMNS):
        right[a : a + GRAM_COLUMNS] = data[:, a : a + GRAM_COLUMNS].astype(np.float64).T @ vectors
    right /= np.sqrt(values)
    q, r = np.linalg.qr(right)
    return q * np.sign(np.diag(r))  # QR's signs flipped back to the vectors' own
