"""How well `talkmesh rig` carries the 52 ARKit blendshapes onto a head, where the truth is known.

The bundled head is turned into "user" meshes whose true blendshapes follow from the bundled ones:
rescaled to centimetres or millimetres and rotated to another up-axis (truth: the same offsets,
scaled and rotated), remeshed denser by one midpoint subdivision (truth: the subdivided shapes),
with its vertices shuffled, and the bundled identities (one blendshape set serves them all, so it is their truth). Per shape: the mean
vertex error in mm and as % of the shape's own mean displacement; the jaw opening (lip gap under
jawOpen) and the lip gap under mouthClose + jawOpen, truth vs transfer.

    PYTHONPATH=src python bench/rig_transfer.py
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import trimesh

from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import list_identities, load_head
from talkmesh.face.rig import rig_head

JAW, CLOSE = ARKIT_NAMES.index("jawOpen"), ARKIT_NAMES.index("mouthClose")


def rotation(axis, degrees) -> np.ndarray:
    return trimesh.transformations.rotation_matrix(np.radians(degrees), axis)[:3, :3]


def subdivide(vertices, faces, shapes):
    """One midpoint subdivision of the head and of every shape (the shapes' truth)."""
    new_v, new_f = trimesh.remesh.subdivide(vertices, faces)
    moved = [trimesh.remesh.subdivide(vertices + s, faces)[0] - new_v for s in shapes]
    return new_v, new_f, np.stack(moved)


def lip_gap(vertices, offsets, weights, pair):
    """Distance between the two lip vertices ``pair`` with ``weights`` {shape: w} applied."""
    v = vertices[pair] + sum(w * offsets[k][pair] for k, w in weights.items())
    return float(np.linalg.norm(v[0] - v[1]))


def cases(head):
    v, f, s = head.template.astype(np.float64), head.faces, head.blendshapes.astype(np.float64)
    r_z = rotation([1, 0, 0], -90)  # a Z-up export
    pair = head.regions.lip_pair
    yield "cm, Z-up", 100 * v @ r_z.T + [3, -2, 10], f, 100 * s @ r_z.T, 100, pair
    r = rotation([0.3, 1, 0.2], 37)
    yield "mm, rotated 37 deg", 1000 * v @ r.T, f, 1000 * s @ r.T, 1000, pair
    sv, sf, ss = subdivide(v, f, s)
    yield "denser (subdivided)", sv, sf, ss, 1, pair  # the original vertices come first
    perm = np.random.default_rng(0).permutation(len(v))
    inverse = np.argsort(perm)
    yield "shuffled vertices", v[perm], inverse[f], s[:, perm], 1, inverse[pair]
    for name in list_identities()[:3]:
        other = load_head(name)
        yield f"identity {name}", other.template.astype(np.float64), f, s, 1, pair


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.parse_args()
    head = load_head()
    print(
        "| case | vertices | units | up | mean err mm | worst shape mm | mean % | worst % | "
        "jaw gap mm true/ours | close+jaw gap mm true/ours | s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, v, f, truth, unit, pair in cases(head):
        t = time.perf_counter()
        rig = rig_head(v, f, head)
        seconds = time.perf_counter() - t
        err = np.linalg.norm(rig.blendshapes - truth, axis=2).mean(1) / unit * 1000
        mag = np.linalg.norm(truth, axis=2).mean(1) / unit * 1000
        pct = 100 * err / mag
        # the user's lip vertices: the nearest to the bundled ones, mapped by the fitted pose
        gaps = [
            lip_gap(v, o, w, pair) / unit * 1000
            for w in ({JAW: 1.0}, {JAW: 1.0, CLOSE: 1.0})
            for o in (truth, rig.blendshapes)
        ]
        print(
            f"| {name} | {len(v)} | {rig.units} | {rig.up_axis} | {err.mean():.3f} | "
            f"{err.max():.3f} ({ARKIT_NAMES[int(err.argmax())]}) | {pct.mean():.1f} | "
            f"{pct.max():.1f} | {gaps[0]:.1f}/{gaps[1]:.1f} | {gaps[2]:.1f}/{gaps[3]:.1f} | "
            f"{seconds:.1f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
