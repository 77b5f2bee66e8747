"""How well `talkmesh rig` carries the 52 ARKit blendshapes onto a head, where the truth is known.

The bundled head is turned into "user" meshes whose true blendshapes follow from the bundled ones:

* rescaled to centimetres or millimetres and rotated to another up-axis (truth: the same offsets,
  scaled and rotated);
* remeshed denser by one midpoint subdivision (truth: the subdivided shapes);
* remeshed coarser by quadric decimation (fast-simplification) to 50% and 25% of its triangles
  (truth: the bundled shapes at each new vertex's closest point on the bundled surface, among the
  triangles facing its way);
* with its vertices shuffled;
* the bundled identities (one blendshape set serves them all, so it is their truth).

Both methods run on every case: ``transfer`` (deformation transfer, the default) and ``closest``
(closest-point offsets, the earlier method). Per shape: the mean vertex error in mm and as % of the
shape's own mean displacement, averaged over the 52 shapes (and the worst shape); the lip gap
(between the rig's upper_lip and lower_lip landmarks) under jawOpen and under mouthClose +
jawOpen, truth vs transfer.

    PYTHONPATH=src python bench/rig_transfer.py [--quick] [--landmarks] [--automatic nose_tip,...]
        [--no-pre-fit] [--only identity,coarser,...]

``--landmarks`` prints instead how far (mm) each landmark the rig places automatically (the nose
tip, lips, mouth corners, chin and eye corners found on the user's mesh, the others placed from
the registered head) lies from its true point. ``--automatic`` names the landmarks found on the
mesh that hold the registration (default: all of ``rig.AUTOMATIC``; ``nose_tip`` alone is the fit
before the others were found). ``--no-pre-fit`` starts the non-rigid solve from the rigid fit
(the registration before the smoothed pull came first); ``--only`` keeps the cases whose names
contain one of the words given.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import trimesh

from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import list_identities, load_head
from talkmesh.face.registration import closest_points, vertex_normals
from talkmesh.face.rig import AUTOMATIC, LANDMARK_NAMES, METHODS, head_landmarks, rig_head

JAW, CLOSE = ARKIT_NAMES.index("jawOpen"), ARKIT_NAMES.index("mouthClose")


def rotation(axis, degrees) -> np.ndarray:
    return trimesh.transformations.rotation_matrix(np.radians(degrees), axis)[:3, :3]


def subdivide(vertices, faces, shapes):
    """One midpoint subdivision of the head and of every shape (the shapes' truth)."""
    new_v, new_f = trimesh.remesh.subdivide(vertices, faces)
    moved = [trimesh.remesh.subdivide(vertices + s, faces)[0] - new_v for s in shapes]
    return new_v, new_f, np.stack(moved)


def decimate(vertices, faces, shapes, keep):
    """Quadric decimation to ``keep`` of the triangles; truth: the shapes at the closest point."""
    import fast_simplification

    new_v, new_f = fast_simplification.simplify(
        vertices.astype(np.float32), faces.astype(np.int64), target_reduction=1 - keep
    )
    new_v = new_v.astype(np.float64)
    normals = vertex_normals(new_v, new_f)
    face, bary, _ = closest_points(new_v, vertices, faces.astype(np.int64), normals)
    truth = np.einsum("vc,kvcx->kvx", bary, shapes[:, faces[face]])
    return new_v, new_f, truth


def lip_gap(vertices, offsets, weights, pair):
    """Distance between the two lip vertices ``pair`` with ``weights`` {shape: w} applied."""
    v = vertices[pair] + sum(w * offsets[k][pair] for k, w in weights.items())
    return float(np.linalg.norm(v[0] - v[1]))


def cases(head, quick: bool):
    """(name, vertices, faces, true shapes, units per metre, true landmark points (L, 3))."""
    v, f, s = (
        head.template.astype(np.float64),
        head.faces,
        head.blendshapes.astype(np.float64),
    )
    at = v[[head_landmarks(head)[k] for k in LANDMARK_NAMES]]
    r_z = rotation([1, 0, 0], -90)  # a Z-up export
    yield (
        "cm, Z-up",
        100 * v @ r_z.T + [3, -2, 10],
        f,
        100 * s @ r_z.T,
        100,
        100 * at @ r_z.T + [3, -2, 10],
    )
    if not quick:
        r = rotation([0.3, 1, 0.2], 37)
        yield (
            "mm, rotated 37 deg",
            1000 * v @ r.T,
            f,
            1000 * s @ r.T,
            1000,
            1000 * at @ r.T,
        )
        yield ("denser (subdivided)", *subdivide(v, f, s), 1, at)
    yield ("coarser (50% of triangles)", *decimate(v, f, s, 0.5), 1, at)
    cv, cf, cs = decimate(v, f, s, 0.25)
    r = rotation([1, 0.2, 0], 25)
    yield (
        "coarser (25%), mm, rotated 25 deg",
        1000 * cv @ r.T,
        cf,
        1000 * cs @ r.T,
        1000,
        1000 * at @ r.T,
    )
    if not quick:
        perm = np.random.default_rng(0).permutation(len(v))
        yield "shuffled vertices", v[perm], np.argsort(perm)[f], s[:, perm], 1, at
    for name in list_identities()[: 1 if quick else 3]:
        other = load_head(name).template.astype(np.float64)
        yield (
            f"identity {name}",
            other,
            f,
            s,
            1,
            other[[head_landmarks(head)[k] for k in LANDMARK_NAMES]],
        )


def landmark_table(head, chosen, options) -> None:
    """The automatic landmarks' distance (mm) from the true points, per landmark and case."""
    print("| case | " + " | ".join(LANDMARK_NAMES) + " | mean |")
    print("|---|" + "---|" * (len(LANDMARK_NAMES) + 1))
    for name, v, f, _, unit, at in chosen:
        rig = rig_head(v, f, head, method="closest", **options)
        placed = v[[rig.landmarks[k] for k in LANDMARK_NAMES]]
        err = np.linalg.norm(placed - at, axis=1) / unit * 1000
        print(f"| {name} | " + " | ".join(f"{e:.1f}" for e in err) + f" | {err.mean():.1f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="three cases only")
    parser.add_argument(
        "--landmarks",
        action="store_true",
        help="the automatic landmarks' error instead",
    )
    parser.add_argument(
        "--automatic",
        default=",".join(AUTOMATIC),
        help="landmarks found on the mesh that hold the fit, comma-separated",
    )
    parser.add_argument(
        "--no-pre-fit",
        action="store_true",
        help="start the non-rigid solve from the rigid fit, not the smoothed pull",
    )
    parser.add_argument("--only", default="", help="cases whose names contain one of these words")
    args = parser.parse_args()
    options = {
        "automatic": tuple(k for k in args.automatic.split(",") if k),
        "pre_fit": not args.no_pre_fit,
    }
    words = [w for w in args.only.split(",") if w]
    head = load_head()
    chosen = (c for c in cases(head, args.quick) if not words or any(w in c[0] for w in words))
    if args.landmarks:
        landmark_table(head, chosen, options)
        return
    print(
        "| case | method | vertices | units | up | mean err mm | worst shape mm | mean % | "
        "worst % | jaw gap mm true/ours | close+jaw gap mm true/ours | s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, v, f, truth, unit, _ in chosen:
        for method in METHODS:
            t = time.perf_counter()
            rig = rig_head(v, f, head, method=method, **options)
            seconds = time.perf_counter() - t
            err = np.linalg.norm(rig.blendshapes - truth, axis=2).mean(1) / unit * 1000
            mag = np.linalg.norm(truth, axis=2).mean(1) / unit * 1000
            pct = 100 * err / mag
            pair = [rig.landmarks["upper_lip"], rig.landmarks["lower_lip"]]
            gaps = [
                lip_gap(v, o, w, pair) / unit * 1000
                for w in ({JAW: 1.0}, {JAW: 1.0, CLOSE: 1.0})
                for o in (truth, rig.blendshapes)
            ]
            print(
                f"| {name} | {method} | {len(v)} | {rig.units} | {rig.up_axis} | "
                f"{err.mean():.3f} | {err.max():.3f} ({ARKIT_NAMES[int(err.argmax())]}) | "
                f"{pct.mean():.1f} | {pct.max():.1f} | {gaps[0]:.1f}/{gaps[1]:.1f} | "
                f"{gaps[2]:.1f}/{gaps[3]:.1f} | {seconds:.1f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
