"""Your own character: ARKit weights written as an animation clip into a copy of an avatar.

``animate_avatar("my.glb", weights, fps, "talking.glb")`` finds every mesh whose morph targets
carry ARKit names (in any of the spellings :mod:`talkmesh.face.arkit_names` knows: head, teeth,
tongue and beard meshes that share names move together), and writes ONE animation, ``talk``,
with a ``weights`` channel per node of those meshes, as the FIRST clip (viewers that play a
file's first clip, three.js examples, model-viewer, Blender's first action, play the speech); a
clip of the avatar named ``talk`` (an earlier run's) is replaced, the other clips follow it.
Avatars without ARKit mouth shapes but with Oculus visemes (``viseme_aa``...) get all 15 visemes
driven instead (:func:`talkmesh.face.visemes.oculus_visemes`: lips and jaw through the documented
ARKit -> viseme map, the tongue visemes from the phones when the motion was made from phones,
else from the motion); their ARKit-named shapes (blinks) are still driven. A VRM avatar without
ARKit mouth shapes but with the VRM mouth presets gets its presets driven instead, through the
morph targets the VRM extension binds to them (:mod:`talkmesh.output.vrm`).

Nothing else changes: the JSON of every node, mesh, skin, material, texture, image, extension
(VRM included) and other animation is kept as it was, and the binary chunk is kept byte for
byte, with the clip's keyframes appended after it. Units and up-axis are the avatar's, since no
geometry is touched. Input and output are binary glTF (``.glb``, or ``.vrm``, which is a .glb with
the VRM extension); morph target names are read from ``mesh.extras.targetNames`` (three.js,
Blender) or, where that is absent, from the first primitive's ``extras.targetNames`` (UniVRM).
"""

from __future__ import annotations

import json
import os
import struct
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES, NUM_ARKIT
from talkmesh.face.arkit_names import (
    MOUTH_CHANNELS,
    VISEMES,
    arkit_channel,
    viseme_channel,
)
from talkmesh.face.visemes import oculus_visemes
from talkmesh.output.avatar_head import head_node, head_rotations
from talkmesh.output.scene import AvatarScene, load_scene
from talkmesh.output.vrm import MOUTH, PRESETS, preset_weights, read_expressions, target_matrix

AVATAR_SUFFIXES = (".glb", ".vrm")
CLIP_NAME = "talk"
GLB_MAGIC, GLB_JSON, GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942  # glTF 2.0 spec, 4.4
FLOAT, SCALAR = 5126, "SCALAR"
OPENING_VISEMES = ("aa", "E", "I", "O", "U")  # a viseme avatar needs one of these to talk


@dataclass(frozen=True)
class MeshBinding:
    """How one mesh's morph targets follow the stream.

    Attributes:
        mesh: index into the glTF ``meshes``.
        name: the mesh's name (or ``mesh N``).
        nodes: the nodes that instance the mesh (each gets a channel).
        num_targets: its number of morph targets (K).
        arkit: (K,) index into ``ARKIT_NAMES`` per target, -1 where none.
        visemes: (K,) index into ``VISEMES`` per target, -1 where none or not used.
        rest: (K,) the mesh's default weights (kept by targets that follow nothing).
        presets: (P, K) the VRM expression presets' bind weights on its targets, or None.
    """

    mesh: int
    name: str
    nodes: tuple[int, ...]
    num_targets: int
    arkit: np.ndarray
    visemes: np.ndarray
    rest: np.ndarray
    presets: np.ndarray | None = None

    def weights(
        self, arkit: np.ndarray, visemes: np.ndarray | None, presets: np.ndarray | None = None
    ) -> np.ndarray:
        """(T, 52) ARKit, (T, 15) viseme and (T, P) VRM preset weights -> (T, K) weights of this
        mesh's targets."""
        out = np.repeat(self.rest[None].astype(np.float32), len(arkit), axis=0)
        driven = self.arkit >= 0
        out[:, driven] = arkit[:, self.arkit[driven]]
        if visemes is not None:
            driven = self.visemes >= 0
            out[:, driven] = visemes[:, self.visemes[driven]]
        if presets is not None and self.presets is not None:
            driven = self.presets.any(axis=0)
            out[:, driven] = np.clip(presets @ self.presets, 0.0, 1.0)[:, driven]
        return out

    @property
    def driven(self) -> bool:
        """Whether anything drives one of its targets."""
        return bool(
            (self.arkit >= 0).any()
            or (self.visemes >= 0).any()
            or (self.presets is not None and self.presets.any())
        )


