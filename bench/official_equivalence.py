"""Imported official checkpoints against the official code's own output: max abs difference.

    python bench/official_equivalence.py [--fixtures tests/fixtures/official] [--meshtalk DIR]

Reads the official-format fixtures (tiny official models with random weights and the official
``predict`` output on speech.wav, made by ``scripts/make_official_fixtures.py --official PATH``),
imports each with ``talkmesh.models.official.import_checkpoint`` and prints, per family, dataset and
generation mode, the frame counts and max |talkmesh - official| / max |official motion|.

MeshTalk: ``--meshtalk DIR`` (default: the tiny fixture) is a folder written by
``scripts/make_official_fixtures.py --official MESHTALK_CHECKOUT [--meshtalk-size released]
[--wav WAV] --out DIR``: the official release files, the smoothing masks and the official
outputs of ``animate_face.py``'s steps (argmax codes; Gumbel draws under a seed), with the official
code's wall time. The table adds whether the codes are the official ones and both wall times
(talkmesh: import, then ``generate`` with the same seed: audio encoder, prior, decoder, smoothing).
"""

from __future__ import annotations

import argparse
import time
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
    p.add_argument("--meshtalk", type=Path, help="a MeshTalk folder (default: the fixture's)")
    p.add_argument("--wav", type=Path, help="the speech the MeshTalk folder was made from")
    p.add_argument("--only-meshtalk", action="store_true", help="skip FaceFormer and CodeTalker")
    args = p.parse_args()
    if not args.only_meshtalk:
        fixtures(args.fixtures)
    meshtalk(args.meshtalk or args.fixtures / "meshtalk", args.wav or args.fixtures / "speech.wav")


def meshtalk(folder: Path, wav: Path) -> None:
    """Rows for an official MeshTalk folder: codes equal, frames, max diff, wall times."""
    audio = torch.from_numpy(load_audio(wav))[None]
    model = import_checkpoint([folder], "meshtalk", "meshtalk")
    with np.load(folder / "meshtalk.npz", allow_pickle=False) as f:
        fx = {k: f[k] for k in f.files}
    template = torch.from_numpy(fx["template"])[None]
    V = template.shape[1]
    print()
    print(
        "| MeshTalk (V, H x C) | draws | frames (official / talkmesh) | same codes | "
        "max diff / motion | official s | talkmesh s |"
    )
    print("|---|---|---|---|---|---|---|")
    H, C = model.cfg.model.num_heads, model.cfg.model.num_classes
    for mode in ("argmax", "gumbel"):
        start = time.perf_counter()
        out = model.generate(audio, template, seed=int(fx["sample_seed"]), argmax=mode == "argmax")
        seconds = time.perf_counter() - start
        codes = model.sample_codes(audio, seed=int(fx["sample_seed"]), argmax=mode == "argmax")
        ref = fx[f"{mode}_smoothed"]
        out = out[0].numpy()
        n = min(len(out), len(ref))
        diff = np.abs(out[:n] - ref[:n]).max() / np.abs(ref - fx["template"]).max()
        same = bool(np.array_equal(codes[0, :n].numpy(), fx[f"{mode}_codes"][:n]))
        print(
            f"| {V}, {H} x {C} | {mode} | {len(ref)} / {len(out)} | {same} | {diff:.1e} | "
            f"{float(fx[f'{mode}_seconds']):.2f} | {seconds:.2f} |"
        )


def fixtures(folder: Path) -> None:
    """Rows for the FaceFormer and CodeTalker fixtures."""
    args = argparse.Namespace(fixtures=folder)
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
