"""``animate --template``: a neutral face from the files users have, on any topology.

A mesh with the bundled head's vertex count gets the bundled topology, blendshapes and regions
(:func:`talkmesh.face.assets.load_template`). Any other mesh is taken as a learned model's own
topology (VOCASET's FLAME, 5023 vertices; BIWI, 23370) with the triangles from the user's files
(:func:`talkmesh.face.assets.plain_head`), in the layouts the datasets ship:

* ``templates.pkl`` (VOCASET, and the BIWI folder of FaceFormer and CodeTalker): a dict of
  subject -> (V, 3); ``templates.pkl:SUBJECT`` picks one (without it: the only one, or the
  subject that ``--style`` names alone). The triangles come from the mesh beside it (or in
  ``templates/`` beside it, FaceFormer's layout) with the same vertex count
  (``FLAME_sample.ply``, ``BIWI.ply``).
* ``.ply`` / ``.obj`` (``FLAME_sample.ply``, ``BIWI.ply``, BIWI's ``rigid_scans/<SUBJECT>.obj``):
  vertices and triangles in file order.
* ``.vl`` (one BIWI frame, as BIWI ships them) and ``.npy`` ((V, 3) or (V*3,)): vertices only;
  the triangles come from the mesh beside it, needed only by outputs that draw or export a surface
  (a video, ``.glb``, ``.obj``): ``.npy`` and ``.npz`` outputs take the vertices alone.

What is changed, and said (:class:`FaceTemplate` ``.note``; ``talkmesh animate`` prints it):

* a mesh of the bundled topology in other units or axes (millimetres, a Z-up export): found by
  fitting it to the bundled head vertex for vertex (Umeyama), and converted to metres, +y up
  (:func:`talkmesh.face.assets.bundled_frame`, as the Python API's ``load_template`` does); a
  mesh in metres and +y up is taken as it is, wherever it sits;
* BIWI's raw scans, known by their files (a ``.vl`` frame, ``rigid_scans/<SUBJECT>.obj``), or any
  BIWI-topology mesh when asked (``normalize=True``, ``--normalize-template``): normalised as
  ``talkmesh prepare-biwi`` normalises the dataset (rotated by pi about x, centred, unit surface
  area), the frame BIWI models are trained in. Any other mesh is taken as it is.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from talkmesh.datasets.biwi import NUM_VERTICES as BIWI_VERTICES
from talkmesh.datasets.biwi import normalize_frames, read_obj, read_vl, surface_area
from talkmesh.datasets.reader import load_templates
from talkmesh.errors import TalkmeshError
from talkmesh.face.assets import (
    MAX_MESH_BYTES,
    Head,
    bundled_frame,
    load_head,
    plain_head,
    read_mesh_vertices,
)

MESH_SUFFIXES = (".ply", ".obj")  # files that carry triangles
UNIT_AREA_TOLERANCE = 0.01  # a BIWI mesh whose total area is this close to 1 is normalised


class FaceTemplate(NamedTuple):
    """A ``--template`` read: the face, and what was done to the user's mesh ("" for nothing),
    a line for the terminal."""

    head: Head
    note: str


def split_spec(spec: str | Path) -> tuple[Path, str | None]:
    """``templates.pkl:SUBJECT`` -> (path, subject); any other path -> (path, None)."""
    text = str(spec)
    head, sep, subject = text.rpartition(":")
    if sep and head.lower().endswith(".pkl") and subject:
        return Path(head), subject
    return Path(text), None


def _pick(
    templates: dict[str, np.ndarray], subject: str | None, path: Path
) -> tuple[str, np.ndarray]:
    names = list(templates)
    if subject is None and len(names) == 1:
        subject = names[0]
    if subject is None:
        raise TalkmeshError(
            f"{path} holds {len(names)} subjects' templates: pick one with "
            f"--template {path}:SUBJECT (e.g. {names[0]})"
        )
    if subject not in templates:
        raise TalkmeshError(f"{path} has no template of {subject}: it has {', '.join(names)}")
    return subject, templates[subject]


def read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) vertices and (F, 3) triangles of a .ply or .obj, in file order."""
    if path.suffix.lower() == ".obj":
        vertices, faces = read_obj(path)
        return vertices.astype(np.float32), faces
    import trimesh

    try:
        mesh = trimesh.load(path, process=False, force="mesh")
    except Exception as e:  # trimesh raises many types on bad files
        raise TalkmeshError(f"{path}: not a readable mesh ({type(e).__name__})") from None
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int64)


