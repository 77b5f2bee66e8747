"""Small rigged avatars written by the tests: the kinds of .glb/.vrm files users bring.

``make_avatar`` writes a skinned head, teeth and tongue (three meshes whose morph targets carry
ARKit names in three exporters' spellings), a beard-less hat without morph targets, a PNG texture,
a skin with two joints and an existing idle animation of the neck joint.
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np

HEAD_NAMES = [
    "blendShape1.jawOpen",
    "blendShape1.eyeBlinkLeft",
    "blendShape1.eyeBlinkRight",
    "blendShape1.mouthSmileLeft",
    "blendShape1.mouthFunnel",
    "blendShape1.browInnerUp",
]
TEETH_NAMES = ["JawOpen", "MouthFunnel", "CustomSculpt"]
TONGUE_NAMES = ["jaw_open", "tongue_out"]
VISEME_NAMES = [
    "viseme_sil",
    "viseme_PP",
    "viseme_aa",
    "viseme_O",
    "viseme_U",
    "eyeBlinkLeft",
    "eyeBlinkRight",
]
HEAD_DRIVEN = {
    "jawOpen",
    "eyeBlinkLeft",
    "eyeBlinkRight",
    "mouthSmileLeft",
    "mouthFunnel",
    "browInnerUp",
    "tongueOut",
}


def png_bytes(size: int = 4) -> bytes:
    """A tiny RGB PNG (a checker), written by hand so the test needs no imaging library."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    rows = b"".join(
        b"\0"
        + bytes(c for x in range(size) for c in ((200, 90, 80) if (x + y) % 2 else (40, 40, 40)))
        for y in range(size)
    )
    header = struct.pack(">IIBBBBB", size, size, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows))
        + chunk(b"IEND", b"")
    )