@dataclass(frozen=True)
class AvatarBinding:
    """What of an avatar the ARKit stream drives.

    Attributes:
        meshes: the meshes with morph targets that follow the stream.
        channels: the ARKit names at least one mesh has.
        missing: the ARKit names no mesh has.
        visemes: the Oculus visemes driven (only when no mesh has ARKit mouth shapes).
        clips: the names of the avatar's own animations (``talk`` among them is replaced).
        expressions: the VRM presets driven (only when no mesh has ARKit mouth shapes).
        vrm: the VRM version the presets were read from ("0.x", "1.0"; "" for none).
    """

    meshes: tuple[MeshBinding, ...]
    channels: tuple[str, ...]
    missing: tuple[str, ...]
    visemes: tuple[str, ...]
    clips: tuple[str, ...] = ()
    expressions: tuple[str, ...] = ()
    vrm: str = ""

    def summary(self) -> str:
        """One line for the user: what moves and which ARKit channels the avatar lacks."""
        line = f"drives {len(self.channels)} of {NUM_ARKIT} ARKit channels on {_mesh_names(self)}"
        if self.expressions:
            shown = " ".join(self.expressions)
            line += f" and VRM {self.vrm} expressions {shown} (no ARKit mouth shapes)"
        if self.visemes:
            line += (
                f" and {len(self.visemes)} of {len(VISEMES)} Oculus visemes (no ARKit mouth shapes)"
            )
            lacking = [v for v in VISEMES if v not in self.visemes]
            if lacking:
                line += f"; lacks visemes {', '.join(lacking)}: export all 15 to drive them"
        if self.missing:
            shown = ", ".join(self.missing[:6]) + (", ..." if len(self.missing) > 6 else "")
            line += f"; lacks {len(self.missing)}: {shown}"
        kept = [c for c in self.clips if c != CLIP_NAME]
        if CLIP_NAME in self.clips:
            line += f"; the speech replaces its clip '{CLIP_NAME}'"
        if kept:
            shown = ", ".join(kept[:3]) + (", ..." if len(kept) > 3 else "")
            line += f"; its other clips follow the speech clip ({shown})"
        return line


def _mesh_names(binding: AvatarBinding, shown: int = 4) -> str:
    """The driven meshes' names, each once with its count (``Head, Teeth x 3``), the first
    ``shown`` of them: an avatar of 3000 meshes named alike is one short line."""
    counts: dict[str, int] = {}
    for m in binding.meshes:
        counts[m.name] = counts.get(m.name, 0) + 1
    names = [f"{n} x {k}" if k > 1 else n for n, k in counts.items()]
    more = f" and {len(names) - shown} more names" if len(names) > shown else ""
    meshes = f"{len(binding.meshes)} meshes: " if len(binding.meshes) > 1 else ""
    return meshes + ", ".join(names[:shown]) + more


