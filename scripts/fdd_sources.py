"""Where the synthetic corpus's upper-face dynamics come from: the ground-truth D (mean over
upper-face vertices of the std over time of the distance to the template, the quantity FDD
compares) with each group of ARKit channels removed from the truth's own weights.

    python scripts/fdd_sources.py --data corpus/synth [--split test]
"""

from __future__ import annotations

import argparse

import numpy as np

from talkmesh.arkit import ARKIT_NAMES
from talkmesh.assets import load_head
from talkmesh.datasets import open_dataset
from talkmesh.metrics import dynamics

GROUPS = {
    "blinks": lambda n: n.startswith("eyeBlink"),
    "brows and squint": lambda n: n.startswith(("brow", "eyeSquint")),
    "gaze": lambda n: n.startswith("eyeLook"),
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default="corpus/synth")
    p.add_argument("--split", default="test")
    args = p.parse_args()
    ds = open_dataset("synth", args.data, args.split)
    head = load_head()
    upper = ds.regions.fdd
    full, without = [], {g: [] for g in GROUPS}
    for i in range(len(ds)):
        s = ds[i]
        w = np.load(f"{args.data}/arkit/{s.name}.npy")[::2][: len(s.vertices)]  # 60 -> 30 fps
        neutral = head.vertices_from_weights(np.zeros_like(w[:1]))
        full.append(dynamics(s.vertices, s.template, upper, squared=False))
        for g, pick in GROUPS.items():
            w2 = w.copy()
            w2[:, [k for k, n in enumerate(ARKIT_NAMES) if pick(n)]] = 0
            v = s.template[None] + head.vertices_from_weights(w2) - neutral
            without[g].append(dynamics(v, s.template, upper, squared=False))
    d = np.mean(full)
    print(f"{len(ds)} sequences; ground-truth D = {d * 1e3:.3f} mm\n")
    print("| channels removed | D (mm) | share of D |")
    print("|---|---|---|")
    for g, vals in without.items():
        print(f"| {g} | {np.mean(vals) * 1e3:.3f} | {(d - np.mean(vals)) / d:.0%} |")


if __name__ == "__main__":
    main()
