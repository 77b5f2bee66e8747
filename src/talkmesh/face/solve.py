"""ARKit weights from any vertex model's motion, on the model's own topology.

A learned model trained on real faces moves its own mesh (FLAME's 5023 vertices, BIWI's 23370,
MeshTalk's 6172, a user's), not the bundled head, so it has no ARKit weights to export. Here the
topology's neutral face is rigged with the 52 bundled shapes (:func:`solver_for_mesh`: the
registration of :mod:`talkmesh.face.rig`, closest-point shapes, saved per mesh by
:mod:`talkmesh.face.rig_cache` as ``animate --head`` saves its own), and every frame's offsets
``d_t`` (V, 3) are solved for the weights ``w_t`` (52,) in [0, 1] that minimise

    sum_t |w_t B - d_t|^2 + LIPS c sum_t |w_t A - a_t|^2 + SMOOTH sum_t |(w_t - w_{t-1}) S|^2

``B`` (52, 3V) the shapes, ``A`` (52, 3) the lower minus the upper lip vertex of each shape and
``a_t`` the same difference of the frame's motion (so a lip closure the model makes is kept where
the 52 shapes would spread the error over it), ``c = trace(B B^T) / trace(A A^T)`` (the pair
counts LIPS times as much as the whole face), and ``S S^T = B B^T + OWN diag(B B^T)``: a jump
costs the vertex motion it makes, and a share of each channel's own jump (so mixes of shapes that
look alike do not flicker; a small shape such as ``eyeLookUpLeft`` counts at its own size). All
terms scale with the mesh, so units do not matter. The problem is a box-constrained quadratic in
52 x T numbers: projected gradient descent with Nesterov momentum from the clipped per-frame solution,
all frames of a block at once, each block continuing from the last frame of the one before.
``Solved.residual`` is the share of the motion (sum of squares) the 52 shapes do not express.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from talkmesh.animation import Animation, AnimationBlocks
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES, NUM_ARKIT

SMOOTH = 0.02  # temporal smoothness: share of a frame-to-frame jump's vertex motion
OWN = 0.1  # ... plus this share of each channel's own jump (ambiguous mixes do not flicker)
LIPS = 0.5  # weight of the lip pair's relative motion, against the whole face's
RIDGE = 1e-6  # keeps shapes the mesh cannot show (no eyeballs: eyeLook*) at zero
ITERATIONS = 300


class Solved(NamedTuple):
    """Weights ``(T, 52)`` in [0, 1] (ARKit order), the residual share of the motion and the
    motion's sum of squares (what the share is of)."""

    weights: np.ndarray
    residual: float
    total: float = 0.0


@dataclass
class Residual:
    """The residual share over everything solved so far (blocks of one clip add up here)."""

    missed: float = 0.0
    total: float = 0.0

    @property
    def share(self) -> float:
        return self.missed / self.total if self.total > 0 else 0.0


