"""Lip sync in many languages: held-out voices of trained languages and languages never trained on.

    talkmesh synth --multilingual --out corpus/multilingual
    python bench/multilingual.py --data corpus/multilingual [--methods procedural,codetalker-synth-raw,codetalker-synth]
        [--conditions clean,snr15] [--per-voice 4] [--face gus] [--out docs/results]

The test split of the multilingual corpus (:mod:`talkmesh.datasets.multilingual`): voices no
model trained on, in languages trained on and in languages never trained on. Timing truth is the
synthesiser's own phone timings (``phones/NAME.json``), exact. Every method hears the audio
alone, clean and under real recorded noise (alsa-utils' ``Noise.wav``) at 15 dB SNR, and is
scored with the real-speech metrics (:mod:`talkmesh.evaluation.real_speech`) on the head of the
sequence's subject. Methods are those of ``bench/real_speech.py`` (``procedural``: the animator on
the phones the English recogniser finds, as ``--model procedural`` does; ``MODEL-raw``: a learned
model with every correction off; ``MODEL``: as ``animate`` runs it; ``MODEL-streamMS``: alone, as
``talkmesh serve`` streams it with MS ms of look-ahead; ``MODEL`` may be a release file), plus
``truth`` (the corpus's motion truth, the teacher: clean only).

Prints a table per language (medians over its clips) and the pooled medians; with ``--out`` also
writes ``multilingual.json`` and the plot ``multilingual.png`` there. ``--face`` animates every
clip on one face instead of its subject's (the truth, made on the subject's face, is then left
out): whether a language's score comes from its voice or from the face it was heard with.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_speech import _animate_condition, _fmt  # noqa: E402

from talkmesh.audio.loading import load_audio  # noqa: E402
from talkmesh.datasets.multilingual import read_phones  # noqa: E402
from talkmesh.evaluation.real_speech import (  # noqa: E402
    METRICS,
    NOISE_FILE,
    add_noise,
    closed_of_all,
    score_opening,
)
from talkmesh.face.assets import lip_opening, list_identities, load_head  # noqa: E402

FPS = 30.0
CONDITIONS = ("clean", "snr15")
TITLES = {"bilabial": "/p b m/ closed", "vowel_mm": "Open vowels' opening above rest (mm)"}


def _sequences(root: Path, split: str, per_voice: int, languages: set[str]):
    manifest = json.loads((root / "manifest.json").read_text())
    for subject, ids in manifest["splits"][split].items():
        info = manifest["subjects"][subject]
        if languages and info["language"] not in languages:
            continue
        trained = any(
            manifest["subjects"][s]["language"] == info["language"]
            for s in manifest["splits"]["train"]
        )
        for sid in ids[:per_voice]:
            yield f"{subject}_{sid}", info, trained


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", required=True, type=Path, help="a multilingual corpus")
    ap.add_argument("--split", default="test")
    ap.add_argument("--methods", default="procedural,codetalker-synth-raw,codetalker-synth")
    ap.add_argument("--conditions", default=",".join(CONDITIONS))
    ap.add_argument("--per-voice", type=int, default=4, help="utterances per held-out voice")
    ap.add_argument("--languages", default="", help="comma-separated codes (default: all)")
    ap.add_argument(
        "--face",
        default="",
        help="animate every clip on this face (an identity: gus, lars, ...) instead of its "
        "subject's, to tell what a voice costs from what a face costs",
    )
    ap.add_argument("--out", type=Path, default=None, help="folder for multilingual.json/.png")
    ap.add_argument(
        "--merge",
        type=Path,
        action="append",
        default=[],
        help="rows of an earlier run (multilingual.json) to report beside these (same clips)",
    )
    args = ap.parse_args()
    if not (args.data / "manifest.json").is_file():
        raise SystemExit(f"{args.data}: no multilingual corpus (talkmesh synth --multilingual)")
    methods = [m for m in args.methods.split(",") if m]
    if args.face and "truth" in methods:
        raise SystemExit("--face: the truth was made on each subject's own face; leave it out")
    if args.face and args.face not in list_identities():
        raise SystemExit(
            f"--face {args.face}: no such face; use one of {', '.join(list_identities())}"
        )
    conditions = [c for c in args.conditions.split(",") if c]
    noise = load_audio(NOISE_FILE) if NOISE_FILE.is_file() else None
    if any(c != "clean" for c in conditions) and noise is None:
        raise SystemExit(f"{NOISE_FILE} is missing: install alsa-utils for the noise condition")
    wanted = {c for c in args.languages.split(",") if c}
    todo = list(_sequences(args.data, args.split, args.per_voice, wanted))
    if not todo:
        raise SystemExit(f"{args.data}: nothing in the {args.split} split to score")
    rows = []
    heads = {}
    for k, (name, info, trained) in enumerate(tqdm(todo, desc="multilingual", unit="clip")):
        identity = args.face or info["identity"]
        head = heads.setdefault(identity, load_head(identity))
        rest = float(lip_opening(head.template[None], head.regions)[0]) * 1000
        wave = load_audio(args.data / "wav" / f"{name}.wav")
        phones = read_phones(args.data, name)
        for condition in conditions:
            heard = wave if condition == "clean" else add_noise(wave, noise, 15.0, seed=k)
            learned = [m for m in methods if m != "truth"]
            animated = _animate_condition(heard, learned, head)
            if "truth" in methods and condition == "clean":
                truth = np.load(args.data / "vertices_npy" / f"{name}.npy")[::2]
                animated["truth"] = truth.reshape(len(truth), -1, 3)
            for method, vertices in animated.items():
                opening = lip_opening(vertices, head.regions) * 1000
                scores = score_opening(opening, rest, phones, heard, FPS)
                rows.append(
                    {
                        "clip": name,
                        "language": info["language"],
                        "trained_language": trained,
                        "condition": condition,
                        "method": method,
                        **scores,
                    }
                )
    for earlier in args.merge:
        old = json.loads(earlier.read_text())
        methods = [*dict.fromkeys([r["method"] for r in old] + methods)]
        rows = old + rows
    print(report(rows, methods, conditions))
    faces = _identities(args.data)
    faces = {s: args.face for s in faces} if args.face else faces
    print(by_head(rows, methods, faces))
    print(by_head(rows, methods, faces, "vowel_mm"))
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "multilingual.json").write_text(json.dumps(rows, indent=1))
        plot(rows, methods, conditions, args.out / "multilingual.png")
        print(f"wrote {args.out / 'multilingual.json'} and {args.out / 'multilingual.png'}")


def _median(rows, key):
    vals = [r[key] for r in rows if not math.isnan(r[key])]
    return float(np.median(vals)) if vals else math.nan


def _extreme(rows, key, pick):
    vals = [r[key] for r in rows if not math.isnan(r[key])]
    return pick(vals) if vals else math.nan


def report(rows, methods, conditions) -> str:
    languages = sorted({r["language"] for r in rows})
    lines = []
    for condition in conditions:
        lines += [
            f"### {condition}",
            "",
            "| language | trained on | method | clips | "
            + " | ".join(METRICS)
            + " | worst pause | slowest speed_ratio | /p b m/ closed of all |",
            "|---|---|---|---|" + "---|" * (len(METRICS) + 3),
        ]
        for lang in [*languages, "all"]:
            for m in methods:
                sel = [
                    r
                    for r in rows
                    if r["method"] == m
                    and r["condition"] == condition
                    and (lang == "all" or r["language"] == lang)
                ]
                if not sel:
                    continue
                trained = "-" if lang == "all" else ("yes" if sel[0]["trained_language"] else "no")
                vals = " | ".join(_fmt(_median(sel, k)) for k in METRICS)
                worst = _extreme(sel, "pause_mm", max)
                slowest = _extreme(sel, "speed_ratio", min)
                closed, total = closed_of_all((r["bilabial"], r["bilabials"]) for r in sel)
                lines.append(
                    f"| {lang} | {trained} | {m} | {len(sel)} | {vals} | {_fmt(worst)} | "
                    f"{_fmt(slowest)} | {closed}/{total} |"
                )
        lines.append("")
    return "\n".join(lines)


def _identities(root: Path) -> dict[str, str]:
    """Subject -> the face it speaks with, from the corpus manifest."""
    manifest = json.loads((root / "manifest.json").read_text())
    return {s: info["identity"] for s, info in manifest["subjects"].items()}


def by_head(rows, methods, identities: dict[str, str], key: str = "bilabial") -> str:
    """/p b m/ closure (clean) per face, by how far its lips stand apart at rest: a closure
    moves them that far, so a model that does not know the face closes some faces and not others.
    ``key="vowel_mm"``: the open vowels' opening above rest per face instead."""
    heads: dict[str, list] = {}
    for r in rows:
        if r["condition"] == "clean":
            subject = r["clip"].rsplit("_", 1)[0]
            heads.setdefault(identities.get(subject, "?"), []).append(r)
    rest = {h: float(lip_opening(load_head(h).template[None], load_head(h).regions)[0]) * 1000
            for h in heads if h != "?"}  # fmt: skip
    lines = [
        f"### {TITLES[key]}, clean, per face (by its lips' opening at rest)",
        "",
        "| face | rest opening (mm) | " + " | ".join(methods) + " |",
        "|---|---|" + "---|" * len(methods),
    ]
    for h in sorted(rest, key=rest.get):
        vals = []
        for m in methods:
            sel = [r for r in heads[h] if r["method"] == m]
            vals.append(_fmt(_median(sel, key)) if sel else "-")
        lines.append(f"| {h} | {rest[h]:.2f} | " + " | ".join(vals) + " |")
    return "\n".join(lines) + "\n"