class _Builder:
    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, raw: bytes, target: int | None = None) -> int:
        self.data += b"\0" * (-len(self.data) % 4)
        v = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(raw)}
        if target:
            v["target"] = target
        self.data += raw
        self.views.append(v)
        return len(self.views) - 1

    def accessor(
        self, array: np.ndarray, kind: str, target: int | None = None, bounds=False
    ) -> int:
        array = np.ascontiguousarray(array)
        code = {np.float32: 5126, np.uint16: 5123, np.uint8: 5121}[array.dtype.type]
        acc = {
            "bufferView": self.view(array.tobytes(), target),
            "componentType": code,
            "count": int(array.shape[0]),
            "type": kind,
        }
        if bounds:
            flat = array.reshape(len(array), -1)
            acc["min"], acc["max"] = flat.min(0).tolist(), flat.max(0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1


def _box(center, size) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box: 8 vertices (float32), 12 triangles (uint16)."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float32)
    v = (np.asarray(center, np.float32) + 0.5 * np.asarray(size, np.float32) * corners).astype(
        np.float32
    )
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return v, np.array(f, np.uint16).ravel()


def _mesh(
    b: _Builder,
    name,
    center,
    size,
    names,
    *,
    skinned=False,
    material=None,
    uv=False,
    names_on_primitive=False,
) -> dict:
    v, f = _box(center, size)
    attributes = {"POSITION": b.accessor(v, "VEC3", 34962, bounds=True)}
    if uv:
        attributes["TEXCOORD_0"] = b.accessor((v[:, :2] - v[:, :2].min(0)) * 5, "VEC2", 34962)
    if skinned:
        joints = np.zeros((len(v), 4), np.uint8)
        joints[v[:, 1] > center[1], 0] = 1
        attributes["JOINTS_0"] = b.accessor(joints, "VEC4", 34962)
        attributes["WEIGHTS_0"] = b.accessor(
            np.tile([[1, 0, 0, 0]], (len(v), 1)).astype(np.float32), "VEC4", 34962
        )
    rng = np.random.default_rng(len(names))
    targets = [
        {
            "POSITION": b.accessor(
                rng.normal(0, 0.004, v.shape).astype(np.float32), "VEC3", 34962, bounds=True
            )
        }
        for _ in names
    ]
    primitive = {
        "attributes": attributes,
        "indices": b.accessor(f, "SCALAR", 34963),
        "targets": targets,
    }
    if material is not None:
        primitive["material"] = material
    mesh = {"name": name, "primitives": [primitive], "weights": [0.0] * len(names)}
    if names_on_primitive:
        primitive["extras"] = {"targetNames": names}
    else:
        mesh["extras"] = {"targetNames": names}
    return mesh


def make_avatar(
    path: Path, *, vrm: bool = False, visemes: bool = False, head_names: list[str] | None = None
) -> Path:
    """Write a test avatar to ``path`` (.glb, or .vrm with the VRM 0.x extension); ``head_names``
    replaces the head's morph target names (``visemes``: the viseme avatar's teeth and tongue)."""
    b = _Builder()
    image = b.view(png_bytes())
    names = (
        [VISEME_NAMES, ["viseme_aa", "viseme_O"], ["viseme_TH"]]
        if visemes
        else [HEAD_NAMES, TEETH_NAMES, TONGUE_NAMES]
    )
    if head_names is not None:
        names[0] = head_names
    meshes = [
        _mesh(
            b, "Head", (0, 1.6, 0), (0.16, 0.22, 0.18), names[0], skinned=True, material=0, uv=True
        ),
        _mesh(
            b,
            "Teeth",
            (0, 1.55, 0.06),
            (0.05, 0.02, 0.02),
            names[1],
            material=1,
            names_on_primitive=vrm,
        ),
        _mesh(b, "Tongue", (0, 1.54, 0.05), (0.03, 0.01, 0.04), names[2], material=1),
    ]
    hat_v, hat_f = _box((0, 1.75, 0), (0.2, 0.05, 0.2))
    meshes.append(
        {
            "name": "Hat",
            "primitives": [
                {
                    "attributes": {"POSITION": b.accessor(hat_v, "VEC3", 34962, bounds=True)},
                    "indices": b.accessor(hat_f, "SCALAR", 34963),
                    "material": 1,
                }
            ],
        }
    )
    inverse = np.tile(np.eye(4, dtype=np.float32).ravel(), (2, 1))
    inverse[1, 13] = -1.5  # the neck joint sits at y = 1.5 m
    ibm = b.accessor(inverse, "MAT4")
    times = b.accessor(np.array([0.0, 1.0, 2.0], np.float32), "SCALAR", bounds=True)
    sway = np.array([[0, 0, 0, 1], [0, 0.087, 0, 0.996], [0, 0, 0, 1]], np.float32)
    rotations = b.accessor(sway, "VEC4")
    gltf = {
        "asset": {"version": "2.0", "generator": "talkmesh tests"},
        "scene": 0,
        "scenes": [{"name": "Scene", "nodes": [0, 2, 3, 4, 5]}],
        "nodes": [
            {"name": "Hips", "children": [1]},
            {"name": "Neck", "translation": [0, 1.5, 0]},
            {"name": "HeadMesh", "mesh": 0, "skin": 0},
            {"name": "TeethMesh", "mesh": 1},
            {"name": "TongueMesh", "mesh": 2},
            {"name": "HatMesh", "mesh": 3, "translation": [0, 0.01, 0]},
        ],
        "meshes": meshes,
        "skins": [{"name": "Armature", "joints": [0, 1], "inverseBindMatrices": ibm}],
        "materials": [
            {
                "name": "Skin",
                "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0},
            },
            {"name": "Plain", "pbrMetallicRoughness": {"baseColorFactor": [0.9, 0.9, 0.85, 1.0]}},
        ],
        "textures": [{"sampler": 0, "source": 0}],
        "samplers": [{"magFilter": 9729, "minFilter": 9729}],
        "images": [{"name": "skin", "bufferView": image, "mimeType": "image/png"}],
        "animations": [
            {
                "name": "Idle",
                "samplers": [{"input": times, "output": rotations, "interpolation": "LINEAR"}],
                "channels": [{"sampler": 0, "target": {"node": 1, "path": "rotation"}}],
            }
        ],
        "buffers": [{"byteLength": len(b.data)}],
        "bufferViews": b.views,
        "accessors": b.accessors,
    }
    if vrm:
        gltf["extensionsUsed"] = ["VRM"]
        gltf["extensions"] = {
            "VRM": {
                "exporterVersion": "talkmesh-tests",
                "specVersion": "0.0",
                "meta": {
                    "title": "Test avatar",
                    "version": "1",
                    "author": "talkmesh tests",
                    "allowedUserName": "Everyone",
                    "licenseName": "CC0",
                },
                "humanoid": {
                    "humanBones": [{"bone": "neck", "node": 1}, {"bone": "hips", "node": 0}]
                },
                "blendShapeMaster": {
                    "blendShapeGroups": [
                        {
                            "name": "A",
                            "presetName": "a",
                            "binds": [{"mesh": 0, "index": 0, "weight": 100}],
                        }
                    ]
                },
            }
        }
    text = json.dumps(gltf).encode()
    text += b" " * (-len(text) % 4)
    binary = bytes(b.data) + b"\0" * (-len(b.data) % 4)
    body = (
        struct.pack("<II", len(text), 0x4E4F534A)
        + text
        + struct.pack("<II", len(binary), 0x004E4942)
        + binary
    )
    path.write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)
    return path


# --- the bundled head as the three kinds of avatar ------------------------------------------

