"""Saving and loading animations, dispatched on the file extension (like trimesh's registries).

``save_animation(anim, "out/talk.glb")`` looks the suffix up in ``EXPORTERS``;
``load_animation("talk.npz")`` looks it up in ``IMPORTERS``.

=========  ======  ======  =====================================================================
suffix     save    load    contents
=========  ======  ======  =====================================================================
``.npy``   yes     yes     [T, V*3] float32 vertex positions (the VOCASET / FaceFormer layout);
                           loading needs ``faces=`` unless V matches the bundled head.
``.npz``   yes     yes     everything in :class:`Animation` (no pickle).
``.obj``   yes     no      one OBJ per frame: ``out/talk.obj`` writes ``out/talk_00000.obj``, ...;
                           a directory (``out/``, with ``format="obj"``) gets ``frame_00000.obj``...
``.glb``   yes     yes     binary glTF 2.0: one mesh whose morph targets are the ARKit blendshapes
                           (or a PCA basis of the motion) and one animation of their weights.
``.csv``   yes     yes*    ARKit weights as a Live Link Face take (61 values per frame).
``.json``  yes     yes*    ARKit weights: ``{"fps", "names", "frames": [[52 floats], ...]}``.
=========  ======  ======  =====================================================================

\\* Weight files load with :func:`load_arkit_weights`; :func:`load_animation` plays them on the
bundled head.

Writes are atomic: files are written in a private directory next to the target and renamed into
place, and an existing file is never replaced unless ``overwrite=True``. Every problem with the
user's files is a one-line :class:`TalkmeshError` that names the file.
"""

from __future__ import annotations

import csv
import json
import os
import re
import struct
import tempfile
import zipfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from talkmesh.animation import Animation
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import (
    ARKIT_NAMES,
    LIVE_LINK_BLENDSHAPES,
    LIVE_LINK_COLUMNS,
    arkit_index,
    to_arkit_order,
)

NPY_DEFAULT_FPS = 30.0  # FaceFormer / CodeTalker write VOCASET predictions at 30 fps
GLB_MAX_ERROR = 1e-4  # metres: PCA morph targets reproduce every vertex to 0.1 mm ...
MAX_PCA_TARGETS = 64  # ... using at most this many targets
PCA_TOLERANCE = GLB_MAX_ERROR / 2  # headroom for rounding the targets to float32
EXACT_SVD_LIMIT = 512  # above this many frames and coordinates, use a randomised SVD
NPZ_FORMAT_VERSION = 1
SEQUENCE_SUFFIXES = (".obj",)  # formats written as one file per frame

Exporter = Callable[[Animation, Path], None]
"""Writes an animation to ``path`` (a sequence exporter may also write siblings named after it)."""
Importer = Callable[[Path, np.ndarray | None, float | None], Animation]
"""``(path, faces, fps) -> Animation``; ``faces``/``fps`` are None unless the caller gave them."""


class ArkitWeights(NamedTuple):
    """ARKit blendshape weights read from a ``.csv`` or ``.json`` file.

    Attributes:
        weights: (T, 52) float32 weights in ``ARKIT_NAMES`` order.
        fps: frames per second.
    """

    weights: np.ndarray
    fps: float


# ---------------------------------------------------------------------------------------------
# Public API


