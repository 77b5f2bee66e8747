"""Saving and loading animations, dispatched on the file extension (like trimesh's registries).

``save_animation(anim, "out/talk.glb")`` looks the suffix up in ``EXPORTERS``;
``load_animation("talk.npz")`` looks it up in ``IMPORTERS``.

=========  ======  ======  =====================================================================
suffix     save    load    contents
=========  ======  ======  =====================================================================
``.npy``   yes     yes     [T, V*3] float32 vertex positions (the VOCASET / FaceFormer layout);
                           loading needs ``faces=`` unless V matches the bundled head.
``.npz``   yes     yes     everything in :class:`Animation` (no pickle), deflated; the motion as
                           float16 offsets from the template (format 2; format 1 files, float32
                           vertices, still load). Written as frames arrive by
                           :mod:`.streaming`. ``NAME.weights.npz``: the same without per-frame
                           vertices, read back as ``template + weights @ basis`` (lossy for
                           learned models).
``.obj``   yes     no      one OBJ per frame: ``out/talk.obj`` writes ``out/talk_00000.obj``, ...;
                           a directory (``out/``, with ``format="obj"``) gets ``frame_00000.obj``...
``.glb``   yes     yes     binary glTF 2.0: one mesh whose morph targets are the ARKit blendshapes
                           (or a PCA basis of the motion) and one animation of their weights.
                           ``NAME.rig.glb``: the mesh and targets alone, no animation
                           (``talkmesh rig``).
``.csv``   yes     yes*    ARKit weights as a Live Link Face take (61 values per frame).
``.json``  yes     yes*    ARKit weights: ``{"fps", "names", "frames": [[52 floats], ...]}``.
                           ``NAME.visemes.json``: the 15 Oculus visemes per frame and Azure's 22
                           viseme ids as timed events (:mod:`.viseme_files`); save only.
=========  ======  ======  =====================================================================

\\* Weight files load with :func:`load_arkit_weights`; :func:`load_animation` plays them on the
bundled head.

Each format lives in its own module (:mod:`.npy`, :mod:`.obj`, :mod:`.arkit_files`, :mod:`.gltf`,
with the morph rig in :mod:`.morph`); this module holds the registries and the dispatch. A new
format is one module plus one line in ``EXPORTERS`` and/or ``IMPORTERS``.

Writes are atomic: files are written in a private directory next to the target and renamed into
place, and an existing file is never replaced unless ``overwrite=True``. Every problem with the
user's files is a one-line :class:`TalkmeshError` that names the file.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from talkmesh.animation import Animation
from talkmesh.errors import TalkmeshError
from talkmesh.output.arkit_files import (
    WEIGHT_IMPORTERS,
    ArkitWeights,
    export_arkit_json,
    export_live_link_csv,
    import_weights_on_head,
    load_arkit_weights,
)
from talkmesh.output.atomic import temp_prefix
from talkmesh.output.files import check_readable, exists_error, file_extension, move_file, reading
from talkmesh.output.gltf import export_glb, export_rig_glb, import_glb
from talkmesh.output.morph import MorphRig, morph_rig, principal_components
from talkmesh.output.npy import (
    export_npy,
    export_npz,
    export_npz_weights,
    import_npy,
    import_npz,
)
from talkmesh.output.obj import export_obj, obj_frame_path
from talkmesh.output.viseme_files import export_visemes_json

__all__ = [
    "EXPORTERS",
    "IMPORTERS",
    "WEIGHT_IMPORTERS",
    "ArkitWeights",
    "MorphRig",
    "load_animation",
    "load_arkit_weights",
    "morph_rig",
    "obj_frame_path",
    "principal_components",
    "save_animation",
]

SEQUENCE_SUFFIXES = (".obj",)  # formats written as one file per frame

Exporter = Callable[[Animation, Path], None]
"""Writes an animation to ``path`` (a sequence exporter may also write siblings named after it)."""
Importer = Callable[[Path, np.ndarray | None, float | None], Animation]
"""``(path, faces, fps) -> Animation``; ``faces``/``fps`` are None unless the caller gave them."""


def save_animation(
    anim: Animation, path: str | Path, *, format: str | None = None, overwrite: bool = False
) -> list[Path]:
    """Write ``anim`` in the format named by ``path``'s suffix (or by ``format``, e.g. ``"obj"``).

    Returns the files written (several for an OBJ sequence). Refuses to replace an existing file
    unless ``overwrite`` is True.
    """
    raw = str(path)
    path = Path(path)
    ext = file_extension(path, format)
    if format is None and "".join(path.suffixes[-2:]).lower() in EXPORTERS:
        ext = "".join(path.suffixes[-2:]).lower()  # a compound suffix (.weights.npz)
    exporter = EXPORTERS.get(ext)
    if exporter is None:
        raise TalkmeshError(
            f"{path}: cannot save '{ext or path.name}' files; use one of {', '.join(EXPORTERS)}"
        )
    if anim.num_frames == 0:
        raise TalkmeshError(f"{path}: the animation has no frames to save")
    frames = range(0, anim.num_frames, 1024)  # a block at a time: no (T, V, 3) mask
    if not all(np.isfinite(anim.vertices[a : a + 1024]).all() for a in frames) or (
        anim.weights is not None and not np.isfinite(anim.weights).all()
    ):  # never a file of NaN: glTF readers and players take them as they are
        raise TalkmeshError(f"{path}: the animation holds NaN or infinite values: nothing written")
    sequence = ext in SEQUENCE_SUFFIXES
    if raw.endswith(("/", os.sep)) or path.is_dir():
        if not sequence:
            raise TalkmeshError(f"{path} is a directory: give a file name such as {path}/talk{ext}")
        path = path / f"frame{ext}"
    if not sequence and path.exists() and not overwrite:
        raise exists_error(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # Write into a private directory beside the target, then rename: readers never see a
        # half-written file and a failed export leaves nothing behind.
        with tempfile.TemporaryDirectory(dir=path.parent, prefix=temp_prefix()) as tmp:
            exporter(anim, Path(tmp) / path.name)
            written = sorted(Path(tmp).iterdir())
            targets = [path.parent / p.name for p in written]
            clash = [t for t in targets if t.exists()]
            if clash and not overwrite:
                raise exists_error(clash[0])
            for src, dst in zip(written, targets, strict=True):
                move_file(src, dst, overwrite)
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
    check_readable(path)
    if fps is not None and not 0 < fps < float("inf"):
        raise TalkmeshError(f"--fps must be positive and finite, got {fps}")
    with reading(path):
        return importer(path, None if faces is None else np.asarray(faces), fps)


EXPORTERS: dict[str, Exporter] = {
    ".npy": export_npy,
    ".npz": export_npz,
    ".obj": export_obj,
    ".glb": export_glb,
    ".csv": export_live_link_csv,
    ".json": export_arkit_json,
    ".weights.npz": export_npz_weights,  # NAME.weights.npz: a compound suffix
    ".rig.glb": export_rig_glb,  # NAME.rig.glb or format="rig.glb": no animation clip
    ".visemes.json": export_visemes_json,  # 15 Oculus visemes per frame, Azure's viseme events
}

IMPORTERS: dict[str, Importer] = {
    ".npy": import_npy,
    ".npz": import_npz,
    ".glb": import_glb,
    ".csv": import_weights_on_head,
    ".json": import_weights_on_head,
}
