"""Avatar videos: how long posing and drawing an avatar's frame takes (``talkmesh.output.scene``).

    PYTHONPATH=src python bench/avatar_video.py [--frames 90] [--size 512]

The avatars (``tests/avatars.py``): the bundled head as an ARKit glb (52 shapes), as a VRM 1.0
with only the mouth and blink presets, and with only the 15 Oculus visemes; the tests' box
avatar (a skin of two joints, four meshes, a texture); and a body-sized avatar: the ARKit head
under a head bone with a skinned body of 40962 vertices (an icosphere), about a VRoid model's
vertex count. Each plays random ARKit weights and a head pose through ``talking_scene`` (the clip
``animate --avatar`` writes). Per avatar: posing (``AvatarScene.vertices``: the clip sampled,
morphs, skins) and drawing (``Renderer.draw``) in ms per frame, and frames/s of the whole video
(``render_avatar_video``: posing, drawing and H.264 encoding) at ``--size``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from avatars import head_avatar, make_avatar  # noqa: E402

from talkmesh.blas import one_blas_thread  # noqa: E402
from talkmesh.output.avatar import glb_bytes, read_glb, talking_scene  # noqa: E402
from talkmesh.output.render import avatar_renderer, render_avatar_video  # noqa: E402

FPS = 30.0


def append(gltf: dict, data: bytearray, array: np.ndarray, kind: str, code: int) -> int:
    """``array`` appended to the binary chunk as an accessor of ``kind``; its index."""
    data.extend(b"\0" * (-len(data) % 4))
    gltf["bufferViews"].append({"buffer": 0, "byteOffset": len(data), "byteLength": array.nbytes})
    data.extend(np.ascontiguousarray(array).tobytes())
    acc = {"bufferView": len(gltf["bufferViews"]) - 1, "componentType": code}
    acc.update({"count": len(array), "type": kind})
    if kind == "VEC3" and code == 5126:
        acc["min"], acc["max"] = array.min(0).tolist(), array.max(0).tolist()
    gltf["accessors"].append(acc)
    return len(gltf["accessors"]) - 1


def body_avatar(path: Path) -> Path:
    """The ARKit head under a head bone, over a skinned icosphere body (see the module doc)."""
    import trimesh

    gltf, binary = read_glb(head_avatar(path.with_suffix(".head.glb")))
    data = bytearray(binary)
    sphere = trimesh.creation.icosphere(6)
    v = (sphere.vertices * [0.25, 0.6, 0.18] + [0.0, -0.65, -0.03]).astype(np.float32)
    f = sphere.faces.astype(np.uint32).ravel()
    neck = np.clip((v[:, 1] + 0.15) / 0.1, 0.0, 1.0)  # the top of the body follows the head
    joints = np.tile(np.array([0, 1, 0, 0], np.uint8), (len(v), 1))
    weights = np.stack([1 - neck, neck, 0 * neck, 0 * neck], 1).astype(np.float32)
    attributes = {
        "POSITION": append(gltf, data, v, "VEC3", 5126),
        "JOINTS_0": append(gltf, data, joints, "VEC4", 5121),
        "WEIGHTS_0": append(gltf, data, weights, "VEC4", 5126),
    }
    ibm = np.tile(np.eye(4, dtype=np.float32), (2, 1, 1))
    ibm[1, 3, 1] = 0.1  # the head joint sits at y = -0.1 (column-major: translation in row 3)
    gltf["materials"].append({"pbrMetallicRoughness": {"baseColorFactor": [0.2, 0.3, 0.6, 1]}})
    gltf["meshes"].append(
        {
            "name": "Body",
            "primitives": [
                {
                    "attributes": attributes,
                    "indices": append(gltf, data, f, "SCALAR", 5125),
                    "material": len(gltf["materials"]) - 1,
                }
            ],
        }
    )
    face = next(k for k, n in enumerate(gltf["nodes"]) if "mesh" in n)
    n = len(gltf["nodes"])
    gltf["nodes"] += [
        {"name": "Hips", "children": [n + 1]},
        {"name": "Head", "translation": [0, -0.1, 0], "children": [n + 2]},
        {"name": "face", "mesh": gltf["nodes"][face].pop("mesh"), "translation": [0, 0.1, 0]},
        {"name": "Body", "mesh": len(gltf["meshes"]) - 1, "skin": 0},
    ]
    gltf["skins"] = [{"joints": [n, n + 1], "inverseBindMatrices": append(
        gltf, data, ibm.reshape(2, 16), "MAT4", 5126)}]  # fmt: skip
    gltf["scenes"] = [{"nodes": [n, n + 3]}]
    gltf["buffers"] = [{"byteLength": len(data)}]
    path.write_bytes(glb_bytes(gltf, bytes(data)))
    return path


def avatars(tmp: Path):
    yield "ARKit glb (bundled head)", head_avatar(tmp / "arkit.glb", "arkit")
    yield "VRM 1.0, presets only", head_avatar(tmp / "presets.vrm", "vrm")
    yield "Oculus visemes only", head_avatar(tmp / "visemes.glb", "visemes")
    yield "box avatar (tests)", make_avatar(tmp / "box.vrm", vrm=True)
    yield "head + skinned body", body_avatar(tmp / "body.glb")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=90)
    p.add_argument("--size", type=int, default=512)
    args = p.parse_args()
    rng = np.random.default_rng(0)
    weights = rng.uniform(0, 0.6, (args.frames, 52)).astype(np.float32)
    pose = np.concatenate([rng.uniform(-0.2, 0.2, (args.frames, 3)), np.zeros((args.frames, 3))], 1)
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}; {args.frames} frames")
    print(f"| avatar | vertices | triangles | pose ms/frame | draw ms/frame | video frames/s at "
          f"{args.size} |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for label, path in avatars(Path(tmp)):
            scene = talking_scene(path, weights, FPS, head_pose=pose.astype(np.float32))
            with one_blas_thread():  # as render_avatar_video poses them
                start = time.perf_counter()
                frames = [scene.vertices(t) for t in range(scene.num_frames)]
                posing = (time.perf_counter() - start) / scene.num_frames
            with avatar_renderer(scene, args.size) as renderer:
                renderer.draw(frames[0])
                start = time.perf_counter()
                for v in frames:
                    renderer.draw(v)
                drawing = (time.perf_counter() - start) / len(frames)
            start = time.perf_counter()
            render_avatar_video(scene, Path(tmp) / "v.mp4", args.size)
            video = scene.num_frames / (time.perf_counter() - start)
            (Path(tmp) / "v.mp4").unlink()
            print(
                f"| {label} | {scene.num_vertices} | {len(scene.faces)} | {1000 * posing:.1f} | "
                f"{1000 * drawing:.1f} | {video:.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
