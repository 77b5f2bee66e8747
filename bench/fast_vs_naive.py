"""Fast (cached) against naive (the paper's loop) CodeTalker generation: what the one approximation
of fast mode costs in accuracy, on the synthetic unseen-speaker test split, in one run.

    python bench/fast_vs_naive.py --model codetalker-synth --data corpus/synth [--limit 40] [--int8]
        [--dither]

Both modes generate the same sequences with the same model (unseen speakers use the mean style);
each prediction set is scored with both metric protocols. Prints LVE, FDD and MVE per mode, the
relative LVE difference, the largest per-frame vertex difference between the two modes, and the
generation time of each mode. ``exact`` is the naive loop's output with the stage-2 caches (it
differs from ``fast`` only with the paper's bidirectional VQ decoder). ``fast-steps`` is fast mode one frame per pass (block=1): fast mode
must give the same codes; how many frames its passes keep on a trained model is printed.
``--dither`` adds exact fast mode on the audio plus inaudible noise (uniform, half a 16-bit step):
an autoregressive model's trajectory can turn on a near-tie between two codes, so even such a
change moves LVE; it is the yardstick for the int8 rows. ``--noise 1e-3,1e-2`` adds exact fast mode
with Gaussian noise of that size (relative to the features' standard deviation, seeded per
sequence) added to the speech encoder's output: how far LVE moves for a given size of error in the
features, whatever its source (int8 or bf16 arithmetic has errors of about 1e-2 to 5e-2).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from inference import count_passes  # bench/inference.py (the scripts run from bench/)

from talkmesh.audio.loading import SAMPLE_RATE
from talkmesh.datasets.reader import open_dataset
from talkmesh.evaluation.evaluate import evaluate_dataset
from talkmesh.models.int8 import quantize_int8
from talkmesh.models.release import load_model


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True, help="CodeTalker release (.safetensors) or name")
    p.add_argument("--data", default="corpus/synth", help="synthetic corpus root")
    p.add_argument("--split", default="test")
    p.add_argument("--limit", type=int, default=40, help="sequences to generate (default 40)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument(
        "--int8",
        action="store_true",
        help="also fast mode with int8 layers: speech encoder, decoders, both",
    )
    p.add_argument(
        "--dither",
        action="store_true",
        help="also fast mode on the audio plus uniform noise of half a 16-bit step: "
        "the LVE change that inaudible input changes cause, next to int8's",
    )
    p.add_argument(
        "--noise",
        type=lambda v: [float(r) for r in v.split(",")],
        default=[],
        help="also fast mode with Gaussian noise of these sizes (relative to their "
        "standard deviation) added to the speech features, e.g. 1e-3,1e-2",
    )
    return p.parse_args()


class FeatureNoise:
    """A forward hook on the speech encoder adding seeded Gaussian noise of ``size`` times the
    features' standard deviation (nothing while ``size`` is 0)."""

    def __init__(self) -> None:
        self.size, self.seed = 0.0, 0

    def __call__(self, module, inputs, feats):
        if not self.size:
            return feats
        g = torch.Generator().manual_seed(self.seed)
        return feats + torch.randn(feats.shape, generator=g) * (self.size * feats.std())


def rows(net, args: argparse.Namespace) -> dict[str, torch.nn.Module]:
    """The table's rows (mode name -> the model that generates it), in print order."""
    nets = {"fast": net, "fast-steps": net, "naive": net, "exact": net}
    if args.dither:  # the same exact fast mode on audio with inaudible noise: how much LVE moves
        nets["fast-dither"] = net  # when nothing but the last bits of the input change
    for size in args.noise:
        nets[f"fast-noise{size:g}"] = net
    if args.int8:  # the rows of bench/inference.py
        nets["fast-int8-speech"] = quantize_int8(net, speech=True, decoders=False)
        nets["fast-int8"] = quantize_int8(net)
        nets["fast-int8-all"] = quantize_int8(net, speech=True)
    return nets


class Generated(NamedTuple):
    seconds: dict[str, float]  # generation time per row
    biggest: float  # largest vertex difference fast vs naive
    steps_diff: float  # largest vertex difference fast vs fast-steps
    frames_per_pass: float  # frames fast mode kept per pass


