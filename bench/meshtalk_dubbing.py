"""MeshTalk dubbing (paper Sec. 4.4) on the synthetic unseen-speaker test split, in one run.

    python bench/meshtalk_dubbing.py --model runs/meshtalk_synth/prior/model.safetensors [--limit 20]

Pairs of sentences of the same test speaker (i, j = the next sentence): the original animation of
sentence i is dubbed with the audio of sentence j (both cut to the shorter length). Reported:

* upper-face error: mean vertex distance over the upper face (the FDD region) to the ORIGINAL
  animation i (what dubbing should keep: blinks, brows);
* lip vertex error (max over lips per frame, mean over frames) against the ground truth of the
  NEW sentence j (what dubbing should change);

for the dubbed animation, next to: the original animation itself (no dubbing), MeshTalk's own
reconstruction of sentence j from its true motion and audio (the best the codes allow), MeshTalk's
prior driven by audio j alone (when the release has one: direct animation of the new audio), the
procedural animator driven by audio j, and the bundled CodeTalker driven by audio j.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from talkmesh.datasets.reader import open_dataset
from talkmesh.evaluation.metrics import lip_max_error


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True, type=Path, help="MeshTalk expression-space release")
    p.add_argument("--data", default="corpus/synth")
    p.add_argument("--limit", type=int, default=20, help="sentence pairs (default 20)")
    p.add_argument("--codetalker", default="codetalker-synth")
    args = p.parse_args()
    torch.set_num_threads(2)

    from talkmesh.audio.loading import SAMPLE_RATE
    from talkmesh.audio.phonemes import recognize_phones
    from talkmesh.face.assets import load_head
    from talkmesh.face.lipsync import phones_to_weights
    from talkmesh.models.release import load_model
    from talkmesh.training.meshtalk import load_system

    system = load_system(args.model)
    net = system.model
    ct = load_model(args.codetalker) if args.codetalker else None
    ds = open_dataset("synth", args.data, "test")
    lips, upper = ds.regions.lve, ds.regions.fdd
    by_subject: dict[str, list[int]] = {}
    for k in range(len(ds)):
        by_subject.setdefault(ds[k].subject, []).append(k)
    pairs = [(a, b) for ks in by_subject.values() for a, b in zip(ks, ks[1:] + ks[:1])]
    pairs = pairs[: args.limit]
    import json

    ids = {
        s: m["identity"]
        for s, m in json.loads((Path(args.data) / "manifest.json").read_text())["subjects"].items()
    }
    rows: dict[str, list[tuple[float, float]]] = {}

    def add(name: str, pred: np.ndarray, orig: np.ndarray, new: np.ndarray) -> None:
        up = np.linalg.norm(pred[:, upper] - orig[:, upper], axis=-1).mean() * 1e3
        lve = lip_max_error(pred, new, lips, squared=False).mean() * 1e3
        rows.setdefault(name, []).append((float(up), float(lve)))

    for a, b in pairs:
        sa, sb = ds[a], ds[b]
        T = min(len(sa.vertices), len(sb.vertices))
        S = int(T / ds.spec.motion_fps * SAMPLE_RATE)
        orig, new = sa.vertices[:T], sb.vertices[:T]
        template = torch.from_numpy(sa.template)[None]
        audio_b = torch.from_numpy(sb.audio[:S].astype(np.float32))[None]
        with torch.inference_mode():
            dubbed = net.dub(torch.from_numpy(orig)[None], template, audio_b)[0].numpy()
            recon = net.dub(torch.from_numpy(new)[None], template, audio_b)[0].numpy()
        add("dubbed (original i, audio j)", dubbed, orig, new)
        add("original animation i, undubbed", orig, orig, new)
        add("MeshTalk reconstruction of j (its motion and audio)", recon, orig, new)
        head = load_head(ids[sb.subject]).with_template(sb.template, sb.subject)
        weights = phones_to_weights(
            recognize_phones(sb.audio[:S]), T, ds.spec.motion_fps, audio=sb.audio[:S], seed=b
        )
        add("procedural, audio j", head.vertices_from_weights(weights), orig, new)
        if system.prior is not None:  # MeshTalk animating the new audio alone (prior sampling)
            verts = system.generate(audio_b, template, num_frames=T, seed=b)[0].numpy()
            add("MeshTalk animate (prior), audio j", verts, orig, new)
        if ct is not None:
            with torch.inference_mode():
                n = len(ct.cfg.stage2.styles)
                verts = ct.generate(
                    audio_b, template, style_weights=torch.full((1, n), 1 / n), num_frames=T
                )[0].numpy()
            add(f"{args.codetalker}, audio j", verts, orig, new)

    print(f"\n{len(pairs)} sentence pairs of the synthetic test speakers\n")
    print(
        "| animation | upper-face error to the original i (mm) | LVE to the new sentence j (mm) |"
    )
    print("|---|---|---|")
    for name, vals in rows.items():
        v = np.array(vals)
        print(f"| {name} | {v[:, 0].mean():.3f} | {v[:, 1].mean():.3f} |")


if __name__ == "__main__":
    main()
