"""Binary glTF 2.0 (.glb): one mesh whose morph targets are the ARKit blendshapes (or a PCA basis
of the motion) and one animation of their weights."""

from __future__ import annotations

import json
import re
import struct
from pathlib import Path

import numpy as np

from talkmesh.animation import Animation
from talkmesh.constants import MOTION_FPS
from talkmesh.face.arkit import ARKIT_NAMES, arkit_index
from talkmesh.face.geometry import vertex_normals
from talkmesh.face.head_motion import quaternions
from talkmesh.output.files import finite
from talkmesh.output.morph import MorphRig, morph_rig

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
    """The binary chunk of a .glb, with one bufferView and accessor per array. The arrays are
    kept as they are (little-endian, contiguous: views of the caller's, not copies) and written
    one after the other (:meth:`write`): 52 targets on a million vertices are 750 MB, which a
    growing bytearray would hold twice while it reallocates."""

    def __init__(self) -> None:
        self.chunks: list[np.ndarray | bytes] = []
        self.size = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def write(self, f) -> None:
        for chunk in self.chunks:
            f.write(memoryview(chunk).cast("B"))

    def add(
        self, array: np.ndarray, kind: str, *, target: int | None = None, bounds: bool = False
    ) -> int:
        """Append (N,) or (N, C) ``array`` as an accessor of type ``kind``; returns its index."""
        array = np.ascontiguousarray(array)
        pad = -self.size % 4  # accessors must be aligned to their components
        if pad:
            self.chunks.append(b"\0" * pad)
            self.size += pad
        view = {"buffer": 0, "byteOffset": self.size, "byteLength": array.nbytes}
        if target is not None:
            view["target"] = target
        self.chunks.append(array.astype(array.dtype.newbyteorder("<"), copy=False))
        self.size += array.nbytes
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


def export_glb(anim: Animation, path: Path, *, clip: bool = True) -> None:
    """Binary glTF 2.0: one mesh with morph targets and a LINEAR ``weights`` animation.

    Target names are in ``mesh.extras.targetNames`` (three.js and Blender read them); normals are
    those of the neutral face. ``clip`` False writes the rigged mesh alone, without an animation
    (``talkmesh rig``: viewers that play a file's first clip would play a still one).
    """
    rig = morph_rig(anim)
    buf = _GlbBuffer()
    attributes = {
        "POSITION": buf.add(rig.base, "VEC3", target=ARRAY_BUFFER, bounds=True),
        "NORMAL": buf.add(vertex_normals(rig.neutral(), anim.faces), "VEC3", target=ARRAY_BUFFER),
    }
    base_color = [0.8, 0.62, 0.52, 1.0]  # skin, unless the vertices carry their colours
    if anim.colors is not None:
        colors = np.asarray(anim.colors, np.float32)
        assert colors.shape == (anim.num_vertices, 3), colors.shape
        # glTF's COLOR_0 is linear; the colours are sRGB (IEC 61966-2-1)
        linear = np.where(colors <= 0.04045, colors / 12.92, ((colors + 0.055) / 1.055) ** 2.4)
        attributes["COLOR_0"] = buf.add(linear.astype(np.float32), "VEC3", target=ARRAY_BUFFER)
        base_color = [1.0, 1.0, 1.0, 1.0]
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
    sampler = _weights_sampler(anim, rig, buf) if clip else None
    nodes, samplers, channels = _nodes(anim, buf, sampler)
    gltf = {
        "asset": {"version": "2.0", "generator": "talkmesh"},
        "scene": 0,
        "scenes": [{"nodes": [len(nodes) - 1]}],
        "nodes": nodes,
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
                    "baseColorFactor": base_color,
                    "metallicFactor": 0.0,
                    "roughnessFactor": 0.6,
                },
            }
        ],
    }
    if clip:
        gltf["animations"] = [
            {
                "name": "talk",
                "extras": {"fps": float(anim.fps)},  # for one-frame files, whose times cannot tell
                "samplers": samplers,
                "channels": channels,
            }
        ]
    gltf.update(
        {
            "buffers": [{"byteLength": buf.size}],
            "bufferViews": buf.views,
            "accessors": buf.accessors,
        }
    )
    write_glb(path, gltf, buf)


