"""Streaming: latency, real-time keep-up and the quality cost of a bounded look-ahead, in one run.

    python bench/streaming.py --model runs/codetalker_stream/stage2/model.safetensors \
        [--data corpus/synth] [--minutes 10] [--chunk-ms 20] [--lookaheads 0,50,100,200] \
        [--json out.json] [--plot docs/images/streaming-quality.png]

Latency (per animator, default look-ahead 100 ms unless --latency-lookaheads): ``--minutes`` of
test-split speech (the sentences back to back, repeated) is pushed in ``--chunk-ms`` chunks. Each
push is timed; a single-worker real-time server is then replayed on a virtual clock: chunk k
arrives when its last sample has been captured, waits for the previous push to finish, and its
frames are emitted when its own push ends. Per frame, "end-to-end latency" is its emission time
minus the capture time of the audio at the frame's own time stamp (what a viewer sees as the lag
of the mouth behind the voice: look-ahead + chunking + queueing + compute); "after the completing
chunk" is its emission time minus the arrival of the chunk that completed its look-ahead
(queueing + compute only). "Keeps up" means the
backlog does not grow: the latency of the last minute stays within 50 ms of the first minute's.

Quality: the unseen-speaker test split streamed at each look-ahead in ``--lookaheads`` (20 ms
chunks), scored with LVE / FDD / MVE, next to the offline animators: procedural (whole-clip phone
recognition), the streaming model offline (``generate``, at its largest look-ahead) and the bundled
offline CodeTalker (``--offline-model``).
"""

from __future__ import annotations

import os

# one BLAS thread: a real-time stream does small products every 20 ms, and waking a second BLAS
# thread on a busy machine costs more than the product (measured: 5 ms instead of 0.2 ms a frame)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from talkmesh.audio.loading import SAMPLE_RATE  # noqa: E402
from talkmesh.datasets.reader import open_dataset  # noqa: E402
from talkmesh.evaluation.evaluate import evaluate_dataset, write_baseline, write_model_predictions  # noqa: E402
from talkmesh.serve.stream import open_stream  # noqa: E402


def identities(data: Path) -> dict[str, str]:
    manifest = json.loads((data / "manifest.json").read_text())
    return {s: m["identity"] for s, m in manifest["subjects"].items()}


def head_for(sample, ids: dict[str, str]):
    from talkmesh.face.assets import load_head

    return load_head(ids[sample.subject]).with_template(sample.template, sample.subject)


def stream_clip(streamer, audio: np.ndarray, chunk: int) -> list:
    frames = []
    for i in range(0, len(audio), chunk):
        frames += streamer.push(audio[i : i + chunk])
    return frames + streamer.flush()


# -- latency ---------------------------------------------------------------------------------


def latency_run(make, audio: np.ndarray, chunk: int, fps: float) -> dict:
    streamer = make()
    finish = 0.0
    latencies, after_chunk, emit_times, compute = [], [], [], 0.0
    frames_out = 0
    for i in range(0, len(audio), chunk):
        piece = audio[i : i + chunk]
        arrival = (i + len(piece)) / SAMPLE_RATE
        t0 = time.perf_counter()
        frames = streamer.push(piece)
        spent = time.perf_counter() - t0
        compute += spent
        finish = max(arrival, finish) + spent
        for f in frames:
            latencies.append(finish - f.time)
            after_chunk.append(finish - arrival)
            emit_times.append(f.time)
        frames_out += len(frames)
    t0 = time.perf_counter()
    frames_out += len(streamer.flush())
    compute += time.perf_counter() - t0
    lat = np.array(latencies) * 1000
    times = np.array(emit_times)
    first, last = lat[times < 60], lat[times >= times[-1] - 60]
    duration = len(audio) / SAMPLE_RATE
    return {
        "seconds": duration,
        "frames": frames_out,
        "compute_ms_per_frame": compute / frames_out * 1000,
        "real_time_factor": compute / duration,
        "latency_median_ms": float(np.median(lat)),
        "latency_p95_ms": float(np.percentile(lat, 95)),
        "latency_max_ms": float(lat.max()),
        "after_chunk_median_ms": float(np.median(after_chunk) * 1000),
        "after_chunk_p95_ms": float(np.percentile(after_chunk, 95) * 1000),
        "first_minute_median_ms": float(np.median(first)),
        "last_minute_median_ms": float(np.median(last)),
        "keeps_up": bool(np.median(last) - np.median(first) < 50 and compute < duration),
    }


