"""MeshTalk prior: per-frame sampling cost, cached (ring buffers) vs uncached (whole history).

    python bench/meshtalk_prior.py [--preset released] [--seconds 4 30] [--threads 2]

Random weights (cost does not depend on them). The cached sampler runs the whole clip; the uncached
reference is timed on its last ``--uncached-frames`` frames after a prompt of the rest (its cost per
frame grows with the frame index, so this is its cost at that length). The mel audio encoder runs once
per clip, outside the autoregressive loop, and is timed separately.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from functools import partial

import torch

from talkmesh.audio.loading import SAMPLE_RATE
from talkmesh.models.meshtalk.prior import AutoregressivePrior, prior_config

FPS = 30.0


def per_frame_ms(fn, frames: int, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return 1000.0 * best / frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="released", choices=["paper", "released", "small"])
    parser.add_argument("--seconds", type=float, nargs="+", default=[4.0, 30.0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--uncached-frames", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    prior = AutoregressivePrior(prior_config(args.preset, FPS)).eval()
    cfg = prior.config
    params = sum(p.numel() for p in prior.parameters()) / 1e6
    print(
        f"prior: preset {args.preset}, H={cfg.num_heads}, C={cfg.num_classes}, width {cfg.width}, "
        f"dilations {cfg.dilations}, receptive field {cfg.receptive_field} frames, {params:.1f} M params"
    )
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"torch {torch.__version__}, {args.threads} threads, {FPS:g} fps\n"
    )
    print(
        f"| {'clip':>5} | {'frames':>6} | {'mel encoder ms/frame':>20} | {'cached ms/frame':>15} "
        f"| {'uncached ms/frame':>17} | {'speed-up':>8} | {'cached RTF':>10} |"
    )
    print(f"|{'-' * 7}|{'-' * 8}|{'-' * 22}|{'-' * 17}|{'-' * 19}|{'-' * 10}|{'-' * 12}|")
    for seconds in args.seconds:
        T = int(round(seconds * FPS))
        audio = 0.1 * torch.randn(1, int(seconds * SAMPLE_RATE))
        with torch.inference_mode():
            mel_ms = per_frame_ms(partial(prior.audio_features, audio, None, T), T, args.repeats)
            feats = prior.audio_features(audio, None, T)
        gen = torch.Generator().manual_seed(0)
        cached = per_frame_ms(partial(prior.sample, feats, generator=gen), T, args.repeats)
        n = min(args.uncached_frames, T - 1)
        prompt = torch.randint(0, cfg.num_classes, (1, T - n, cfg.num_heads))
        uncached = per_frame_ms(
            partial(prior.sample_uncached, feats, generator=gen, prompt=prompt), n, 1
        )
        rtf = cached * FPS / 1000.0
        print(
            f"| {f'{seconds:g} s':>5} | {T:>6} | {mel_ms:>20.3f} | {cached:>15.2f} "
            f"| {uncached:>17.1f} | {uncached / cached:>7.0f}x | {rtf:>10.3f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
