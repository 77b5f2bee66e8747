"""Why the lip opening follows the loudness less than the procedural animator's: two checks.

    python bench/loudness.py real [--methods procedural,codetalker-synth-raw] [--conditions clean]
    python bench/loudness.py synthetic --data corpus/multilingual [--per-voice 1]
    python bench/loudness.py teacher --data corpus/multilingual [--per-voice 3]

``real``: on the real recordings (clean), the ``loudness_r`` of
:mod:`talkmesh.evaluation.real_speech` with the opening shifted by -3..+3 frames (+1: the
opening one frame after the sound; the shift with the highest r says how late a method's lips
are: a frame's opening is the face at its start and its loudness the mean over it, so lips in
time with the sound peak between 0 and +1), and with the /p b m/ windows left out (a voiced
/m b/ is loud with the lips shut). Then every metric of each method with its whole animation
moved 0, 1 and 2 frames earlier: what its timing costs on each target.

``synthetic``: the same shifts on a multilingual corpus's test split (clean), for the truth
and each method against the loudness, and for each method against the truth's opening.

``teacher``: on a multilingual corpus's test split, the ``loudness_r`` of the teacher's truth
(:mod:`talkmesh.face.teacher`) built again from each clip's phones and audio, with all its rules
and with one rule left out at a time: what the truth itself scores against the target "at least
the procedural animator's".
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_speech import _animate_condition  # noqa: E402

from talkmesh.audio.loading import load_audio  # noqa: E402
from talkmesh.evaluation.real_speech import (  # noqa: E402
    BILABIALS,
    CONDITIONS,
    METRICS,
    NOISE_FILE,
    builtin_clips,
    degrade,
    log_loudness,
    phone_window,
    read_clip,
    score_opening,
    truth_phones,
)
from talkmesh.face.assets import lip_opening, load_head  # noqa: E402

FPS = 30.0
SHIFTS = range(-3, 4)
EARLIER = (0, 1, 2)


def correlation(opening: np.ndarray, loudness: np.ndarray, shift: int = 0) -> float:
    """r of the opening ``shift`` frames after the loudness (0: the metric as defined)."""
    n = len(opening)
    a = opening[max(0, shift) : n + min(0, shift)]
    b = loudness[max(0, -shift) : n - max(0, shift)]
    return float(np.corrcoef(a, b)[0, 1])


def real(methods: list[str], conditions: list[str]) -> None:
    head = load_head()
    rest = float(lip_opening(head.template[None], head.regions)[0]) * 1000
    noise = load_audio(NOISE_FILE) if NOISE_FILE.is_file() else None
    shifted = {m: {s: [] for s in SHIFTS} for m in methods}
    outside = {m: [] for m in methods}
    earlier = {(c, m, k): [] for c in conditions for m in methods for k in EARLIER}
    for clip in tqdm(builtin_clips(), desc="real clips", unit="clip"):
        wave = read_clip(clip)
        phones = truth_phones(clip, wave)
        for condition in conditions:
            heard = degrade(wave, condition, noise, seed=0)
            for method, vertices in _animate_condition(heard, methods, head).items():
                opening = lip_opening(vertices, head.regions) * 1000
                for k in EARLIER:  # the animation k frames earlier, its last frame held
                    moved = np.concatenate([opening[k:], np.repeat(opening[-1:], k)])
                    scores = score_opening(moved, rest, phones, heard, FPS)
                    earlier[condition, method, k].append(scores)
                if condition != "clean":
                    continue
                n = len(opening)
                loud = log_loudness(wave, FPS, n)
                for s in SHIFTS:
                    shifted[method][s].append(correlation(opening, loud, s))
                keep = np.ones(n, bool)
                for p in phones:
                    if p.label in BILABIALS:
                        lo, hi = phone_window(p, FPS, n)
                        keep[lo:hi] = False
                outside[method].append(correlation(opening[keep], loud[keep]))
    if "clean" in conditions:
        print(
            "loudness_r (median over clean clips) with the opening shifted by k frames (+: later)\n"
        )
        print("| method | " + " | ".join(f"{s:+d}" for s in SHIFTS) + " | outside /p b m/ |")
        print("|---|" + "---|" * (len(SHIFTS) + 1))
        for m in methods:
            cells = [f"{statistics.median(shifted[m][s]):.3f}" for s in SHIFTS]
            print(f"| {m} | " + " | ".join(cells) + f" | {statistics.median(outside[m]):.3f} |")
    print("\nMedians over clips with the animation moved k frames earlier\n")
    print("| condition | method | earlier | " + " | ".join(METRICS) + " |")
    print("|---|---|---|" + "---|" * len(METRICS))
    for (condition, method, k), rows in earlier.items():
        cells = [_median([r[key] for r in rows]) for key in METRICS]
        print(f"| {condition} | {method} | {k} | " + " | ".join(cells) + " |")


def _median(values: list[float]) -> str:
    kept = [v for v in values if not np.isnan(v)]
    return f"{statistics.median(kept):.3f}" if kept else "-"


def _table(title: str, rows: dict[str, dict[int, list[float]]]) -> None:
    print(f"\n{title}\n")
    print("| opening | " + " | ".join(f"{s:+d}" for s in SHIFTS) + " |")
    print("|---|" + "---|" * len(SHIFTS))
    for name, by_shift in rows.items():
        print(
            f"| {name} | "
            + " | ".join(f"{statistics.median(v):.3f}" for v in by_shift.values())
            + " |"
        )


def synthetic(data: Path, per_voice: int, methods: list[str]) -> None:
    manifest = json.loads((data / "manifest.json").read_text())
    todo = [(s, i) for s, ids in manifest["splits"]["test"].items() for i in ids[:per_voice]]
    loudness = {m: {s: [] for s in SHIFTS} for m in ["truth", *methods]}
    truth = {m: {s: [] for s in SHIFTS} for m in methods}
    heads = {}
    for subject, sid in tqdm(todo, desc="synthetic clips", unit="clip"):
        identity, name = manifest["subjects"][subject]["identity"], f"{subject}_{sid}"
        head = heads.setdefault(identity, load_head(identity))
        wave = load_audio(data / "wav" / f"{name}.wav")
        animated = _animate_condition(wave, methods, head)
        true = np.load(data / "vertices_npy" / f"{name}.npy")[::2]
        animated["truth"] = true.reshape(len(true), -1, 3)
        opening = {m: lip_opening(v, head.regions) * 1000 for m, v in animated.items()}
        n = min(map(len, opening.values()))
        loud = log_loudness(wave, FPS, n)
        for m, o in opening.items():
            for s in SHIFTS:
                loudness[m][s].append(correlation(o[:n], loud, s))
                if m != "truth":
                    truth[m][s].append(correlation(o[:n], opening["truth"][:n], s))
    _table(f"r with the loudness, {len(todo)} test clips, shifted by k frames (+: later)", loudness)
    _table("r with the truth's opening, shifted by k frames (+: later than the truth)", truth)


def teacher(data: Path, per_voice: int) -> None:
    import talkmesh.face.teacher as rules
    from talkmesh.datasets.multilingual import read_phones
    from talkmesh.face.lipsync import SpeakingStyle, phones_to_weights

    manifest = json.loads((data / "manifest.json").read_text())
    todo = [(s, i) for s, ids in manifest["splits"]["test"].items() for i in ids[:per_voice]]
    keep = rules.close_lips, rules.pause_gate, rules.LOUDNESS_SHARE, rules.lead
    variants = {
        "the teacher, every rule": {},
        "in step with the phones (no lead)": {"lead": lambda weights, *a: weights},
        "without its /p b m/ closure rule": {"close_lips": lambda *a, **k: None},
        "without its pause rule": {"pause_gate": lambda phones, fps, n: np.ones(n)},
        "every opening scaled by loudness (LOUDNESS_SHARE 1.0)": {"LOUDNESS_SHARE": 1.0},
    }
    scores = {v: [] for v in variants}
    heads = {}
    for subject, sid in tqdm(todo, desc="teacher", unit="clip"):
        info, name = manifest["subjects"][subject], f"{subject}_{sid}"
        head = heads.setdefault(info["identity"], load_head(info["identity"]))
        rest = float(lip_opening(head.template[None], head.regions)[0]) * 1000
        wave = load_audio(data / "wav" / f"{name}.wav")
        phones = read_phones(data, name)
        n = max(1, int(round(len(wave) / 16_000 * 2 * FPS)))  # the corpus's 60 fps
        style = SpeakingStyle(**info["style"])
        base = phones_to_weights(phones, n, 2 * FPS, audio=wave, style=style).astype(np.float32)
        for variant, changes in variants.items():
            for key, value in changes.items():
                setattr(rules, key, value)
            try:
                weights = rules.teach(
                    base.copy(), phones, 2 * FPS, head, audio=wave,
                    jaw_scale=style.jaw * style.articulation,
                )  # fmt: skip
            finally:
                rules.close_lips, rules.pause_gate, rules.LOUDNESS_SHARE, rules.lead = keep
            opening = lip_opening(head.vertices_from_weights(weights)[::2], head.regions) * 1000
            scores[variant].append(score_opening(opening, rest, phones, wave, FPS)["loudness_r"])
    print(f"\n| truth ({len(todo)} test clips, clean) | loudness_r (median) |\n|---|---|")
    for variant, values in scores.items():
        print(f"| {variant} | {statistics.median(values):.2f} |")


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("check", choices=("real", "synthetic", "teacher"))
    ap.add_argument("--methods", default="procedural,codetalker-synth-raw")
    ap.add_argument("--conditions", default="clean", help="real: e.g. clean,snr10,reverb")
    ap.add_argument("--data", type=Path, help="a multilingual corpus (synthetic, teacher)")
    ap.add_argument("--per-voice", type=int, default=3, help="test clips a voice (corpus checks)")
    args = ap.parse_args()
    methods = [m for m in args.methods.split(",") if m]
    if args.per_voice < 1 or (args.check != "teacher" and not methods):
        raise SystemExit("--per-voice must be at least 1 and --methods name at least one method")
    if args.check == "real":
        conditions = [c for c in args.conditions.split(",") if c]
        unknown = sorted(set(conditions) - set(CONDITIONS))
        if unknown or not conditions:
            raise SystemExit(f"--conditions: use some of {', '.join(CONDITIONS)} (got {unknown})")
        if any(c.startswith("snr") for c in conditions) and not NOISE_FILE.is_file():
            raise SystemExit(
                f"{NOISE_FILE} is missing: install alsa-utils for the noise conditions"
            )
        if not builtin_clips():
            raise SystemExit(
                "no real recordings found: install pocketsphinx-testdata and alsa-utils"
            )
        real(methods, conditions)
    elif args.data is None or not (args.data / "manifest.json").is_file():
        raise SystemExit(
            f"{args.check} needs --data: a multilingual corpus (talkmesh synth --multilingual)"
        )
    elif args.check == "synthetic":
        synthetic(args.data, args.per_voice, [m for m in methods if m != "procedural"])
    else:
        teacher(args.data, args.per_voice)


if __name__ == "__main__":
    main()