# -- quality ---------------------------------------------------------------------------------


def write_streamed(
    model: str, data: Path, out: Path, lookahead: float, chunk: int, blinks: bool
) -> float:
    """Stream every test sequence; returns the compute time."""
    dataset = open_dataset("synth", data, "test")
    ids = identities(data)
    out.mkdir(parents=True, exist_ok=True)
    spent = 0.0
    for index in range(len(dataset)):
        sample = dataset[index]
        head = head_for(sample, ids)
        # the procedural animator takes the data's frame rate; a model streams its own, with eyes
        extra = {"fps": dataset.spec.motion_fps} if model == "procedural" else {"blinks": blinks}
        streamer = open_stream(
            model, lookahead_ms=lookahead, head=head, offsets=True, seed=index, **extra
        )
        t0 = time.perf_counter()
        frames = stream_clip(streamer, sample.audio, chunk)
        spent += time.perf_counter() - t0
        offsets = np.stack([f.offsets for f in frames])
        T = len(sample.vertices)
        offsets = offsets[np.minimum(np.arange(T), len(offsets) - 1)]  # same length as the truth
        verts = offsets + sample.template[None]
        np.save(out / f"{sample.name}.npy", verts.reshape(T, -1).astype(np.float32))
    return spent


def score(data: Path, pred: Path) -> dict:
    scores, _ = evaluate_dataset(open_dataset("synth", data, "test"), pred, protocol="physical")
    return {
        "lve_mm": scores.lve * 1e3,
        "fdd_mm": scores.fdd * 1e3,
        "mve_mm": scores.mve * 1e3,
        "lip_sync_r": scores.lip_sync,
    }


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", help="a release that streams (.safetensors) or a bundled model")
    p.add_argument("--data", default="corpus/synth", type=Path)
    p.add_argument("--minutes", type=float, default=10.0)
    p.add_argument("--chunk-ms", type=float, default=20.0)
    p.add_argument("--latency-lookaheads", default="50,100")
    p.add_argument("--lookaheads", default="0,50,100,200")
    p.add_argument("--offline-model", default="codetalker-synth")
    p.add_argument(
        "--no-blinks",
        dest="blinks",
        action="store_false",
        help="stream the model without the procedural blinks and gaze it adds by default",
    )
    p.add_argument("--skip", default="", help="comma list of parts to skip: latency,quality")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--json", type=Path)
    p.add_argument("--plot", type=Path)
    return p.parse_args()


