"""What a CodeTalker's motion stage can draw: /p b m/ closed when the truth's own codes are decoded.

    python bench/vq_closure.py --data corpus/multilingual --models codetalker-synth,runs/x/model.safetensors
        [--split test] [--per-voice 2]

The speech stage picks codes and the VQ decoder draws them, so a closure the decoder cannot draw
from the truth's own codes is one no speech stage can give. Each clip's motion truth (the
teacher) is encoded, quantised and decoded by each model's stage 1 alone
(``CodeTalker.reconstruct``); every /p b m/ of the synthesiser's timings counts as closed where
the lips come within ``CLOSED_MM`` of each other during the phone, as in the real-speech metrics.
Prints per face (by how far its lips stand apart at rest) the share closed by the truth and by
each model's reconstruction, and the median smallest opening.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from multilingual import FPS, _sequences  # noqa: E402

from talkmesh.datasets.multilingual import read_phones  # noqa: E402
from talkmesh.evaluation.real_speech import BILABIALS, CLOSED_MM, phone_window  # noqa: E402
from talkmesh.face.assets import lip_opening, load_head  # noqa: E402
from talkmesh.models.release import load_model  # noqa: E402


def smallest_openings(opening_mm: np.ndarray, phones) -> list[float]:
    """The smallest lip opening (mm) within each /p b m/ of ``phones`` (one frame either side)."""
    out = []
    for p in phones:
        lo, hi = phone_window(p, FPS, len(opening_mm))
        if p.label in BILABIALS and hi > lo:
            out.append(float(opening_mm[lo:hi].min()))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=Path, help="a multilingual corpus")
    ap.add_argument("--models", default="codetalker-synth", help="comma-separated releases")
    ap.add_argument("--split", default="test")
    ap.add_argument("--per-voice", type=int, default=2, help="utterances per voice")
    args = ap.parse_args()
    models = [m for m in args.models.split(",") if m]
    nets = {m: load_model(m, family="codetalker") for m in models}
    faces: dict[str, dict] = {}
    clips = list(_sequences(args.data, args.split, args.per_voice, set()))
    for name, info, _ in tqdm(clips, desc="vq closure", unit="clip"):
        head = load_head(info["identity"])
        truth = np.load(args.data / "vertices_npy" / f"{name}.npy")[::2]  # 60 -> 30 fps
        truth = truth.reshape(len(truth), -1, 3).astype(np.float32)
        phones = read_phones(args.data, name)
        face = faces.setdefault(info["identity"], {"rest": _rest(head), "truth": []})
        face["truth"] += smallest_openings(lip_opening(truth, head.regions) * 1000, phones)
        template = torch.from_numpy(head.template.astype(np.float32))[None]
        for m, net in nets.items():
            with torch.inference_mode():
                drawn = net.reconstruct(torch.from_numpy(truth)[None], template)[0].numpy()
            opening = lip_opening(drawn, head.regions) * 1000
            face.setdefault(m, []).extend(smallest_openings(opening, phones))
    print(report(faces, models))


def _rest(head) -> float:
    return float(lip_opening(head.template[None], head.regions)[0]) * 1000


def report(faces: dict[str, dict], models: list[str]) -> str:
    """Per face: /p b m/ closed by the truth and each model's stage 1, and (in brackets) the
    median smallest opening in mm."""
    lines = [
        f"/p b m/ closed (smallest opening <= {CLOSED_MM} mm; median smallest opening, mm)",
        "",
        "| face | rest opening (mm) | /p b m/ | truth | " + " | ".join(models) + " |",
        "|---|---|---|---|" + "---|" * len(models),
    ]
    for h, f in sorted(faces.items(), key=lambda kv: kv[1]["rest"]):
        cells = []
        for key in ("truth", *models):
            v = np.asarray(f[key])
            cells.append(f"{(v <= CLOSED_MM).mean():.2f} ({np.median(v):.2f})" if len(v) else "-")
        lines.append(f"| {h} | {f['rest']:.2f} | {len(f['truth'])} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
