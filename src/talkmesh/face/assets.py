"""The bundled CC0 head: topology, neutral identities, ARKit-52 blendshapes and vertex regions.

Built from MakeHuman assets by ``scripts/build_assets.py`` (see ``data/ASSETS.md``). Coordinates are
metres, head centred at the origin, +y up, +z towards the viewer.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from talkmesh.errors import MissingDependencyError, TalkmeshError, TalkmeshWarning

DATA_DIR = Path(__file__).resolve().parents[1] / "data"
HEAD_FILE = "head.npz"
MAX_MESH_BYTES = 512 * 1024 * 1024  # refuse absurd template files before reading them
UNITS = {0: "metres", 1: "decimetres", 2: "centimetres", 3: "millimetres"}  # by decade
AXIS_SNAP_DEGREES = 30.0  # a fitted rotation this close to an axis swap is that swap


@dataclass(frozen=True)
class Regions:
    """Vertex regions of the head (indices are 0-based into the V vertices).

    Attributes:
        lips: (L,) lip vertices, used by the lip vertex error.
        upper_face: (U,) forehead, brow and eye vertices, used by FDD.
        eyelids: (E,) eyelid vertices (MeshTalk's eyelid loss).
        mouth_weight: (V,) soft mouth map in [0, 1] (MeshTalk's cross-modality loss).
        upper_weight: (V,) soft upper-face map in [0, 1].
        vertex_part: (V,) part id per vertex (0 skin, 1 eye, 2 teeth, 3 tongue).
        lip_pair: (2,) inner upper-lip and lower-lip midline vertices; their distance is the
            lip opening.
    """

    lips: np.ndarray
    upper_face: np.ndarray
    eyelids: np.ndarray
    mouth_weight: np.ndarray
    upper_weight: np.ndarray
    vertex_part: np.ndarray
    lip_pair: np.ndarray


@dataclass(frozen=True)
class Head:
    """A neutral head with its blendshapes.

    Attributes:
        name: identity name (or the template file's stem).
        template: (V, 3) float32 neutral vertices in metres.
        faces: (F, 3) int32 triangles.
        blendshapes: (52, V, 3) float32 ARKit blendshape offsets in metres; None for a face of
            another topology (:func:`plain_head`: a learned model's own, e.g. FLAME's).
        blendshape_names: the 52 ARKit names, in the order of ``blendshapes`` (empty without).
        regions: vertex regions (None without blendshapes).
    """

    name: str
    template: np.ndarray
    faces: np.ndarray
    blendshapes: np.ndarray | None
    blendshape_names: tuple[str, ...]
    regions: Regions | None

    @property
    def num_vertices(self) -> int:
        return int(self.template.shape[0])

    @property
    def rigged(self) -> bool:
        """Whether the head has the bundled blendshapes and regions (the bundled topology)."""
        return self.blendshapes is not None

    def vertices_from_weights(self, weights: np.ndarray) -> np.ndarray:
        """(T, 52) blendshape weights -> (T, V, 3) vertex positions."""
        weights = np.asarray(weights, dtype=np.float32)
        assert weights.ndim == 2 and weights.shape[1] == len(self.blendshape_names), weights.shape
        basis = self.blendshapes.reshape(len(self.blendshape_names), -1)
        vertices = weights @ basis  # (T, 3V): built in place, one copy even for 10 minutes
        vertices += self.template.reshape(1, -1)
        return vertices.reshape(len(weights), self.num_vertices, 3)

    def with_template(self, template: np.ndarray, name: str) -> Head:
        """The same topology and blendshapes on another neutral mesh."""
        template = np.asarray(template, dtype=np.float32)
        if template.shape != self.template.shape:
            raise TalkmeshError(
                f"template has {template.shape[0]} vertices but the head has {self.num_vertices}: "
                "use a mesh with the bundled head's topology (export one with `talkmesh export`)"
            )
        if not np.isfinite(template).all():
            raise TalkmeshError(f"{name}: the template has NaN or infinite coordinates")
        return Head(
            name, template, self.faces, self.blendshapes, self.blendshape_names, self.regions
        )


def plain_head(
    template: np.ndarray, faces: np.ndarray, name: str, *, triangles: bool = True
) -> Head:
    """A neutral face of another topology than the bundled head's (a learned model's own: FLAME's
    5023 vertices for VOCASET models, BIWI's 23370): (V, 3) vertices and (F, 3) triangles, no
    blendshapes or regions, so learned models animate it and the motion is exported as it is.
    ``triangles=False`` accepts (0, 3) faces: vertices only, for outputs that draw no surface."""
    template = np.asarray(template, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int32)
    if template.ndim != 2 or template.shape[1] != 3 or not len(template):
        raise TalkmeshError(f"{name}: a template must be (V, 3) vertices, got {template.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or (triangles and not len(faces)):
        raise TalkmeshError(f"{name}: the mesh needs triangles (F, 3), got {faces.shape}")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(template)):
        raise TalkmeshError(f"{name}: a face points past the {len(template)} vertices")
    return Head(name, template, faces, None, (), None)


@lru_cache(maxsize=1)
def _head_data() -> dict[str, np.ndarray]:
    with np.load(DATA_DIR / HEAD_FILE, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def list_identities() -> list[str]:
    """Names of the bundled neutral identities."""
    return [str(n) for n in _head_data()["identity_names"]]


def default_identity() -> str:
    return str(_head_data()["default_identity"])


def load_head(identity: str | None = None) -> Head:
    """The bundled head with one of its identities (the default one if ``identity`` is None)."""
    d = _head_data()
    names = list_identities()
    identity = identity or default_identity()
    if identity not in names:
        raise TalkmeshError(f"unknown identity '{identity}': choose one of {', '.join(names)}")
    regions = Regions(
        lips=d["lips"],
        upper_face=d["upper_face"],
        eyelids=d["eyelids"],
        mouth_weight=d["mouth_weight"],
        upper_weight=d["upper_weight"],
        vertex_part=d["vertex_part"],
        lip_pair=d["lip_pair"],
    )
    return Head(
        name=identity,
        template=d["identities"][names.index(identity)],
        faces=d["faces"],
        blendshapes=d["blendshapes"],
        blendshape_names=tuple(str(n) for n in d["blendshape_names"]),
        regions=regions,
    )


def read_mesh_vertices(path: str | Path) -> np.ndarray:
    """(V, 3) float32 vertices of a mesh file (.obj, .ply, .npy [V, 3] or [V*3]), in file order."""
    path = Path(path)
    if not path.is_file():
        raise TalkmeshError(f"{path}: no such mesh file")
    size = path.stat().st_size
    if size == 0:
        raise TalkmeshError(f"{path}: the mesh file is empty")
    if size > MAX_MESH_BYTES:
        raise TalkmeshError(f"{path}: {size / 1e6:.0f} MB is too large for a face mesh")
    suffix = path.suffix.lower()
    try:
        if suffix == ".obj":
            rows = [
                ln.split()[1:4]
                for ln in path.read_text(errors="replace").splitlines()
                if ln.startswith("v ")
            ]
            verts = np.array(rows, dtype=np.float32)
        elif suffix == ".npy":
            verts = np.load(path, allow_pickle=False).astype(np.float32).reshape(-1, 3)
        elif suffix in (".ply", ".stl", ".off", ".glb", ".gltf"):
            try:
                import trimesh
            except ImportError as e:
                raise MissingDependencyError("trimesh", "all", f"reading {suffix} meshes") from e
            mesh = trimesh.load(path, process=False, force="mesh")
            verts = np.asarray(mesh.vertices, dtype=np.float32)
        else:
            raise TalkmeshError(
                f"{path}: unsupported mesh format '{suffix}' (use .obj, .ply or .npy)"
            )
    except TalkmeshError:
        raise
    except Exception as e:  # any parser failure is a corrupt file to the user
        raise TalkmeshError(f"{path}: could not read the mesh ({type(e).__name__}: {e})") from None
    if verts.ndim != 2 or verts.shape[1] != 3 or len(verts) == 0:
        raise TalkmeshError(f"{path}: no vertices found")
    if not np.isfinite(verts).all():
        raise TalkmeshError(f"{path}: the mesh has NaN or infinite coordinates")
    return verts


def load_template(path: str | Path, *, convert: bool = True) -> Head:
    """The bundled head's topology and blendshapes on the neutral mesh in ``path``.

    ``convert``: a mesh in other units or axes (millimetres, a Z-up export) is converted to
    metres and +y up, as ``talkmesh animate --template`` does (:func:`bundled_frame`), with a
    :class:`~talkmesh.errors.TalkmeshWarning` saying what was done; False takes it as it is."""
    head = load_head()
    try:
        vertices = read_mesh_vertices(path)
        if convert and vertices.shape == head.template.shape:
            vertices, note = bundled_frame(vertices, head.template)
            if note:
                warnings.warn(f"{path}: {note}", TalkmeshWarning, stacklevel=2)
        return head.with_template(vertices, Path(path).stem)
    except TalkmeshError as e:
        msg = str(e)
        raise TalkmeshError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None


def _axis_name(vector: np.ndarray) -> str:
    k = int(np.argmax(np.abs(vector)))
    return ("+" if vector[k] > 0 else "-") + "xyz"[k]


def bundled_frame(vertices: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, str]:
    """(V, 3) vertices of the bundled topology in any units and axes -> (metres, +y up, +z to
    the viewer) and a note saying what was converted ("" when nothing was).

    The similarity fit (Umeyama) onto ``reference`` (the bundled head, vertex for vertex) gives
    the scale, whose decade is the unit (1000: millimetres), and the rotation, which is
    converted only where it is an axis swap (a Z-up export); a head turned by a few degrees, or
    placed elsewhere, is the user's and stays so. Units and axes are converted about the origin,
    so the mesh keeps its place in its own frame.
    """
    from talkmesh.face.registration import nearest_axis_rotation, similarity

    vertices = np.asarray(vertices, np.float64)
    scale, rotation, _ = similarity(vertices, np.asarray(reference, np.float64))
    if not np.isfinite(scale) or scale <= 0:
        return vertices.astype(np.float32), ""
    decade = int(np.clip(np.round(-np.log10(scale)), 0, 3))
    swap = nearest_axis_rotation(rotation, AXIS_SNAP_DEGREES)
    changes = []
    if decade:
        changes.append(f"{UNITS[decade]} -> metres")
    if swap is not None and not np.allclose(swap, np.eye(3)):
        up = swap.T[:, 1]  # the user's axis that the head's up (+y) is
        changes.append(f"up {_axis_name(up)} -> +y")
    else:
        swap = None
    if not changes:
        return vertices.astype(np.float32), ""
    converted = vertices * 10.0**-decade
    if swap is not None:
        converted = converted @ swap.T
    return converted.astype(np.float32), "converted: " + ", ".join(changes)


def lip_opening(vertices: np.ndarray, regions: Regions) -> np.ndarray:
    """(T, V, 3) vertices -> (T,) distance in metres between the inner lips at the midline."""
    upper, lower = regions.lip_pair
    return np.linalg.norm(vertices[:, upper] - vertices[:, lower], axis=-1)