@dataclass(frozen=True)
class ArkitSolver:
    """The 52 shapes on one topology, factorised for the bounded least-squares solve.

    Attributes:
        template: (V, 3) the topology's neutral face.
        blendshapes: (52, V, 3) the shapes on it (its units and axes).
        lip_pair: (2,) its upper and lower lip vertex at the midline.
    """

    template: np.ndarray
    blendshapes: np.ndarray
    lip_pair: tuple[int, int]
    smooth: float = SMOOTH
    lips: float = LIPS
    iterations: int = ITERATIONS
    _factors: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        v = len(self.template)
        assert self.blendshapes.shape == (NUM_ARKIT, v, 3), self.blendshapes.shape
        basis = np.asarray(self.blendshapes, np.float64).reshape(NUM_ARKIT, -1)
        upper, lower = self.lip_pair
        lip = np.asarray(self.blendshapes[:, lower] - self.blendshapes[:, upper], np.float64)
        gram = basis @ basis.T
        scale = max(float(np.trace(gram)) / NUM_ARKIT, 1e-30)
        # the lip pair counts LIPS times as much as the whole face: one pair against V vertices
        lips = self.lips * float(np.trace(gram)) / max(float(np.sum(lip**2)), 1e-30)
        hessian = gram + lips * lip @ lip.T + RIDGE * scale * np.eye(NUM_ARKIT)
        # (52, 52): the jump's vertex motion, plus a share of each channel's own size
        smooth = self.smooth * (gram + np.diag(OWN * np.diag(gram) + RIDGE * scale))
        self._factors.update(
            basis=basis,
            gram=gram,
            lip=lip,
            lips=lips,
            scale=scale,
            hessian=hessian,
            smooth=smooth,
            inverse=np.linalg.inv(hessian),
            step=1.0 / (np.linalg.eigvalsh(hessian)[-1] + 4 * np.linalg.eigvalsh(smooth)[-1]),
        )

    def solve(self, offsets: np.ndarray, previous: np.ndarray | None = None) -> Solved:
        """(T, V, 3) offsets from ``template`` -> :class:`Solved`; ``previous`` (52,): the
        weights of the frame before (the last of the block before), for smoothness across."""
        f = self._factors
        offsets = np.asarray(offsets, np.float64)
        assert offsets.ndim == 3 and offsets.shape[1:] == self.template.shape, offsets.shape
        flat = offsets.reshape(len(offsets), -1)
        upper, lower = self.lip_pair
        projection = flat @ f["basis"].T  # (T, 52): all the solve needs of the vertices
        lip_motion = offsets[:, lower] - offsets[:, upper]
        target = projection + f["lips"] * lip_motion @ f["lip"].T
        w = _bounded_smooth(target, f, previous, self.iterations)
        # |d - w B|^2 = |d|^2 - 2 w.(B d) + w G w, without a (T, 3V) array of what is missed
        total = float(np.einsum("ij,ij->", flat, flat))
        gram = f["gram"]
        missed = total - 2 * float(np.sum(w * projection)) + float(np.sum((w @ gram) * w))
        share = max(missed, 0.0) / total if total > 0 else 0.0
        return Solved(w.astype(np.float32), share, total)

    def solve_blocks(self, anim: AnimationBlocks, residual: Residual | None = None):
        """``anim`` (this topology's motion, block by block) with its ARKit weights solved;
        ``residual`` (if given) adds up the clip's residual share as the blocks go by."""
        template = np.asarray(self.template, np.float64)

        def blocks() -> Iterator[Animation]:
            previous = None
            for block in anim.blocks:
                offsets = np.asarray(block.vertices, np.float64) - template
                solved = self.solve(offsets, previous)
                if residual is not None:
                    residual.total += solved.total
                    residual.missed += solved.residual * solved.total
                previous = solved.weights[-1].astype(np.float64) if len(solved.weights) else None
                yield replace(block, weights=solved.weights, weight_names=list(ARKIT_NAMES))

        # every other field (the head pose, the basis, the phones) as the model made it
        return replace(anim, blocks=blocks(), weight_names=list(ARKIT_NAMES))


def _bounded_smooth(target, f: dict, previous, iterations: int) -> np.ndarray:
    """argmin over W in [0, 1]^(T x 52) of 0.5 sum_t (w H w - 2 w q_t) + 0.5 sum_t
    |(w_t - w_{t-1}) S|^2 (w_{-1} = ``previous`` when given): FISTA on the projected gradient."""
    hessian, step, smooth = f["hessian"], f["step"], f["smooth"]
    w = np.clip(target @ f["inverse"].T, 0.0, 1.0)
    y, momentum = w.copy(), 1.0
    for _ in range(iterations):
        grad = y @ hessian - target
        if len(y) > 1:
            diff = np.diff(y, axis=0) @ smooth
            grad[:-1] -= diff
            grad[1:] += diff
        if previous is not None and len(y):
            grad[0] += (y[0] - previous) @ smooth
        new = np.clip(y - step * grad, 0.0, 1.0)
        next_momentum = (1 + np.sqrt(1 + 4 * momentum**2)) / 2
        y = new + (momentum - 1) / next_momentum * (new - w)
        w, momentum = new, next_momentum
    return w


def solver_for_mesh(vertices: np.ndarray, faces: np.ndarray, name: str = "the template"):
    """The :class:`ArkitSolver` of a topology's neutral mesh (V, 3) with its triangles (F, 3):
    the mesh rigged with the bundled shapes (registered once per mesh, and saved as
    ``talkmesh rig`` saves its registrations). One-line TalkmeshError when it cannot be rigged."""
    from talkmesh.face.rig_files import rig_mesh

    vertices = np.asarray(vertices, np.float32)
    if faces is None or not len(faces):
        raise TalkmeshError(
            f"{name}: ARKit weights on this topology need its triangles to rig it: give the "
            "template with its faces (a .obj/.ply, or templates.pkl beside its mesh)"
        )
    try:
        rig = rig_mesh(vertices, np.asarray(faces, np.int64))
    except TalkmeshError as e:
        raise TalkmeshError(
            f"{name}: the 52 ARKit shapes cannot be rigged onto it ({e}); write .npz, .npy, "
            ".glb, .obj or a video instead of ARKit weights"
        ) from None
    pair = (rig.landmarks["upper_lip"], rig.landmarks["lower_lip"])
    return ArkitSolver(vertices, rig.blendshapes, (int(pair[0]), int(pair[1])))
