"""An avatar as the renderer draws it: every mesh of a .glb/.vrm, posed frame by frame as its first
animation clip moves it (the clip a viewer plays, the speech clip of ``animate --avatar``).

``load_scene(gltf, binary, source)`` walks the default scene's node tree (glTF 2.0 spec, 3.5) and
gathers every triangle primitive (strips and fans turned into triangles; points and lines
skipped) into one vertex array with one triangle list and one colour per vertex: the material's
``baseColorFactor`` times its ``baseColorTexture`` sampled at the vertex's texture coordinate
(and ``COLOR_0``), so that :class:`~talkmesh.output.raster.Renderer` draws the whole avatar in
one call. :meth:`AvatarScene.vertices` poses frame ``t``: the clip's channels (LINEAR, STEP or
CUBICSPLINE samplers, sampled at the clip's frame rate) set the nodes' translation, rotation,
scale and morph weights; each primitive is morphed (spec 3.7.2.2), then skinned by its joints'
world matrices times their inverse bind matrices (3.7.3), or moved by its node's world matrix.

What the renderer cannot show is approximated: a texture is one colour per vertex (sampled from
a copy shrunk to at most :data:`TEXTURE_SIZE` pixels a side, so a vertex takes its
neighbourhood's mean colour), and a blended or masked material keeps the triangles whose
vertices are opaque on average. VRM 0.x avatars face -z: they are turned half a turn about +y so
that, as every other glTF, they face the camera (+z). The renderer aims at :attr:`focus`, the
head: the vertices skinned to the head bone (:func:`~talkmesh.output.avatar_head.head_node`) or
its children, else those the morph targets move (the face, with a margin), else everything.
"""

from __future__ import annotations

import base64
import io
import json
import os
import struct
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from talkmesh.errors import TalkmeshError
from talkmesh.output.avatar_head import head_node

if TYPE_CHECKING:
    import scipy.sparse

MAX_JSON_BYTES = 256 * 2**20  # a glTF JSON chunk larger than this is not read to classify the file
MAX_ZEROS = 2**26  # values an accessor without a buffer view may stand for (sparse bases)
TEXTURE_SIZE = 64  # pixels a side a texture is shrunk to before vertices sample it
FOCUS_MARGIN = 0.2  # the moving vertices' box grows by this share of its size on each side
ALPHA_CUTOFF = 0.5  # glTF's default ``alphaCutoff``, used for BLEND materials too
FPS_DEFAULT = 30.0  # a clip whose keys do not tell its rate
MIN_KEY_FPS, MAX_KEY_FPS = 10.0, 240.0  # keys this dense are taken as the clip's frames
TRIANGLES, TRIANGLE_STRIP, TRIANGLE_FAN = 4, 5, 6  # primitive modes (spec 3.7.2.1)
UNREADABLE = {  # extensions whose data this reader cannot decode
    "KHR_draco_mesh_compression": "Draco-compressed meshes",
    "EXT_meshopt_compression": "meshopt-compressed buffers",
}
_COMPONENTS = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_NORMALIZE = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def read_accessor(gltf: dict, binary: bytes, index: int) -> np.ndarray:
    """(count, width) values of accessor ``index``: normalized integers as floats in [0, 1] or
    [-1, 1], sparse substitutions applied, interleaved views (``byteStride``) read in place."""
    acc = gltf["accessors"][index]
    code, width, count = acc["componentType"], _WIDTHS[acc["type"]], int(acc["count"])
    dtype = np.dtype(_COMPONENTS[code])
    if "bufferView" in acc:
        out = _view_array(
            gltf, binary, acc["bufferView"], acc.get("byteOffset", 0), dtype, count, width
        )
    elif count * width > MAX_ZEROS:  # zeros the file does not hold: a count to check first
        raise ValueError(f"accessor {index} claims {count} elements without data")
    else:
        out = np.zeros((count, width), dtype)
    sparse = acc.get("sparse")
    if sparse:
        n = int(sparse["count"])
        idx, val = sparse["indices"], sparse["values"]
        rows = _view_array(
            gltf, binary, idx["bufferView"], idx.get("byteOffset", 0),
            np.dtype(_COMPONENTS[idx["componentType"]]), n, 1, packed=True,
        )[:, 0].astype(np.int64)  # fmt: skip
        if len(rows) and (rows.min() < 0 or rows.max() >= count):
            raise ValueError(f"accessor {index}'s sparse indices run past its {count} elements")
        out = out.copy()
        out[rows] = _view_array(
            gltf, binary, val["bufferView"], val.get("byteOffset", 0), dtype, n, width, packed=True
        )
    if acc.get("normalized") and code in _NORMALIZE:
        return np.maximum(out.astype(np.float32) / _NORMALIZE[code], -1.0)
    return out


