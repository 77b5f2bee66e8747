"""Imported official checkpoints against the official code's own output: max abs difference.

    python bench/official_equivalence.py [--fixtures tests/fixtures/official]

Reads the official-format fixtures (tiny official models with random weights and the official
``predict`` output on speech.wav, made by ``scripts/make_official_fixtures.py --official PATH``),
imports each with ``talkmesh.models.official.import_checkpoint`` and prints, per family, dataset and
generation mode, the frame counts and max |talkmesh - official| / max |official motion|.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from talkmesh.audio.loading import load_audio
from talkmesh.models.official import import_checkpoint

ROOT = Path(__file__).resolve().parents[1]
CASES = {
    "faceformer": lambda d: [f"faceformer_{d}.pth"],
    "codetalker": lambda d: [f"codetalker_{d}_stage1.pth.tar", f"codetalker_{d}_stage2.pth.tar"],
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--fixtures", type=Path, default=ROOT / "tests" / "fixtures" / "official")
    args = p.parse_args()
    audio = torch.from_numpy(load_audio(args.fixtures / "speech.wav"))[None]
    print("| family | dataset | mode | frames (official) | frames (talkmesh) | max diff / motion |")
    print("|---|---|---|---|---|---|")
    for family, files in CASES.items():
        for dataset in ("vocaset", "biwi"):
            paths = [args.fixtures / f for f in files(dataset)]
            model = import_checkpoint(paths, family, dataset)
            with np.load(args.fixtures / f"{family}_{dataset}.npz", allow_pickle=False) as f:
                template, ref, condition = f["template"], f["vertices"], str(f["condition"])
            scale = np.abs(ref - template).max()
            style = torch.tensor([list(model.styles).index(condition)])
            for mode in model.generation_modes:
                out = model.generate(
                    audio, torch.from_numpy(template)[None], styles=style, mode=mode
                )[0].numpy()
                n = min(len(out), len(ref))
                diff = np.abs(out[:n] - ref[:n]).max() / scale
                print(f"| {family} | {dataset} | {mode} | {len(ref)} | {len(out)} | {diff:.1e} |")


if __name__ == "__main__":
    main()
