"""ARKit weights solved from the vertex motion of another topology, where the truth is known.

The procedural animator's ARKit weights for a real speech clip move the bundled head; the motion
is carried onto other topologies whose true shapes follow from the bundled ones (as in
bench/rig_transfer.py), and :mod:`talkmesh.face.solve` solves the weights back from the vertices
alone, rigging each mesh from scratch (no correspondence given):

* the bundled head itself with its own shapes (the solve alone: what smoothing and the lip term
  cost);
* remeshed coarser (quadric decimation to 50% of its triangles; truth: the shapes at each new
  vertex's closest point on the bundled surface), in millimetres and Z-up;
* a FLAME-sized mesh of 5023 vertices (FLAME's count): the bundled head with its 257 longest
  edges split at their midpoints (truth: the midpoints' mean motion), its vertices shuffled,
  turned 10 degrees and moved; its surface is another bundled identity's (the registration
  starts from the default one), whose true shapes are the bundled ones. No FLAME data is used.

Per case: the weights' mean absolute error over the clip (mean over the 52 channels, and the worst
channel), the lip gap (the bundled head's midline lip pair, carried to the mesh by the truth)
solved vs true, frame by frame (largest difference, mm), the residual share the solve reports,
and the solve's time per frame (the registration, once per mesh and then saved, separately).

    PYTHONPATH=src python bench/arkit_solve.py [--audio FILE.wav]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from rig_transfer import decimate, rotation  # noqa: E402

from talkmesh.face.arkit import ARKIT_NAMES  # noqa: E402
from talkmesh.face.assets import list_identities, load_head  # noqa: E402
from talkmesh.face.solve import ArkitSolver, solver_for_mesh  # noqa: E402

FLAME_VERTICES = 5023
DEFAULT_AUDIO = Path(
    "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0880.wav"
)


def split_edges(vertices, faces, shapes, count):
    """``count`` of the longest edges split at their midpoints (no two in one triangle): the
    mesh gets ``count`` more vertices; the new vertices' shapes are their ends' mean."""
    faces = np.asarray(faces, np.int64)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    owner = np.tile(np.arange(len(faces)), 3)
    key = np.sort(edges, axis=1)
    length = np.linalg.norm(vertices[key[:, 0]] - vertices[key[:, 1]], axis=1)
    used, chosen = np.zeros(len(faces), bool), {}
    for i in np.argsort(-length):
        k = tuple(key[i])
        if k in chosen:
            continue
        sharing = owner[(key[:, 0] == k[0]) & (key[:, 1] == k[1])]
        if used[sharing].any():
            continue
        used[sharing] = True
        chosen[k] = len(vertices) + len(chosen)
        if len(chosen) == count:
            break
    pairs = np.array(list(chosen), np.int64)
    new_v = np.concatenate([vertices, vertices[pairs].mean(1)])
    new_s = np.concatenate([shapes, shapes[:, pairs].mean(2)], axis=1)
    out = []
    for a, b, c in faces:
        for x, y, z in ((a, b, c), (b, c, a), (c, a, b)):
            m = chosen.get((min(x, y), max(x, y)))
            if m is not None:
                out += [(x, m, z), (m, y, z)]
                break
        else:
            out.append((a, b, c))
    return new_v, np.array(out, np.int64), new_s


def cases(head):
    """(name, vertices, faces, true shapes (52, V, 3), units per metre, lip pair on the mesh)."""
    v, f = head.template.astype(np.float64), head.faces.astype(np.int64)
    s = head.blendshapes.astype(np.float64)
    upper, lower = (int(i) for i in head.regions.lip_pair)
    yield "bundled head, its own shapes", v, f, s, 1.0, (upper, lower)
    cv, cf, cs = decimate(v, f, s, 0.5)
    lower_jaw = float(np.linalg.norm(s[ARKIT_NAMES.index("jawOpen"), lower]))
    pair = lip_pair(cv, cs, v[[upper, lower]], lower_jaw)
    r = rotation([1, 0, 0], -90)
    yield "remeshed (50% of triangles), mm, Z-up", 1000 * cv @ r.T, cf, 1000 * cs @ r.T, 1000, pair
    other = list_identities()[1]
    ov = load_head(other).template.astype(np.float64)  # one shape set serves every identity
    fv, ff, fs = split_edges(ov, f, s, FLAME_VERTICES - len(v))
    assert len(fv) == FLAME_VERTICES
    perm = np.random.default_rng(0).permutation(len(fv))
    back = np.argsort(perm)
    r = rotation([0.2, 1, 0.1], 10)
    yield (
        f"FLAME-sized ({FLAME_VERTICES} vertices): identity {other}, shuffled, turned 10 deg",
        fv[perm] @ r.T + [0.01, -0.02, 0.03],
        back[ff],
        fs[:, perm] @ r.T,
        1.0,
        (int(back[upper]), int(back[lower])),
    )


def lip_pair(vertices, shapes, points, true_shapes_at):
    """The mesh's vertices for the bundled upper and lower lip ``points`` (2, 3): the nearest
    vertex that jawOpen moves less (upper) or more (lower) than half the bundled lower lip."""
    jaw = np.linalg.norm(shapes[ARKIT_NAMES.index("jawOpen")], axis=1)
    half = 0.5 * true_shapes_at
    dist = [np.linalg.norm(vertices - p, axis=1) for p in points]
    upper = np.flatnonzero(jaw < half)[np.argmin(dist[0][jaw < half])]
    lower = np.flatnonzero(jaw > half)[np.argmin(dist[1][jaw > half])]
    return int(upper), int(lower)


def gap(points: np.ndarray, pair) -> np.ndarray:
    """(T, V, 3) -> (T,) distance between the pair's two vertices."""
    return np.linalg.norm(points[:, pair[0]] - points[:, pair[1]], axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--audio", type=Path, default=DEFAULT_AUDIO)
    args = parser.parse_args()
    import os

    from talkmesh.pipeline import animate

    os.environ.setdefault("TALKMESH_CACHE", tempfile.mkdtemp())  # register from scratch
    head = load_head()
    truth = animate(args.audio, model="procedural").weights.astype(np.float64)
    print(f"{args.audio.name}: {len(truth)} frames at 30 fps, procedural ARKit weights\n")
    print(
        "| case | vertices | weight error, mean of 52 channels | worst channel | lip gap, "
        "largest error (mm) | lip gap range (mm) | residual share | solve ms/frame | rig s |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name, v, f, shapes, unit, pair in cases(head):
        offsets = np.einsum("tk,kvx->tvx", truth, shapes)
        start = time.perf_counter()
        if name.startswith("bundled"):
            solver = ArkitSolver(v.astype(np.float32), shapes.astype(np.float32), pair)
        else:
            solver = solver_for_mesh(v, f)
        rig_s = time.perf_counter() - start
        start = time.perf_counter()
        solved = solver.solve(offsets)
        ms = 1000 * (time.perf_counter() - start) / len(truth)
        rows = [(name, solver, solved, ms)]
        if name.startswith("FLAME"):  # the same rig without the lip term
            plain = ArkitSolver(solver.template, solver.blendshapes, solver.lip_pair, lips=0.0)
            rows.append((f"{name}, no lip term", plain, plain.solve(offsets), ms))
        for name, solver, solved, ms in rows:
            row(name, v, unit, pair, truth, offsets, solver, solved, ms, rig_s)


def row(name, v, unit, pair, truth, offsets, solver, solved, ms, rig_s) -> None:
    """One line of the table."""
    error = np.abs(solved.weights - truth).mean(0)
    worst = int(np.argmax(error))
    moved = np.einsum("tk,kvx->tvx", solved.weights.astype(np.float64), solver.blendshapes)
    true_gap = gap(v + offsets, pair) * 1000 / unit
    solved_gap = gap(v + moved, pair) * 1000 / unit
    print(
        f"| {name} | {len(v)} | {error.mean():.4f} | {ARKIT_NAMES[worst]} {error[worst]:.3f} | "
        f"{np.abs(solved_gap - true_gap).max():.2f} | {true_gap.min():.1f}-"
        f"{true_gap.max():.1f} | {solved.residual:.4f} | {ms:.2f} | "
        f"{'-' if name.startswith('bundled') else f'{rig_s:.0f}'} |"
    )


if __name__ == "__main__":
    main()