def plot(rows, methods, conditions, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    languages = sorted({r["language"] for r in rows})
    fig, axes = plt.subplots(len(conditions), 1, figsize=(10, 2.6 * len(conditions)), squeeze=False)
    width = 0.8 / max(1, len(methods))
    x = np.arange(len(languages))
    for ax, condition in zip(axes[:, 0], conditions):
        for k, m in enumerate(methods):
            vals = [
                _median(
                    [
                        r
                        for r in rows
                        if r["method"] == m
                        and r["condition"] == condition
                        and r["language"] == lang
                    ]
                    or [{"bilabial": math.nan}],
                    "bilabial",
                )
                for lang in languages
            ]
            ax.bar(x + k * width, vals, width, label=m)
        ax.axhline(0.85, color="k", lw=0.6, ls="--")
        ax.set_xticks(x + width * (len(methods) - 1) / 2, languages, fontsize=7)
        ax.set_ylim(0, 1.05)
        ax.set_ylabel("/p b m/ closed", fontsize=8)
        ax.set_title(f"/p b m/ closure per language ({condition}; dashed: 0.85)", fontsize=9)
    axes[0, 0].legend(fontsize=7, ncol=len(methods))
    fig.tight_layout()
    fig.savefig(path, dpi=80)


if __name__ == "__main__":
    main()
