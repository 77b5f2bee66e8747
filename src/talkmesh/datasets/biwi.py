"""``talkmesh prepare-biwi RAW OUT``: CodeTalker's BIWI preprocessing, in Python.

Per frame (REFERENCE: CodeTalker's BIWI pipeline): rotate by pi about x ((x, y, z) -> (x, -y, -z)),
subtract that frame's centroid, divide by the square root of that frame's total surface area (the
sum of the mixed-Voronoi vertex areas, which partition the surface, equals the sum of the triangle
areas), so every frame has unit area and no units.

RAW holds the scans as sequences (users export BIWI's per-frame scans to this layout)::

    RAW/vertices/<SUBJECT>_<SENTENCE>.npy   [T, V*3] or [T, V, 3] raw positions
    RAW/wav/<SUBJECT>_<SENTENCE>.wav        speech (copied as is)
    RAW/*.ply or RAW/*.obj                  one mesh giving the triangles (BIWI.ply)
    RAW/templates/<SUBJECT>.npy             optional neutral scans [V, 3]; else the first frame
                                            of the subject's first sequence
    RAW/regions/                            optional lve.txt / fdd.txt, copied

OUT is a dataset in the contract of :mod:`talkmesh.datasets.reader` (kind ``biwi`` or ``folder``).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from talkmesh.datasets.reader import parse_name, write_templates
from talkmesh.errors import TalkmeshError


def surface_area(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(..., V, 3) vertices, (F, 3) faces -> (...) total triangle area."""
    v = np.asarray(vertices, dtype=np.float64)
    a, b, c = v[..., faces[:, 0], :], v[..., faces[:, 1], :], v[..., faces[:, 2], :]
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=-1).sum(axis=-1)


def normalize_frames(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(T, V, 3) raw scans -> rotated, centred, unit-area frames (float32)."""
    v = np.asarray(vertices, dtype=np.float64) * np.array([1.0, -1.0, -1.0])  # pi about x
    v = v - v.mean(axis=1, keepdims=True)
    area = surface_area(v, faces)
    if (area <= 0).any():
        raise TalkmeshError(
            "a frame has zero surface area: are the faces right for these vertices?"
        )
    return (v / np.sqrt(area)[:, None, None]).astype(np.float32)


def _faces(raw: Path) -> tuple[np.ndarray, Path]:
    import trimesh

    meshes = sorted(raw.glob("*.ply")) + sorted(raw.glob("*.obj"))
    if not meshes:
        raise TalkmeshError(f"{raw}: no .ply or .obj with the triangles (e.g. BIWI.ply)")
    try:
        mesh = trimesh.load(meshes[0], process=False, force="mesh")
    except Exception as e:  # trimesh raises many types
        raise TalkmeshError(f"{meshes[0]}: unreadable mesh ({type(e).__name__})") from None
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if faces.ndim != 2 or len(faces) == 0:
        raise TalkmeshError(f"{meshes[0]}: has no triangles")
    return faces, meshes[0]


def prepare_biwi(raw: Path, out: Path, *, progress: bool = True, overwrite: bool = False) -> int:
    """Preprocess RAW (see the module docstring) into OUT; returns the number of sequences."""
    from tqdm import tqdm

    raw, out = Path(raw), Path(out)
    src = raw / "vertices"
    if not src.is_dir():
        raise TalkmeshError(
            f"{src} is missing: put the raw sequences there as <SUBJECT>_<SENTENCE>.npy"
        )
    files = sorted(src.glob("*.npy"))
    if not files:
        raise TalkmeshError(f"{src}: no .npy sequences")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise TalkmeshError(f"{out} is not empty: choose a new output directory")
    faces, mesh_path = _faces(raw)
    for sub in ("vertices_npy", "wav"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    templates: dict[str, np.ndarray] = {}
    for path in tqdm(files, desc="prepare-biwi", unit="seq", disable=not progress):
        subject, _ = parse_name(path.stem)
        try:
            seq = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            raise TalkmeshError(f"{path}: not a readable .npy ({e})") from None
        seq = seq.reshape(len(seq), -1, 3) if seq.ndim == 2 else seq
        if seq.ndim != 3 or seq.shape[2] != 3 or (seq.shape[1] and faces.max() >= seq.shape[1]):
            raise TalkmeshError(
                f"{path}: shape {seq.shape} does not fit the faces of {mesh_path.name}"
            )
        frames = normalize_frames(seq, faces)
        np.save(out / "vertices_npy" / path.name, frames.reshape(len(frames), -1))
        wav = raw / "wav" / f"{path.stem}.wav"
        if wav.is_file():
            shutil.copyfile(wav, out / "wav" / wav.name)
        if subject not in templates:
            neutral = raw / "templates" / f"{subject}.npy"
            base = np.load(neutral)[None] if neutral.is_file() else seq[:1]
            templates[subject] = normalize_frames(base, faces)[0]
    write_templates(out / "templates.pkl", templates)
    shutil.copyfile(mesh_path, out / ("BIWI" + mesh_path.suffix))
    if (raw / "regions").is_dir():
        shutil.copytree(raw / "regions", out / "regions", dirs_exist_ok=True)
    return len(files)
