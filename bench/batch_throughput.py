"""Throughput of ``talkmesh animate LIBRARY --workers N``: one worker against two, on two cores.

    python bench/batch_throughput.py                          # bundled CodeTalker, 8 files, 1 vs 2
    python bench/batch_throughput.py --model procedural --files 16 --repeats 3

Makes a library of ``--files`` real recordings (the pocketsphinx test clips, 3-7 s, cycled) and
runs the command a user runs, ``talkmesh animate LIB -o OUT/{stem}.npz --workers N -q``, as a
fresh process per run (model loading and worker start-up included), into a new output folder
each time. The runs alternate (1, 1 with one thread, 2, 1, ...) so that load from other
processes on the machine falls on all alike. The whole benchmark is pinned to ``--cores`` CPUs
(default 2, the first ones this process may use), so a larger machine measures the two-core case
too.

One worker runs twice per round: as users run it (PyTorch's default threads, one per core) and
with one thread (``OMP_NUM_THREADS=1``), what each of N workers gets on N cores
(``talkmesh.batch.library.run_local`` gives each worker cores / N threads). The bundled model's
ops are small, so a second thread buys one worker little and costs it the other core's cache:
the one-thread row is the fair baseline for "N workers vs one". Prints a markdown table, one row
per configuration: wall time (median, min, max), the CPU seconds of all its processes
(user + system), files/s, seconds of speech per wall second, and the speed-up (ratio of median
wall times) over one worker as run by default and over one worker with one thread.
Linux (CPU affinity).
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import soundfile as sf

CLIPS = Path("/usr/share/pocketsphinx/test/data/librivox")


def make_library(folder: Path, files: int) -> float:
    """``files`` copies of the test clips (cycled) in ``folder``; their total seconds."""
    clips = sorted(CLIPS.glob("*.wav"))
    if not clips:
        sys.exit(
            f"no clips in {CLIPS}: install pocketsphinx's test data (apt pocketsphinx-testdata)"
        )
    folder.mkdir(parents=True)
    total = 0.0
    for k in range(files):
        src = clips[k % len(clips)]
        shutil.copyfile(src, folder / f"line{k:03d}.wav")
        total += sf.info(src).duration
    return total


def children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


class Config(NamedTuple):
    label: str
    workers: int
    one_thread: bool  # OMP_NUM_THREADS=1: PyTorch (and BLAS) use one thread


def configs(counts: list[int]) -> list[Config]:
    """The runs of a round: each worker count, and one worker with one thread after one worker."""
    out = []
    for w in counts:
        out.append(Config(str(w), w, False))
        if w == 1:
            out.append(Config("1, one thread", 1, True))
    return out


def run_once(lib: Path, out: Path, config: Config, model: str) -> tuple[float, float]:
    """Wall and CPU seconds (all its processes) of one ``talkmesh animate`` over the library."""
    cmd = [sys.executable, "-m", "talkmesh", "animate", str(lib), "-o", f"{out}/{{stem}}.npz"]
    cmd += ["--workers", str(config.workers), "--model", model, "-q"]
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    env["HF_HUB_OFFLINE"] = "1"
    if config.one_thread:
        env["OMP_NUM_THREADS"] = "1"
    cpu, start = children_cpu(), time.perf_counter()
    res = subprocess.run(cmd, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if res.returncode != 0:
        sys.exit(f"talkmesh animate failed ({res.returncode}):\n{res.stderr[-2000:]}")
    return seconds, children_cpu() - cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="codetalker-synth", help="model to animate with")
    ap.add_argument("--files", type=int, default=8, help="files in the library")
    ap.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    ap.add_argument("--repeats", type=int, default=2, help="runs per worker count")
    ap.add_argument("--cores", type=int, default=2, help="CPUs the benchmark is pinned to")
    args = ap.parse_args()
    allowed = sorted(os.sched_getaffinity(0))
    if len(allowed) < args.cores:
        sys.exit(f"--cores {args.cores}: this process may use only {len(allowed)} CPUs")
    os.sched_setaffinity(0, allowed[: args.cores])  # children inherit it
    counts = [int(w) for w in args.workers.split(",")]
    with tempfile.TemporaryDirectory(prefix="batch-bench-") as tmp:
        root = Path(tmp)
        speech = make_library(root / "lib", args.files)
        print(
            f"{args.files} files, {speech:.1f} s of speech, model {args.model}, "
            f"{args.cores} cores (CPUs {allowed[: args.cores]}), load before: "
            f"{os.getloadavg()[0]:.2f}"
        )
        runs = configs(counts)
        walls: dict[Config, list[float]] = {c: [] for c in runs}
        cpus: dict[Config, list[float]] = {c: [] for c in runs}
        for r in range(args.repeats):
            for k, c in enumerate(runs):
                wall, cpu = run_once(root / "lib", root / f"out-{k}-{r}", c, args.model)
                walls[c].append(wall)
                cpus[c].append(cpu)
                print(
                    f"  run {r + 1}: {c.label} worker(s) {wall:.1f} s wall, {cpu:.1f} s CPU, "
                    f"load {os.getloadavg()[0]:.2f}",
                    flush=True,
                )
        print(f"load after: {os.getloadavg()[0]:.2f}\n")
    print(table(runs, walls, cpus, args.files, speech))


def table(runs, walls, cpus, files: int, speech: float) -> str:
    """The markdown table: a row per configuration, speed-ups over the one-worker rows."""
    med = {c: statistics.median(walls[c]) for c in runs}
    bases = [c for c in runs if c.workers == 1]
    lines = [
        "| workers | wall s (median) | min | max | CPU s (median) | files/s | speech s per s | "
        + " | ".join(f"speed-up over {b.label}" for b in bases)
        + " |",
        "|---|---:|---:|---:|---:|---:|---:|" + "---:|" * len(bases),
    ]
    for c in runs:
        ups = " | ".join(f"{med[b] / med[c]:.2f}x" for b in bases)
        lines.append(
            f"| {c.label} | {med[c]:.1f} | {min(walls[c]):.1f} | {max(walls[c]):.1f} | "
            f"{statistics.median(cpus[c]):.1f} | {files / med[c]:.3f} | {speech / med[c]:.2f} | "
            f"{ups} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    main()