def latency_table(args: argparse.Namespace, labels: dict[str, str], chunk: int) -> list[dict]:
    """``--minutes`` of test-split speech streamed through every animator; prints the table."""
    dataset = open_dataset("synth", args.data, "test")
    one = np.concatenate([dataset[i].audio for i in range(len(dataset))])
    reps = int(np.ceil(args.minutes * 60 * SAMPLE_RATE / len(one)))
    audio = np.tile(one, reps)[: int(args.minutes * 60 * SAMPLE_RATE)]
    rows = []
    print(
        f"\n## Latency: {args.minutes:g} min of speech in {args.chunk_ms:g} ms chunks, "
        f"{args.threads} threads\n"
    )
    print(
        "| animator | look-ahead (ms) | compute / frame (ms) | RTF | latency median (ms) "
        "| p95 (ms) | max (ms) | after the completing chunk: median / p95 (ms) "
        "| first min / last min median (ms) | keeps up |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for animator, label in labels.items():
        for la in map(float, args.latency_lookaheads.split(",")):

            def make(animator=animator, la=la):
                return open_stream(animator, lookahead_ms=la, offsets=True)

            r = latency_run(make, audio, chunk, 30.0)
            r.update(animator=label, lookahead_ms=la)
            rows.append(r)
            print(
                f"| {r['animator']} | {la:g} | {r['compute_ms_per_frame']:.2f} | "
                f"{r['real_time_factor']:.3f} | {r['latency_median_ms']:.0f} | "
                f"{r['latency_p95_ms']:.0f} | {r['latency_max_ms']:.0f} | "
                f"{r['after_chunk_median_ms']:.1f} / {r['after_chunk_p95_ms']:.1f} | "
                f"{r['first_minute_median_ms']:.0f} / {r['last_minute_median_ms']:.0f} | "
                f"{'yes' if r['keeps_up'] else 'NO'} |",
                flush=True,
            )
    return rows


def quality_table(args: argparse.Namespace, labels: dict[str, str], chunk: int) -> list[dict]:
    """Offline and streamed predictions of the test split, scored; prints the table."""
    data, rows = args.data, []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)

        def offline(name: str, model: str, lookahead: str) -> None:
            out = tmp / name
            if model == "procedural":
                write_baseline("synth", data, out, method="procedural", progress=False)
            else:
                write_model_predictions(
                    "synth", data, out, model, blinks=args.blinks, progress=False
                )
            rows.append({"animator": name, "lookahead_ms": lookahead, **score(data, out)})

        offline("procedural", "procedural", "offline")
        if args.offline_model:
            name = f"{args.offline_model} (offline, Whisper)"
            offline(name, args.offline_model, "offline")
        if args.model:
            offline("streaming CodeTalker, offline generate()", args.model, "max")
        for animator, label in labels.items():
            for la in map(float, args.lookaheads.split(",")):
                out = tmp / f"{label}-{la:g}".replace(" ", "_")
                spent = write_streamed(animator, data, out, la, chunk, args.blinks)
                streamed = {"animator": f"{label} (streamed)", "lookahead_ms": la}
                rows.append({**streamed, "compute_s": spent, **score(data, out)})
                print(f"streamed {label} at {la:g} ms", flush=True)
    print("\n## Quality: synthetic unseen-speaker test split (40 sequences)\n")
    print("| animator | look-ahead (ms) | LVE (mm) | FDD (mm) | MVE (mm) | lip-sync r |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['animator']} | {r['lookahead_ms']} | {r['lve_mm']:.3f} | "
            f"{r['fdd_mm']:.3f} | {r['mve_mm']:.3f} | {r['lip_sync_r']:.3f} |"
        )
    return rows


def main() -> None:
    args = parse_args()
    torch.set_num_threads(args.threads)
    chunk = int(round(args.chunk_ms / 1000 * SAMPLE_RATE))
    skip = set(filter(None, args.skip.split(",")))
    animators = ["procedural"] + ([args.model] if args.model else [])
    labels = {a: "procedural" if a == "procedural" else Path(a).stem for a in animators}
    report: dict = {"chunk_ms": args.chunk_ms, "threads": args.threads}
    if "latency" not in skip:
        report["latency"] = latency_table(args, labels, chunk)
    if "quality" not in skip:
        report["quality"] = quality_table(args, labels, chunk)
        if args.plot:
            plot(report["quality"], args.plot)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8, 3.2), dpi=90)
    for metric, ax in zip(("lve_mm", "fdd_mm"), axes):
        streamed = [r for r in rows if "(streamed)" in r["animator"]]
        for name in dict.fromkeys(r["animator"] for r in streamed):
            pts = [(r["lookahead_ms"], r[metric]) for r in streamed if r["animator"] == name]
            line = ax.plot(*zip(*pts), marker="o", label=name.replace(" (streamed)", ""))[0]
            offline = [
                r
                for r in rows
                if r["lookahead_ms"] in ("offline", "max")
                and r["animator"].split(" ")[0] == name.split(" ")[0]
            ]
            for r in offline:
                ax.axhline(r[metric], color=line.get_color(), ls="--", lw=1)
        ax.set_xlabel("look-ahead (ms)")
        ax.set_ylabel(metric.split("_")[0].upper() + " (mm)")
    axes[0].legend(fontsize=7)
    fig.suptitle("Streaming quality vs look-ahead (dashed: the same animator offline)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)


if __name__ == "__main__":
    main()