def _weights_sampler(anim: Animation, rig: MorphRig, buf: _GlbBuffer) -> dict:
    """The rig's (T, K) weights as a LINEAR sampler, a key per frame."""
    times = (np.arange(anim.num_frames, dtype=np.float64) / anim.fps).astype(np.float32)
    return {
        "input": buf.add(times, "SCALAR", bounds=True),
        "output": buf.add(rig.weights.ravel(), "SCALAR"),
        "interpolation": "LINEAR",
    }


def _nodes(anim: Animation, buf: _GlbBuffer, sampler: dict | None) -> tuple[list, list, list]:
    """The scene's nodes (the mesh first, the scene's root last) and the ``talk`` animation's
    samplers and channels (none without a ``sampler``): the morph weights, and the head pose on a
    parent node when there is one."""
    nodes: list[dict] = [{"name": "face", "mesh": 0}]
    samplers: list = []
    channels: list = []
    if sampler is not None:
        samplers.append(sampler)
        channels.append({"sampler": 0, "target": {"node": 0, "path": "weights"}})
        if anim.head_pose is not None:  # the head's motion: a parent node rotating and moving
            frame = None if anim.pose_frame is None else np.asarray(anim.pose_frame, np.float64)
            if frame is not None:  # the pose acts in its own frame: into it below the head node
                nodes.append(
                    {"name": "pose frame", "children": [0], "matrix": _matrix(np.linalg.inv(frame))}
                )
            nodes.append({"name": "head", "children": [len(nodes) - 1]})
            head = len(nodes) - 1
            _head_channels(buf, anim.head_pose, sampler["input"], head, samplers, channels)
            if frame is not None:  # ... and back out of it above
                nodes.append({"name": "user frame", "children": [head], "matrix": _matrix(frame)})
    if anim.to_gltf is not None and not np.allclose(anim.to_gltf, np.eye(4)):
        # the user's frame (units, up-axis) to glTF's, as the root: the vertices stay as given
        child = len(nodes) - 1
        nodes.append({"name": "root", "children": [child], "matrix": _matrix(anim.to_gltf)})
    return nodes, samplers, channels


def _matrix(matrix: np.ndarray) -> list[float]:
    """A (4, 4) matrix as a glTF node's ``matrix`` (column-major)."""
    return np.asarray(matrix, np.float64).T.ravel().tolist()


def _head_channels(
    buf: _GlbBuffer, pose: np.ndarray, times: int, node: int, samplers: list, channels: list
) -> None:
    """The (T, 6) head pose as LINEAR rotation (unit quaternions) and translation samplers of
    ``node``, keyed at the accessor ``times``."""
    quats = quaternions(pose[:, :3]).astype(np.float32)
    for path, values, kind in (("rotation", quats, "VEC4"), ("translation", pose[:, 3:], "VEC3")):
        output = buf.add(np.ascontiguousarray(values, np.float32), kind)
        samplers.append({"input": times, "output": output, "interpolation": "LINEAR"})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": node, "path": path}})


def export_rig_glb(anim: Animation, path: Path) -> None:
    """:func:`export_glb` without an animation: a rigged mesh (``NAME.rig.glb``, or
    ``format="rig.glb"``) whose morph targets an avatar clip or a player drives."""
    export_glb(anim, path, clip=False)


def write_glb(path: Path, gltf: dict, binary: _GlbBuffer) -> None:
    """:func:`glb_bytes` written to ``path`` piece by piece, the binary chunk straight from the
    arrays it holds (no copy of it is made)."""
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    pad = b"\0" * (-binary.size % 4)
    length = 12 + 8 + len(text) + 8 + binary.size + len(pad)
    with open(path, "wb") as f:
        f.write(struct.pack("<III", GLB_MAGIC, 2, length))
        f.write(struct.pack("<II", len(text), GLB_JSON))
        f.write(text)
        f.write(struct.pack("<II", binary.size + len(pad), GLB_BIN))
        binary.write(f)
        f.write(pad)


def glb_bytes(gltf: dict, binary: bytes) -> bytes:
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
    vertices = finite(rig.vertices(), "vertices")
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
        fps=fps or stored_fps or MOTION_FPS,
        weights=weights,
        weight_names=weight_names,
        template=rig.neutral(),
        basis=basis,
    )
