"""Rigging a plain head mesh: the bundled 52 ARKit blendshapes carried onto any head.

``rig_head(vertices, faces)`` does it in four steps:

1. Registration (:mod:`talkmesh.face.registration`): rigid + scale (this gives the units, mm / cm
   / m, and the up-axis), a smoothed closest-point pull, then a non-rigid fit of the bundled
   head's skin onto the user's surface started from it, held by landmarks (``LANDMARK_NAMES``):
   those the user gives as vertex ids (four or more also start the rigid fit; they always win)
   and those found on the mesh's own geometry near where the rigid fit puts them
   (:mod:`talkmesh.face.landmarks`: nose tip, lips and mouth corners from the lip gap, chin, eye
   corners from the eye openings; ``AUTOMATIC`` names those that hold the fit, and only where the
   mesh is no coarser there than ``COARSER`` times the bundled head); the other landmarks are
   placed on the fitted head afterwards.
2. Checks: a mesh the bundled head cannot be fitted to is "not a head"; lips joined across the
   mouth (the shortest path over the surface from the upper to the lower lip landmark is shorter
   than ``SEALED_LIPS`` of the head's size) mean "no mouth opening": the jaw could not open.
3. Skin: deformation transfer (:mod:`talkmesh.face.transfer`): every user triangle takes the
   deformation gradient of its corresponding bundled triangle (the closest one facing the same
   way on the registered head), rotated into the user's axes, and the offsets are solved for in
   the least-squares sense, anchored weakly to the closest-point offsets. Triangles far from the
   head (hair, shoulders) keep their shape and fade to no motion.
4. Other parts: each separate connected component of the user's mesh that lies on the bundled
   head's eyeballs or teeth follows that part rigidly (eyes turn with the ``eyeLook*`` shapes, the
   lower teeth move with the jaw); other small components (tongue, lashes) take the closest-point
   offsets.

``method="closest"`` skips steps 3-4 and gives every vertex the closest-point offsets (the
comparison the bench makes). :meth:`Rig.carry` maps any motion of the bundled topology (a vertex
model's prediction) onto the user's mesh through the same correspondence, and
:meth:`Rig.carry_blocks` a whole animation (``talkmesh animate --head``; :func:`talkmesh.face.rig_files.load_rig` registers
a mesh file once, and saves the registration for later runs: :mod:`talkmesh.face.rig_cache`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from talkmesh.animation import Animation, AnimationBlocks
from talkmesh.constants import MOTION_FPS
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import Head, load_head
from talkmesh.face.landmarks import IDENTITY, Frame, eye_opening, find_landmarks
from talkmesh.face.registration import (
    closest_points,
    nearest_axis_rotation,
    nonrigid_fit,
    rigid_fit,
    smoothed_pull,
    vertex_normals,
)
from talkmesh.face.rig_dense import carry_back, closest_shapes, reduce_mesh
from talkmesh.face.transfer import (
    SAMPLES,
    deformation_gradients,
    fitted_gradients,
    frames,
    rigid_follow,
    transfer,
)

FALLOFF = (0.02, 0.06)  # fraction of the head's RMS radius: full motion within, none beyond
MIN_VERTICES = 100
COARSER = 1.5  # a found landmark holds the fit where the mesh's edges are at most this x the head's
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
NOT_A_HEAD = 0.08  # median registration distance over RMS radius beyond which it is no head
SEALED_LIPS = 0.2  # surface path between the lips shorter than this x the RMS radius: no mouth
# (around the mouth corners it is its width, over 0.35 x; over welded lips 0.1 x)
METHODS = ("transfer", "closest")
# over this many vertices a mesh is registered on a copy decimated to it and its shapes are carried
# back CARRY_BLOCK vertices at a time (talkmesh.face.rig_dense; docs/results/rigging.md)
REDUCE_ABOVE = 12_000
CARRY_BLOCK = 32_768
CARRY_VALUES = 1 << 23  # float64 values (64 MB) of Rig.carry's gather at a time
BLOCK_VALUES = 1 << 25  # float32 values (128 MB) of the frames of a block Rig.carry_blocks yields
CHECK_POINTS = 3000  # vertices of a dense mesh its not-a-head check fits (before decimating)
PART_SKIN = 8  # skin vertices nearest each part vertex whose mean motion the part takes
PART_MATCH = 0.3  # mean distance to a part over its RMS radius within which a component is it
SKIN, EYE, TEETH, TONGUE = 0, 1, 2, 3  # Regions.vertex_part
OTHER = -1  # a separate component that is no bundled part: closest-point offsets

# Landmarks: name -> how to find it on the bundled head. "Left" is the face's own left (+x), as in
# ARKit's names. The lips, mouth corners and chin are found from the geometry (as on a user's mesh,
# :mod:`talkmesh.face.landmarks`); eyelids and brows where a blendshape moves most; eye corners at
# the ends of the eye opening seen from the front.
LANDMARK_SHAPES = {
    "mouth_left": "mouthSmileLeft",
    "mouth_right": "mouthSmileRight",
    "eyelid_left": "eyeBlinkLeft",
    "eyelid_right": "eyeBlinkRight",
    "brow_left": "browOuterUpLeft",
    "brow_right": "browOuterUpRight",
}
EYE_CORNERS = ("eye_inner_left", "eye_outer_left", "eye_inner_right", "eye_outer_right")
LANDMARK_NAMES = ("nose_tip", "chin", "upper_lip", "lower_lip", *LANDMARK_SHAPES, *EYE_CORNERS)
# The landmarks found on the user's geometry that hold the registration by default (the others
# found are placed from the registered head like those not found): on bench/rig_transfer.py the
# eye corners took bo from 17.8 to 15.1% and cost nothing elsewhere; the lips, mouth corners and
# chin found on the geometry cost the denser mesh 0.4% and gained nothing on the identities.
AUTOMATIC = ("nose_tip", *EYE_CORNERS)


@lru_cache(maxsize=1)
def _bundled_landmarks() -> dict[str, int]:
    """The landmarks of the bundled topology (found on its default identity)."""
    return head_landmarks(load_head())


def head_landmarks(head: Head) -> dict[str, int]:
    """The bundled head's landmark vertex ids, by name (see ``LANDMARK_NAMES``): first guesses
    from its blendshapes and extremes, refined as :func:`find_landmarks` finds them on any mesh."""
    t, skin = head.template.astype(np.float64), head.regions.vertex_part == SKIN
    midline = skin & (np.abs(t[:, 0]) < 0.002)
    out = {"nose_tip": int(np.flatnonzero(midline)[np.argmax(t[midline, 2])])}
    chin = np.flatnonzero(midline & (t[:, 1] < -0.068))  # below the labiomental fold
    out["chin"] = int(chin[np.argmax(t[chin, 2])])
    out["upper_lip"], out["lower_lip"] = (int(i) for i in head.regions.lip_pair)
    for name, shape in LANDMARK_SHAPES.items():
        size = np.linalg.norm(head.blendshapes[ARKIT_NAMES.index(shape)], axis=1) * skin
        out[name] = int(np.argmax(size))
    faces = head.faces.astype(np.int64)
    ids = np.flatnonzero(skin)
    for side, sign in (("left", 1.0), ("right", -1.0)):
        eye = t[(head.regions.vertex_part == EYE) & (sign * t[:, 0] > 0)].mean(0)
        ends = eye_opening(t, faces, skin[faces].all(1), eye)
        a, b = (int(ids[cKDTree(t[ids]).query(p)[1]]) for p in ends)
        out[f"eye_inner_{side}"], out[f"eye_outer_{side}"] = (a, b) if sign > 0 else (b, a)
    predicted = {k: t[i] for k, i in out.items()}
    found = find_landmarks(t, faces, vertex_normals(t, faces), IDENTITY, predicted)
    out.update({k: i for k, i in found.items() if skin[i]})
    return out


@dataclass(frozen=True)
class Rig:
    """The bundled blendshapes on a user's head.

    Attributes:
        vertices: (V, 3) float32 the user's neutral vertices, as given.
        faces: (F, 3) int32 the user's triangles.
        blendshapes: (52, V, 3) float32 offsets in the user's units and axes.
        scale: user units per metre of the bundled head (1000: millimetres).
        rotation: (3, 3) the bundled head's axes in the user's frame (columns: x, y up, z front).
        translation: (3,) so that ``scale * rotation @ p + translation`` takes a point p of the
            bundled head (metres) into the user's frame.
        residual: median distance (user units) from the registered head to the user's surface.
        landmarks: name -> the user vertex id each landmark was placed at.
        parts: what the user's separate components were taken for: 'eye', 'teeth', ... -> count.
        corners: (V, 3) bundled head vertices around each user vertex's corresponding point.
        weights: (V, 3) their barycentric weights, times the fade to no motion far from the head.
    """

    vertices: np.ndarray
    faces: np.ndarray
    blendshapes: np.ndarray
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    residual: float
    landmarks: dict[str, int] = field(default_factory=dict)
    parts: dict[str, int] = field(default_factory=dict)
    corners: np.ndarray | None = None
    weights: np.ndarray | None = None

    @property
    def units(self) -> str:
        """The unit the fitted scale is closest to (by decades): mm, cm or m."""
        decade = int(np.clip(np.round(np.log10(self.scale)), 0, 3))
        return {0: "m", 1: "dm", 2: "cm", 3: "mm"}[decade]

    def to_gltf(self) -> np.ndarray:
        """(4, 4) from the user's frame to glTF's (metres, +y up): the unit's decade and the axis
        swap nearest the fitted rotation (identity for a mesh in metres, +y up)."""
        decade = int(np.clip(np.round(np.log10(self.scale)), 0, 3))
        swap = nearest_axis_rotation(self.rotation.T, 45.0)
        matrix = np.eye(4)
        matrix[:3, :3] = (np.eye(3) if swap is None else swap) * 10.0**-decade
        return matrix

    @property
    def up_axis(self) -> str:
        """The user's axis the head's up (+y) maps to: '+y', '-z', ..."""
        up = self.rotation[:, 1]
        k = int(np.argmax(np.abs(up)))
        return ("+" if up[k] > 0 else "-") + "xyz"[k]

    def carry(self, offsets: np.ndarray) -> np.ndarray:
        """(T, Vh, 3) offsets of the bundled topology (metres, e.g. a vertex model's prediction
        minus its template) -> (T, V, 3) offsets on the user's mesh, in its units and axes,
        through the closest-point correspondence, a block of user vertices at a time (a frame's
        (V, 3, 3) gather is 72 MB of float64 at a million vertices: ``CARRY_VALUES`` at most)."""
        offsets = np.asarray(offsets, np.float64)
        assert offsets.ndim == 3 and offsets.shape[2] == 3, offsets.shape
        out = np.empty((len(offsets), len(self.corners), 3), np.float32)
        step = max(1, CARRY_VALUES // (9 * max(1, len(offsets))))
        turn = self.scale * self.rotation.T
        for a in range(0, len(self.corners), step):
            b = slice(a, a + step)
            moved = np.einsum("vc,tvcx->tvx", self.weights[b], offsets[:, self.corners[b]])
            out[:, b] = moved @ turn
        return out

    def carry_blocks(self, anim: AnimationBlocks, template: np.ndarray) -> AnimationBlocks:
        """``anim`` (a vertex model's or the procedural animator's motion of the bundled topology,
        its (Vh, 3) neutral ``template`` in metres) moving the user's mesh, block by block: every
        frame is ``vertices + carry(frame - template)``, in the user's units and axes. ARKit
        weights pass through unchanged; no basis (the motion is the model's, not the shapes'). A
        block comes in as many as its frames' float32 vertices take ``BLOCK_VALUES``. The head
        pose passes unchanged too, with :meth:`pose_frame` saying where its frame lies."""
        template = np.asarray(template, np.float32)

        # a model's block (256 frames) of a million-vertex head would be 3 GB: cut smaller
        step = max(1, BLOCK_VALUES // (3 * len(self.vertices)))

        def blocks():
            for block in anim.blocks:
                assert block.vertices.shape[1:] == template.shape, block.vertices.shape
                for a in range(0, block.num_frames, step):
                    moved = self.carry(block.vertices[a : a + step] - template)
                    moved += self.vertices
                    yield Animation(
                        vertices=moved,
                        faces=self.faces,
                        fps=block.fps,
                        weights=None if block.weights is None else block.weights[a : a + step],
                        weight_names=list(block.weight_names),
                        head_pose=None
                        if block.head_pose is None
                        else block.head_pose[a : a + step],
                    )

        return AnimationBlocks(
            blocks=blocks(),
            num_frames=anim.num_frames,
            faces=self.faces,
            fps=anim.fps,
            audio=anim.audio,
            sample_rate=anim.sample_rate,
            weight_names=list(anim.weight_names),
            template=self.vertices,
            audio_file=anim.audio_file,
            to_gltf=self.to_gltf(),
            phones=anim.phones,
            pose_frame=self.pose_frame(),
        )

    def pose_frame(self) -> np.ndarray:
        """(4, 4) the bundled head's frame (metres, its axes: where head poses are made) in the
        user's: ``scale * rotation @ p + translation``."""
        frame = np.eye(4)
        frame[:3, :3] = self.scale * np.asarray(self.rotation, np.float64)
        frame[:3, 3] = self.translation
        return frame

    def facing(self, anim: Animation) -> Animation:
        """``anim`` of the user's mesh turned and scaled into the bundled head's axes and metres
        (y up, looking along +z), as the renderer's front camera expects."""
        vertices = (anim.vertices - self.translation) @ self.rotation / self.scale
        return replace(
            anim, vertices=vertices, template=None, basis=None, to_gltf=None, pose_frame=None
        )

    def neutral_animation(self) -> Animation:
        """One neutral frame with the 52 blendshapes as its ``basis`` (all weights zero): saved as
        .glb it is the rigged head, one ARKit-named morph target per blendshape."""
        return Animation(
            vertices=self.vertices[None],
            faces=self.faces,
            fps=MOTION_FPS,
            weights=np.zeros((1, len(ARKIT_NAMES)), np.float32),
            weight_names=list(ARKIT_NAMES),
            template=self.vertices,
            basis=self.blendshapes,
            to_gltf=self.to_gltf(),
        )


