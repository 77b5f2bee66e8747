""".npy ([T, V*3] vertex positions, the VOCASET / FaceFormer layout) and .npz (a whole
:class:`Animation`, no pickle)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from talkmesh.animation import Animation
from talkmesh.constants import MOTION_FPS, SAMPLE_RATE
from talkmesh.errors import TalkmeshError
from talkmesh.output.files import bundled_head, check_magic, finite

NPY_DEFAULT_FPS = MOTION_FPS  # FaceFormer / CodeTalker write VOCASET predictions at 30 fps
NPZ_FORMAT_VERSION = 1


def export_npy(anim: Animation, path: Path) -> None:
    """[T, V*3] float32 vertex positions, the VOCASET / FaceFormer layout."""
    with open(path, "wb") as f:
        np.save(f, anim.vertices.reshape(anim.num_frames, -1), allow_pickle=False)


def import_npy(path: Path, faces: np.ndarray | None, fps: float | None) -> Animation:
    """[T, V*3] (or [T, V, 3]) vertex positions; faces from the caller or the bundled head."""
    check_magic(path, b"\x93NUMPY", ".npy array")
    arr = np.load(path, allow_pickle=False)
    if not isinstance(arr, np.ndarray):
        raise ValueError("not a single .npy array")
    if arr.ndim == 2 and arr.shape[1] % 3 == 0 and arr.shape[1] > 0:
        arr = arr.reshape(len(arr), -1, 3)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"expected [T, V*3] vertex positions, got an array of shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"expected numbers, got {arr.dtype}")
    vertices = finite(arr.astype(np.float32), "vertices")
    if faces is None:
        head = bundled_head()
        if head is None or head.num_vertices != vertices.shape[1]:
            raise TalkmeshError(
                f"{path}: {vertices.shape[1]} vertices do not match the bundled head; "
                "pass the mesh's faces (faces=...)"
            )
        faces = head.faces
    return Animation(vertices, faces, fps or NPY_DEFAULT_FPS)


def export_npz(anim: Animation, path: Path) -> None:
    """Every field of the animation, loadable with ``np.load(path, allow_pickle=False)``."""
    arrays: dict[str, np.ndarray] = {
        "format_version": np.int64(NPZ_FORMAT_VERSION),
        "vertices": anim.vertices,
        "faces": anim.faces,
        "fps": np.float64(anim.fps),
    }
    if anim.audio is not None:
        arrays["audio"] = anim.audio
        arrays["sample_rate"] = np.int64(anim.sample_rate)
    if anim.weights is not None:
        arrays["weights"] = anim.weights
        arrays["weight_names"] = np.array(anim.weight_names, dtype=np.str_)
    if anim.template is not None:
        arrays["template"] = anim.template
    if anim.basis is not None:
        arrays["basis"] = anim.basis
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def import_npz(path: Path, faces: np.ndarray | None, fps: float | None) -> Animation:
    """An animation saved by :func:`export_npz`."""
    check_magic(path, b"PK", ".npz archive")
    with np.load(path, allow_pickle=False) as z:
        missing = [k for k in ("vertices", "faces", "fps") if k not in z.files]
        if missing:
            raise TalkmeshError(f"{path}: not a talkmesh animation (no {', '.join(missing)})")
        d = {k: z[k] for k in z.files}
    if int(d.get("format_version", NPZ_FORMAT_VERSION)) > NPZ_FORMAT_VERSION:
        raise TalkmeshError(f"{path}: written by a newer talkmesh; upgrade talkmesh to read it")
    weights = d.get("weights")
    return Animation(
        vertices=finite(d["vertices"], "vertices"),
        faces=d["faces"] if faces is None else faces,
        fps=fps or float(d["fps"]),
        audio=d.get("audio"),
        sample_rate=int(d.get("sample_rate", SAMPLE_RATE)),
        weights=None if weights is None else finite(weights, "weights"),
        weight_names=[str(n) for n in d.get("weight_names", [])],
        template=d.get("template"),
        basis=d.get("basis"),
    )
