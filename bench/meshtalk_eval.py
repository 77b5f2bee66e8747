"""MeshTalk on the synthetic corpus: the paper's Table 1, disentanglement (Fig. 5), diversity, speed.

    python bench/meshtalk_eval.py table1 xMod=runs/meshtalk_synth/prior/model.safetensors \\
        l2=runs/meshtalk_synth_l2/prior/model.safetensors expr=runs/meshtalk_synth_expr/prior/...
    python bench/meshtalk_eval.py disentangle --model M [--figure docs/images/meshtalk_disentangle.png]
    python bench/meshtalk_eval.py diversity --model M [--seeds 5]
    python bench/meshtalk_eval.py speed --model M [--seconds 4 30]
    python bench/meshtalk_eval.py retarget-video --model M --target bo -o docs/images/meshtalk_retarget.mp4

All on the unseen-speaker test split of ``--data`` (default corpus/synth); every section prints a
markdown table. Distances are Euclidean vertex distances in mm (the corpus is in metres).

* table1: reconstruction error (the expression space with its own motion and audio, argmax codes,
  mean vertex distance to the truth over all vertices and frames; paper footnote 1) and the prior's
  perplexity on the test codes (Eq. 9, pooled over all (frame, head) positions).
* disentangle: pairs of test sentences (i, j), cut to the shorter: codes E(x_i, a_i) against
  E(x_i, a_j) (audio varied, expression fixed) and against E(x_j, a_i) (expression varied, audio
  fixed), both decoded on template i; the mean vertex change over the mouth (lip region) and the
  upper face (the FDD region), and a heatmap of the per-vertex change.
* diversity: one test sentence sampled with several seeds; the per-vertex standard deviation across
  samples, averaged over frames, for the lips and the upper face (and the eyelids alone).
* speed: ``MeshTalkModel.generate`` (mel features, prior sampling, decoding) at each length with the
  cached sampler and with the reference sampler that recomputes the whole history at every
  (frame, head), in one run; real-time factor = time / audio length.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

from talkmesh.audio.loading import SAMPLE_RATE

MM = 1000.0  # corpus units (m) -> mm


def load(model: str):
    from talkmesh.training.meshtalk import load_system

    return load_system(model)


def test_split(data: str):
    from talkmesh.datasets.reader import open_dataset

    return open_dataset("synth", data, "test")


def encode(net, vertices: np.ndarray, template: np.ndarray, audio: np.ndarray) -> torch.Tensor:
    """Argmax codes (1, T, H) of one sequence."""
    return net.model.encode(
        torch.from_numpy(np.ascontiguousarray(vertices))[None],
        torch.from_numpy(template)[None],
        torch.from_numpy(audio)[None],
        sample=False,
    ).codes


def decode(net, template: np.ndarray, codes: torch.Tensor) -> np.ndarray:
    return net.model.decode(torch.from_numpy(template)[None], codes)[0].numpy()


def cut(sample, frames: int, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """The first ``frames`` motion frames and their audio."""
    samples = int(round(frames / fps * SAMPLE_RATE))
    audio = sample.audio[:samples]
    if len(audio) < samples:
        audio = np.pad(audio, (0, samples - len(audio)))
    return sample.vertices[:frames], audio


# ---------------------------------------------------------------------------------------------


@torch.inference_mode()
def table1(args) -> None:
    ds = test_split(args.data)
    rows = []
    for spec in args.variants:
        label, _, path = spec.partition("=")
        net = load(path)
        if net.prior is None:
            sys.exit(f"{path}: no prior: train the prior stage first")
        err_sum, err_n, nll_sum, nll_n = 0.0, 0, 0.0, 0
        for k in range(len(ds)):
            s = ds[k]
            codes = encode(net, s.vertices, s.template, s.audio)
            recon = decode(net, s.template, codes)
            dist = np.linalg.norm(recon - s.vertices, axis=-1) * MM
            err_sum += float(dist.sum())
            err_n += dist.size
            feats = net.audio_features(torch.from_numpy(s.audio)[None], None, codes.shape[1])
            loss = net.prior.loss(codes, feats).loss
            nll_sum += float(loss) * codes.numel()
            nll_n += codes.numel()
        inputs = "expression" if net.model.config.inputs == "expression" else "expr. + audio"
        w = net.model.config.loss
        loss = "L_xMod + L_eyelid" if w.mouth or w.upper else "l2 + L_eyelid"
        rows.append((label, inputs, loss, err_sum / err_n, float(np.exp(nll_sum / nll_n))))
    print(f"MeshTalk Table 1 on {args.data}, test split ({len(ds)} sequences)\n")
    print(
        "| latent space | encoder inputs | decoder loss | reconstruction error (mm) | prior perplexity |"
    )
    print("|---|---|---|---|---|")
    for label, inputs, loss, err, ppl in rows:
        print(f"| {label} | {inputs} | {loss} | {err:.3f} | {ppl:.3f} |")


@torch.inference_mode()
def disentangle(args) -> None:
    net = load(args.model)
    ds = test_split(args.data)
    lips, upper = ds.regions.lve, ds.regions.fdd
    V = net.num_vertices
    change = {"audio varied": np.zeros(V), "expression varied": np.zeros(V)}
    frames_total = 0
    pairs = [(k, (k + 1) % len(ds)) for k in range(0, min(len(ds), 2 * args.pairs), 2)]
    for i, j in pairs:
        si, sj = ds[i], ds[j]
        T = min(len(si.vertices), len(sj.vertices))
        xi, ai = cut(si, T, net.motion_fps)
        xj, aj = cut(sj, T, net.motion_fps)
        base = decode(net, si.template, encode(net, xi, si.template, ai))
        a_var = decode(net, si.template, encode(net, xi, si.template, aj))
        x_var = decode(net, si.template, encode(net, xj, si.template, ai))
        change["audio varied"] += (np.linalg.norm(a_var - base, axis=-1) * MM).sum(0)
        change["expression varied"] += (np.linalg.norm(x_var - base, axis=-1) * MM).sum(0)
        frames_total += T
    print(
        f"MeshTalk disentanglement on {args.data}, {len(pairs)} test sentence pairs, {frames_total} frames"
    )
    print(f"model: {args.model}\n")
    print("| decoded with | mean vertex change, mouth (lips) mm | upper face mm | mouth / upper |")
    print("|---|---|---|---|")
    for name, total in change.items():
        per_vertex = total / frames_total
        change[name] = per_vertex
        m, u = per_vertex[lips].mean(), per_vertex[upper].mean()
        print(f"| {name} | {m:.3f} | {u:.3f} | {m / max(u, 1e-9):.2f} |")
    if args.figure:
        figure(change, args.figure)


def figure(change: dict[str, np.ndarray], out: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from talkmesh.evaluation.benchmark import draw_on_mesh, save_png
    from talkmesh.face.assets import load_head

    head = load_head()
    vmax = max(float(v.max()) for v in change.values())
    fig, axes = plt.subplots(1, len(change), figsize=(3.2 * len(change), 3.6))
    for ax, (name, values) in zip(axes, change.items()):
        art = draw_on_mesh(ax, head.template, head.faces, values, vmax)
        ax.set_title(f"{name}: max {values.max():.2f} mm", fontsize=9)
    fig.colorbar(art, ax=list(axes), shrink=0.7, label="mean vertex change (mm)")
    save_png(fig, Path(out))
    plt.close(fig)
    print(f"wrote {out} ({Path(out).stat().st_size // 1024} KB)")


@torch.inference_mode()
def diversity(args) -> None:
    net = load(args.model)
    ds = test_split(args.data)
    from talkmesh.face.assets import load_head

    eyelids = np.asarray(load_head().regions.eyelids)
    lips, upper = ds.regions.lve, ds.regions.fdd
    rows = []
    for k in range(min(args.sentences, len(ds))):
        s = ds[k]
        audio = torch.from_numpy(s.audio)[None]
        template = torch.from_numpy(s.template)[None]
        samples = np.stack(
            [
                net.generate(audio, template, num_frames=len(s.vertices), seed=seed)[0].numpy()
                for seed in range(args.seeds)
            ]
        )  # (seeds, T, V, 3)
        centre = samples.mean(0, keepdims=True)
        spread = np.sqrt((np.linalg.norm(samples - centre, axis=-1) ** 2).mean(0)) * MM  # (T, V)
        per_vertex = spread.mean(0)
        # the region's own motion in the truth: per-vertex std over time (mm)
        truth = (
            np.sqrt((np.linalg.norm(s.vertices - s.vertices.mean(0), axis=-1) ** 2).mean(0)) * MM
        )
        rows.append(
            (
                s.name,
                per_vertex[lips].mean(),
                per_vertex[upper].mean(),
                per_vertex[eyelids].mean(),
                truth[lips].mean(),
                truth[upper].mean(),
            )
        )
    print(f"MeshTalk diversity: {args.seeds} seeds per sentence, {len(rows)} test sentences")
    print(f"model: {args.model}\n")
    print("Spread across seeds (mm), and relative to the region's own motion in the truth (its")
    print("per-vertex std over time).\n")
    print(
        "| sentence | lips | upper face | eyelids | upper / lips | lips, relative | upper, relative |"
    )
    print("|---|---|---|---|---|---|---|")

    def line(name, lip, up, eye, t_lip, t_up):
        print(
            f"| {name} | {lip:.3f} | {up:.3f} | {eye:.3f} | {up / max(lip, 1e-9):.2f} | "
            f"{lip / t_lip:.2f} | {up / t_up:.2f} |"
        )

    for row in rows:
        line(*row)
    line("mean", *(float(np.mean([r[c] for r in rows])) for c in range(1, 6)))


@torch.inference_mode()
def speed(args) -> None:
    net = load(args.model)
    torch.set_num_threads(args.threads)
    template = torch.from_numpy(net.model.template_mean.numpy())[None]
    rng = np.random.default_rng(0)
    print(f"MeshTalk generation speed, model {args.model}")
    print(
        f"machine: {platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, "
        f"{args.threads} threads\n"
    )
    print(
        "| audio | frames | cached s | cached RTF | whole-history s | whole-history RTF | speed-up |"
    )
    print("|---|---|---|---|---|---|---|")
    for seconds in args.seconds:
        audio = torch.from_numpy(rng.normal(0, 0.1, int(seconds * SAMPLE_RATE)).astype(np.float32))[
            None
        ]
        times = {}
        for cached in (True, False):
            start = time.perf_counter()
            out = net.generate(audio, template, seed=0, cached=cached)
            times[cached] = time.perf_counter() - start
            if cached:
                reference = out
            elif not torch.equal(out, reference):
                print("warning: cached and whole-history samples differ", file=sys.stderr)
        print(
            f"| {seconds:g} s | {out.shape[1]} | {times[True]:.2f} | {times[True] / seconds:.3f} | "
            f"{times[False]:.1f} | {times[False] / seconds:.2f} | {times[False] / times[True]:.0f}x |"
        )


@torch.inference_mode()
def retarget_video(args) -> None:
    """The first test sentence, its truth and its codes decoded on another identity's face."""
    from talkmesh.animation import Animation
    from talkmesh.face.assets import load_head
    from talkmesh.output.render import render_side_by_side

    net = load(args.model)
    ds = test_split(args.data)
    s = ds[args.index]
    target = load_head(args.target)
    codes = encode(net, s.vertices, s.template, s.audio)
    moved = decode(net, target.template, codes)
    recon = decode(net, s.template, codes)
    anims = [
        Animation(
            vertices=v,
            faces=target.faces,
            fps=net.motion_fps,
            audio=s.audio,
            sample_rate=SAMPLE_RATE,
        )
        for v in (s.vertices, recon, moved)
    ]
    labels = [f"{s.subject}: truth", "MeshTalk codes, own face", f"same codes on {args.target}"]
    render_side_by_side(anims, labels, args.output, size=args.size, progress=True)
    print(f"wrote {args.output} ({Path(args.output).stat().st_size // 1024} KB): {s.name}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default="corpus/synth")
    sub = p.add_subparsers(dest="command", required=True)
    t = sub.add_parser("table1")
    t.add_argument(
        "variants", nargs="+", help="LABEL=release.safetensors (expression space + prior)"
    )
    d = sub.add_parser("disentangle")
    d.add_argument("--model", required=True)
    d.add_argument("--pairs", type=int, default=20)
    d.add_argument("--figure", default=None)
    v = sub.add_parser("diversity")
    v.add_argument("--model", required=True)
    v.add_argument("--seeds", type=int, default=5)
    v.add_argument("--sentences", type=int, default=5)
    s = sub.add_parser("speed")
    s.add_argument("--model", required=True)
    s.add_argument("--seconds", type=float, nargs="+", default=[4.0, 30.0])
    s.add_argument("--threads", type=int, default=2)
    r = sub.add_parser("retarget-video")
    r.add_argument("--model", required=True)
    r.add_argument("--target", default="bo", help="bundled identity to re-target onto")
    r.add_argument("--index", type=int, default=0, help="test sequence")
    r.add_argument("--size", type=int, default=256)
    r.add_argument("-o", "--output", required=True)
    args = p.parse_args()
    if args.command != "speed":
        torch.set_num_threads(2)
    commands = {
        "table1": table1,
        "disentangle": disentangle,
        "diversity": diversity,
        "speed": speed,
        "retarget-video": retarget_video,
    }
    commands[args.command](args)


if __name__ == "__main__":
    main()