def read_landmarks(path: str | Path) -> dict[str, int]:
    """Landmark vertex ids from a JSON file ``{"nose_tip": 1234, ...}`` (plain data only)."""
    import json

    path = Path(path)
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise TalkmeshError(f"{path}: cannot read landmarks ({type(e).__name__}: {e})") from None
    if not isinstance(data, dict) or not all(
        isinstance(v, int) and not isinstance(v, bool) for v in data.values()
    ):
        raise TalkmeshError(f'{path}: give landmarks as a JSON object {{"nose_tip": 1234, ...}}')
    return data


def _check_landmarks(landmarks: dict[str, int], num_vertices: int) -> None:
    for name, index in landmarks.items():
        if name not in LANDMARK_NAMES:
            raise TalkmeshError(
                f"unknown landmark '{name}': choose from {', '.join(LANDMARK_NAMES)}"
            )
        if not 0 <= int(index) < num_vertices:
            raise TalkmeshError(
                f"landmark {name}={index}: the mesh has vertices 0 to {num_vertices - 1}"
            )


def _check_input(vertices: np.ndarray, faces: np.ndarray) -> None:
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < MIN_VERTICES:
        raise TalkmeshError(
            f"a head mesh needs at least {MIN_VERTICES} vertices, got {len(vertices)}"
        )
    if faces.ndim != 2 or faces.shape[1] != 3 or not len(faces):
        raise TalkmeshError("the mesh has no triangles: give a surface mesh (OBJ, PLY, glTF)")
    if not np.isfinite(vertices).all():
        raise TalkmeshError("the mesh's vertices contain NaN or infinite values")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise TalkmeshError("the mesh's triangles refer to vertices it does not have")
    extent = np.sort(np.ptp(vertices, axis=0))
    if not extent[-1] > 0 or extent[1] <= 1e-6 * extent[-1]:  # a point or a line: no surface
        raise TalkmeshError(
            f"the mesh has no extent (its vertices span {extent[-1]:.3g} x {extent[1]:.3g} x "
            f"{extent[0]:.3g}): not a head"
        )