def save_animation(
    anim: Animation, path: str | Path, *, format: str | None = None, overwrite: bool = False
) -> list[Path]:
    """Write ``anim`` in the format named by ``path``'s suffix (or by ``format``, e.g. ``"obj"``).

    Returns the files written (several for an OBJ sequence). Refuses to replace an existing file
    unless ``overwrite`` is True.
    """
    raw = str(path)
    path = Path(path)
    ext = _extension(path, format)
    exporter = EXPORTERS.get(ext)
    if exporter is None:
        raise TalkmeshError(
            f"{path}: cannot save '{ext or path.name}' files; use one of {', '.join(EXPORTERS)}"
        )
    if anim.num_frames == 0:
        raise TalkmeshError(f"{path}: the animation has no frames to save")
    sequence = ext in SEQUENCE_SUFFIXES
    if raw.endswith(("/", os.sep)) or path.is_dir():
        if not sequence:
            raise TalkmeshError(f"{path} is a directory: give a file name such as {path}/talk{ext}")
        path = path / f"frame{ext}"
    if not sequence and path.exists() and not overwrite:
        raise _exists_error(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # Write into a private directory beside the target, then rename: readers never see a
        # half-written file and a failed export leaves nothing behind.
        with tempfile.TemporaryDirectory(dir=path.parent, prefix=".talkmesh-") as tmp:
            exporter(anim, Path(tmp) / path.name)
            written = sorted(Path(tmp).iterdir())
            targets = [path.parent / p.name for p in written]
            clash = [t for t in targets if t.exists()]
            if clash and not overwrite:
                raise _exists_error(clash[0])
            for src, dst in zip(written, targets, strict=True):
                _move(src, dst, overwrite)
    except OSError as e:
        raise TalkmeshError(f"{path}: cannot write it ({e.strerror or e})") from None
    return targets


def load_animation(
    path: str | Path, *, faces: np.ndarray | None = None, fps: float | None = None
) -> Animation:
    """Read an animation from ``path``, dispatching on its suffix.

    Args:
        path: a ``.npy``, ``.npz``, ``.glb``, ``.csv`` or ``.json`` file.
        faces: (F, 3) triangles for ``.npy`` files (default: the bundled head's, when the vertex
            count matches); replaces the stored faces of other formats.
        fps: frame rate for formats that do not store one (``.npy``: default 30); replaces the
            stored one otherwise.
    """
    path = Path(path)
    importer = IMPORTERS.get(path.suffix.lower())
    if importer is None:
        raise TalkmeshError(
            f"{path}: cannot load '{path.suffix or path.name}' files; "
            f"use one of {', '.join(IMPORTERS)}"
        )
    _check_readable(path)
    if fps is not None and not fps > 0:
        raise TalkmeshError(f"fps must be positive, got {fps}")
    with _reading(path):
        return importer(path, None if faces is None else np.asarray(faces), fps)


def load_arkit_weights(path: str | Path, *, fps: float | None = None) -> ArkitWeights:
    """(T, 52) ARKit weights from a Live Link Face ``.csv`` or a talkmesh ``.json`` file.

    ``fps`` replaces the stored frame rate (a Live Link CSV stores none: it is inferred from the
    timecodes, which needs at least 2 s of frames).
    """
    path = Path(path)
    reader = WEIGHT_IMPORTERS.get(path.suffix.lower())
    if reader is None:
        raise TalkmeshError(
            f"{path}: cannot read ARKit weights from '{path.suffix or path.name}' files; "
            f"use one of {', '.join(WEIGHT_IMPORTERS)}"
        )
    _check_readable(path)
    with _reading(path):
        weights, stored_fps = reader(path)
        fps = fps or stored_fps
        if fps is None:
            raise TalkmeshError("cannot tell the frame rate from under 2 s of timecodes; pass fps=")
        if not fps > 0:
            raise TalkmeshError(f"fps must be positive, got {fps}")
        return ArkitWeights(_finite(weights, "weights").astype(np.float32), float(fps))


# ---------------------------------------------------------------------------------------------
# Writing files safely


def _extension(path: Path, format: str | None) -> str:
    if format:
        return "." + format.lower().lstrip(".")
    return path.suffix.lower()


def _move(src: Path, dst: Path, overwrite: bool) -> None:
    """Rename ``src`` to ``dst`` atomically; without ``overwrite``, never replace ``dst``."""
    if overwrite:
        os.replace(src, dst)
        return
    try:
        os.link(src, dst)  # fails if dst exists, unlike rename, so a racing writer is not clobbered
    except FileExistsError:
        raise _exists_error(dst) from None
    except OSError:  # no hard links on this filesystem
        if dst.exists():
            raise _exists_error(dst) from None
        os.replace(src, dst)
    else:
        src.unlink()


def _exists_error(path: Path) -> TalkmeshError:
    return TalkmeshError(f"{path} already exists: pass overwrite=True (--overwrite) to replace it")


def _check_readable(path: Path) -> None:
    if not path.is_file():
        raise TalkmeshError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise TalkmeshError(f"{path}: the file is empty")


_PARSE_ERRORS = (
    OSError,
    ValueError,
    KeyError,
    IndexError,
    TypeError,
    EOFError,
    struct.error,
    zipfile.BadZipFile,
    csv.Error,
)


@contextmanager
def _reading(path: Path) -> Iterator[None]:
    """Turn any failure to parse ``path`` into a one-line TalkmeshError that names it."""
    try:
        yield
    except TalkmeshError as e:
        msg = _one_line(e)
        raise TalkmeshError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
    except _PARSE_ERRORS as e:
        raise TalkmeshError(
            f"{path}: cannot read it ({type(e).__name__}: {_one_line(e)})"
        ) from None


def _one_line(e: BaseException) -> str:
    lines = str(e).strip().splitlines()
    return lines[0] if lines else type(e).__name__


def _check_magic(path: Path, magic: bytes, kind: str) -> None:
    with open(path, "rb") as f:
        if f.read(len(magic)) != magic:
            raise TalkmeshError(f"{path}: not a {kind}")


def _finite(values: np.ndarray, what: str) -> np.ndarray:
    if not np.isfinite(values).all():
        raise TalkmeshError(f"the {what} contain NaN or infinite values")
    return values


def _bundled_head():
    """The bundled head (``talkmesh.face.assets.load_head()``), or None where it is unavailable."""
    try:
        from talkmesh.face.assets import load_head
    except ImportError:
        return None
    try:
        return load_head()
    except (TalkmeshError, OSError):
        return None


def _arkit_weights_of(anim: Animation, path: Path) -> np.ndarray:
    """(T, 52) weights of ``anim`` in ARKit order, or a TalkmeshError saying it has none."""
    if anim.weights is None:
        raise TalkmeshError(
            f"{path}: the animation has no ARKit weights (only vertices); "
            "save it as .glb, .npz, .npy or .obj instead"
        )
    return to_arkit_order(anim.weights, anim.weight_names)


# ---------------------------------------------------------------------------------------------
# .npy / .npz


def export_npy(anim: Animation, path: Path) -> None:
    """[T, V*3] float32 vertex positions, the VOCASET / FaceFormer layout."""
    with open(path, "wb") as f:
        np.save(f, anim.vertices.reshape(anim.num_frames, -1), allow_pickle=False)


def import_npy(path: Path, faces: np.ndarray | None, fps: float | None) -> Animation:
    """[T, V*3] (or [T, V, 3]) vertex positions; faces from the caller or the bundled head."""
    _check_magic(path, b"\x93NUMPY", ".npy array")
    arr = np.load(path, allow_pickle=False)
    if not isinstance(arr, np.ndarray):
        raise ValueError("not a single .npy array")
    if arr.ndim == 2 and arr.shape[1] % 3 == 0 and arr.shape[1] > 0:
        arr = arr.reshape(len(arr), -1, 3)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"expected [T, V*3] vertex positions, got an array of shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"expected numbers, got {arr.dtype}")
    vertices = _finite(arr.astype(np.float32), "vertices")
    if faces is None:
        head = _bundled_head()
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
    _check_magic(path, b"PK", ".npz archive")
    with np.load(path, allow_pickle=False) as z:
        missing = [k for k in ("vertices", "faces", "fps") if k not in z.files]
        if missing:
            raise TalkmeshError(f"{path}: not a talkmesh animation (no {', '.join(missing)})")
        d = {k: z[k] for k in z.files}
    if int(d.get("format_version", NPZ_FORMAT_VERSION)) > NPZ_FORMAT_VERSION:
        raise TalkmeshError(f"{path}: written by a newer talkmesh; upgrade talkmesh to read it")
    weights = d.get("weights")
    return Animation(
        vertices=_finite(d["vertices"], "vertices"),
        faces=d["faces"] if faces is None else faces,
        fps=fps or float(d["fps"]),
        audio=d.get("audio"),
        sample_rate=int(d.get("sample_rate", 16_000)),
        weights=None if weights is None else _finite(weights, "weights"),
        weight_names=[str(n) for n in d.get("weight_names", [])],
        template=d.get("template"),
        basis=d.get("basis"),
    )


# ---------------------------------------------------------------------------------------------
# OBJ sequence


def obj_frame_path(path: Path, frame: int, num_frames: int) -> Path:
    """Where frame ``frame`` of an OBJ sequence saved as ``path`` goes: ``talk_00042.obj``."""
    width = max(5, len(str(num_frames - 1)))
    return path.with_name(f"{path.stem}_{frame:0{width}d}.obj")


def export_obj(anim: Animation, path: Path) -> None:
    """One OBJ per frame, ``<stem>_00000.obj``... next to ``path`` (positions in metres)."""
    num_vertices = anim.num_vertices
    # One %-format over the whole array runs in C: no per-vertex Python loop.
    faces_text = ("f %d %d %d\n" * len(anim.faces)) % tuple((anim.faces + 1).ravel().tolist())
    vertex_format = "v %.6f %.6f %.6f\n" * num_vertices
    for t in range(anim.num_frames):
        header = f"# talkmesh frame {t} of {anim.num_frames} at {anim.fps:g} fps\n"
        vertices_text = vertex_format % tuple(anim.vertices[t].ravel().tolist())
        obj_frame_path(path, t, anim.num_frames).write_text(header + vertices_text + faces_text)


# ---------------------------------------------------------------------------------------------
# ARKit weights: Live Link Face CSV and JSON


def export_live_link_csv(anim: Animation, path: Path) -> None:
    """A Live Link Face take: ``Timecode,BlendShapeCount,EyeBlinkLeft,...,RightEyeRoll``.

    Timecodes are ``HH:MM:SS:FF.mmm`` with FF counted at the animation's fps; head and eye
    rotations are zero.
    """
    weights = _arkit_weights_of(anim, path)
    columns = [arkit_index(n) for n in LIVE_LINK_BLENDSHAPES]
    values = np.zeros((anim.num_frames, len(LIVE_LINK_COLUMNS)), dtype=np.float64)
    values[:, : len(columns)] = weights[:, columns]
    row_format = "%s," + str(len(LIVE_LINK_COLUMNS)) + ",%.8f" * len(LIVE_LINK_COLUMNS) + "\n"
    lines = ["Timecode,BlendShapeCount," + ",".join(LIVE_LINK_COLUMNS) + "\n"]
    lines += [row_format % (_timecode(t, anim.fps), *row) for t, row in enumerate(values.tolist())]
    path.write_text("".join(lines))


def _timecode(frame: int, fps: float) -> str:
    """``HH:MM:SS:FF.mmm`` of frame ``frame`` at ``fps`` (FF is the frame within the second)."""
    seconds = int(np.floor(frame / fps + 1e-9))
    within = max(frame - seconds * fps, 0.0)
    ff = int(within + 1e-9)
    millis = min(max(round((within - ff) * 1000), 0), 999)
    minutes, s = divmod(seconds, 60)
    h, m = divmod(minutes, 60)
    return f"{h:02d}:{m:02d}:{s:02d}:{ff:02d}.{millis:03d}"


_TIMECODE = re.compile(r"^\s*(\d+):(\d+):(\d+)[:;](\d+)(?:\.(\d+))?\s*$")


def read_live_link_csv(path: Path) -> tuple[np.ndarray, float | None]:
    """(T, 52) weights in ARKit order and the fps inferred from the timecodes (None if < 2 s)."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    header = [h.strip() for h in rows[0]]
    body = [r for r in rows[1:] if any(c.strip() for c in r)]
    if not body:
        raise ValueError("no frames after the header")
    names = [n for n in header if arkit_index(n) >= 0]
    cols = [header.index(n) for n in names]
    table = np.array([[float(r[c]) for c in cols] for r in body], dtype=np.float64)
    weights = to_arkit_order(table, names)
    fps = None
    if header and header[0].lower() == "timecode":
        seconds = []
        for r in body:
            match = _TIMECODE.match(r[0])
            if match is None:
                raise ValueError(f"bad timecode '{r[0]}' (expected HH:MM:SS:FF.mmm)")
            h, m, s = (int(match.group(i)) for i in (1, 2, 3))
            seconds.append(h * 3600 + m * 60 + s)
        # Rows per whole second: the first and last seconds may be partial.
        _, counts = np.unique(seconds, return_counts=True)
        if len(counts) >= 3:
            fps = float(np.median(counts[1:-1]))
    return weights, fps


def export_arkit_json(anim: Animation, path: Path) -> None:
    """``{"fps": 30.0, "names": [52 ARKit names], "frames": [[52 weights], ...]}``."""
    weights = _arkit_weights_of(anim, path)
    doc = {
        "fps": float(anim.fps),
        "names": list(ARKIT_NAMES),
        "frames": np.round(weights.astype(np.float64), 6).tolist(),
    }
    path.write_text(json.dumps(doc, separators=(",", ":")) + "\n")


def read_arkit_json(path: Path) -> tuple[np.ndarray, float | None]:
    """(T, 52) weights in ARKit order and the stored fps, from :func:`export_arkit_json`."""
    doc = json.loads(path.read_text())
    if not isinstance(doc, dict) or "frames" not in doc or "names" not in doc:
        raise ValueError('expected {"fps": ..., "names": [...], "frames": [[...], ...]}')
    names = [str(n) for n in doc["names"]]
    frames = np.array(doc["frames"], dtype=np.float64).reshape(-1, len(names))
    fps = doc.get("fps")
    return to_arkit_order(frames, names), None if fps is None else float(fps)


def _import_weights_on_head(path: Path, faces: np.ndarray | None, fps: float | None) -> Animation:
    """ARKit weights played on the bundled head (``faces`` is not used)."""
    weights, stored_fps = load_arkit_weights(path, fps=fps)
    head = _bundled_head()
    if head is None:
        raise TalkmeshError(
            f"{path}: playing ARKit weights needs the bundled head (talkmesh.face.assets)"
        )
    order = [arkit_index(n) for n in head.blendshape_names]
    head_weights = weights[:, order]
    return Animation(
        vertices=head.vertices_from_weights(head_weights),
        faces=head.faces,
        fps=stored_fps,
        weights=head_weights,
        weight_names=list(head.blendshape_names),
        template=head.template,
        basis=head.blendshapes,
    )


# ---------------------------------------------------------------------------------------------
# glTF binary (.glb) with morph-target animation


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
        offset = np.tensordot(self.rest_weights.astype(np.float64), self.targets, axes=1)
        return (self.base + offset).astype(np.float32)


BLOCK_FRAMES = 1024  # frames processed at a time when checking long animations


def _blend(weights: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """(T, K) weights and (K, V, 3) basis -> (T, V, 3) offsets in float64."""
    return np.tensordot(weights.astype(np.float64), basis, axes=1)


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
        basis = anim.basis.astype(np.float64)
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
    # Long animations (10 min is 1 GB of float32 vertices) are checked in blocks of frames; the
    # full residual is only built when principal components are really needed.
    needs_pca = not has_basis or _max_over_blocks(residual_block, anim.num_frames) >= PCA_TOLERANCE
    if needs_pca:
        residual = np.empty((anim.num_frames, num_v, 3), np.float32)  # float32: 10 min is 1 GB
        for s in range(0, anim.num_frames, BLOCK_FRAMES):
            residual[s : s + BLOCK_FRAMES] = residual_block(slice(s, s + BLOCK_FRAMES))
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
        targets=np.concatenate(targets).astype(np.float32),
        weights=np.concatenate(weights, axis=1).astype(np.float32),
        rest_weights=np.concatenate(rest).astype(np.float32),
        names=names,
    )


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
    basis = _row_space(data, max_components)  # (3V, R), most important first
    coeffs = data @ basis.astype(data.dtype, copy=False)

    def max_error(k: int) -> float:
        err = 0.0
        for start in range(0, num_t, 256):  # in blocks of frames to bound memory
            block = slice(start, start + 256)
            approx = coeffs[block, :k] @ basis[:, :k].T
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
        _, _, vt = np.linalg.svd(data, full_matrices=False)
        return vt[:max_components].T
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


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) vertices, (F, 3) faces -> (V, 3) float32 unit area-weighted normals (+z if none)."""
    v = vertices.astype(np.float64)
    face_normals = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    corners = faces.ravel()
    normals = np.stack(
        [
            np.bincount(corners, np.repeat(face_normals[:, c], 3), minlength=len(v))
            for c in range(3)
        ],
        axis=1,
    )
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.where(length > 1e-20, normals / np.maximum(length, 1e-300), [0.0, 0.0, 1.0])
    return normals.astype(np.float32)


# glTF constants (glTF 2.0 spec, section 5).
GLB_MAGIC, GLB_JSON, GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
TRIANGLES, POINTS = 4, 0
_COMPONENT_TYPES = {
    5120: np.int8,
    5121: np.uint8,
    5122: np.int16,
    5123: np.uint16,
    5125: np.uint32,
    5126: np.float32,
}
_COMPONENT_CODES = {np.dtype(t): code for code, t in _COMPONENT_TYPES.items()}
_TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


class _GlbBuffer:
    """The binary chunk of a .glb, with one bufferView and accessor per array."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(
        self, array: np.ndarray, kind: str, *, target: int | None = None, bounds: bool = False
    ) -> int:
        """Append (N,) or (N, C) ``array`` as an accessor of type ``kind``; returns its index."""
        array = np.ascontiguousarray(array)
        self.data += b"\0" * (-len(self.data) % 4)  # accessors must be aligned to their components
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": array.nbytes}
        if target is not None:
            view["target"] = target
        self.data += array.astype(array.dtype.newbyteorder("<"), copy=False).tobytes()
        self.views.append(view)
        accessor = {
            "bufferView": len(self.views) - 1,
            "componentType": _COMPONENT_CODES[array.dtype],
            "count": int(array.shape[0]),
            "type": kind,
        }
        if bounds:  # required for POSITION and animation inputs; must equal the data exactly
            flat = array.reshape(array.shape[0], -1)
            accessor["min"] = flat.min(axis=0).tolist()
            accessor["max"] = flat.max(axis=0).tolist()
        self.accessors.append(accessor)
        return len(self.accessors) - 1


def export_glb(anim: Animation, path: Path) -> None:
    """Binary glTF 2.0: one mesh with morph targets and a LINEAR ``weights`` animation.

    Target names are in ``mesh.extras.targetNames`` (three.js and Blender read them); normals are
    those of the neutral face.
    """
    rig = morph_rig(anim)
    buf = _GlbBuffer()
    attributes = {
        "POSITION": buf.add(rig.base, "VEC3", target=ARRAY_BUFFER, bounds=True),
        "NORMAL": buf.add(vertex_normals(rig.neutral(), anim.faces), "VEC3", target=ARRAY_BUFFER),
    }
    primitive: dict = {"attributes": attributes, "material": 0, "mode": TRIANGLES}
    if len(anim.faces):
        # 65535 is the primitive-restart index, so 16-bit indices reach 65534 at most.
        index_type = np.uint16 if anim.num_vertices <= 65535 else np.uint32
        indices = anim.faces.ravel().astype(index_type)
        primitive["indices"] = buf.add(indices, "SCALAR", target=ELEMENT_ARRAY_BUFFER)
    else:
        primitive["mode"] = POINTS
    primitive["targets"] = [
        {"POSITION": buf.add(t, "VEC3", target=ARRAY_BUFFER, bounds=True)} for t in rig.targets
    ]
    times = (np.arange(anim.num_frames, dtype=np.float64) / anim.fps).astype(np.float32)
    sampler = {
        "input": buf.add(times, "SCALAR", bounds=True),
        "output": buf.add(rig.weights.ravel(), "SCALAR"),
        "interpolation": "LINEAR",
    }
    gltf = {
        "asset": {"version": "2.0", "generator": "talkmesh"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"name": "face", "mesh": 0}],
        "meshes": [
            {
                "name": "face",
                "primitives": [primitive],
                "weights": rig.rest_weights.tolist(),
                "extras": {"targetNames": rig.names},
            }
        ],
        "materials": [
            {
                "name": "skin",
                "pbrMetallicRoughness": {
                    "baseColorFactor": [0.8, 0.62, 0.52, 1.0],
                    "metallicFactor": 0.0,
                    "roughnessFactor": 0.6,
                },
            }
        ],
        "animations": [
            {
                "name": "talk",
                "extras": {"fps": float(anim.fps)},  # for one-frame files, whose times cannot tell
                "samplers": [sampler],
                "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}],
            }
        ],
        "buffers": [{"byteLength": len(buf.data)}],
        "bufferViews": buf.views,
        "accessors": buf.accessors,
    }
    path.write_bytes(_glb_bytes(gltf, bytes(buf.data)))


def _glb_bytes(gltf: dict, binary: bytes) -> bytes:
    """The GLB container: 12-byte header, JSON chunk (space-padded), BIN chunk (zero-padded)."""
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    length = 12 + 8 + len(text) + 8 + len(binary)
    return b"".join(
        [
            struct.pack("<III", GLB_MAGIC, 2, length),
            struct.pack("<II", len(text), GLB_JSON),
            text,
            struct.pack("<II", len(binary), GLB_BIN),
            binary,
        ]
    )


def _parse_glb(data: bytes) -> tuple[dict, bytes]:
    """The JSON and BIN chunks of a .glb file."""
    if len(data) < 20:
        raise ValueError("too short to be a .glb file")
    magic, version, length = struct.unpack_from("<III", data)
    if magic != GLB_MAGIC:
        raise ValueError("not a binary glTF (.glb) file")
    if version != 2:
        raise ValueError(f"glTF version {version} is not supported (only 2)")
    if length > len(data):
        raise ValueError(f"truncated: the header says {length} bytes but the file has {len(data)}")
    gltf, binary, offset = None, b"", 12
    while offset + 8 <= length:
        size, kind = struct.unpack_from("<II", data, offset)
        offset += 8
        if offset + size > length:
            raise ValueError("truncated: a chunk runs past the end of the file")
        chunk = data[offset : offset + size]
        if kind == GLB_JSON and gltf is None:
            gltf = json.loads(chunk.decode("utf-8"))
        elif kind == GLB_BIN and not binary:
            binary = chunk
        offset += size
    if not isinstance(gltf, dict):
        raise ValueError("no JSON chunk")
    return gltf, binary


def _read_accessor(gltf: dict, binary: bytes, index: int) -> np.ndarray:
    """(count, components) array of accessor ``index`` (embedded buffer only, no sparse)."""
    acc = gltf["accessors"][index]
    if "sparse" in acc:
        raise ValueError("sparse accessors are not supported")
    dtype = np.dtype(_COMPONENT_TYPES[acc["componentType"]]).newbyteorder("<")
    width, count = _TYPE_SIZES[acc["type"]], int(acc["count"])
    if "bufferView" not in acc or count == 0:
        return np.zeros((count, width), dtype=dtype)
    view = gltf["bufferViews"][acc["bufferView"]]
    if view.get("buffer", 0) != 0 or "uri" in gltf["buffers"][view.get("buffer", 0)]:
        raise ValueError("external buffers are not supported")
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    stride = view.get("byteStride") or dtype.itemsize * width
    end = start + stride * (count - 1) + dtype.itemsize * width
    if end > view.get("byteOffset", 0) + view["byteLength"] or end > len(binary):
        raise ValueError(f"accessor {index} runs past the end of the binary chunk")
    return np.ndarray(
        (count, width), dtype=dtype, buffer=binary, offset=start, strides=(stride, dtype.itemsize)
    ).copy()


def read_glb_rig(path: Path) -> tuple[MorphRig, np.ndarray, float | None]:
    """The morph rig, (F, 3) faces and sampler-time fps of the first mesh in a .glb file."""
    gltf, binary = _parse_glb(path.read_bytes())
    node_index = next((i for i, n in enumerate(gltf.get("nodes", [])) if "mesh" in n), None)
    if node_index is None:
        raise ValueError("no mesh in the file")
    mesh = gltf["meshes"][gltf["nodes"][node_index]["mesh"]]
    primitive = mesh["primitives"][0]
    base = _read_accessor(gltf, binary, primitive["attributes"]["POSITION"])
    if base.dtype != np.float32 or base.shape[1] != 3:
        raise ValueError("POSITION must be FLOAT VEC3")
    if "indices" in primitive:
        faces = _read_accessor(gltf, binary, primitive["indices"]).reshape(-1, 3)
    elif primitive.get("mode", TRIANGLES) == TRIANGLES:
        faces = np.arange(len(base)).reshape(-1, 3)
    else:
        faces = np.zeros((0, 3), dtype=np.int32)
    targets = np.zeros((0, len(base), 3), dtype=np.float32)
    if primitive.get("targets"):
        targets = np.stack(
            [
                _read_accessor(gltf, binary, t["POSITION"]) if "POSITION" in t else 0 * base
                for t in primitive["targets"]
            ]
        ).astype(np.float32)
    num_k = len(targets)
    names = [str(n) for n in mesh.get("extras", {}).get("targetNames", [])]
    names = names or [f"target_{k}" for k in range(num_k)]
    rest = np.asarray(mesh.get("weights", [0.0] * num_k), dtype=np.float32)
    if len(names) != num_k or rest.shape != (num_k,):
        raise ValueError("the morph target names or weights do not match the targets")
    weights, fps = rest[None], None
    channel = next(
        (
            (anim, c)
            for anim in gltf.get("animations", [])
            for c in anim["channels"]
            if c["target"].get("node") == node_index and c["target"]["path"] == "weights"
        ),
        None,
    )
    if channel is not None and num_k:
        anim, c = channel
        sampler = anim["samplers"][c["sampler"]]
        times = _read_accessor(gltf, binary, sampler["input"])[:, 0].astype(np.float64)
        values = (
            _read_accessor(gltf, binary, sampler["output"])
            .astype(np.float64)
            .reshape(len(times), -1)
        )
        if sampler.get("interpolation") == "CUBICSPLINE":  # in-tangent, value, out-tangent
            values = values.reshape(len(times), 3, -1)[:, 1]
        if values.shape[1] != num_k:
            raise ValueError(f"the animation has {values.shape[1]} weights per key, not {num_k}")
        weights, fps = _uniform_frames(times, values)
        if fps is None and isinstance(anim.get("extras", {}).get("fps"), int | float):
            fps = float(anim["extras"]["fps"])
    rig = MorphRig(base.astype(np.float32), targets, weights.astype(np.float32), rest, names)
    return rig, faces.astype(np.int32), fps


def _uniform_frames(times: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, float | None]:
    """Keyframes (N,), (N, K) -> (T, K) frames at a uniform rate, and that rate (None if N=1)."""
    if len(times) < 2:
        return values, None
    span = float(times[-1] - times[0])
    if not span > 0 or np.any(np.diff(times) <= 0):
        raise ValueError("the animation's key times do not increase")
    fps = round((len(times) - 1) / span, 3)
    grid = times[0] + np.arange(round(span * fps) + 1) / fps
    if len(grid) == len(times) and np.abs(grid - times).max() < 0.25 / fps:
        return values, fps
    columns = [np.interp(grid, times, values[:, k]) for k in range(values.shape[1])]
    return np.stack(columns, axis=1), fps


def import_glb(path: Path, faces: np.ndarray | None, fps: float | None) -> Animation:
    """A .glb written by :func:`export_glb` (or any morph-target animation of one mesh).

    Vertices are ``base + weights @ targets`` at the sampler's frame rate. Targets named after the
    52 ARKit blendshapes come back as ``weights`` and ``basis`` (in ARKit order).
    """
    rig, stored_faces, stored_fps = read_glb_rig(path)
    vertices = _finite(rig.vertices(), "vertices")
    shape_ids = [k for k, n in enumerate(rig.names) if not re.fullmatch(r"(pca|residual)_\d+", n)]
    weights = basis = None
    weight_names: list[str] = []
    if sorted(arkit_index(rig.names[k]) for k in shape_ids) == list(range(len(ARKIT_NAMES))):
        order = sorted(shape_ids, key=lambda k: arkit_index(rig.names[k]))
        weights, basis = rig.weights[:, order], rig.targets[order]
        weight_names = list(ARKIT_NAMES)
    return Animation(
        vertices=vertices,
        faces=stored_faces if faces is None else faces,
        fps=fps or stored_fps or NPY_DEFAULT_FPS,
        weights=weights,
        weight_names=weight_names,
        template=rig.neutral(),
        basis=basis,
    )


# ---------------------------------------------------------------------------------------------
# Registries

EXPORTERS: dict[str, Exporter] = {
    ".npy": export_npy,
    ".npz": export_npz,
    ".obj": export_obj,
    ".glb": export_glb,
    ".csv": export_live_link_csv,
    ".json": export_arkit_json,
}

IMPORTERS: dict[str, Importer] = {
    ".npy": import_npy,
    ".npz": import_npz,
    ".glb": import_glb,
    ".csv": _import_weights_on_head,
    ".json": _import_weights_on_head,
}

WEIGHT_IMPORTERS: dict[str, Callable[[Path], tuple[np.ndarray, float | None]]] = {
    ".csv": read_live_link_csv,
    ".json": read_arkit_json,
}
