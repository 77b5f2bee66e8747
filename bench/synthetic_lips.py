"""The real-speech lip metrics on the synthetic test split, where the motion truth is known.

    talkmesh synth --out corpus/synth
    talkmesh predict --model codetalker-synth --dataset synth --data corpus/synth --blinks -o runs/pred
    python bench/synthetic_lips.py --data corpus/synth --pred runs/pred [--variants default,faithful]

Scores, per test sequence and as medians, the lip metrics of :mod:`talkmesh.evaluation.real_speech`
(pause opening, speech:pause speed, /p b m/ closure, open-vowel opening, loudness correlation;
timing truth from forcing the sentence onto the audio) for: the corpus's own motion truth, the
model's saved predictions alone (``raw``), the predictions with each set of mouth corrections
(``default``: what ``talkmesh animate`` does; ``faithful``: :data:`FAITHFUL`; ``nobilabial``,
``nogain``), and the procedural animator on the recognised phones, with each one's LVE against
the truth (the physical protocol of ``talkmesh evaluate``).

It shows what the synthetic truth itself does on the real-speech targets: a correction that moves
the real recordings towards a target the truth does not meet costs LVE on this split.
"""

from __future__ import annotations

import argparse
import json
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from talkmesh.audio.loading import SAMPLE_RATE
from talkmesh.audio.phonemes import recognize_phones
from talkmesh.datasets.reader import open_dataset
from talkmesh.errors import TalkmeshError
from talkmesh.evaluation.evaluate import _identities, bundled_lip_pairs
from talkmesh.evaluation.metrics import pool, score_sequence
from talkmesh.evaluation.real_speech import METRICS, score_opening
from talkmesh.face.assets import lip_opening, load_head
from talkmesh.face.corrections import FAITHFUL, NONE, Corrections, correct_mouth
from talkmesh.pipeline import animate

FPS = 30.0
VARIANTS = {
    "raw": NONE,
    "default": Corrections(),
    "faithful": FAITHFUL,
    "nobilabial": replace(Corrections(), bilabial=False),
    "nogain": replace(Corrections(), gain=0.0),
}


def _aligned(audio: np.ndarray, text: str):
    """The sentence forced onto the audio, or None where it does not align."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UserWarning)
        phones = recognize_phones(audio, SAMPLE_RATE, text=text)
    return None if any(issubclass(w.category, UserWarning) for w in caught) else phones


def _outputs(sample, pred, face, variants, seed):
    """name -> (T, V, 3): the truth, the procedural animator and each variant of ``pred``."""
    phones = recognize_phones(sample.audio, SAMPLE_RATE)
    out = {"truth": sample.vertices}
    for name in variants:
        out[name] = correct_mouth(pred.copy(), face, phones, sample.audio, FPS, VARIANTS[name])
    out["procedural"] = animate(sample.audio, head=face, phones=phones, fps=FPS, seed=seed).vertices
    return out


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", required=True, type=Path, help="a `talkmesh synth` corpus")
    ap.add_argument("--pred", required=True, type=Path, help="`talkmesh predict` output (bare)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--variants", default=",".join(VARIANTS), help=", ".join(VARIANTS))
    ap.add_argument("--json", type=Path, default=None, help="also write the per-sequence scores")
    args = ap.parse_args()
    variants = [v for v in args.variants.split(",") if v]
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        raise SystemExit(f"unknown variant {unknown[0]}: choose from {', '.join(VARIANTS)}")
    dataset = open_dataset("synth", args.data, args.split)
    sentences = json.loads((args.data / "manifest.json").read_text())["sentences"]
    identities = _identities(args.data)
    methods = ["truth", *variants, "procedural"]
    scores = {m: [] for m in methods}
    pending = {m: [] for m in methods}
    for index in tqdm(range(len(dataset)), desc="synthetic lips", unit="seq"):
        name = dataset.names[index]
        sample = dataset[index]
        path = args.pred / f"{name}.npy"
        if not path.is_file():
            raise SystemExit(f"{path}: no prediction for {name}: run `talkmesh predict` first")
        pred = np.load(path).reshape(len(sample.vertices), -1, 3)
        face = load_head(identities.get(sample.subject)).with_template(
            sample.template, sample.subject
        )
        rest = float(lip_opening(face.template[None], face.regions)[0]) * 1000
        aligned = _aligned(sample.audio, sentences[name])
        pairs = bundled_lip_pairs(len(sample.template))
        regions = dataset.regions
        for m, verts in _outputs(sample, pred, face, variants, index).items():
            pending[m].append(
                score_sequence(
                    verts,
                    sample.vertices,
                    sample.template,
                    regions.lve,
                    regions.fdd,
                    "physical",
                    pairs,
                    name,
                    None,
                )
            )
            if aligned is not None:
                opening = lip_opening(verts, face.regions) * 1000
                scores[m].append(
                    {"sequence": name, **score_opening(opening, rest, aligned, sample.audio, FPS)}
                )
    print(f"{len(dataset)} {args.split} sequences ({len(scores['truth'])} aligned); medians:\n")
    print("| motion | LVE (mm) | " + " | ".join(METRICS) + " |")
    print("|---|---|" + "---|" * len(METRICS))
    for m in methods:
        lve = pool(pending[m], "physical").lve * 1000
        med = [np.nanmedian([s[k] for s in scores[m]]) for k in METRICS]
        print(f"| {m} | {lve:.3f} | " + " | ".join(f"{v:.2f}" for v in med) + " |")
    if args.json:
        args.json.write_text(json.dumps(scores, indent=1))


if __name__ == "__main__":
    try:
        main()
    except TalkmeshError as e:  # a missing corpus or a bad file: one line, no traceback
        raise SystemExit(f"synthetic_lips: {e}") from None