def _view_array(gltf, binary, view_index, offset, dtype, count, width, packed=False):
    view = gltf["bufferViews"][view_index]
    buffer = gltf["buffers"][view.get("buffer", 0)]
    if view.get("buffer", 0) != 0 or "uri" in buffer:
        raise ValueError("binary data in an external file")
    start = int(view.get("byteOffset", 0)) + int(offset)
    element = dtype.itemsize * width
    stride = element if packed else int(view.get("byteStride") or element)
    end = start + stride * (count - 1) + element if count else start
    if end > int(view.get("byteOffset", 0)) + int(view["byteLength"]) or end > len(binary):
        raise ValueError(f"buffer view {view_index} runs past the end of the binary chunk")
    return np.ndarray(
        (count, width), dtype=dtype, buffer=binary, offset=start, strides=(stride, dtype.itemsize)
    ).copy()


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (x, y, z, w) -> (..., 3, 3) rotation matrices."""
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-12)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def _trs(t: np.ndarray, r: np.ndarray, s: np.ndarray) -> np.ndarray:
    """A node's local matrix T * R * S (spec 3.5.3)."""
    m = np.eye(4)
    m[:3, :3] = _quat_matrix(np.asarray(r, np.float64)) * np.asarray(s, np.float64)[None, :]
    m[:3, 3] = t
    return m


@dataclass
class _Primitive:
    """One triangle primitive of a mesh instanced by a node."""

    node: int
    mesh: int
    positions: np.ndarray  # (N, 3) float64, the mesh's own frame
    targets: np.ndarray | None  # (K, N, 3) float32 morph target offsets
    skin: int | None
    joints: np.ndarray | None = None  # (N, J) skin joint slots
    weights: np.ndarray | None = None  # (N, J) their weights
    skinning: scipy.sparse.csr_matrix | None = None  # (N, joints of the skin) the weights
    start: int = 0  # its first vertex in the scene's array
    cache: tuple | None = field(default=None, repr=False)


@dataclass
class _Track:
    """One channel sampled on the clip's frames: (T, C) values of ``path`` of ``node``."""

    node: int
    path: str
    values: np.ndarray


