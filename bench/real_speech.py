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

``MODEL-streamMS`` is a learned model alone (every correction off) as ``talkmesh serve`` streams it
with a look-ahead of MS ms: for the bundled CodeTalker its Whisper features a 3-frame block at a
time (:mod:`talkmesh.models.whisper_stream`), computed offline by ``generate_streamed``, which the
stream equals (tests/test_whisper_stream.py):

    python bench/real_speech.py --methods codetalker-synth-raw,codetalker-synth-stream100,codetalker-synth-stream300

``--emotions`` animates every method again under each emotion at full intensity (method names
``METHOD+EMOTION``) and prints how far its /p b m/ closure, pause rest and vowel opening are from
the neutral run (docs/guide/performance.md):

    python bench/real_speech.py --methods procedural,codetalker-synth --conditions clean \
        --emotions neutral,happy,sad,angry,surprised,fearful,disgusted
"""

from __future__ import annotations

import argparse
import json
import math
import re
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
    pooled_bilabials,
    read_clip,
    score_clip,
    to_json,
    truth_phones,
)
from talkmesh.face.arkit import WeightFitter
from talkmesh.face.assets import load_head
from talkmesh.face.composition import compose_vertices, rest_gap
from talkmesh.face.corrections import FAITHFUL, NONE, PREVIOUS, Corrections, correct_mouth
from talkmesh.face.performance import Performance
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
    "-noclosure": replace(Corrections(), lip_closure=False),
    # the pause gate alone, its pauses from voice activity (any language) or the recogniser
    "-gate": Corrections(mix=0.0, gain=0.0, bilabial=False),
    "-recgate": Corrections(mix=0.0, gain=0.0, bilabial=False, pauses="recognizer"),
    # no recogniser at all: the gate from voice activity and every near-closure shut
    "-anylang": Corrections(mix=0.0, gain=0.0, bilabial=False, lip_closure=True, met_lips=True),
}


STREAM = re.compile(r"^(?P<model>.+)-stream(?P<ms>[0-9]+)$")  # MODEL-streamMS
_LOADED: dict[str, object] = {}


def _model_streamed(wave: np.ndarray, head, model: str, lookahead_ms: float) -> np.ndarray:
    """(T, V, 3): the learned ``model`` alone as it streams with ``lookahead_ms``."""
    from talkmesh.models.codetalker.generate import generate_streamed
    from talkmesh.models.release import load_model

    if model not in _LOADED:
        _LOADED[model] = load_model(model).eval()
    return generate_streamed(_LOADED[model], wave, head.template, lookahead_ms)


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
        streamed = STREAM.match(method)
        if streamed:
            out[method] = _model_streamed(wave, head, streamed["model"], float(streamed["ms"]))
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


def _with_emotions(animated: dict[str, np.ndarray], wave, head, emotions, phones) -> None:
    """Adds ``METHOD+EMOTION`` to ``animated`` for every emotion but neutral, at intensity 1:
    the procedural animator animates again with it; a learned model's vertices get it as
    ``animate`` adds it (ARKit weights fitted, the emotion composed in as blendshape offsets)."""
    fitter = WeightFitter(head.blendshapes)
    for method, vertices in list(animated.items()):
        weights = None
        for emotion in emotions:
            if emotion == "neutral":
                continue
            perf = Performance({emotion: 1.0})
            name = f"{method}+{emotion}"
            if method == "procedural":
                animated[name] = animate(
                    wave, head=head, phones=phones, fps=FPS, seed=0, performance=perf
                ).vertices
                continue
            if weights is None:
                weights = fitter(vertices.astype(np.float64) - head.template)
            moved = vertices.copy()
            emo = perf.weights(np.arange(len(vertices)) / FPS)
            pair = head.regions.lip_pair
            rest = rest_gap(head.template, pair)
            compose_vertices(moved, weights, emo, head.blendshapes, pair, rest)
            animated[name] = moved


EMOTION_METRICS = ("bilabial", "pause_mm", "vowel_mm")


def emotion_table(med, methods, emotions, condition: str) -> str:
    """Each method under each emotion against its neutral run: the medians and their change."""
    lines = [
        "| method | emotion | " + " | ".join(EMOTION_METRICS) + " | change (closure, pause, "
        "vowel) |",
        "|---|---|" + "---|" * (len(EMOTION_METRICS) + 1),
    ]
    for m in methods:
        base = med.get((m, condition))
        for e in emotions:
            key = (m if e == "neutral" else f"{m}+{e}", condition)
            if base is None or key not in med:
                continue
            vals = " | ".join(_fmt(med[key][k]) for k in EMOTION_METRICS)
            change = ", ".join(_change(med[key][k], base[k]) for k in EMOTION_METRICS)
            lines.append(f"| {m} | {e} | {vals} | {change} |")
    return "\n".join(lines)


def _change(value: float, neutral: float) -> str:
    """The change from neutral, in % of it (and in its units where neutral is near 0)."""
    if math.isnan(value) or math.isnan(neutral):
        return "-"
    if abs(neutral) < 0.05:
        return f"{value - neutral:+.2f}"
    return f"{100 * (value - neutral) / abs(neutral):+.1f}%"


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
        "Medians over clips (and every clip's /p b m/ together):",
        "",
        "| condition | method | " + " | ".join(METRICS) + " | /p b m/ closed of all |",
        "|---|---|" + "---|" * (len(METRICS) + 1),
    ]
    pooled = pooled_bilabials(rows)
    for c in conditions:
        for m in methods:
            if (m, c) in med:
                vals = " | ".join(_fmt(med[(m, c)][k]) for k in METRICS)
                closed, total = pooled.get((m, c), (0, 0))
                lines.append(f"| {c} | {m} | {vals} | {closed}/{total} |")
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
        "MODEL-closure (with the lip closure at every near-closure), MODEL-noclosure (without), MODEL-gate / -recgate (the "
        "pause gate alone, from voice activity / from the recogniser), MODEL-streamMS (alone, as it "
        "streams with MS ms of look-ahead)",
    )
    ap.add_argument("--conditions", default=",".join(CONDITIONS))
    ap.add_argument("--clips", default="", help="comma-separated name prefixes (default: all)")
    ap.add_argument("--out", type=Path, default=None, help="folder for real-speech.json/.png")
    ap.add_argument(
        "--emotions",
        default="neutral",
        help="also animate each method under these emotions at full intensity and compare them "
        "with neutral (e.g. neutral,happy,sad,angry,surprised,fearful,disgusted)",
    )
    args = ap.parse_args()
    emotions = [e for e in args.emotions.split(",") if e]
    methods = [m for m in args.methods.split(",") if m]
    scored = [m if e == "neutral" else f"{m}+{e}" for m in methods for e in emotions]
    conditions = [c for c in args.conditions.split(",") if c]
    prefixes = [p for p in args.clips.split(",") if p]
    clips = [c for c in builtin_clips() if not prefixes or c.name.startswith(tuple(prefixes))]
    if not clips:
        raise SystemExit("no real recordings found: install pocketsphinx-testdata and alsa-utils")
    head = load_head()
    noise = load_audio(NOISE_FILE) if NOISE_FILE.is_file() else None
    rows = []
    with tqdm(total=len(clips) * len(conditions) * len(scored), desc="real speech") as bar:
        for clip in clips:
            wave = read_clip(clip)
            phones = truth_phones(clip, wave)
            for condition in conditions:
                degraded = degrade(wave, condition, noise, seed=0)
                animated = _animate_condition(degraded, methods, head)
                if emotions != ["neutral"]:
                    found = recognize_phones(degraded, SAMPLE_RATE)
                    _with_emotions(animated, degraded, head, emotions, found)
                for method in scored:
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
    print(table(rows, med, scored, conditions))
    if emotions != ["neutral"]:
        for condition in conditions:
            print(f"\nEmotions at full intensity against neutral ({condition}):\n")
            print(emotion_table(med, methods, emotions, condition))
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "real-speech.json").write_text(json.dumps(to_json(rows), indent=1))
        plot(med, scored, conditions, args.out / "real-speech.png")
        print(f"wrote {args.out / 'real-speech.json'} and {args.out / 'real-speech.png'}")


if __name__ == "__main__":
    main()
