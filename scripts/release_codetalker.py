"""Bundle a trained CodeTalker: fp16 release in src/talkmesh/data/models/ plus its model card,
with every number on the card measured in this run on the synthetic unseen-speaker test split.

    python scripts/release_codetalker.py --stage1 runs/codetalker_synth/stage1 \\
        --stage2 runs/codetalker_synth/stage2 --recipe configs/codetalker_synth.yaml

Measures: stage-1 reconstruction (LVE/FDD/MVE) and codebook usage on the training split; the fp16
release with the mean style (plain, and with the procedural blinks/gaze that `animate` adds);
the static and procedural baselines; both metric protocols. Writes NAME.safetensors, NAME.md and
NAME.json (all scores).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from talkmesh.datasets.reader import open_dataset
from talkmesh.evaluation.evaluate import evaluate, write_baseline, write_model_predictions
from talkmesh.models.release import MODELS_DIR, load_model, save_model


def scores(data: str, pred: Path) -> dict:
    out = {}
    for protocol in ("physical", "codetalker"):
        s = evaluate("synth", data, pred, protocol=protocol)
        out[protocol] = {
            "lve": s.lve,
            "fdd": s.fdd,
            "mve": s.mve,
            "lip_sync": s.lip_sync,
            "n_sequences": s.n_sequences,
            "n_frames": s.n_frames,
        }
    return out


def codebook_usage(stage1: Path, data: str) -> tuple[int, int, float]:
    """Distinct codes used encoding the whole training split, codebook size, perplexity."""
    net = load_model(stage1 / "model.safetensors")
    ds = open_dataset("synth", data, "train")
    counts = torch.zeros(net.cfg.vq.codebook_size)
    with torch.inference_mode():
        for i in range(len(ds)):
            s = ds[i]
            motion = torch.tensor(s.vertices - s.template[None]).flatten(1)[None]
            codes = net.vqvae.encode(motion).codes
            counts += torch.bincount(codes.flatten(), minlength=len(counts)).float()
    p = counts / counts.sum()
    perplexity = float(torch.exp(-(p[p > 0] * p[p > 0].log()).sum()))
    return int((counts > 0).sum()), len(counts), perplexity


def data_note(data: str, styles) -> str:
    """What the model was trained on, from the corpus's manifest."""
    manifest = json.loads((Path(data) / "manifest.json").read_text())
    if not manifest.get("teacher"):
        return (
            "The default synthetic corpus (`talkmesh synth --out corpus/synth`: 12 synthetic voices "
            "x 40 sentences on 12 CC0 identities, 60 fps motion from the procedural animator with "
            "exact synthesiser phone timings, read at 30 fps). Trained on the 8 training subjects "
            f"({', '.join(styles)}); validated on 2; tested on 2 unseen voices and faces."
        )
    subjects = manifest["subjects"]
    train = manifest["splits"]["train"]
    langs = sorted({subjects[s]["language"] for s in train})
    test = manifest["splits"]["test"]
    unseen = sorted({subjects[s]["language"] for s in test} - set(langs))
    engines = {subjects[s].get("engine", "mbrola") for s in train}
    voices = " and ".join(
        text
        for engine, text in (
            ("mbrola", "MBROLA voices through espeak-ng"),
            ("espeak-lib", "espeak-ng's own voices"),
        )
        if engine in engines
    )
    families = sorted({subjects[s].get("family", "") for s in train} - {""})
    return (
        "The multilingual corpus (`talkmesh synth --multilingual --out corpus/multilingual`: "
        f"{voices}, {len(langs)} languages "
        + (f"of {len(families)} families " if families else "")
        + f"trained on ({', '.join(langs)}), "
        "two sentences with a pause between them per utterance, 60 fps motion truth from the "
        "procedural animator with the teacher's rules (lips met through /p b m/, rest in pauses, "
        "open vowels by loudness; talkmesh.face.teacher) on exact phone timings, read at 30 fps). "
        f"Trained on {len(train)} voices; tested on {len(test)} held-out voices, in the trained "
        f"languages and in {len(unseen)} never trained on ({', '.join(unseen)})."
    )


def train_minutes(data: str) -> float:
    import soundfile as sf

    splits = json.loads((Path(data) / "manifest.json").read_text())["splits"]["train"]
    wavs = [Path(data) / "wav" / f"{s}_{i}.wav" for s, ids in splits.items() for i in ids]
    return sum(sf.info(str(w)).duration for w in wavs if w.is_file()) / 60


def run_minutes(run: Path) -> float:
    start = (run / "recipe.json").stat().st_mtime
    return ((run / "model.safetensors").stat().st_mtime - start) / 60