def read_glb(path: str | Path) -> tuple[dict, bytes]:
    """The JSON and binary chunks of a .glb / .vrm file; one-line TalkmeshErrors for bad files."""
    path = Path(path)
    if not path.is_file():
        raise TalkmeshError(f"{path}: no such file")
    data = path.read_bytes()
    if len(data) < 20 or struct.unpack_from("<I", data)[0] != GLB_MAGIC:
        hint = " (a .gltf: pack it into one .glb first)" if data.lstrip()[:1] == b"{" else ""
        raise TalkmeshError(f"{path}: not a binary glTF (.glb/.vrm) file{hint}")
    _, version, length = struct.unpack_from("<III", data)
    if version != 2:
        raise TalkmeshError(f"{path}: glTF version {version} is not supported (only 2)")
    if length != len(data):  # shorter: truncated; longer: data past the stated end is lost
        raise TalkmeshError(
            f"{path}: {'truncated' if length > len(data) else 'inconsistent'} (the header says "
            f"{length} bytes, the file has {len(data)}): export the avatar again"
        )
    gltf, binary, offset = None, b"", 12
    while offset + 8 <= length:
        size, kind = struct.unpack_from("<II", data, offset)
        chunk = data[offset + 8 : offset + 8 + size]
        if len(chunk) != size:
            raise TalkmeshError(f"{path}: truncated (a chunk runs past the end of the file)")
        if kind == GLB_JSON and gltf is None:
            try:
                gltf = json.loads(chunk.decode("utf-8"))
            except (UnicodeDecodeError, ValueError) as e:
                raise TalkmeshError(f"{path}: its JSON chunk is not valid JSON ({e})") from None
            except RecursionError:
                raise TalkmeshError(f"{path}: its JSON chunk is nested too deeply") from None
        elif kind == GLB_BIN and offset > 12 and not binary:
            binary = chunk
        offset += 8 + size
    if not isinstance(gltf, dict):
        raise TalkmeshError(f"{path}: no JSON chunk")
    return gltf, binary


