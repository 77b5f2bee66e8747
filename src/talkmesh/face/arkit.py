"""The 52 ARKit blendshape names, and the Live Link Face spelling and column order.

``ARKIT_NAMES`` are the raw values of ARKit's ``ARFaceAnchor.BlendShapeLocation`` in the order of
Apple's documentation (left eye, right eye, jaw and mouth, brows, cheeks, nose, tongue). Every
``(T, 52)`` weight array in talkmesh uses this order unless its ``weight_names`` say otherwise.

Epic's Live Link Face app writes the same 52 shapes capitalised (``EyeBlinkLeft``) and in its own
order: it swaps ``jawLeft``/``jawRight`` and ``mouthLeft``/``mouthRight`` relative to ARKit, and
adds nine head and eye rotations (61 values per row, its ``BlendShapeCount``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from talkmesh.blas import one_blas_thread
from talkmesh.errors import TalkmeshError

# fmt: skip keeps one line per face region, as Apple lists them.
ARKIT_NAMES: tuple[str, ...] = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft",
    "eyeSquintLeft", "eyeWideLeft",
    "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
    "eyeSquintRight", "eyeWideRight",
    "jawForward", "jawLeft", "jawRight", "jawOpen",
    "mouthClose", "mouthFunnel", "mouthPucker", "mouthLeft", "mouthRight",
    "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft", "mouthFrownRight",
    "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft", "mouthStretchRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
    "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight",
    "mouthUpperUpLeft", "mouthUpperUpRight",
    "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight",
    "noseSneerLeft", "noseSneerRight",
    "tongueOut",
)  # fmt: skip
NUM_ARKIT = len(ARKIT_NAMES)
assert NUM_ARKIT == 52

# ARKit name -> Live Link Face column name (same shape, capitalised).
LIVE_LINK_NAMES: dict[str, str] = {n: n[0].upper() + n[1:] for n in ARKIT_NAMES}

# Live Link Face column order, as in the header of the CSV files the app exports.
# fmt: skip keeps the two swaps against ARKit order on lines of their own.
LIVE_LINK_BLENDSHAPES: tuple[str, ...] = tuple(
    LIVE_LINK_NAMES[n]
    for n in (
        *ARKIT_NAMES[:15],
        "jawRight", "jawLeft",
        *ARKIT_NAMES[17:21],
        "mouthRight", "mouthLeft",
        *ARKIT_NAMES[23:],
    )
)  # fmt: skip
# fmt: skip keeps one line each for the head, the left eye and the right eye.
LIVE_LINK_ROTATIONS: tuple[str, ...] = (
    "HeadYaw", "HeadPitch", "HeadRoll",
    "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
    "RightEyeYaw", "RightEyePitch", "RightEyeRoll",
)  # fmt: skip
LIVE_LINK_COLUMNS: tuple[str, ...] = LIVE_LINK_BLENDSHAPES + LIVE_LINK_ROTATIONS
assert sorted(LIVE_LINK_BLENDSHAPES) == sorted(LIVE_LINK_NAMES.values())
assert len(LIVE_LINK_COLUMNS) == 61
# Live Link Face's rotations are not radians: Unreal's ARKit face support (``ToBlendShapeMap`` in
# AppleARKitFaceSupport's AppleARKitFaceMeshConversion.h) maps each angle's -180..180 degrees
# to -1..1 (``HeadYaw = Rotator.Yaw / 180``), and pylivelinkface documents head rotations
# "between -1 and 1". A value is the angle in radians over pi.
LIVE_LINK_HEAD_FROM_POSE = [
    1,
    0,
    2,
]  # a head pose is pitch, yaw, roll; the columns yaw, pitch, roll


def live_link_head(pose: np.ndarray) -> np.ndarray:
    """(T, 6) head pose (radians, :mod:`talkmesh.face.head_motion`) -> (T, 3) float32 HeadYaw,
    HeadPitch, HeadRoll as Live Link Face carries them: half turns, -1 to 1."""
    return (np.asarray(pose, np.float64)[:, LIVE_LINK_HEAD_FROM_POSE] / np.pi).astype(np.float32)


def arkit_index(name: str) -> int:
    """Index into ``ARKIT_NAMES`` of a name in either spelling (case-insensitive); -1 if unknown."""
    return _LOWER_INDEX.get(name.lower(), -1)


_LOWER_INDEX = {n.lower(): i for i, n in enumerate(ARKIT_NAMES)}


def to_arkit_order(weights: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """(T, N) weights with column ``names`` -> (T, 52) float32 weights in ``ARKIT_NAMES`` order.

    Names match case-insensitively, so Live Link spellings work too; extra columns are dropped.
    """
    weights = np.asarray(weights, dtype=np.float32)
    if weights.ndim != 2 or weights.shape[1] != len(names):
        raise TalkmeshError(f"weights {weights.shape} do not match {len(names)} names")
    column = {n.lower(): i for i, n in enumerate(names)}
    missing = [n for n in ARKIT_NAMES if n.lower() not in column]
    if missing:
        raise TalkmeshError(
            f"the weights lack {len(missing)} ARKit blendshapes: {', '.join(missing[:3])}"
            + (", ..." if len(missing) > 3 else "")
        )
    return weights[:, [column[n.lower()] for n in ARKIT_NAMES]]


def fit_weights(
    vertices: np.ndarray,
    basis: np.ndarray,
    template: np.ndarray | None = None,
    iterations: int = 200,
    block: int = 2048,
) -> np.ndarray:
    """Per-frame vertices (T, V, 3) -> the ARKit weights (T, 52) in [0, 1] whose blend
    ``template + weights @ basis`` is closest to them in the least-squares sense (``template``
    None: the vertices are already offsets).

    For models that output vertices (CodeTalker, MeshTalk) on the bundled topology, so that their
    animations export to ARKit consumers (Live Link CSV, glTF morph targets). Solved as a box-
    constrained least-squares problem by projected gradient descent from the clipped unconstrained
    solution, all frames at once; frames are projected onto the basis in blocks, so memory stays
    at a few blocks of vertices.
    """
    fitter = WeightFitter(basis, iterations)
    base = 0.0 if template is None else np.asarray(template, np.float64)
    out = np.zeros((len(vertices), basis.shape[0]), np.float32)
    for i in range(0, len(vertices), block):
        out[i : i + block] = fitter(np.asarray(vertices[i : i + block], np.float64) - base)
    return out


class WeightFitter:
    """:func:`fit_weights` with the basis factorised once: call it on (T, V, 3) offsets (streaming
    calls it on one frame at a time)."""

    def __init__(self, basis: np.ndarray, iterations: int = 200) -> None:
        k = basis.shape[0]
        self.basis = np.asarray(basis, np.float64).reshape(k, -1)
        self.gram = self.basis @ self.basis.T
        reg = self.gram + np.eye(k) * 1e-9 * np.trace(self.gram) / k
        self.inverse = np.linalg.inv(reg)
        self.step = 1.0 / np.linalg.eigvalsh(self.gram)[-1]
        self.iterations = iterations

    def __call__(self, offsets: np.ndarray) -> np.ndarray:
        proj = np.asarray(offsets, np.float64).reshape(len(offsets), -1) @ self.basis.T
        return self.from_projection(proj)

    def from_projection(self, proj: np.ndarray) -> np.ndarray:
        """The fit from the offsets' projections onto the basis, (T, 52) ``offsets @ basis.T``
        (a model can compute those without the offsets themselves)."""
        with one_blas_thread():
            w = np.clip(proj @ self.inverse.T, 0.0, 1.0)
            for _ in range(self.iterations):
                w = np.clip(w - self.step * (w @ self.gram - proj), 0.0, 1.0)
        return w.astype(np.float32)