class AvatarScene:
    """All the triangles of an avatar, posed frame by frame as its first clip moves them.

    Attributes:
        faces: (F, 3) int32 triangles into the scene's vertices.
        colors: (V, 3) sRGB colour per vertex in [0, 1].
        focus: (V,) bool, the vertices the camera aims at (the head).
        fps: the clip's frame rate; num_frames: its frames (1 without a clip).
        clip: the clip's name ("" without one).
    """

    def __init__(self, gltf: dict, binary: bytes, source: str) -> None:
        self._gltf, self._binary, self.source = gltf, binary, source
        nodes = gltf.get("nodes") or []
        self._rest = [self._rest_trs(n) for n in nodes]
        self._local = [r if isinstance(r, np.ndarray) else _trs(*r) for r in self._rest]
        self._parent = {c: k for k, n in enumerate(nodes) for c in n.get("children") or []}
        self._order = self._scene_nodes()
        self._turn = np.eye(4)
        if (gltf.get("extensions") or {}).get("VRM") is not None:  # VRM 0.x faces -z
            self._turn = np.diag([-1.0, 1.0, -1.0, 1.0])
        self._skins = [self._read_skin(s) for s in gltf.get("skins") or []]
        self.clip, self.fps, self.num_frames, self._tracks = self._read_clip()
        self._prims: list[_Primitive] = []
        faces, colors, start = [], [], 0
        for node in self._order:
            if isinstance(nodes[node].get("mesh"), int):
                for prim, tri, rgba in self._read_mesh(node):
                    prim.start, start = start, start + len(prim.positions)
                    self._prims.append(prim)
                    faces.append(tri + prim.start)
                    colors.append(rgba)
        if not self._prims or not sum(len(f) for f in faces):
            raise TalkmeshError(
                f"{source} has no triangle meshes to draw: export the avatar with its meshes "
                "(triangles, not points or lines)"
            )
        self.faces = np.concatenate(faces).astype(np.int32)
        self.colors = np.concatenate(colors).astype(np.float32)
        self.focus = self._focus()

    @property
    def num_vertices(self) -> int:
        return len(self.colors)

    @property
    def animated(self) -> bool:
        """Whether its first clip moves a node or a morph target."""
        return bool(self._tracks)

    # --- the node tree and the clip ----------------------------------------------------------

    @staticmethod
    def _rest_trs(node: dict) -> np.ndarray | tuple:
        if "matrix" in node:
            return np.asarray(node["matrix"], np.float64).reshape(4, 4).T
        return (
            np.asarray(node.get("translation", [0, 0, 0]), np.float64),
            np.asarray(node.get("rotation", [0, 0, 0, 1]), np.float64),
            np.asarray(node.get("scale", [1, 1, 1]), np.float64),
        )

    def _scene_nodes(self) -> list[int]:
        """The default scene's nodes, parents before children (each once)."""
        gltf, nodes = self._gltf, self._gltf.get("nodes") or []
        scenes = gltf.get("scenes") or []
        if scenes:
            roots = list(scenes[gltf.get("scene", 0)].get("nodes") or [])
        else:
            roots = [k for k in range(len(nodes)) if k not in self._parent]
        order, seen, stack = [], set(), roots[::-1]
        while stack:
            k = stack.pop()
            if k in seen:
                continue
            seen.add(k)
            order.append(int(k))
            stack.extend((nodes[k].get("children") or [])[::-1])
        return order

    def _read_skin(self, skin: dict) -> tuple[list[int], np.ndarray]:
        joints = [int(j) for j in skin["joints"]]
        if "inverseBindMatrices" in skin:
            ibm = read_accessor(self._gltf, self._binary, skin["inverseBindMatrices"])
            ibm = ibm.astype(np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)
        else:
            ibm = np.tile(np.eye(4), (len(joints), 1, 1))
        if len(ibm) != len(joints):
            raise ValueError(f"a skin has {len(joints)} joints and {len(ibm)} bind matrices")
        return joints, ibm

    def _read_clip(self) -> tuple[str, float, int, list[_Track]]:
        """The first animation's channels, sampled on a uniform frame grid."""
        clips = self._gltf.get("animations") or []
        if not clips:
            return "", FPS_DEFAULT, 1, []
        clip = clips[0]
        keyed = []
        for channel in clip.get("channels") or []:
            target = channel["target"]
            if "node" not in target or target["path"] not in (
                "translation", "rotation", "scale", "weights",
            ):  # fmt: skip
                continue  # KHR_animation_pointer and the like: not a node's transform
            sampler = clip["samplers"][channel["sampler"]]
            times = read_accessor(self._gltf, self._binary, sampler["input"])[:, 0]
            values = read_accessor(self._gltf, self._binary, sampler["output"])
            keyed.append((int(target["node"]), target["path"], times.astype(np.float64), values,
                          sampler.get("interpolation", "LINEAR")))  # fmt: skip
        if not keyed:
            return str(clip.get("name", "")), FPS_DEFAULT, 1, []
        fps = _clip_fps(clip, [k[2] for k in keyed])
        start = min(float(k[2][0]) for k in keyed if len(k[2]))
        end = max(float(k[2][-1]) for k in keyed if len(k[2]))
        num_frames = max(1, round((end - start) * fps) + 1)
        grid = start + np.arange(num_frames) / fps
        tracks = [
            _Track(node, path, _sample(times, values, grid, kind, path))
            for node, path, times, values, kind in keyed
            if len(times)
        ]
        return str(clip.get("name", "")), fps, num_frames, tracks

    # --- meshes -------------------------------------------------------------------------------

    def _read_mesh(self, node: int):
        """(primitive, (Fp, 3) triangles, (Np, 3) sRGB colours) of node ``node``'s mesh."""
        gltf, binary = self._gltf, self._binary
        n = gltf["nodes"][node]
        m = int(n["mesh"])
        skin = n.get("skin") if isinstance(n.get("skin"), int) else None
        for primitive in gltf["meshes"][m].get("primitives") or []:
            mode = primitive.get("mode", TRIANGLES)
            if mode not in (TRIANGLES, TRIANGLE_STRIP, TRIANGLE_FAN):
                continue
            attributes = primitive["attributes"]
            positions = read_accessor(gltf, binary, attributes["POSITION"]).astype(np.float64)
            if positions.shape[1] != 3 or not len(positions):
                continue
            if "indices" in primitive:
                indices = read_accessor(gltf, binary, primitive["indices"])[:, 0].astype(np.int64)
            else:
                indices = np.arange(len(positions))
            tri = _triangles(indices, mode)
            if len(tri) and (tri.min() < 0 or tri.max() >= len(positions)):
                raise ValueError(f"mesh {m} has indices past its {len(positions)} vertices")
            targets = [
                read_accessor(gltf, binary, t["POSITION"]).astype(np.float64)
                if "POSITION" in t
                else np.zeros_like(positions)
                for t in primitive.get("targets") or []
            ]
            stacked = np.stack(targets).astype(np.float32) if targets else None
            prim = _Primitive(node, m, positions, stacked, skin)
            if skin is not None and "JOINTS_0" in attributes:
                sets = [k for k in range(8) if f"JOINTS_{k}" in attributes]
                joints = [read_accessor(gltf, binary, attributes[f"JOINTS_{k}"]) for k in sets]
                weights = [read_accessor(gltf, binary, attributes[f"WEIGHTS_{k}"]) for k in sets]
                prim.joints = np.concatenate(joints, axis=1).astype(np.int64)
                prim.weights = np.concatenate(weights, axis=1).astype(np.float64)
                num_joints = len(self._skins[skin][0])
                if prim.joints.max(initial=0) >= num_joints:
                    raise ValueError(f"mesh {m} names a joint its skin does not have")
                import scipy.sparse  # here: animate's output checks import this module

                rows = np.repeat(np.arange(len(positions)), prim.joints.shape[1])
                prim.skinning = scipy.sparse.csr_matrix(
                    (prim.weights.ravel(), (rows, prim.joints.ravel())),
                    shape=(len(positions), num_joints),
                )  # duplicate (vertex, joint) pairs add up, as the spec's sum does
            else:
                prim.skin = None
            rgba = self._colors(primitive, len(positions))
            yield prim, _opaque(tri, rgba, self._material(primitive)), _srgb(rgba[:, :3])

    def _material(self, primitive: dict) -> dict:
        index = primitive.get("material")
        materials = self._gltf.get("materials") or []
        return materials[index] if isinstance(index, int) else {}

    def _colors(self, primitive: dict, count: int) -> np.ndarray:
        """(N, 4) linear RGBA: base colour factor x texture x COLOR_0."""
        material = self._material(primitive)
        pbr = material.get("pbrMetallicRoughness") or {}
        rgba = np.tile(np.asarray(pbr.get("baseColorFactor", [1, 1, 1, 1]), np.float64), (count, 1))
        info = pbr.get("baseColorTexture")
        uv_name = f"TEXCOORD_{(info or {}).get('texCoord', 0)}"
        if info is not None and uv_name in primitive["attributes"]:
            texture = self._texture(int(info["index"]))
            if texture is not None:
                uv = read_accessor(self._gltf, self._binary, primitive["attributes"][uv_name])
                rgba *= _sample_texture(texture, uv.astype(np.float64))
        if "COLOR_0" in primitive["attributes"]:
            c = read_accessor(self._gltf, self._binary, primitive["attributes"]["COLOR_0"])
            rgba[:, : c.shape[1]] *= c.astype(np.float64)
        return rgba

    def _texture(self, index: int) -> np.ndarray | None:
        """(H, W, 4) linear RGBA of texture ``index``, shrunk; None if it cannot be decoded."""
        from talkmesh.output.labels import import_pil

        texture = self._gltf["textures"][index]
        source = texture.get("source")
        for ext in (texture.get("extensions") or {}).values():  # EXT_texture_webp and the like
            source = ext.get("source", source) if isinstance(ext, dict) else source
        if not isinstance(source, int):
            return None
        image = self._gltf["images"][source]
        try:
            if "bufferView" in image:
                data = _view_array(
                    self._gltf, self._binary, image["bufferView"], 0, np.dtype("u1"),
                    int(self._gltf["bufferViews"][image["bufferView"]]["byteLength"]), 1,
                )  # fmt: skip
                data = data.tobytes()
            elif str(image.get("uri", "")).startswith("data:"):
                data = base64.b64decode(image["uri"].split(",", 1)[1])
            else:
                return None
            Image, _, _ = import_pil()
            with Image.open(io.BytesIO(data)) as im:
                im = im.convert("RGBA")
                im.thumbnail((TEXTURE_SIZE, TEXTURE_SIZE), Image.Resampling.BOX)
                pixels = np.asarray(im, np.float64) / 255.0
        except Exception:  # an image PIL cannot read (KTX2, a broken PNG): the factor alone
            return None
        pixels[..., :3] = _linear(pixels[..., :3])
        return pixels

    # --- framing ------------------------------------------------------------------------------

    def _focus(self) -> np.ndarray:
        """(V,) bool: the head's vertices (see the module's docstring)."""
        rest = self.vertices(0)
        focus = np.zeros(self.num_vertices, bool)
        head = head_node(self._gltf)
        if head is not None:
            below = {head}
            for k in self._order:  # parents come first
                if self._parent.get(k) in below:
                    below.add(k)
            for p in self._prims:
                span = slice(p.start, p.start + len(p.positions))
                if p.skin is not None:
                    joints = np.asarray(self._skins[p.skin][0])[p.joints]
                    focus[span] = (p.weights * np.isin(joints, list(below))).sum(1) > 0.5
                else:
                    focus[span] = p.node in below
        if not focus.any():
            moved = np.zeros(self.num_vertices, bool)
            for p in self._prims:
                if p.targets is not None:
                    span = slice(p.start, p.start + len(p.positions))
                    moved[span] = np.abs(p.targets).max(axis=(0, 2)) > 0
            used = np.zeros(self.num_vertices, bool)
            used[self.faces.ravel()] = True
            moved &= used
            if moved.any():
                lo, hi = rest[moved].min(0), rest[moved].max(0)
                grow = FOCUS_MARGIN * (hi - lo).max()
                focus = used & np.all((rest >= lo - grow) & (rest <= hi + grow), axis=1)
        if not focus.any():
            focus[self.faces.ravel()] = True
        return focus

    # --- posing -------------------------------------------------------------------------------

    def _world(self, t: int) -> tuple[np.ndarray, dict[int, np.ndarray]]:
        """(N, 4, 4) world matrices of every node at frame ``t``, and the nodes' morph weights."""
        nodes = self._gltf.get("nodes") or []
        local = [list(r) if isinstance(r, tuple) else r for r in self._rest]
        weights: dict[int, np.ndarray] = {}
        for track in self._tracks:
            value = track.values[min(t, len(track.values) - 1)]
            if track.path == "weights":
                weights[track.node] = value
            elif isinstance(local[track.node], list):
                local[track.node][("translation", "rotation", "scale").index(track.path)] = value
        moved = {k.node for k in self._tracks if k.path != "weights"}
        world = np.tile(np.eye(4), (len(nodes), 1, 1))
        for k in self._order:
            m = _trs(*local[k]) if k in moved and isinstance(local[k], list) else self._local[k]
            parent = self._parent.get(k)
            world[k] = (self._turn if parent is None else world[parent]) @ m
        return world, weights

    def vertices(self, t: int) -> np.ndarray:
        """(V, 3) float32 vertices of frame ``t`` (0 <= t < num_frames), in the avatar's units."""
        world, animated = self._world(t)
        meshes = self._gltf["meshes"]
        out = np.empty((self.num_vertices, 3), np.float32)
        for p in self._prims:
            w = animated.get(p.node)
            if w is None:
                w = self._gltf["nodes"][p.node].get("weights") or meshes[p.mesh].get("weights")
            w = np.zeros(0) if p.targets is None else np.asarray(w if w is not None else [], float)
            if p.targets is not None and len(w) != len(p.targets):
                w = np.zeros(len(p.targets))
            if p.skin is not None:
                joints, ibm = self._skins[p.skin]
                matrices = world[joints] @ ibm
            else:
                matrices = world[p.node][None]
            key = (w.tobytes(), matrices.tobytes())
            if p.cache is None or p.cache[0] != key:
                p.cache = (key, self._pose(p, w, matrices))
            out[p.start : p.start + len(p.positions)] = p.cache[1]
        return out

    @staticmethod
    def _pose(p: _Primitive, w: np.ndarray, matrices: np.ndarray) -> np.ndarray:
        v = p.positions
        if p.targets is not None and w.any():  # a matrix-vector product over (K, N * 3)
            k = len(p.targets)
            v = v + (w.astype(np.float32) @ p.targets.reshape(k, -1)).reshape(v.shape)
        if p.skin is None:
            m = matrices[0]
            return v @ m[:3, :3].T + m[:3, 3]
        # each vertex's blend of its joints' matrices (spec 3.7.3.3): a sparse (N, J) weight
        # matrix times the (J, 12) top rows of the joint matrices
        blend = (p.skinning @ matrices[:, :3, :].reshape(len(matrices), 12)).reshape(-1, 3, 4)
        return np.einsum("nab,nb->na", blend[:, :, :3], v) + blend[:, :, 3]


