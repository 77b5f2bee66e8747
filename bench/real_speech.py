"""Lip sync on real recordings, clean, under noise and under reverb: procedural vs bundled models.

    python bench/real_speech.py [--methods procedural,codetalker-synth,codetalker-synth-raw] [--conditions clean,snr10]
        [--clips cards,librivox] [--out docs/results]

Every real recording with a transcript that Debian packages put on the machine
(pocketsphinx-testdata: cards, LibriVox, goforward; alsa-utils' voice prompts), timing truth from
forced alignment of the transcript, metrics as defined in :mod:`talkmesh.evaluation.real_speech`.
Prints a per-clip table and the medians; with ``--out`` also writes ``real-speech.json`` and the
plot ``real-speech.png`` there.

``procedural-stream`` is the procedural animator as ``talkmesh serve`` streams it (audio pushed in
20 ms chunks, 100 ms look-ahead, the streaming recogniser settings ``ALLPHONE_STREAM``);
``procedural-stream-full`` streams the same way with the offline recogniser settings:

    python bench/real_speech.py --methods procedural,procedural-stream-full,procedural-stream --conditions clean
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from talkmesh.audio.loading import SAMPLE_RATE, load_audio
from talkmesh.audio.phonemes import ALLPHONE, ALLPHONE_STREAM, recognize_phones
from talkmesh.audio.vad import speech_pauses
from talkmesh.evaluation.real_speech import (
    BETTER,
    CONDITIONS,
    METRICS,
    NOISE_FILE,
    builtin_clips,
    degrade,
    medians,
    read_clip,
    score_clip,
    to_json,
    truth_phones,
)
from talkmesh.face.assets import load_head
from talkmesh.face.corrections import FAITHFUL, NONE, PREVIOUS, Corrections, correct_mouth
from talkmesh.pipeline import animate, available_models
from talkmesh.serve.stream import DEFAULT_LOOKAHEAD_MS, ProceduralStreamer

FPS = 30.0
STREAMED = {"procedural-stream": ALLPHONE_STREAM, "procedural-stream-full": ALLPHONE}
CHUNK = SAMPLE_RATE // 50  # 20 ms pushes, as bench/serve_load.py's clients send


# method suffixes: a learned model with no correction (the bare model), one default one off, the
# settings within 3% of the synthetic LVE (FAITHFUL) or the lip closure at every near-closure on
VARIANTS = {
    "": Corrections(),
    "-raw": NONE,
    "-nogate": replace(Corrections(), pause_gate=False),
    "-nomix": replace(Corrections(), mix=0.0),
    "-nogain": replace(Corrections(), gain=0.0),
    "-nobilabial": replace(Corrections(), bilabial=False),
    "-faithful": FAITHFUL,
    "-previous": PREVIOUS,
    "-closure": replace(Corrections(), lip_closure=True),
    # the pause gate alone, its pauses from voice activity (any language) or the recogniser
    "-gate": Corrections(mix=0.0, gain=0.0, bilabial=False),
    "-recgate": Corrections(mix=0.0, gain=0.0, bilabial=False, pauses="recognizer"),
    # no recogniser at all: the gate from voice activity and every near-closure shut
    "-anylang": Corrections(mix=0.0, gain=0.0, bilabial=False, lip_closure=True, met_lips=True),
}


def _split(method: str) -> tuple[str, Corrections]:
    for suffix, corrections in VARIANTS.items():
        if suffix and method.endswith(suffix):
            return method.removesuffix(suffix), corrections
    return method, VARIANTS[""]


def _streamed(wave: np.ndarray, head, search) -> np.ndarray:
    """(T, V, 3): the procedural animator streamed in 20 ms chunks with ``search``."""
    stream = ProceduralStreamer(DEFAULT_LOOKAHEAD_MS, head, True, fps=FPS, search=search)
    frames = []
    for i in range(0, len(wave), CHUNK):
        frames += stream.push(wave[i : i + CHUNK])
    frames += stream.flush()
    return head.template + np.stack([f.offsets for f in frames])


def _animate_condition(wave, methods, head) -> dict[str, np.ndarray]:
    """method -> (T, V, 3). The phones are recognised once: the procedural animator is driven by
    them and the corrections use them; a learned model runs once, bare, and each variant corrects
    a copy (the corrections move the mouth only, so this equals ``animate`` on the lips)."""
    phones = recognize_phones(wave, SAMPLE_RATE)
    pauses = None  # voice activity, found once when a variant's pause gate needs it
    bare = {}
    out = {}
    for method in methods:
        if method in STREAMED:
            out[method] = _streamed(wave, head, STREAMED[method])
            continue
        model, corrections = _split(method)
        if model == "procedural":
            out[method] = animate(wave, head=head, phones=phones, fps=FPS, seed=0).vertices
            continue
        if model not in bare:
            bare[model] = animate(
                wave,
                head=head,
                model=model,
                fps=FPS,
                pause_gate=False,
                lip_closure=False,
                procedural_mix=0.0,
                loudness_gain=0.0,
                bilabial_closure=False,
            ).vertices
        if corrections.pause_gate and corrections.pauses == "vad" and pauses is None:
            pauses = speech_pauses(wave)
        out[method] = correct_mouth(
            bare[model].copy(), head, phones, wave, FPS, corrections, pauses=pauses
        )
    return out


def _fmt(v: float) -> str:
    return "-" if math.isnan(v) else f"{v:.2f}"


def table(rows, med, methods, conditions) -> str:
    lines = [
        "| clip | condition | method | " + " | ".join(METRICS) + " |",
        "|---|---|---|" + "---|" * len(METRICS),
    ]
    for r in rows:
        vals = " | ".join(_fmt(getattr(r, m)) for m in METRICS)
        lines.append(f"| {r.clip} | {r.condition} | {r.method} | {vals} |")
    lines += [
        "",
        "Medians over clips:",
        "",
        "| condition | method | " + " | ".join(METRICS) + " |",
        "|---|---|" + "---|" * len(METRICS),
    ]
    for c in conditions:
        for m in methods:
            if (m, c) in med:
                vals = " | ".join(_fmt(med[(m, c)][k]) for k in METRICS)
                lines.append(f"| {c} | {m} | {vals} |")
    return "\n".join(lines)


def plot(med, methods, conditions, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(METRICS), figsize=(3.0 * len(METRICS), 2.8))
    x = np.arange(len(conditions))
    width = 0.8 / max(1, len(methods))
    for ax, metric in zip(axes, METRICS):
        for k, m in enumerate(methods):
            vals = [med.get((m, c), {}).get(metric, math.nan) for c in conditions]
            ax.bar(x + k * width, vals, width, label=m)
        ax.set_xticks(x + width * (len(methods) - 1) / 2, conditions, rotation=45, fontsize=7)
        arrow = "higher" if BETTER[metric] > 0 else "lower"
        ax.set_title(f"{metric} ({arrow} is better)", fontsize=8)
        if metric == "speed_ratio":
            ax.set_yscale("log")
    axes[0].legend(fontsize=7)
    fig.suptitle("Real recordings: median over clips", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    learned = [m for m in available_models() if m != "procedural"]
    default = ["procedural", *(m + v for m in learned for v in VARIANTS)]
    ap.add_argument(
        "--methods",
        default=",".join(default),
        help="procedural, procedural-stream(-full) (module docstring), bundled models as animate "
        "runs them (default corrections), MODEL-raw (none), MODEL-nogate / -nomix / -nogain / "
        "-nobilabial (one off), MODEL-faithful (the settings within 3% of the synthetic LVE), "
        "MODEL-closure (with the lip closure at every near-closure), MODEL-gate / -recgate (the "
        "pause gate alone, from voice activity / from the recogniser)",
    )
    ap.add_argument("--conditions", default=",".join(CONDITIONS))
    ap.add_argument("--clips", default="", help="comma-separated name prefixes (default: all)")
    ap.add_argument("--out", type=Path, default=None, help="folder for real-speech.json/.png")
    args = ap.parse_args()
    methods = [m for m in args.methods.split(",") if m]
    conditions = [c for c in args.conditions.split(",") if c]
    prefixes = [p for p in args.clips.split(",") if p]
    clips = [c for c in builtin_clips() if not prefixes or c.name.startswith(tuple(prefixes))]
    if not clips:
        raise SystemExit("no real recordings found: install pocketsphinx-testdata and alsa-utils")
    head = load_head()
    noise = load_audio(NOISE_FILE) if NOISE_FILE.is_file() else None
    rows = []
    with tqdm(total=len(clips) * len(conditions) * len(methods), desc="real speech") as bar:
        for clip in clips:
            wave = read_clip(clip)
            phones = truth_phones(clip, wave)
            for condition in conditions:
                degraded = degrade(wave, condition, noise, seed=0)
                animated = _animate_condition(degraded, methods, head)
                for method in methods:
                    vertices = animated[method]
                    rows.append(
                        score_clip(
                            clip,
                            method,
                            condition,
                            vertices,
                            head,
                            phones,
                            degraded,
                            FPS,
                        )
                    )
                    bar.update()
    med = medians(rows)
    print(table(rows, med, methods, conditions))
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "real-speech.json").write_text(json.dumps(to_json(rows), indent=1))
        plot(med, methods, conditions, args.out / "real-speech.png")
        print(f"wrote {args.out / 'real-speech.json'} and {args.out / 'real-speech.png'}")


if __name__ == "__main__":
    main()
