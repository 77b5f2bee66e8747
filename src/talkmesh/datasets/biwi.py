"""``talkmesh prepare-biwi RAW OUT``: CodeTalker's BIWI preprocessing, in Python.

Per frame (CodeTalker's ``BIWI/data_preprocess/creatDataset_BIWI.m``): rotate by pi about x
((x, y, z) -> (x, -y, -z)), subtract that frame's centroid, divide by the square root of that
frame's total surface area (the sum of the mixed-Voronoi vertex areas, which partition the surface,
equals the sum of the triangle areas), so every frame has unit area and no units. The neutral
templates get the same treatment (``process_BIWI_template.m``), from the subject's rigid scan.

RAW is BIWI's release (the Biwi 3D Audiovisual Corpus of Affective Communication, requested from
https://data.vision.ee.ethz.ch/cvl/datasets/b3dac2.en.html) with its archives decompressed::

    RAW/faces/<SUBJECT>/<SENTENCE>/*.vl      tracked frames (or the sequence's <SENTENCE>.tar)
    RAW/rigid_scans/<SUBJECT>.obj            the official neutral template (and its triangles)
    RAW/videos/<SUBJECT>_<SENTENCE>.flv      audio track, extracted at 44.1 kHz with ffmpeg
    RAW/wav/<SUBJECT>_<SENTENCE>.wav         optional: audio already extracted (copied as is)
    RAW/BIWI.ply, RAW/regions/               optional: CodeTalker's BIWI/BIWI.ply and
                                             BIWI/regions/{lve,fdd}.txt, copied (``--regions``)

A ``.vl`` file is one frame: a uint32 vertex count then that many (x, y, z) float32, little-endian.
Frames are taken in file-name order (``frame_001.vl`` ...), as MATLAB's ``dir`` lists them.

The older layout of this command still works: ``RAW/vertices/<SUBJECT>_<SENTENCE>.npy`` raw
sequences, ``RAW/wav/``, one ``RAW/*.ply`` and optional ``RAW/templates/<SUBJECT>.npy``.

OUT is a dataset in the contract of :mod:`talkmesh.datasets.reader` (kind ``biwi``).
"""

from __future__ import annotations

import shutil
import subprocess
import tarfile
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

from talkmesh.datasets.reader import (
    BIWI_TRAIN,
    BIWI_UNSEEN,
    REGIONS_DIR,
    TEMPLATES_FILE,
    VERTICES_DIR,
    WAV_DIR,
    parse_name,
    write_templates,
)
from talkmesh.errors import TalkmeshError, TalkmeshWarning

BIWI_SUBJECTS = tuple(sorted(BIWI_TRAIN + BIWI_UNSEEN))  # F1-F8, M1-M6
BIWI6 = BIWI_TRAIN  # the six speakers FaceFormer and CodeTalker train and test (Test-A) on
SENTENCES = tuple(f"e{k:02d}" for k in range(1, 41))
AUDIO_RATE = 44_100  # Hz: CodeTalker's video2audio.py extracts at this rate
NUM_VERTICES = 23_370
SUBSETS = {"all": BIWI_SUBJECTS, "biwi6": BIWI6}
OBTAIN = (
    "request BIWI at https://data.vision.ee.ethz.ch/cvl/datasets/b3dac2.en.html and decompress "
    "its faces, rigid_scans and videos archives into RAW"
)
REGIONS_HINT = (
    "no regions/lve.txt and regions/fdd.txt: copy CodeTalker's BIWI/regions/ into OUT/regions "
    "(or pass --regions DIR) before `talkmesh evaluate`"
)