def generate(nets, noise: FeatureNoise, dataset, indices: list[int], dirs) -> Generated:
    """Every row's predictions of the sequences ``indices``, saved as ``dirs[row]/NAME.npy``."""
    styles = len(nets["fast"].cfg.stage2.styles)
    seconds = {m: 0.0 for m in nets}
    biggest = steps_diff = 0.0
    passes = count_passes()
    frames = fast_passes = 0
    for i in indices:
        s = dataset[i]
        audio = torch.from_numpy(s.audio)[None]
        template = torch.from_numpy(s.template)[None]
        weights = torch.full((1, styles), 1.0 / styles)
        out = {}
        for mode in seconds:
            heard = audio
            if mode == "fast-dither":  # seeded per sequence, outside the timed part
                g = torch.Generator().manual_seed(i)
                heard = audio + (torch.rand(audio.shape, generator=g) - 0.5) / 32768
            noise.size = float(mode[10:]) if mode.startswith("fast-noise") else 0.0
            noise.seed = i
            start = time.perf_counter()
            before = len(passes)
            block = 1 if mode == "fast-steps" else None
            verts = nets[mode].generate(
                heard,
                template,
                style_weights=weights,
                num_frames=len(s.vertices),
                mode=mode.split("-")[0],
                block=block,
            )
            out[mode] = verts[0].numpy()
            if mode == "fast":
                frames += len(s.vertices)
                fast_passes += len(passes) - before
            seconds[mode] += time.perf_counter() - start
            np.save(dirs[mode] / f"{s.name}.npy", out[mode].reshape(len(out[mode]), -1))
        biggest = max(biggest, float(np.abs(out["fast"] - out["naive"]).max()))
        steps_diff = max(steps_diff, float(np.abs(out["fast"] - out["fast-steps"]).max()))
        print(f"\r{i + 1}/{len(indices)} sequences", end="", flush=True)
    print()
    return Generated(seconds, biggest, steps_diff, frames / max(fast_passes, 1))


def score_table(dataset, dirs, seconds: dict[str, float], audio_s: float) -> dict:
    """Print each row's scores; returns {row: (physical LVE, anchor LVE)}."""
    print("| mode | LVE (mm) | FDD (mm, abs.) | MVE (mm) | LVE (x1e-4, anchor) | time (s) | RTF |")
    print("|---|---|---|---|---|---|---|")
    lve = {}
    for mode, d in dirs.items():
        phys, _ = evaluate_dataset(dataset, d, protocol="physical")
        anchor, _ = evaluate_dataset(dataset, d, protocol="codetalker")
        lve[mode] = (phys.lve, anchor.lve)
        print(
            f"| {mode} | {phys.lve * 1e3:.3f} | {phys.fdd * 1e3:.3f} | {phys.mve * 1e3:.3f} | "
            f"{anchor.lve * 1e4:.4f} | {seconds[mode]:.1f} | {seconds[mode] / audio_s:.3f} |"
        )
    return lve


def main() -> None:
    args = parse_args()
    torch.set_num_threads(args.threads)
    net = load_model(args.model)
    noise = FeatureNoise()  # set per row being generated
    net.speech.register_forward_hook(noise)
    nets = rows(net, args)
    dataset = open_dataset("synth", args.data, args.split)
    indices = list(range(min(args.limit, len(dataset))))
    with tempfile.TemporaryDirectory() as tmp:
        dirs = {m: Path(tmp) / m for m in nets}
        for d in dirs.values():
            d.mkdir()
        g = generate(nets, noise, dataset, indices, dirs)
        audio_s = sum(len(dataset[i].audio) for i in indices) / SAMPLE_RATE
        print(f"{len(indices)} sequences, {audio_s:.1f} s of audio; model {args.model}\n")
        lve = score_table(dataset, dirs, g.seconds, audio_s)
    seconds = g.seconds
    print(
        f"\nlargest vertex difference fast vs naive {g.biggest * 1e3:.3f} mm, fast vs fast-steps "
        f"{g.steps_diff * 1e3:.6f} mm; naive/fast time {seconds['naive'] / seconds['fast']:.1f}x, "
        f"fast-steps/fast {seconds['fast-steps'] / seconds['fast']:.2f}x; "
        f"fast mode kept {g.frames_per_pass:.1f} frames per pass"
    )
    for mode in nets:
        if mode != "naive":
            rel = [abs(lve[mode][k] - lve["naive"][k]) / lve["naive"][k] * 100 for k in range(2)]
            print(
                f"LVE difference {mode} vs naive: {rel[0]:.3f}% (physical), {rel[1]:.3f}% (anchor)"
            )


if __name__ == "__main__":
    main()