# Shapes of the VRM presets and the Oculus visemes, as sums of ARKit shapes (plausible mouths for
# pictures and tests; an exporter's own shapes differ).
VRM_PRESETS = {
    "aa": {"jawOpen": 0.8},
    "ih": {"jawOpen": 0.2, "mouthSmileLeft": 0.6, "mouthSmileRight": 0.6},
    "ou": {"jawOpen": 0.15, "mouthPucker": 0.9},
    "ee": {"jawOpen": 0.25, "mouthStretchLeft": 0.6, "mouthStretchRight": 0.6},
    "oh": {"jawOpen": 0.35, "mouthFunnel": 0.8},
    "blink": {"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0},
}
VISEME_SHAPES = {
    "sil": {},
    "PP": {"mouthPressLeft": 0.6, "mouthPressRight": 0.6},
    "FF": {"jawOpen": 0.1, "mouthRollLower": 0.8},
    "TH": {"jawOpen": 0.2, "tongueOut": 0.6},
    "DD": {"jawOpen": 0.2},
    "kk": {"jawOpen": 0.25},
    "CH": {"jawOpen": 0.15, "mouthFunnel": 0.6},
    "SS": {"jawOpen": 0.1, "mouthStretchLeft": 0.4, "mouthStretchRight": 0.4},
    "nn": {"jawOpen": 0.15},
    "RR": {"jawOpen": 0.15, "mouthPucker": 0.4},
    "aa": {"jawOpen": 0.8},
    "E": {"jawOpen": 0.25, "mouthStretchLeft": 0.6, "mouthStretchRight": 0.6},
    "I": {"jawOpen": 0.2, "mouthSmileLeft": 0.6, "mouthSmileRight": 0.6},
    "O": {"jawOpen": 0.35, "mouthFunnel": 0.8},
    "U": {"jawOpen": 0.15, "mouthPucker": 0.9},
}
HEAD_KINDS = ("arkit", "vrm", "visemes")


def head_avatar(path: Path, kind: str = "arkit") -> Path:
    """The bundled head in its colours (``COLOR_0``) as an avatar of ``kind``: ``arkit`` (its 52
    ARKit shapes, as ``talkmesh rig`` writes them), ``vrm`` (a VRM 1.0 with only the mouth and
    blink presets, bound to targets named as VRoid names them) or ``visemes`` (the 15 Oculus
    visemes and the two blinks, as Ready Player Me exports them)."""
    from talkmesh.animation import Animation
    from talkmesh.face.arkit import ARKIT_NAMES
    from talkmesh.face.assets import load_head
    from talkmesh.face.look import head_colors
    from talkmesh.output.avatar import glb_bytes, read_glb
    from talkmesh.output.formats import save_animation

    head = load_head()
    shape = {n: head.blendshapes[ARKIT_NAMES.index(n)] for n in ARKIT_NAMES}

    def mix(parts: dict[str, float]) -> np.ndarray:
        return sum((w * shape[n] for n, w in parts.items()), np.zeros_like(head.template))

    if kind == "arkit":
        names, basis = list(ARKIT_NAMES), head.blendshapes
    elif kind == "vrm":
        names = [f"Fcl_MTH_{p.upper()}" if p != "blink" else "Fcl_EYE_Close" for p in VRM_PRESETS]
        basis = np.stack([mix(parts) for parts in VRM_PRESETS.values()])
    elif kind == "visemes":
        names = [f"viseme_{v}" for v in VISEME_SHAPES] + ["eyeBlinkLeft", "eyeBlinkRight"]
        blinks = [shape["eyeBlinkLeft"], shape["eyeBlinkRight"]]
        basis = np.stack([mix(parts) for parts in VISEME_SHAPES.values()] + blinks)
    else:
        raise ValueError(f"kind {kind!r} is not one of {HEAD_KINDS}")
    rig = Animation(
        head.template[None],
        head.faces,
        30.0,
        weights=np.zeros((1, len(names)), np.float32),
        weight_names=names,
        template=head.template,
        basis=basis.astype(np.float32),
        colors=head_colors(head),
    )
    plain = path.with_name(path.stem + ".plain.rig.glb")
    save_animation(rig, plain, format="rig.glb")
    if kind != "vrm":
        plain.replace(path)
        return path
    gltf, binary = read_glb(plain)
    plain.unlink()
    node = next(k for k, n in enumerate(gltf["nodes"]) if "mesh" in n)
    gltf["extensionsUsed"] = ["VRMC_vrm"]
    gltf["extensions"] = {
        "VRMC_vrm": {
            "specVersion": "1.0",
            "meta": {"name": "talkmesh head", "authors": ["talkmesh tests"]},
            "humanoid": {"humanBones": {}},
            "expressions": {
                "preset": {
                    p: {"morphTargetBinds": [{"node": node, "index": i, "weight": 1.0}]}
                    for i, p in enumerate(VRM_PRESETS)
                }
            },
        }
    }
    path.write_bytes(glb_bytes(gltf, binary))
    return path
