"""Rendering throughput: frames/s of rasterisation alone and of rendering + H.264 encoding.

    python bench/render.py [--frames 120] [--sizes 256 512 1024]

Uses the bundled head (``talkmesh.face.assets.load_head``) with a jaw-opening motion, or a procedural
~5k-vertex head-sized ellipsoid if the bundled head cannot be loaded.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from talkmesh.animation import Animation
from talkmesh.output.render import Renderer, render_video

FPS = 30.0
WARMUP_FRAMES = 5


def procedural_head(rings: int = 60, segments: int = 80) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere squashed to a 0.16 x 0.24 x 0.2 m ellipsoid -> (V, 3) vertices, (F, 3) faces."""
    theta = np.linspace(0, np.pi, rings + 1)[1:-1]  # polar angle, poles added separately
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.sin(p), np.cos(t), np.sin(t) * np.cos(p)], -1).reshape(-1, 3)
    unit = np.concatenate([[[0, 1, 0]], ring, [[0, -1, 0]]])
    vertices = (unit * [0.08, 0.12, 0.10]).astype(np.float32)
    faces = []
    idx = 1 + np.arange((rings - 1) * segments).reshape(rings - 1, segments)
    nxt = np.roll(idx, -1, axis=1)
    faces += [np.stack([np.zeros(segments, int), idx[0], nxt[0]], 1)]
    for r in range(rings - 2):
        faces += [np.stack([idx[r], idx[r + 1], nxt[r]], 1)]
        faces += [np.stack([nxt[r], idx[r + 1], nxt[r + 1]], 1)]
    bottom = len(unit) - 1
    faces += [np.stack([np.full(segments, bottom), nxt[-1], idx[-1]], 1)]
    return vertices, np.concatenate(faces).astype(np.int32)


def bench_motion(num_frames: int) -> tuple[str, Animation]:
    """A named (T, V, 3) animation: the bundled head opening its jaw, or the fallback ellipsoid."""
    t = np.arange(num_frames, dtype=np.float32) / FPS
    try:
        from talkmesh.face.assets import load_head

        head = load_head()
        weights = np.zeros((num_frames, len(head.blendshape_names)), dtype=np.float32)
        weights[:, head.blendshape_names.index("jawOpen")] = 0.3 + 0.3 * np.sin(2 * np.pi * t)
        vertices, faces, name = head.vertices_from_weights(weights), head.faces, "bundled head"
    except Exception as e:  # no (or a broken) bundled head: measure an equivalent mesh
        template, faces = procedural_head()
        wobble = 1 + 0.05 * np.sin(2 * np.pi * t)[:, None, None] * (template[None, :, 1:2] < 0)
        vertices, name = template[None] * wobble, f"procedural ellipsoid ({type(e).__name__})"
    audio = np.zeros(round(num_frames / FPS * 16_000), dtype=np.float32)
    return name, Animation(vertices, faces, FPS, audio=audio)


def raster_fps(anim: Animation, size: int) -> float:
    with Renderer(anim.faces, size, reference=anim.vertices[0]) as renderer:
        for v in anim.vertices[:WARMUP_FRAMES]:
            renderer.render(v)
        start = time.perf_counter()
        for v in anim.vertices:
            renderer.render(v)
        return anim.num_frames / (time.perf_counter() - start)


def video_fps(anim: Animation, size: int) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        render_video(anim, Path(tmp) / "bench.mp4", size)
        return anim.num_frames / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=120, help="frames per measurement")
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    args = parser.parse_args()

    name, anim = bench_motion(args.frames)
    print(f"mesh: {name}, {anim.num_vertices} vertices, {len(anim.faces)} triangles")
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs")
    print(f"{args.frames} frames per measurement; render+encode includes H.264 + AAC into an mp4\n")
    print(f"| {'size':>9} | {'raster frames/s':>15} | {'render+encode frames/s':>22} |")
    print(f"|{'-' * 11}|{'-' * 17}|{'-' * 24}|")
    for size in args.sizes:
        raster, video = raster_fps(anim, size), video_fps(anim, size)
        print(f"| {f'{size}x{size}':>9} | {raster:>15.1f} | {video:>22.1f} |", flush=True)


if __name__ == "__main__":
    main()