def _clip_fps(clip: dict, times: list[np.ndarray]) -> float:
    """The clip's frame rate: ``extras.fps`` (talkmesh writes it), else its densest keys' when
    they are a key per frame, else :data:`FPS_DEFAULT`."""
    fps = (clip.get("extras") or {}).get("fps")
    if isinstance(fps, int | float) and 0 < fps <= 1000:
        return float(fps)
    densest = max(times, key=len)
    if len(densest) > 1 and densest[-1] > densest[0]:
        rate = round((len(densest) - 1) / (densest[-1] - densest[0]), 3)
        if MIN_KEY_FPS <= rate <= MAX_KEY_FPS:  # a key per frame
            return float(rate)
    return FPS_DEFAULT  # sparse keys (an idle's few poses): sampled at the video's usual rate


def _sample(times, values, grid, kind: str, path: str) -> np.ndarray:
    """(N,) key times and their values -> (len(grid), C) values at ``grid``."""
    n = len(times)
    values = values.astype(np.float64).reshape(n * (3 if kind == "CUBICSPLINE" else 1), -1)
    if kind == "CUBICSPLINE":  # in-tangent, value, out-tangent per key: the values
        values = values.reshape(n, 3, -1)[:, 1]
    if path == "weights":
        values = values.reshape(n, -1)
    if kind == "STEP":
        at = np.clip(np.searchsorted(times, grid, side="right") - 1, 0, n - 1)
        return values[at]
    if path == "rotation":  # normalised linear interpolation, close to slerp for dense keys
        values = values.copy()
        for k in range(1, n):  # the shorter way between neighbouring keys
            if np.dot(values[k], values[k - 1]) < 0:
                values[k] = -values[k]
    out = np.stack([np.interp(grid, times, values[:, c]) for c in range(values.shape[1])], 1)
    if path == "rotation":
        out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
    return out