def surface_area(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(..., V, 3) vertices, (F, 3) faces -> (...) total triangle area."""
    v = np.asarray(vertices, dtype=np.float64)
    a, b, c = v[..., faces[:, 0], :], v[..., faces[:, 1], :], v[..., faces[:, 2], :]
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=-1).sum(axis=-1)


def normalize_frames(
    vertices: np.ndarray, faces: np.ndarray, dtype: type = np.float32
) -> np.ndarray:
    """(T, V, 3) raw scans -> rotated, centred, unit-area frames (``dtype``)."""
    v = np.asarray(vertices, dtype=np.float64) * np.array([1.0, -1.0, -1.0])  # pi about x
    v = v - v.mean(axis=1, keepdims=True)
    area = surface_area(v, faces)
    if (area <= 0).any():
        raise TalkmeshError(
            "a frame has zero surface area: are the faces right for these vertices?"
        )
    return (v / np.sqrt(area)[:, None, None]).astype(dtype)


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
    """Preprocess RAW (see the module docstring) into OUT; returns the number of sequences.

    RAW in the release layout (a ``faces/`` folder) goes through :func:`prepare_biwi_release`.
    """
    if (Path(raw) / "faces").is_dir():
        return prepare_biwi_release(raw, out, progress=progress).written
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


# ---------------------------------------------------------------------------------------------
# BIWI's release: .vl frames, rigid-scan templates, .flv audio


def read_vl(data: bytes, name: str) -> np.ndarray:
    """One ``.vl`` frame (uint32 count, then count x (x, y, z) float32) -> (V, 3) float64."""
    if len(data) < 4:
        raise TalkmeshError(f"{name}: empty .vl file")
    (count,) = np.frombuffer(data[:4], "<u4")
    if len(data) != 4 + 12 * int(count):
        raise TalkmeshError(
            f"{name}: {len(data)} bytes for {count} vertices (expected {4 + 12 * int(count)}): "
            "truncated .vl file"
        )
    return np.frombuffer(data[4:], "<f4").reshape(int(count), 3).astype(np.float64)


def _vl_frames(faces_dir: Path, subject: str, sentence: str) -> Iterator[tuple[str, bytes]] | None:
    """(name, bytes) of a sequence's .vl frames in name order, from its folder or its .tar."""
    folder = faces_dir / subject / sentence
    if folder.is_dir():
        return ((str(p), p.read_bytes()) for p in sorted(folder.glob("*.vl")))
    archive = faces_dir / subject / f"{sentence}.tar"
    if archive.is_file():
        return _tar_frames(archive)
    return None


def _tar_frames(archive: Path) -> Iterator[tuple[str, bytes]]:
    # members are read into memory, never extracted: no path in the archive touches the disk
    try:
        with tarfile.open(archive) as tar:
            members = sorted(
                (m for m in tar.getmembers() if m.isfile() and m.name.endswith(".vl")),
                key=lambda m: Path(m.name).name,
            )
            for m in members:
                f = tar.extractfile(m)
                yield f"{archive}:{m.name}", f.read() if f else b""
    except (tarfile.TarError, OSError, EOFError) as e:
        raise TalkmeshError(f"{archive}: unreadable archive ({e})") from None


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """An .obj's ``v`` lines (V, 3) and ``f`` lines (F, 3), 0-based, in file order.

    Like CodeTalker's ``readObj_my.m``: vertex positions only (no splitting on texture
    coordinates, which would reorder vertices); polygons are split into triangle fans.
    """
    verts, faces = [], []
    try:
        for line in path.read_text(errors="replace").splitlines():
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "v":
                verts.append([float(t) for t in parts[1:4]])
            elif parts[0] == "f":
                ids = [int(t.split("/")[0]) for t in parts[1:]]
                ids = [i - 1 if i > 0 else len(verts) + i for i in ids]
                faces += [(ids[0], ids[k], ids[k + 1]) for k in range(1, len(ids) - 1)]
    except (ValueError, IndexError):
        raise TalkmeshError(f"{path}: not a readable .obj") from None
    if not verts or not faces:
        raise TalkmeshError(f"{path}: no vertices or no faces")
    v, f = np.array(verts, np.float64), np.array(faces, np.int64)
    if f.min() < 0 or f.max() >= len(v):
        raise TalkmeshError(f"{path}: a face points past the {len(v)} vertices")
    return v, f


class Prepared(NamedTuple):
    """What a preparation run did: sequences written, already there, and skipped (with why)."""

    written: int
    existing: int
    skipped: list[str]


def _extract_audio(video: Path, target: Path) -> None:
    from imageio_ffmpeg import get_ffmpeg_exe

    from talkmesh.datasets.vocaset import write_atomic

    def write(tmp: Path) -> None:
        cmd = [get_ffmpeg_exe(), "-y", "-loglevel", "error", "-i", str(video), "-vn", "-f", "wav"]
        res = subprocess.run([*cmd, "-ar", str(AUDIO_RATE), str(tmp)], capture_output=True)
        if res.returncode != 0:
            raise TalkmeshError(f"{video}: ffmpeg could not read its audio")

    write_atomic(target, write)


def _prepare_sequence(
    raw: Path, out: Path, subject: str, sentence: str, faces: np.ndarray, num_vertices: int
) -> bool:
    """One sequence into OUT; False if RAW has no frames for it. Raises TalkmeshError if bad."""
    from talkmesh.datasets.vocaset import write_atomic

    name = f"{subject}_{sentence}"
    frames = _vl_frames(raw / "faces", subject, sentence)
    if frames is None:
        return False
    wav, video = raw / WAV_DIR / f"{name}.wav", raw / "videos" / f"{name}.flv"
    if not wav.is_file() and not video.is_file():
        raise TalkmeshError(f"{name}: no audio ({video} or {wav}); {OBTAIN}")
    seq = [read_vl(data, where) for where, data in frames]
    if len(seq) < 2:
        raise TalkmeshError(f"{name}: {len(seq)} frames, too short to train or evaluate on")
    counts = sorted({len(v) for v in seq})
    if counts != [num_vertices]:
        raise TalkmeshError(
            f"{name}: frames with {counts} vertices, the rigid scan has {num_vertices}"
        )
    motion = normalize_frames(np.stack(seq), faces, dtype=np.float64)
    target = out / VERTICES_DIR / f"{name}.npy"
    write_atomic(target, lambda tmp: np.save(tmp, motion.reshape(len(motion), -1)))
    if wav.is_file():
        shutil.copyfile(wav, out / WAV_DIR / wav.name)
    else:
        _extract_audio(video, out / WAV_DIR / f"{name}.wav")
    return True


def prepare_biwi_release(
    raw: str | Path,
    out: str | Path,
    *,
    subset: str = "all",
    regions: str | Path | None = None,
    progress: bool = True,
) -> Prepared:
    """BIWI's release in RAW (see the module docstring) -> a ``biwi`` dataset in OUT.

    ``subset`` is ``all`` (14 speakers) or ``biwi6`` (F2 F3 F4 M3 M4 M5: train, val, Test-A).
    A bad sequence (truncated .vl, wrong vertex count, no audio, < 2 frames) is skipped with a
    warning that names it; sequences already in OUT are kept (a re-run finishes the rest).
    """
    from tqdm import tqdm

    raw, out = Path(raw), Path(out)
    if subset not in SUBSETS:
        raise TalkmeshError(f"unknown BIWI subset '{subset}': use one of {', '.join(SUBSETS)}")
    if not (raw / "faces").is_dir():
        raise TalkmeshError(f"{raw / 'faces'} is missing: {OBTAIN}")
    subjects = [s for s in SUBSETS[subset] if (raw / "faces" / s).is_dir()]
    if not subjects:
        raise TalkmeshError(f"{raw / 'faces'}: no subject folders ({', '.join(SUBSETS[subset])})")
    templates, faces = {}, {}
    for subject in subjects:
        scan = raw / "rigid_scans" / f"{subject}.obj"
        if not scan.is_file():
            raise TalkmeshError(
                f"{scan} is missing: the neutral templates come from rigid_scans; {OBTAIN}"
            )
        v, faces[subject] = read_obj(scan)
        templates[subject] = normalize_frames(v[None], faces[subject], dtype=np.float64)[0]
    for sub in (VERTICES_DIR, WAV_DIR):
        (out / sub).mkdir(parents=True, exist_ok=True)
    written = existing = 0
    skipped: list[str] = []
    jobs = [(s, t) for s in subjects for t in SENTENCES]
    for subject, sentence in tqdm(jobs, desc="prepare-biwi", unit="seq", disable=not progress):
        name = f"{subject}_{sentence}"
        if (out / VERTICES_DIR / f"{name}.npy").is_file() and (
            out / WAV_DIR / f"{name}.wav"
        ).is_file():
            existing += 1
            continue
        try:
            written += _prepare_sequence(
                raw, out, subject, sentence, faces[subject], len(templates[subject])
            )
        except TalkmeshError as e:
            warnings.warn(f"skipped {name}: {e}", TalkmeshWarning, stacklevel=2)
            skipped.append(name)
    write_templates(out / TEMPLATES_FILE, templates)
    first = subjects[0]
    if (raw / "BIWI.ply").is_file():
        shutil.copyfile(raw / "BIWI.ply", out / "BIWI.ply")
    elif not (out / "BIWI.ply").is_file():
        import trimesh

        trimesh.Trimesh(templates[first], faces[first], process=False).export(out / "BIWI.ply")
    source = Path(regions) if regions is not None else raw / REGIONS_DIR
    if regions is not None and not source.is_dir():
        raise TalkmeshError(f"regions directory not found: {source}")
    if source.is_dir():
        shutil.copytree(source, out / REGIONS_DIR, dirs_exist_ok=True)
    return Prepared(written, existing, skipped)