def faces_beside(path: Path, num_vertices: int) -> np.ndarray:
    """The triangles of the mesh (.ply/.obj) with ``num_vertices`` vertices in ``path``'s folder
    or its ``templates/`` (FaceFormer's layout: ``VOCASET/templates/FLAME_sample.ply``)."""
    folders = [path.parent, path.parent / "templates"]
    candidates = [p for d in folders if d.is_dir() for p in sorted(d.iterdir())]
    for mesh in (p for p in candidates if p.suffix.lower() in MESH_SUFFIXES):
        if mesh == path or not mesh.is_file() or mesh.stat().st_size > MAX_MESH_BYTES:
            continue
        try:
            vertices, faces = read_mesh(mesh)
        except TalkmeshError:
            continue
        if len(vertices) == num_vertices and len(faces):
            return faces
    raise TalkmeshError(
        f"{path}: {num_vertices} vertices and no triangles: put the topology's mesh beside it "
        "(VOCASET's FLAME_sample.ply, BIWI's BIWI.ply or a rigid_scans/<SUBJECT>.obj) or pass "
        "a .ply/.obj as --template"
    )


def is_raw_biwi(path: Path) -> bool:
    """Whether ``path`` is one of BIWI's files in the scanner's frame: a ``.vl`` frame or a
    ``rigid_scans/<SUBJECT>.obj``."""
    suffix = path.suffix.lower()
    return suffix == ".vl" or (suffix == ".obj" and path.parent.name == "rigid_scans")


def _biwi_frame(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """A BIWI mesh in the scanner's frame -> the normalised frame BIWI models use."""
    if abs(float(surface_area(vertices, faces)) - 1.0) <= UNIT_AREA_TOLERANCE:
        return vertices  # already normalised (templates.pkl, prepared data)
    return normalize_frames(vertices[None], faces)[0]


def load_face_template(
    spec: str | Path,
    subject: str | None = None,
    *,
    triangles: bool = True,
    normalize: bool = False,
) -> Head:
    """``--template`` (see the module doc) -> the face to animate; ``subject`` picks one of a
    templates.pkl's subjects when the spec names none (e.g. the one ``--style`` names).
    ``triangles=False``: the outputs draw no surface (``.npy``, ``.npz``), so a vertex file with no
    mesh beside it is taken with no triangles instead of refused. ``normalize``: normalise a
    BIWI-topology mesh as prepare-biwi does even when its file does not say it is a raw scan.
    :func:`read_face_template` also says what was changed."""
    return read_face_template(spec, subject, triangles=triangles, normalize=normalize).head


def read_face_template(
    spec: str | Path,
    subject: str | None = None,
    *,
    triangles: bool = True,
    normalize: bool = False,
) -> FaceTemplate:
    """:func:`load_face_template`, with the note of what was done to the user's mesh."""
    path, named = split_spec(spec)
    if not path.is_file():
        raise TalkmeshError(f"{path}: no such template file")
    if path.stat().st_size > MAX_MESH_BYTES:
        raise TalkmeshError(f"{path}: {path.stat().st_size / 1e6:.0f} MB is too large for a face")
    suffix = path.suffix.lower()
    faces = None
    name = path.stem
    if suffix == ".pkl":
        templates = load_templates(path)
        if named is None and subject not in templates:
            subject = None
        name, vertices = _pick(templates, named or subject, path)
    elif suffix == ".vl":
        vertices = read_vl(path.read_bytes(), str(path)).astype(np.float32)
    elif suffix in MESH_SUFFIXES:
        vertices, faces = read_mesh(path)
    else:
        vertices = read_mesh_vertices(path)  # .npy and the other formats it reads
    if not np.isfinite(vertices).all():  # else every frame and weight would be NaN
        bad = int((~np.isfinite(np.asarray(vertices).reshape(len(vertices), -1))).any(1).sum())
        raise TalkmeshError(f"{path}: {bad} vertices have NaN or infinite coordinates")
    bundled = load_head()
    if len(vertices) == bundled.num_vertices:
        if not np.ptp(np.asarray(vertices, np.float64), axis=0).max() > 0:
            raise TalkmeshError(f"{path}: every vertex lies at one point: not a face")
        vertices, note = bundled_frame(vertices, bundled.template)
        return FaceTemplate(bundled.with_template(vertices, name), note)
    if faces is None:
        try:
            faces = faces_beside(path, len(vertices))
        except TalkmeshError:
            if triangles:
                raise
            faces = np.zeros((0, 3), np.int32)  # vertices only: nothing drawn needs them
    note = ""
    if len(vertices) == BIWI_VERTICES and (normalize or is_raw_biwi(path)):
        if not len(faces):
            raise TalkmeshError(
                f"{path}: normalising a BIWI scan needs its triangles: put BIWI.ply beside it"
            )
        before = np.asarray(vertices, np.float64)
        vertices = _biwi_frame(before, faces)
        if vertices is not before:
            note = (
                "normalised as prepare-biwi does (a raw BIWI scan: rotated by pi about x, "
                "centred, scaled to unit surface area)"
            )
    elif normalize:
        raise TalkmeshError(
            f"{path}: --normalize-template applies to BIWI's {BIWI_VERTICES}-vertex meshes, "
            f"not {len(vertices)} vertices"
        )
    return FaceTemplate(plain_head(vertices, faces, name, triangles=triangles), note)