def _components(faces: np.ndarray, n: int) -> np.ndarray:
    """(n,) connected component label of every vertex (by shared triangles)."""
    i, j = faces[:, [0, 1, 2]].ravel(), faces[:, [1, 2, 0]].ravel()
    graph = sparse.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    return csgraph.connected_components(graph, directed=False)[1]


def _place_landmarks(user, user_normals, head_points, head_normals) -> np.ndarray:
    """The user vertex nearest each registered head landmark among those facing its way."""
    _, near = cKDTree(user).query(head_points, k=min(16, len(user)))
    facing = np.einsum("lkx,lx->lk", user_normals[near], head_normals) > 0.3
    pick = np.where(facing.any(1), np.argmax(facing, axis=1), 0)  # nearest facing, else nearest
    return near[np.arange(len(near)), pick]


def _check_mouth(vertices, faces, upper: int, lower: int, radius: float) -> None:
    """A one-line error when the lips are one surface (no mouth opening to open the jaw)."""
    if upper == lower:
        raise TalkmeshError(
            "the mesh has no mouth opening: upper and lower lip are one vertex (cut the lips "
            "apart, or give --landmark upper_lip=ID --landmark lower_lip=ID)"
        )
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    length = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    n = len(vertices)
    graph = sparse.coo_matrix((length, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()
    limit = SEALED_LIPS * radius
    path = csgraph.dijkstra(graph, directed=False, indices=upper, limit=limit)[lower]
    if path < limit:
        raise TalkmeshError(
            f"the mesh has no mouth opening: the lips are joined ({path:.3g} units over the "
            "surface from upper to lower lip); cut the lips apart so the jaw can open"
        )


def _edge_lengths(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V,) the mean length of the edges at each vertex."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    length = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    total = np.bincount(edges.ravel(), np.repeat(length, 2), minlength=len(vertices))
    return total / np.maximum(np.bincount(edges.ravel(), minlength=len(vertices)), 1)


def _landmark_pairs(source, vertices, given: dict[str, int]):
    """(L, 3) bundled and user positions of four or more given landmarks (the rigid fit's
    start), else None."""
    if len(given) < 4:
        return None
    marks = _bundled_landmarks()
    names = list(given)
    return source[[marks[k] for k in names]], vertices[[int(given[k]) for k in names]]


def _radius(vertices: np.ndarray) -> float:
    """The RMS distance of the vertices from their centroid."""
    return float(np.sqrt(((vertices - vertices.mean(0)) ** 2).sum(1).mean()))


def _refuse_unless_head(fit: float, radius: float) -> None:
    """A one-line error where the rigid ``fit`` (median distance) is over ``NOT_A_HEAD`` of the
    mesh's ``radius``."""
    if fit > NOT_A_HEAD * radius:
        raise TalkmeshError(
            f"the mesh does not look like a head: the bundled head fits it no closer than "
            f"{100 * fit / radius:.0f}% of its size (give a head, face forward, mouth included)"
        )


def _check_sample(vertices, head, landmarks):
    """The rigid fit (s, R, t) of the bundled head onto ``CHECK_POINTS`` of a dense mesh's
    vertices, before it is decimated: a mesh that is no head is refused in the time of a small
    one, whatever its size. The residual is measured to every vertex, as for a mesh registered
    whole (a sample's sparser points would read farther), within twice the limit (from inside
    a sphere, a nearest-vertex search without a bound visits all of it: 25 s at 1.7M)."""
    source = head.template.astype(np.float64)
    pick = np.random.default_rng(0).choice(len(vertices), min(CHECK_POINTS, len(vertices)), False)
    pairs = _landmark_pairs(source, vertices, landmarks or {})
    scale, rotation, shift, sampled = rigid_fit(source, vertices[pick], pairs)
    radius = _radius(vertices)
    moved = scale * source @ rotation.T + shift
    near = cKDTree(vertices).query(moved, distance_upper_bound=2 * NOT_A_HEAD * radius)[0]
    fit = float(np.median(near))
    _refuse_unless_head(fit if np.isfinite(fit) else sampled, radius)
    return scale, rotation, shift


def _register(vertices, faces, head, landmarks, automatic, pre_fit, start=None):
    """Rigid (from ``start``, a fit found already, if given) + non-rigid registration of the
    head's skin; returns (s, R, t, residual, skin ids, skin faces, registered skin (S, 3), user
    landmark ids by name)."""
    source = head.template.astype(np.float64)
    given = {k: int(v) for k, v in (landmarks or {}).items()}
    _check_landmarks(given, len(vertices))
    pairs = _landmark_pairs(source, vertices, given)
    scale, rotation, shift, fit = rigid_fit(source, vertices, pairs, start)
    radius = _radius(vertices)
    _refuse_unless_head(fit, radius)
    marks = _bundled_landmarks()  # every Head has the bundled topology
    skin = np.flatnonzero(head.regions.vertex_part == SKIN)
    local = np.full(head.num_vertices, -1)
    local[skin] = np.arange(len(skin))
    skin_faces = local[head.faces[(local[head.faces] >= 0).all(1)]]
    rigid = scale * source[skin] @ rotation.T + shift
    user_normals = vertex_normals(vertices, faces)
    # The fit is held by the landmarks given and by those found on the user's geometry near where
    # the rigid fit puts them (features that closest points alone let slide: the nose tip, the lip
    # gap and its corners, the chin, eye openings); the others are placed on the fitted head
    # afterwards.
    predicted = {k: scale * source[i] @ rotation.T + shift for k, i in marks.items()}
    frame = Frame(scale, rotation, shift)
    found = find_landmarks(vertices, faces, user_normals, frame, predicted)
    # A landmark found on a mesh coarser there than the bundled head is a vertex up to half an
    # edge off the feature: the registration's closest points do better (the bench's coarse cases).
    user_edge, head_edge = _edge_lengths(vertices, faces), scale * _edge_lengths(source, head.faces)
    held = {
        k: i
        for k, i in found.items()
        if k in automatic and user_edge[i] <= COARSER * head_edge[marks[k]]
    }
    held.update(given)
    ids = local[[marks[k] for k in held]]
    # The smoothed closest-point pull (the fit before the sparse solve existed) gives the solve's
    # first closest points; its smoothness term still measures the motion from the rigid fit. It
    # pulls towards the user's vertices, so not on a mesh coarser than the bundled head (bench:
    # coarser 25% 7.0 -> 7.1% with it; identities 0.1-1.3 points better, denser 0.2).
    fine = np.median(user_edge) <= COARSER * np.median(head_edge)
    start = smoothed_pull(rigid, skin_faces, vertices) if pre_fit and fine else None
    registered = nonrigid_fit(
        rigid,
        skin_faces,
        vertices,
        faces,
        (ids, vertices[list(held.values())].reshape(-1, 3)),
        start=start,
    )
    names = list(LANDMARK_NAMES)
    at = local[[marks[k] for k in names]]
    placed = _place_landmarks(
        vertices, user_normals, registered[at], vertex_normals(registered, skin_faces)[at]
    )
    found = dict(zip(names, (int(i) for i in placed)))
    found.update(held)
    _check_mouth(vertices, faces, found["upper_lip"], found["lower_lip"], radius)
    return scale, rotation, shift, radius, skin, skin_faces, registered, found, user_normals


def rig_head(
    vertices: np.ndarray,
    faces: np.ndarray,
    head: Head | None = None,
    *,
    landmarks: dict[str, int] | None = None,
    method: str = "transfer",
    automatic: tuple[str, ...] = AUTOMATIC,
    pre_fit: bool = True,
) -> Rig:
    """The bundled head's 52 blendshapes carried onto the mesh (V, 3) vertices, (F, 3) faces.

    Args:
        vertices, faces: the user's neutral head mesh, any units and axes.
        head: the bundled head (its default identity if None).
        landmarks: user vertex ids by landmark name (``LANDMARK_NAMES``), overriding the
            automatic ones; four or more also start the rigid fit.
        method: "transfer" (deformation transfer, the default) or "closest" (closest-point
            offsets everywhere).
        automatic: the landmarks found on the mesh's own geometry that hold the registration
            (:mod:`talkmesh.face.landmarks`; ``("nose_tip",)`` is the fit before they were).
        pre_fit: start the non-rigid solve from the smoothed closest-point pull
            (:func:`~talkmesh.face.registration.smoothed_pull`) where the mesh is no coarser
            than ``COARSER`` x the bundled head (median edge); False: from the rigid fit.
    """
    if method not in METHODS:
        raise TalkmeshError(f"unknown rig method '{method}': choose one of {', '.join(METHODS)}")
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    _check_input(vertices, faces)
    head = head or load_head()
    if len(vertices) > REDUCE_ABOVE:  # registered on a reduced copy, carried back blockwise
        return _rig_reduced(vertices, faces, head, landmarks, method, automatic, pre_fit)
    return _rig(vertices, faces, head, landmarks, method, automatic, pre_fit)


def _rig(vertices, faces, head, landmarks, method, automatic, pre_fit, start=None) -> Rig:
    """:func:`rig_head` on the mesh as it is (its steps 1 to 4); ``start``: a rigid fit found
    already."""
    scale, rotation, shift, radius, skin, skin_faces, registered, found, user_normals = _register(
        vertices, faces, head, landmarks, automatic, pre_fit, start
    )
    # Closest-point correspondence of every user vertex on the registered head (its skin as
    # fitted, eyes, teeth and tongue moved with the skin around them).
    placed = scale * head.template.astype(np.float64) @ rotation.T + shift
    whole = _follow_skin(placed, registered, head)
    head_faces = head.faces.astype(np.int64)
    face, bary, dist = closest_points(vertices, whole, head_faces, user_normals)
    near, far = FALLOFF[0] * radius, FALLOFF[1] * radius
    fade = np.clip((far - dist) / (far - near), 0.0, 1.0)
    corners = head_faces[face]
    weights = bary * fade[:, None]
    guess = closest_shapes(head, corners, weights, scale, rotation, CARRY_BLOCK)
    parts: dict[str, int] = {}
    if method == "transfer":
        labels = _components(faces, len(vertices))
        part_of, follow = _classify(vertices, labels, head, whole)
        on_skin = part_of[faces[:, 0]] == SKIN
        shapes = scale * head.blendshapes[:, skin].astype(np.float64) @ rotation.T
        gradients = _user_gradients(
            vertices, faces[on_skin], registered, placed[skin], skin_faces, shapes, radius
        )
        offsets = transfer(vertices, faces[on_skin], gradients, guess)
        offsets[:, part_of != SKIN] = guess[:, part_of != SKIN]
        for label, source_ids in follow.items():
            mine = labels == label
            part = whole[source_ids]
            moved = scale * head.blendshapes[:, source_ids].astype(np.float64) @ rotation.T
            offsets[:, mine] = rigid_follow(vertices[mine], part, moved)
            name = {EYE: "eye", TEETH: "teeth", TONGUE: "tongue"}[
                int(head.regions.vertex_part[source_ids[0]])
            ]
            parts[name] = parts.get(name, 0) + 1
    else:
        offsets = guess
    return Rig(
        vertices=vertices.astype(np.float32),
        faces=faces.astype(np.int32),
        blendshapes=offsets.astype(np.float32),
        scale=scale,
        rotation=rotation,
        translation=shift,
        residual=float(np.median(cKDTree(vertices).query(registered)[0])),
        landmarks=found,
        parts=parts,
        corners=corners,
        weights=weights,
    )


def _rig_reduced(vertices, faces, head, landmarks, method, automatic, pre_fit) -> Rig:
    """:func:`rig_head` of a mesh over REDUCE_ABOVE vertices: refused if no head on a sample of
    its vertices (:func:`_check_sample`), registered on a copy decimated to REDUCE_ABOVE vertices
    (from the sample's rigid fit), its shapes carried back to every vertex
    (:func:`talkmesh.face.rig_dense.carry_back`)."""
    _check_landmarks(landmarks or {}, len(vertices))
    start = _check_sample(vertices, head, landmarks)
    small_v, small_f = reduce_mesh(vertices, faces, REDUCE_ABOVE)
    near = cKDTree(small_v)
    given = {n: int(near.query(vertices[int(i)])[1]) for n, i in (landmarks or {}).items()}
    small = _rig(small_v, small_f, head, given, method, automatic, pre_fit, start)
    shapes, corners, weights, found = carry_back(
        vertices, faces, small_v, small_f, small, landmarks, CARRY_BLOCK
    )
    return replace(
        small,
        vertices=vertices.astype(np.float32),
        faces=faces.astype(np.int32),
        blendshapes=shapes,
        landmarks=found,
        corners=corners,
        weights=weights,
    )


def _follow_skin(placed: np.ndarray, registered: np.ndarray, head: Head) -> np.ndarray:
    """(Vh, 3) the whole bundled head on the user's: ``placed`` by the rigid fit, its skin
    replaced by the (S, 3) ``registered`` skin, and every other part (eyeball, teeth row, tongue)
    shifted by the mean non-rigid displacement of the skin around it (the ``PART_SKIN`` skin
    vertices nearest each of its vertices: eyelids, lips), so eyes and teeth move with the face."""
    skin = np.flatnonzero(head.regions.vertex_part == SKIN)
    moved = registered - placed[skin]
    out = placed.copy()
    out[skin] = registered
    tree = cKDTree(placed[skin])
    labels = _components(head.faces.astype(np.int64), head.num_vertices)
    for label in np.unique(labels):
        ids = np.flatnonzero(labels == label)
        if head.regions.vertex_part[ids[0]] != SKIN:
            near = np.unique(tree.query(placed[ids], k=PART_SKIN)[1])
            out[ids] += moved[near].mean(0)
    return out


def _classify(vertices, labels, head, placed):
    """What each user component is: (V,) part per vertex, and {component label: bundled vertex
    ids} for those that follow a bundled eyeball or teeth rigidly. The largest component is the
    skin. Another is taken for the bundled eyeball, teeth row or tongue (as placed by the rigid
    fit) it overlaps best: the smallest mean distance from each one's vertices to the other's
    nearest, both ways, within PART_MATCH of that part's RMS radius. Any other component is OTHER
    (lashes, a separate scalp)."""
    head_labels = _components(head.faces.astype(np.int64), head.num_vertices)
    parts = []
    for source in np.unique(head_labels):
        ids = np.flatnonzero(head_labels == source)
        part = int(head.regions.vertex_part[ids[0]])
        if part != SKIN:
            rms = np.sqrt(((placed[ids] - placed[ids].mean(0)) ** 2).sum(1).mean())
            parts.append((ids, part, cKDTree(placed[ids]), rms))
    sizes = np.bincount(labels)
    part_of = np.where(labels == np.argmax(sizes), SKIN, OTHER)
    follow: dict[int, np.ndarray] = {}
    for label in np.flatnonzero(sizes):
        if label == np.argmax(sizes):
            continue
        mine = np.flatnonzero(labels == label)
        own = cKDTree(vertices[mine])
        fits = [
            ((tree.query(vertices[mine])[0].mean() + own.query(placed[ids])[0].mean()) / 2 / r, i)
            for i, (ids, _, tree, r) in enumerate(parts)
        ]
        score, best = min(fits) if fits else (np.inf, 0)
        if score < PART_MATCH:
            ids, part = parts[best][:2]
            part_of[mine] = part
            if part != TONGUE:  # the tongue bends (tongueOut): closest-point offsets
                follow[int(label)] = ids
    return part_of, follow


def _user_gradients(vertices, faces, registered, placed, skin_faces, shapes, radius):
    """(52, F, 3, 3) the deformation gradient each user triangle takes from the (S, 3)
    ``registered`` skin (the ``SAMPLES`` of the triangle matched to their closest points on it,
    facing the same way), in the user's axes, fading to the identity (no motion) far from the
    head.

    A shape's gradient Q on a bundled triangle is I + D, D its displacement gradient. Sumner and
    Popovic give the user's triangle Q itself, so a displacement scales with the triangle it sits
    on; we give it I + R D R^T G^-1, G the registration's own gradient (from the rigidly
    ``placed`` (S, 3) skin to the registered one): the displacement field is carried along the
    registration, and where the heads are alike in shape (G = I) the two agree. A user triangle
    larger than the bundled one under its centre (a coarser mesh) spans several, whose gradients
    do not add up to its own: it takes instead the affine fit of the carried displacements at its
    samples (:func:`fitted_gradients`), blended in as its area grows from one to two times."""
    source = deformation_gradients(placed, skin_faces, shapes)
    pull = frames(placed, skin_faces) @ np.linalg.inv(
        frames(registered, skin_faces) + 1e-12 * np.eye(3)
    )
    tri = vertices[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(normal, axis=1)
    normal /= np.maximum(area, 1e-30)[:, None]
    # The fit's samples, and three more halfway from the centroid to the corners: the carried
    # gradients are averaged over the centroid and these (the corners may fall across a fold).
    inner = np.concatenate([SAMPLES, (SAMPLES[:3] + SAMPLES[-1]) / 2])
    samples = np.einsum("sc,fcx->fsx", inner, tri).reshape(-1, 3)
    match, bary, dist = closest_points(
        samples, registered, skin_faces, np.repeat(normal, len(inner), axis=0)
    )
    near, far = FALLOFF[0] * radius, FALLOFF[1] * radius
    fade = np.clip((far - dist) / (far - near), 0.0, 1.0)  # (F * samples,)
    weights, corners = bary * fade[:, None], skin_faces[match]
    match = match.reshape(len(faces), -1)
    centre = match[:, len(SAMPLES) - 1]  # SAMPLES ends with the centroid
    bundled = registered[skin_faces[centre]]
    bundled_area = np.linalg.norm(
        np.cross(bundled[:, 1] - bundled[:, 0], bundled[:, 2] - bundled[:, 0]), axis=1
    )
    coarse = np.clip(area / np.maximum(bundled_area, 1e-30) - 1.0, 0.0, 1.0)[:, None, None]
    own_fade = fade.reshape(len(faces), -1)[:, len(SAMPLES) - 1, None, None]
    coarse_any = bool(coarse.any())
    out = np.empty((len(shapes), len(faces), 3, 3))
    for k in range(len(shapes)):  # one shape at a time: (F, samples, 3, 3) is large on dense meshes
        carried = (source[k] - np.eye(3)) @ pull  # (S faces, 3, 3) displacement gradients
        local = own_fade * carried[match[:, len(SAMPLES) - 1 :]].mean(axis=1)
        out[k] = np.eye(3) + local
        if coarse_any:  # triangles larger than the bundled ones take the fitted gradient
            sampled = np.einsum("pc,pcx->px", weights, shapes[k][corners])
            sampled = sampled.reshape(len(faces), -1, 3)[None, :, : len(SAMPLES)]
            fitted = fitted_gradients(vertices, faces, sampled)[0]
            out[k] += coarse * (fitted - np.eye(3) - local)
    return out