def glb_bytes(gltf: dict, binary: bytes) -> bytes:
    """The GLB container: 12-byte header, JSON chunk (space-padded), BIN chunk (zero-padded)."""
    text = json.dumps(gltf, ensure_ascii=False, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    chunks = [struct.pack("<II", len(text), GLB_JSON), text]
    if binary:
        binary += b"\0" * (-len(binary) % 4)
        chunks += [struct.pack("<II", len(binary), GLB_BIN), binary]
    body = b"".join(chunks)
    return struct.pack("<III", GLB_MAGIC, 2, 12 + len(body)) + body


def _list(obj: dict, key: str) -> list:
    """``obj[key]`` as a list ([] when absent); a ValueError when it is not a list."""
    value = obj.get(key) or []
    if not isinstance(value, list):
        raise ValueError(f"'{key}' should be a list, not {type(value).__name__}")
    return value


def _target_names(mesh: dict) -> list[str]:
    names = (mesh.get("extras") or {}).get("targetNames")
    if not isinstance(names, list):
        primitives = mesh.get("primitives") or [{}]
        names = (primitives[0].get("extras") or {}).get("targetNames")
    return [str(n) for n in names] if isinstance(names, list) else []


def bind_avatar(gltf: dict, source: str = "the avatar") -> AvatarBinding:
    """Which meshes, nodes and morph targets of ``gltf`` follow ARKit weights (or visemes).

    Raises:
        TalkmeshError: one line naming ``source``: no ARKit or viseme targets, JSON of the wrong
            types (a mesh that is a number, ``weights`` that are text, ...), or binary data kept
            in an external file (refused here, before any model runs).
    """
    try:
        binding = _bind(gltf, source)
        buffers = gltf.get("buffers") or []
        external = any("uri" in b for b in buffers)
    except (AttributeError, TypeError, ValueError, KeyError, IndexError) as e:
        raise TalkmeshError(
            f"{source}: its glTF JSON does not follow the glTF 2.0 schema ({type(e).__name__}: "
            f"{str(e)[:80]}): export it again"
        ) from None
    if external:
        raise TalkmeshError(
            f"{source}: the avatar keeps its binary data in an external file: pack it into one "
            "self-contained .glb first"
        )
    return binding


def _bind(gltf: dict, source: str) -> AvatarBinding:
    for key in ("meshes", "nodes", "buffers", "bufferViews", "accessors", "animations"):
        if not all(isinstance(item, dict) for item in _list(gltf, key)):
            raise ValueError(f"an item of '{key}' is not an object")
    animations = _list(gltf, "animations")
    candidates: list[tuple[int, str, tuple[int, ...], int, np.ndarray, np.ndarray, np.ndarray]] = []
    nodes_of: dict[int, list[int]] = {}
    for i, n in enumerate(_list(gltf, "nodes")):
        mesh = n.get("mesh")
        if isinstance(mesh, int):
            nodes_of.setdefault(mesh, []).append(i)
    for m, mesh in enumerate(_list(gltf, "meshes")):
        primitives = _list(mesh, "primitives")
        num_targets = len(_list(primitives[0], "targets")) if primitives else 0
        names = _target_names(mesh)
        if not num_targets:
            continue
        if len(names) != num_targets:  # no names (VRM presets bind targets by index)
            names = [""] * num_targets
        nodes = tuple(nodes_of.get(m, ()))
        if not nodes:
            continue
        rest = np.asarray(mesh.get("weights") or [0.0] * num_targets, np.float32)
        if rest.shape != (num_targets,) or not np.isfinite(rest).all():
            raise ValueError(f"mesh {m}'s weights are not {num_targets} numbers")
        arkit = np.array([arkit_channel(n) for n in names], np.int64)
        visemes = np.array([viseme_channel(n) for n in names], np.int64)
        arkit[visemes >= 0] = -1  # ``viseme_O`` is a viseme, not an ARKit suffix
        name = str(mesh.get("name") or f"mesh {m}")
        candidates.append((m, name, nodes, num_targets, arkit, visemes, rest))
    found = {int(i) for c in candidates for i in c[4] if i >= 0}
    no_arkit_mouth = not any(ARKIT_NAMES.index(n) in found for n in MOUTH_CHANNELS)
    expressions = read_expressions(gltf)
    use_vrm = no_arkit_mouth and expressions is not None and bool(expressions.mouth)
    if use_vrm:
        _check_mouth_binds(expressions, candidates, source)
    use_visemes = no_arkit_mouth and not use_vrm
    meshes = []
    for m, name, nodes, k, arkit, visemes, rest in candidates:
        visemes = visemes if use_visemes else np.full(k, -1, np.int64)
        presets = target_matrix(expressions, m, k) if use_vrm else None
        binding = MeshBinding(m, name, nodes, k, arkit, visemes, rest, presets)
        if binding.driven:
            meshes.append(binding)
    driven_visemes = sorted({int(i) for b in meshes for i in b.visemes if i >= 0})
    if driven_visemes and not {VISEMES[i] for i in driven_visemes} & set(OPENING_VISEMES):
        raise TalkmeshError(
            f"{source} has Oculus visemes but none that opens the mouth (viseme_aa, viseme_E, "
            "viseme_I, viseme_O, viseme_U): export the full set of 15, or ARKit blendshapes"
        )
    if not meshes and expressions is not None:
        raise TalkmeshError(
            f"{source}: a VRM {expressions.version} without mouth expressions (aa ih ou ee oh "
            "bound to morph targets), ARKit mouth shapes or Oculus visemes: add the mouth presets "
            "(VRoid Studio, UniVRM) or export it with ARKit blendshapes (perfect sync)"
        )
    if not meshes:
        raise TalkmeshError(
            f"{source} has no morph targets with ARKit names (jawOpen, eyeBlinkLeft, ...) or "
            "Oculus visemes (viseme_aa, ...): export it with ARKit blendshapes, or rig a plain "
            "head mesh"
        )
    return AvatarBinding(
        meshes=tuple(meshes),
        channels=tuple(n for i, n in enumerate(ARKIT_NAMES) if i in found),
        missing=tuple(n for i, n in enumerate(ARKIT_NAMES) if i not in found),
        visemes=tuple(VISEMES[i] for i in driven_visemes),
        clips=tuple(str(a.get("name") or f"animation {i}") for i, a in enumerate(animations)),
        expressions=expressions.names if use_vrm else (),
        vrm=expressions.version if use_vrm else "",
    )


def _check_mouth_binds(expressions, candidates: list, source: str) -> None:
    """A VRM whose mouth presets bind no morph target the avatar has (a mesh without targets or
    no node, an index past its last target) would talk without moving: one line instead."""
    rows = [PRESETS.index(p) for p in MOUTH]
    if any(target_matrix(expressions, c[0], c[3])[rows].any() for c in candidates):
        return
    bound = sorted({(m, i) for p in MOUTH for m, i, _ in expressions.binds.get(p, ())})
    shown = ", ".join(f"mesh {m} target {i}" for m, i in bound[:3])
    raise TalkmeshError(
        f"{source}: its VRM {expressions.version} mouth presets ({' '.join(expressions.mouth)}) "
        f"bind no morph target the avatar has ({shown}{', ...' if len(bound) > 3 else ''}): "
        "export it again (VRoid Studio, UniVRM), or with ARKit blendshapes (perfect sync)"
    )


def add_clip(
    gltf: dict,
    binary: bytes,
    binding: AvatarBinding,
    weights: np.ndarray,
    fps: float,
    head_pose: np.ndarray | None = None,
    phones: list[tuple[str, float, float]] | None = None,
) -> tuple[dict, bytes]:
    """A copy of ``gltf`` with one LINEAR clip of ``weights`` (T, 52) at ``fps`` as its first
    animation (replacing one named ``talk``, the others after it; with a (T, 6) ``head_pose``, its
    head bone's rotation too: :mod:`talkmesh.output.avatar_head`), and the binary chunk with its
    keyframes appended (the existing bytes unchanged; a replaced clip's keys stay unused)."""
    weights = np.asarray(weights, np.float32)
    assert weights.ndim == 2 and weights.shape[1] == NUM_ARKIT, weights.shape
    if not len(weights):
        raise TalkmeshError("the animation has no frames")
    buffers = gltf.get("buffers") or []
    if buffers and "uri" in buffers[0]:
        raise TalkmeshError(
            "the avatar keeps its binary data in an external file: pack it into one self-"
            "contained .glb first"
        )
    out = dict(gltf)
    views, accessors = list(gltf.get("bufferViews") or []), list(gltf.get("accessors") or [])
    data = bytearray(binary)

    def add(array: np.ndarray, bounds: bool, kind: str = SCALAR, width: int = 1) -> int:
        data.extend(b"\0" * (-len(data) % 4))
        views.append({"buffer": 0, "byteOffset": len(data), "byteLength": array.nbytes})
        data.extend(array.astype("<f4").tobytes())
        accessor = {
            "bufferView": len(views) - 1,
            "componentType": FLOAT,
            "count": int(array.size) // width,
            "type": kind,
        }
        if bounds:  # required for animation inputs
            accessor["min"], accessor["max"] = [float(array.min())], [float(array.max())]
        accessors.append(accessor)
        return len(accessors) - 1

    visemes = oculus_visemes(weights, fps, phones) if binding.visemes else None
    presets = preset_weights(weights, fps, binding.expressions) if binding.expressions else None
    times = add((np.arange(len(weights), dtype=np.float64) / fps).astype(np.float32), True)
    samplers, channels = [], []
    for mesh in binding.meshes:
        values = add(mesh.weights(weights, visemes, presets).ravel(), False)
        samplers.append({"input": times, "output": values, "interpolation": "LINEAR"})
        for node in mesh.nodes:
            channels.append(
                {"sampler": len(samplers) - 1, "target": {"node": node, "path": "weights"}}
            )
    head = head_node(gltf) if head_pose is not None else None
    if head is not None:
        values = add(head_rotations(gltf, head, head_pose).ravel(), False, "VEC4", 4)
        samplers.append({"input": times, "output": values, "interpolation": "LINEAR"})
        channels.append(
            {"sampler": len(samplers) - 1, "target": {"node": head, "path": "rotation"}}
        )
    clip = {
        "name": CLIP_NAME,
        "samplers": samplers,
        "channels": channels,
        "extras": {"fps": float(fps)},
    }
    others = [a for a in gltf.get("animations") or [] if a.get("name") != CLIP_NAME]
    out["animations"] = [clip, *others]
    out["bufferViews"], out["accessors"] = views, accessors
    out["buffers"] = [{**(buffers[0] if buffers else {}), "byteLength": len(data)}, *buffers[1:]]
    return out, bytes(data)


def animate_avatar(
    avatar: str | Path,
    weights: np.ndarray,
    fps: float,
    output: str | Path,
    *,
    overwrite: bool = False,
    head_pose: np.ndarray | None = None,
    phones: list[tuple[str, float, float]] | None = None,
) -> AvatarBinding:
    """Write a copy of ``avatar`` (.glb/.vrm) with a clip of ``weights`` (T, 52, ARKit order) at
    ``fps`` (and the head bone turned by a (T, 6) ``head_pose``) to ``output`` (.glb/.vrm);
    returns what it drove. ``phones`` (label, start s, end s) drive a viseme avatar's tongue
    visemes. Atomic: a failed write leaves
    nothing, and an existing ``output`` is replaced only with ``overwrite``."""
    avatar, output = Path(avatar), Path(output)
    if output.suffix.lower() not in AVATAR_SUFFIXES:
        raise TalkmeshError(f"{output}: avatars are written as .glb or .vrm files")
    if output.resolve() == avatar.resolve():
        raise TalkmeshError(f"{output}: refusing to write over the avatar")
    if output.exists() and not overwrite:
        raise TalkmeshError(f"{output} already exists: choose another -o or pass --overwrite")
    if not fps > 0:
        raise TalkmeshError(f"fps must be positive, got {fps}")
    gltf, binary = read_glb(avatar)
    binding = bind_avatar(gltf, str(avatar))
    new_gltf, new_binary = add_clip(
        gltf, binary, binding, weights, fps, head_pose=head_pose, phones=phones
    )
    _write_atomic(output, glb_bytes(new_gltf, new_binary), overwrite)
    return binding


def talking_scene(
    avatar: str | Path,
    weights: np.ndarray,
    fps: float,
    *,
    head_pose: np.ndarray | None = None,
    phones: list[tuple[str, float, float]] | None = None,
) -> AvatarScene:
    """The avatar as :func:`animate_avatar` would write it, ready to render: an
    :class:`~talkmesh.output.scene.AvatarScene` playing the speech clip (nothing is written)."""
    gltf, binary = read_glb(avatar)
    binding = bind_avatar(gltf, str(avatar))
    new_gltf, new_binary = add_clip(
        gltf, binary, binding, weights, fps, head_pose=head_pose, phones=phones
    )
    return load_scene(new_gltf, new_binary, str(avatar))


def load_avatar_scene(path: str | Path, *, clip: bool = True) -> AvatarScene:
    """A .glb/.vrm file as an :class:`~talkmesh.output.scene.AvatarScene` playing its first clip;
    with ``clip``, a file without an animation to play is a one-line TalkmeshError."""
    gltf, binary = read_glb(path)
    scene = load_scene(gltf, binary, str(path))
    if clip and not scene.animated:
        raise TalkmeshError(
            f"{path} has no animation clip to play: give it the speech with `talkmesh animate "
            f"speech.wav --avatar {path} -o talking{Path(path).suffix.lower()}` and render that"
        )
    return scene


def _write_atomic(path: Path, data: bytes, overwrite: bool) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".talkmesh-", suffix=path.suffix)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            if overwrite:
                os.replace(tmp, path)
            else:
                os.link(tmp, path)  # fails if path appeared meanwhile, unlike rename
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    except FileExistsError:
        raise TalkmeshError(
            f"{path} already exists: choose another -o or pass --overwrite"
        ) from None
    except OSError as e:
        raise TalkmeshError(f"{path}: cannot write it ({e.strerror or e})") from None
