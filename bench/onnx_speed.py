"""PyTorch and ONNX Runtime side by side on the bundled model, in one run.

    python bench/onnx_speed.py [--model codetalker-synth] [--streams 16] [--steps 60] [--threads N]

Exports the model (``talkmesh export-onnx``) to a temporary folder, then times on the CPU:

* offline: a 3 s speech clip animated whole, PyTorch's ``generate`` (fast mode) against
  :class:`talkmesh.models.onnx.OnnxModel` (the encoder graph and the step graph looped from
  Python), best of 3, with the largest difference of their vertices over the motion's scale;
* one step: one frame of generation for 1 stream and for ``--streams`` streams batched in one
  call, the PyTorch step module (:class:`talkmesh.models.codetalker.export.StepGraph`, the graph
  that is exported) against the ONNX step, median over ``--steps`` frames after the first 5, in
  ms per call and per stream-frame.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from talkmesh.audio.loading import load_audio
from talkmesh.models.onnx import OnnxModel, export_onnx
from talkmesh.models.release import load_model

CLIP = "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0880.wav"


def best_of(n: int, run) -> tuple[float, object]:
    times, out = [], None
    for _ in range(n):
        start = time.perf_counter()
        out = run()
        times.append(time.perf_counter() - start)
    return min(times), out


def step_times(step, inputs: list, names: list[str], frames: int, state_from) -> list[float]:
    """Seconds of each of ``frames`` consecutive steps from frame 0; ``step(*inputs)`` returns
    the motion and the next state, which ``state_from`` puts back into the inputs."""
    times = []
    for t in range(frames):
        inputs[1] = inputs[1] * 0 + t
        start = time.perf_counter()
        out = step(*inputs)
        times.append(time.perf_counter() - start)
        state_from(inputs, out)
    return times[5:]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="codetalker-synth")
    parser.add_argument("--streams", type=int, default=16)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--threads", type=int)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.set_grad_enabled(False)
    model = load_model(args.model)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "model.onnx"
        export_onnx(model, path)
        runtime = OnnxModel(path, threads=args.threads)
        audio = torch.from_numpy(load_audio(CLIP))[None]
        template = torch.zeros(1, model.num_vertices, 3)
        K = len(model.styles)
        weights = torch.full((1, K), 1.0 / K)
        pt, want = best_of(3, lambda: model.generate(audio, template, style_weights=weights))
        ox, got = best_of(3, lambda: runtime.generate(audio, template, style_weights=weights))
        scale = want.abs().max()
        diff = float((got - want).abs().max() / scale)
        seconds = audio.shape[1] / 16000
        print(f"offline, {seconds:.1f} s of speech ({want.shape[1]} frames), best of 3:\n")
        print("| runtime | seconds | real-time factor | max difference / motion scale |")
        print("|---|---:|---:|---:|")
        print(f"| PyTorch generate | {pt:.2f} | {pt / seconds:.2f} | |")
        print(f"| ONNX Runtime | {ox:.2f} | {ox / seconds:.2f} | {diff:.1e} |")
        print(f"\none step (median of {args.steps - 5} frames):\n")
        print(
            "| streams | PyTorch ms/call | ONNX Runtime ms/call | PyTorch ms/stream | ORT ms/stream |"
        )
        print("|---:|---:|---:|---:|---:|")
        _, graph = model.onnx_graphs()
        names = list(runtime.state)
        for B in sorted({1, args.streams}):
            style = runtime.style(None).repeat(B, 0)
            feats = np.random.default_rng(0).normal(size=(B, model.audio_map.in_features))
            feats = feats.astype(np.float32)
            start = runtime.start(style)

            def torch_state(inputs, out):
                inputs[3:] = out[1:]

            pt_inputs = [torch.from_numpy(feats), torch.zeros(B, dtype=torch.long)]
            pt_inputs += [torch.from_numpy(style)] + [torch.from_numpy(start[n]) for n in names]
            pt_times = step_times(graph, pt_inputs, names, args.steps, torch_state)

            def ort_step(feature, t, style_, *state):
                return runtime.step_frames(feature, t, style_, dict(zip(names, state)))

            def ort_state(inputs, out):
                inputs[3:] = [out[1][n] for n in names]

            ort_inputs = [feats, np.zeros(B, np.int64), style] + [start[n] for n in names]
            ort_times = step_times(ort_step, ort_inputs, names, args.steps, ort_state)
            a, b = np.median(pt_times) * 1000, np.median(ort_times) * 1000
            print(f"| {B} | {a:.2f} | {b:.2f} | {a / B:.2f} | {b / B:.2f} |")


if __name__ == "__main__":
    main()
