"""Where the synthetic corpus's upper-face dynamics come from: the ground-truth D (mean over
upper-face vertices of the std over time of the distance to the template, the quantity FDD
compares) with each group of ARKit channels removed from the truth's own weights; then the FDD
that an ORACLE would score: the truth's own channels except the eyes, whose blinks and gaze are
sampled by the procedural animator (as a speech-driven model plus procedural blinks would be at
best), for a few blink seeds.

    python scripts/fdd_sources.py --data corpus/synth [--split test]
"""

from __future__ import annotations

import argparse

import numpy as np

from talkmesh.datasets.reader import open_dataset
from talkmesh.evaluation.metrics import dynamics
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import load_head
from talkmesh.face.lipsync import BLINK_GAZE, blink_gaze_weights

GROUPS = {
    "blinks": lambda n: n.startswith("eyeBlink"),
    "brows and squint": lambda n: n.startswith(("brow", "eyeSquint")),
    "gaze": lambda n: n.startswith("eyeLook"),
}
EYES = [k for k, n in enumerate(ARKIT_NAMES) if n in BLINK_GAZE]
# blink seeds of the oracle: the sequence index (what `talkmesh predict --blinks` uses), and fixed
# seeds shared by every sequence (the procedural baseline uses seed 0 for all of them)
ORACLE_SEEDS = ("index", 0, 1, 2, 3, 4)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default="corpus/synth")
    p.add_argument("--split", default="test")
    args = p.parse_args()
    ds = open_dataset("synth", args.data, args.split)
    head = load_head()
    upper = ds.regions.fdd
    fps = ds.spec.motion_fps
    full, without = [], {g: [] for g in GROUPS}
    oracle = {s: [] for s in ORACLE_SEEDS}
    for i in range(len(ds)):
        s = ds[i]
        w = np.load(f"{args.data}/arkit/{s.name}.npy")[::2][: len(s.vertices)]  # 60 -> 30 fps
        neutral = head.vertices_from_weights(np.zeros_like(w[:1]))

        def d_of(weights: np.ndarray, template=s.template, neutral=neutral) -> float:
            v = template[None] + head.vertices_from_weights(weights) - neutral
            return dynamics(v, template, upper, squared=False)

        d_gt = dynamics(s.vertices, s.template, upper, squared=False)
        full.append(d_gt)
        for g, pick in GROUPS.items():
            w2 = w.copy()
            w2[:, [k for k, n in enumerate(ARKIT_NAMES) if pick(n)]] = 0
            without[g].append(d_of(w2))
        for seed in ORACLE_SEEDS:
            w2 = w.copy()
            eyes = blink_gaze_weights(len(w), fps, seed=i if seed == "index" else seed)
            w2[:, EYES] = eyes[:, EYES]
            oracle[seed].append(abs(d_gt - d_of(w2)))
    d = np.mean(full)
    print(f"{len(ds)} sequences; ground-truth D = {d * 1e3:.3f} mm\n")
    print("| channels removed | D (mm) | share of D |")
    print("|---|---|---|")
    for g, vals in without.items():
        share = round((d - np.mean(vals)) / d, 2) + 0.0  # no "-0%"
        print(f"| {g} | {np.mean(vals) * 1e3:.3f} | {share:.0%} |")
    print("\nOracle: the truth's own weights with the eyes (blinks, gaze) re-sampled\n")
    print("| blink seed | FDD (mm, abs.) |")
    print("|---|---|")
    for seed, vals in oracle.items():
        print(f"| {seed} | {np.mean(vals) * 1e3:.3f} |")
    fixed = [np.mean(v) * 1e3 for k, v in oracle.items() if k != "index"]
    print(
        f"\nfixed seeds: mean {np.mean(fixed):.3f}, min {min(fixed):.3f}, max {max(fixed):.3f} mm"
    )


if __name__ == "__main__":
    main()
