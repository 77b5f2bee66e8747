"""Peak memory and time of `talkmesh rig` as the mesh grows, and how fast a dense non-head is
refused.

The bundled head is subdivided 0 to N times (midpoint subdivision: 4766, 18911, 75k, 300k, 1.2M
vertices) and written in millimetres as .ply; an icosphere stands for a dense mesh that is no
head, at several sizes (icospheres; a UV sphere of 3.48M faces). Each runs as its own `talkmesh
rig` process, whose peak RSS (``ru_maxrss``) and wall time are printed as a table
(docs/results/rigging.md, "Dense meshes").

    PYTHONPATH=src python bench/rig_dense.py [--subdivisions 0,1,3,4] [--sphere 4,8] [--uv 933]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

from talkmesh.face.assets import load_head


def peak_of(cmd: list[str]) -> tuple[int, float, float]:
    """Exit status, wall seconds and peak RSS (MB) of ``cmd`` run alone in a fresh process (the
    largest of it and its decimation's forked child, which holds the mesh's pages shared)."""
    probe = (
        "import resource, subprocess, sys, time; t = time.time(); "
        "rc = subprocess.call(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL); "
        "print(rc, time.time() - t, "
        "resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024)"
    )
    out = subprocess.run([sys.executable, "-c", probe, *cmd], capture_output=True, text=True)
    rc, seconds, mb = out.stdout.split()
    return int(rc), float(seconds), float(mb)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subdivisions", default="0,1,3,4")
    ap.add_argument("--sphere", default="4,8", help="icosphere subdivisions ('': none)")
    ap.add_argument("--uv", type=int, default=933, help="UV sphere rings and segments (0: none)")
    args = ap.parse_args()
    head = load_head()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        meshes = []
        for n in (int(k) for k in args.subdivisions.split(",")):
            v, f = head.template.astype(np.float64), head.faces
            for _ in range(n):
                v, f = trimesh.remesh.subdivide(v, f)
            meshes.append((f"bundled head, subdivided {n}x", 1000 * v, f))
        for n in (int(k) for k in args.sphere.split(",") if k):
            s = trimesh.creation.icosphere(subdivisions=n, radius=100.0)
            meshes.append((f"icosphere({n})", s.vertices, s.faces))
        if args.uv:
            s = trimesh.creation.uv_sphere(radius=100.0, count=[args.uv, args.uv])
            meshes.append((f"UV sphere ({args.uv} x {args.uv})", s.vertices, s.faces))
        for name, v, f in meshes:
            path = Path(tmp) / "mesh.ply"
            trimesh.Trimesh(v, f, process=False).export(path)
            cmd = [sys.executable, "-m", "talkmesh", "rig", str(path), "-o", f"{tmp}/out.glb"]
            rc, seconds, mb = peak_of([*cmd, "--overwrite"])
            result = "rigged" if rc == 0 else "refused" if rc == 2 else f"exit {rc}"
            rows.append((name, len(v), len(f), mb, seconds, result))
            print(rows[-1], flush=True)
    print("| mesh | vertices | faces | peak RSS MB | s | result |")
    print("|---|---|---|---|---|---|")
    for name, nv, nf, mb, seconds, result in rows:
        print(f"| {name} | {nv} | {nf} | {mb:.0f} | {seconds:.0f} | {result} |")


if __name__ == "__main__":
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    t0 = time.time()
    main()
    print(
        f"({time.time() - t0:.0f} s in all; peak RSS of this process "
        f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB)"
    )
