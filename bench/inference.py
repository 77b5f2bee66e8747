"""CodeTalker inference speed: fast (cached) against naive (the paper's loop), one run, one table.

    python bench/inference.py                 # paper VOCASET config: 4 s / 30 s / 10 min fast, 4 s naive
    python bench/inference.py --quick         # skip the 10-minute rows
    python bench/inference.py --config small  # the synthetic-corpus config
    python bench/inference.py --int8          # also fast mode with int8 layers (quantize_int8):
                                              # speech encoder, decoders, or both
    python bench/inference.py --rows fast-int8-speech:600,fast:600   # just these rows

Random weights (no pretrained weights exist on this machine). Rows: ``fast`` is generate()'s
default, passes of up to ``generate_block`` frames that keep the frames whose guessed codes held
(FrameGenerator.block); ``fast-steps`` is the same computation one frame per pass (block=1);
``naive`` is the paper's loop; ``exact`` is its output with the stage-2 caches, one frame at a
time, the fed-back frame from the paper's bidirectional VQ decoder re-run over the prefix (the
paper config's ``fast`` feeds back a cached causal pass instead: an approximation).
``fast-int8-speech`` is fast mode with the speech encoder's linear
and convolution layers in int8 (decoders float32: the passes are exact for its features),
``fast-int8`` with the decoders' per-frame layers in int8, ``fast-int8-all`` both
(``quantize_int8``; their effect on accuracy: bench/fast_vs_naive.py --int8); ``-steps`` after
any of them runs it one frame per pass. The time of ``fast-steps`` and ``naive`` does not depend on the
weights; the time of ``fast`` does: it depends on how often a frame's codes survive a change of
the motion fed back, so the ``frames/pass`` column is printed with it (about 1 means no gain over
steps; a trained model keeps fewer frames per pass than random weights, see docs/results/codetalker.md).
The paper config uses a wav2vec2-base-sized random speech encoder (windows of 20 s with 2 s of
context for long audio). Each row runs in its own process, so its peak memory (maximum resident
set size, model weights included) is its own; the time covers speech encoding, generation and
decoding the vertices, not building the model. Rows of up to 5 s of audio (the 4 s ratios) report
the median of 5 runs after a warm-up run on the same audio (oneDNN builds its kernels per shape on
first use), every mode alike; the runs are printed next to the table; longer rows run once after
a 1 s warm-up.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import torch

from talkmesh.audio.loading import SAMPLE_RATE
from talkmesh.models.codetalker.generate import FrameGenerator
from talkmesh.models.codetalker.model import CodeTalker, paper_vocaset_config, small_synth_config
from talkmesh.models.int8 import quantize_int8

SR = SAMPLE_RATE
MODES = ("fast", "fast-steps", "naive", "exact", "fast-int8-speech", "fast-int8", "fast-int8-all")
SHORT, REPEATS = 5.0, 5  # rows of up to 5 s of audio: the median of 5 runs after a warm-up
WAV2VEC2_BASE = dict(
    hidden_size=768, num_hidden_layers=12, num_attention_heads=12, intermediate_size=3072
)


def build(config: str) -> CodeTalker:
    if config == "small":
        cfg = small_synth_config(tuple(f"s{k}" for k in range(8)))
    else:
        cfg = paper_vocaset_config()
        speech = cfg.stage2.speech.__class__(kind="wav2vec2", hf_config=WAV2VEC2_BASE)
        cfg = cfg.__class__(
            vq=cfg.vq, stage2=cfg.stage2.__class__(**{**cfg.stage2.__dict__, "speech": speech})
        )
    torch.manual_seed(0)
    model = CodeTalker(cfg).eval()
    for p in model.feat_map.parameters():  # zero-initialised in training; random here for real work
        torch.nn.init.normal_(p, std=0.02)
    return model


def row(config: str, mode: str, seconds: float, threads: int) -> dict:
    """One measurement, in this process."""
    torch.set_num_threads(threads)
    model = build(config)
    int8 = mode.removesuffix("-steps")
    if int8.startswith("fast-int8"):  # the float32 original is freed when the name is rebound
        speech, decoders = int8 != "fast-int8", int8 != "fast-int8-speech"
        model = quantize_int8(model, speech=speech, decoders=decoders)
    gen_mode = mode if mode in ("naive", "exact") else "fast"
    block = 1 if mode.endswith("-steps") else None
    passes = count_passes()
    template = torch.zeros(1, model.cfg.vq.num_vertices, 3)
    kwargs = dict(styles=torch.tensor([0]), mode=gen_mode, block=block)
    audio = torch.randn(1, int(seconds * SR)) * 0.1
    short = seconds <= SHORT
    # warm-up (oneDNN builds its kernels per shape on first use): short rows on the same audio
    model.generate(audio if short else audio[:, :SR], template, **kwargs)
    walls = []
    for _ in range(REPEATS if short else 1):
        passes.clear()
        start = time.perf_counter()
        out = model.generate(audio, template, **kwargs)
        walls.append(time.perf_counter() - start)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    per_pass = out.shape[1] / len(passes) if passes else None
    wall = sorted(walls)[len(walls) // 2]
    return {
        "wall": wall,
        "walls": walls,
        "frames": out.shape[1],
        "peak_mb": peak,
        "per_pass": per_pass,
    }


def count_passes() -> list[int]:
    """Count FrameGenerator.block passes (fast mode) from now on, in this process."""
    block, passes = FrameGenerator.block, []

    def counted(self, cross, drafts):
        passes.append(1)
        return block(self, cross, drafts)

    FrameGenerator.block = counted
    return passes


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", choices=["paper", "small"], default="paper")
    p.add_argument("--quick", action="store_true", help="skip the 10-minute rows")
    p.add_argument("--int8", action="store_true", help="also fast mode with int8 layers")
    p.add_argument("--rows", help="only these rows: MODE:SECONDS,... (e.g. fast-int8-speech:600)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--row", help=argparse.SUPPRESS)  # internal: MODE,SECONDS
    args = p.parse_args()
    if args.row:
        mode, seconds = args.row.split(",")
        print(json.dumps(row(args.config, mode, float(seconds), args.threads)))
        return
    rows = [
        ("fast", 4.0),
        ("fast-steps", 4.0),
        ("naive", 4.0),
        ("exact", 4.0),
        ("fast", 30.0),
        ("fast-steps", 30.0),
    ]
    if args.int8:
        for mode in ("fast-int8-speech", "fast-int8", "fast-int8-all"):
            rows += [(mode, 4.0), (mode, 30.0)]
    if not args.quick:
        rows += [("fast", 600.0)] + ([("fast-int8-speech", 600.0)] if args.int8 else [])
    if args.rows:
        rows = []
        for r in args.rows.split(","):
            mode, _, sec = r.partition(":")
            base = (
                mode
                if mode == "fast-steps" or not mode.startswith("fast")
                else mode.removesuffix("-steps")
            )
            if base not in MODES or not sec.replace(".", "", 1).isdigit() or float(sec) <= 0:
                p.error(
                    f"--rows: {r!r} is not MODE:SECONDS with MODE one of {', '.join(MODES)} "
                    "(any fast mode may end in -steps)"
                )
            rows.append((mode, float(sec)))
    params = sum(p.numel() for p in build(args.config).parameters()) / 1e6
    print(
        f"config {args.config}: {params:.0f} M parameters, {args.threads} threads, torch {torch.__version__}"
    )
    print("| mode | audio | frames | frames/pass | time (s) | real-time factor | peak RSS (MB) |")
    print("|---|---|---|---|---|---|---|")
    results, runs = {}, {}
    for mode, seconds in rows:
        cmd = [
            sys.executable,
            __file__,
            "--config",
            args.config,
            "--threads",
            str(args.threads),
            "--row",
            f"{mode},{seconds}",
        ]
        r = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout)
        results[(mode, seconds)] = r["wall"]
        runs[(mode, seconds)] = r["walls"]
        per_pass = "" if r["per_pass"] is None else f"{r['per_pass']:.1f}"
        print(
            f"| {mode} | {seconds:g} s | {r['frames']} | {per_pass} | {r['wall']:.2f} | "
            f"{r['wall'] / seconds:.3f} | {r['peak_mb']:.0f} |",
            flush=True,
        )
    naive = results.get(("naive", 4.0))
    if naive:
        ratios = [
            f"{m}: {naive / t:.1f}x"
            for (m, sec), t in results.items()
            if sec == 4.0 and m != "naive"
        ]
        print("\nnaive / each mode at 4 s: " + ", ".join(ratios))
    for (mode, sec), walls in runs.items():
        if len(walls) > 1:
            print(f"runs of {mode} at {sec:g} s: " + ", ".join(f"{w:.2f}" for w in walls))


if __name__ == "__main__":
    main()