def row(label: str, s: dict) -> str:
    ph, an = s["physical"], s["codetalker"]
    r = ph["lip_sync"]
    return (
        f"| {label} | {ph['lve'] * 1e3:.3f} | {ph['fdd'] * 1e3:.3f} | {ph['mve'] * 1e3:.3f} | "
        f"{'-' if r != r else f'{r:.3f}'} | {an['lve'] * 1e4:.4f} | {an['fdd'] * 1e5:.4f} |"
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--stage1", required=True, type=Path, help="stage-1 run directory")
    p.add_argument("--stage2", required=True, type=Path, help="stage-2 run directory")
    p.add_argument("--recipe", required=True, help="the recipe both stages were trained with")
    p.add_argument("--data", default="corpus/synth")
    p.add_argument("--name", default="codetalker-synth")
    args = p.parse_args()
    torch.set_num_threads(2)
    MODELS_DIR.mkdir(parents=True, exist_ok=True)
    release = save_model(
        load_model(args.stage2 / "model.safetensors"),
        MODELS_DIR / f"{args.name}.safetensors",
        dtype=torch.float16,
    )
    size_mb = release.stat().st_size / 1e6
    net = load_model(release)
    params = sum(t.numel() for t in net.parameters()) / 1e6
    results: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        write_model_predictions(
            "synth",
            args.data,
            tmp / "recon",
            str(args.stage1 / "model.safetensors"),
            mode="reconstruct",
            progress=False,
        )
        results["stage 1 reconstruction"] = scores(args.data, tmp / "recon")
        for method in ("static", "procedural"):
            write_baseline("synth", args.data, tmp / method, method=method, progress=False)
            results[f"{method} baseline"] = scores(args.data, tmp / method)
        start = time.perf_counter()
        write_model_predictions("synth", args.data, tmp / "model", str(release), progress=False)
        seconds = time.perf_counter() - start
        results[args.name] = scores(args.data, tmp / "model")
        write_model_predictions(
            "synth", args.data, tmp / "blinks", str(release), blinks=True, progress=False
        )
        results[f"{args.name} + procedural blinks/gaze"] = scores(args.data, tmp / "blinks")
    used, size, perplexity = codebook_usage(args.stage1, args.data)
    test = open_dataset("synth", args.data, "test")
    audio_s = sum(len(test[i].audio) for i in range(len(test))) / 16_000
    cfg = net.cfg
    card = [
        f"# {args.name}: CodeTalker trained on talkmesh's synthetic corpus",
        "",
        f"A small CodeTalker ({params:.1f} M parameters, {size_mb:.1f} MB in fp16) that ships with "
        "talkmesh as the default animator of `talkmesh animate`. Speech encoder: "
        f"{cfg.stage2.speech.kind} (frozen); VQ-VAE H={cfg.vq.components} x C={cfg.vq.code_dim}, "
        f"N={cfg.vq.codebook_size}, P={cfg.vq.temporal_unit}, {cfg.vq.loss.upper()} reconstruction; "
        f"decoder d={cfg.stage2.d_model}, {cfg.stage2.layers} layers, period {cfg.stage2.period}."
        + (
            f" VQ decoder causal (attention over the last {cfg.vq.causal_window} frames), so fast "
            "generation is exactly the paper's naive loop."
            if cfg.vq.causal
            else ""
        )
        + (
            f" Stage 2 trained with self-feedback {cfg.stage2.self_feedback:g} (that share of the "
            "fed-back frames is the model's own prediction) against exposure bias."
            if cfg.stage2.self_feedback
            else ""
        ),
        "",
        "## Data",
        "",
        data_note(args.data, cfg.stage2.styles),
        "",
        "## How it was trained",
        "",
        "```",
        "pip install 'talkmesh[whisper]' && talkmesh convert-whisper -o runs/whisper-tiny-en",
        f"talkmesh train {args.recipe}",
        f"python scripts/release_codetalker.py --stage1 {args.stage1} --stage2 {args.stage2} "
        f"--recipe {args.recipe}",
        "```",
        "",
        f"On 2 CPU cores: stage 1 took {run_minutes(args.stage1):.0f} min, stage 2 "
        f"{run_minutes(args.stage2):.0f} min (wall clock, with other work sharing the cores).",
        "",
        "## Results (synthetic unseen-speaker test split, measured by the command above)",
        "",
        f"{results[args.name]['physical']['n_sequences']} sequences, "
        f"{results[args.name]['physical']['n_frames']} frames; unseen speakers get the mean of "
        "the training styles. LVE: max lip-vertex error per frame; FDD: upper-face dynamics "
        "deviation; lower is better for both (docs/guide/datasets.md defines them).",
        "",
        "| method | LVE (mm) | FDD (mm, abs.) | MVE (mm) | lip-sync r | LVE (x1e-4, anchor) | FDD (x1e-5, anchor, signed) |",
        "|---|---|---|---|---|---|---|",
        *[row(label, s) for label, s in results.items()],
        "",
        f"Stage-1 codebook usage on the training split: {used} of {size} codes "
        f"({used / size:.0%}), perplexity {perplexity:.1f}.",
        f"Generating the {len(test)} test sequences ({audio_s:.0f} s of audio) took {seconds:.1f} s "
        f"in fast mode (real-time factor {seconds / audio_s:.3f}).",
        "",
        "## Streaming",
        "",
        "A model with a causal VQ decoder and the Whisper encoder streams (`talkmesh serve "
        f"--model {args.name}`): Whisper windows a block of 3 frames at a time, each ending a "
        "look-ahead (default 300 ms) after the block's last frame, with 2 s of context "
        "(`talkmesh.models.whisper_stream`). Its lip sync streamed: `python bench/real_speech.py "
        f"--methods {args.name}-raw,{args.name}-stream300` (docs/results/streaming.md).",
        "",
        "## Limits",
        "",
        f"Trained on {train_minutes(args.data):.0f} minutes of synthetic speech from "
        f"{len(cfg.stage2.styles)} voices and procedural motion: it learns that animator's "
        "mapping (with the teacher's rules where the corpus has them), not real human faces. "
        "Blinks are audio-independent, so a "
        "speech-driven model cannot time them; `talkmesh animate` adds the procedural blinks and "
        "gaze (`--no-blinks` turns that off), shown as a separate row above.",
    ]
    (MODELS_DIR / f"{args.name}.md").write_text("\n".join(card) + "\n")
    (MODELS_DIR / f"{args.name}.json").write_text(
        json.dumps(
            {
                "results": results,
                "codebook": {"used": used, "size": size, "perplexity": perplexity},
                "generation_seconds": seconds,
                "audio_seconds": audio_s,
            },
            indent=1,
        )
    )
    print("\n".join(card))


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
