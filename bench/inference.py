"""CodeTalker inference speed: fast (cached) against naive (the paper's loop), one run, one table.

    python bench/inference.py                 # paper VOCASET config, 4 s / 30 s / 10 min fast, 4 s naive
    python bench/inference.py --quick         # skip 10 min
    python bench/inference.py --config small  # the synthetic-corpus config

Random weights (no pretrained weights exist on this machine): timings do not depend on the values.
The paper config uses a wav2vec2-base-sized random speech encoder. Peak memory is the process's
maximum resident set size after each row (it never goes down, so rows are run shortest first).
"""

from __future__ import annotations

import argparse
import resource
import time

import torch

from talkmesh.models.codetalker import CodeTalker, paper_vocaset_config, small_synth_config

SR = 16_000
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


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run(model: CodeTalker, seconds: float, mode: str) -> tuple[float, float]:
    audio = torch.randn(1, int(seconds * SR)) * 0.1
    template = torch.zeros(1, model.cfg.vq.num_vertices, 3)
    start = time.perf_counter()
    model.generate(audio, template, styles=torch.tensor([0]), mode=mode)
    return time.perf_counter() - start, peak_mb()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", choices=["paper", "small"], default="paper")
    p.add_argument("--quick", action="store_true", help="skip the 10-minute row")
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    model = build(args.config)
    params = sum(p.numel() for p in model.parameters()) / 1e6
    print(f"config {args.config}: {params:.0f} M parameters, {args.threads} threads")
    rows = [("fast", 4.0), ("naive", 4.0), ("fast", 30.0)] + (
        [] if args.quick else [("fast", 600.0)]
    )
    run(model, 1.0, "fast")  # warm-up
    results = {}
    print("| mode | audio | time (s) | real-time factor | peak RSS (MB) |")
    print("|---|---|---|---|---|")
    for mode, seconds in rows:
        wall, mem = run(model, seconds, mode)
        results[(mode, seconds)] = wall
        print(
            f"| {mode} | {seconds:g} s | {wall:.2f} | {wall / seconds:.3f} | {mem:.0f} |",
            flush=True,
        )
    print(f"\nnaive / fast at 4 s: {results[('naive', 4.0)] / results[('fast', 4.0)]:.1f}x")


if __name__ == "__main__":
    main()