def _triangles(indices: np.ndarray, mode: int) -> np.ndarray:
    """(F, 3) triangles of a TRIANGLES, TRIANGLE_STRIP or TRIANGLE_FAN index list."""
    if mode == TRIANGLES:
        return indices[: len(indices) // 3 * 3].reshape(-1, 3)
    if len(indices) < 3:
        return np.zeros((0, 3), np.int64)
    k = np.arange(len(indices) - 2)
    if mode == TRIANGLE_FAN:
        return np.stack([indices[k + 1], indices[k + 2], np.full_like(k, indices[0])], 1)
    even = k % 2 == 0  # a strip flips every other triangle to keep the winding (spec 3.7.2.1)
    a = np.where(even, indices[k], indices[k + 1])
    b = np.where(even, indices[k + 1], indices[k])
    return np.stack([a, b, indices[k + 2]], 1)


def _sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N, 4) texels at (N, 2) texture coordinates (repeating, nearest)."""
    h, w = texture.shape[:2]
    x = np.floor(np.mod(uv[:, 0], 1.0) * w).astype(np.int64).clip(0, w - 1)
    y = np.floor(np.mod(uv[:, 1], 1.0) * h).astype(np.int64).clip(0, h - 1)
    return texture[y, x]


def _opaque(tri: np.ndarray, rgba: np.ndarray, material: dict) -> np.ndarray:
    """The triangles a MASK or BLEND material shows: those opaque on average at their vertices."""
    mode = material.get("alphaMode", "OPAQUE")
    if mode == "OPAQUE" or not len(tri):
        return tri
    cutoff = float(material.get("alphaCutoff", ALPHA_CUTOFF)) if mode == "MASK" else ALPHA_CUTOFF
    return tri[rgba[tri, 3].mean(axis=1) >= cutoff]


def _linear(srgb: np.ndarray) -> np.ndarray:
    return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)


def _srgb(linear: np.ndarray) -> np.ndarray:
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)


def is_avatar(gltf: dict) -> bool:
    """Whether a .glb is more than the one morphing mesh talkmesh's own exports hold (a VRM, a
    skin, several meshes): then only :class:`AvatarScene` draws all of it."""
    if (gltf.get("extensions") or {}).keys() & {"VRM", "VRMC_vrm"} or gltf.get("skins"):
        return True
    return sum(isinstance(n.get("mesh"), int) for n in gltf.get("nodes") or []) > 1


def is_avatar_file(path: str | os.PathLike) -> bool:
    """:func:`is_avatar` of a .glb's JSON chunk, read alone (the binary chunk of a long
    animation is not loaded twice); False for a file that is no readable .glb (its reader then
    says what is wrong)."""
    try:
        with open(path, "rb") as f:
            header = f.read(20)
            if len(header) < 20 or header[:4] != b"glTF" or header[16:20] != b"JSON":
                return False
            (length,) = struct.unpack_from("<I", header, 12)
            if length > MAX_JSON_BYTES:
                return False
            gltf = json.loads(f.read(length).decode("utf-8"))
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(gltf, dict) and is_avatar(gltf)


def load_scene(gltf: dict, binary: bytes, source: str) -> AvatarScene:
    """The avatar of ``gltf`` (and its binary chunk) as an :class:`AvatarScene`.

    Raises:
        TalkmeshError: one line naming ``source``: no triangle meshes, compressed meshes the
            reader cannot decode, binary data in an external file, or JSON that does not follow
            the glTF 2.0 schema.
    """
    required = set(gltf.get("extensionsRequired") or []) | set(gltf.get("extensionsUsed") or [])
    for ext, what in UNREADABLE.items():
        if ext in required:
            raise TalkmeshError(
                f"{source}: its {what} ({ext}) cannot be drawn by talkmesh's renderer: export it "
                "without compression (Blender: uncheck Compression; or `gltf-transform copy`)"
            )
    try:
        return AvatarScene(gltf, binary, source)
    except TalkmeshError:
        raise
    except (AttributeError, TypeError, ValueError, KeyError, IndexError) as e:
        message = str(e)[:100]
        if "external file" in message:
            raise TalkmeshError(
                f"{source}: the avatar keeps its binary data in an external file: pack it into "
                "one self-contained .glb first"
            ) from None
        raise TalkmeshError(
            f"{source}: its glTF does not follow the glTF 2.0 schema ({type(e).__name__}: "
            f"{message}): export it again"
        ) from None
