"""Throughput of ``talkmesh animate LIBRARY --workers N``: one worker against two, on two cores.

    python bench/batch_throughput.py                          # bundled CodeTalker, 8 files, 1 vs 2
    python bench/batch_throughput.py --model procedural --files 16 --repeats 3

Makes a library of ``--files`` real recordings (the pocketsphinx test clips, 3-7 s, cycled) and
runs the command a user runs, ``talkmesh animate LIB -o OUT/{stem}.npz --workers N -q``, as a
fresh process per run (model loading and worker start-up included), into a new output folder
each time. The runs alternate (1, 2, 1, 2, ...) so that load from other processes on the machine
falls on both alike; the speed-up is the ratio of the median wall times of the same run. The whole
benchmark is pinned to ``--cores`` CPUs (default 2, the first ones this process may use), so a
larger machine measures the two-core case too. Prints one row per worker count: wall time
(median, min, max), the CPU seconds of all its processes (user + system), files/s, seconds of
speech per wall second, and the speed-up over one worker.
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


def run_once(lib: Path, out: Path, workers: int, model: str) -> tuple[float, float]:
    """Wall and CPU seconds (all its processes) of one ``talkmesh animate`` over the library."""
    cmd = [sys.executable, "-m", "talkmesh", "animate", str(lib), "-o", f"{out}/{{stem}}.npz"]
    cmd += ["--workers", str(workers), "--model", model, "-q"]
    env = dict(os.environ, HF_HUB_OFFLINE="1")
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
        walls: dict[int, list[float]] = {w: [] for w in counts}
        cpus: dict[int, list[float]] = {w: [] for w in counts}
        for r in range(args.repeats):
            for w in counts:
                wall, cpu = run_once(root / "lib", root / f"out-{w}-{r}", w, args.model)
                walls[w].append(wall)
                cpus[w].append(cpu)
                print(
                    f"  run {r + 1}: {w} worker(s) {wall:.1f} s wall, {cpu:.1f} s CPU, "
                    f"load {os.getloadavg()[0]:.2f}",
                    flush=True,
                )
        print(f"load after: {os.getloadavg()[0]:.2f}\n")
    base = statistics.median(walls[counts[0]])
    print(
        "| workers | wall s (median) | min | max | CPU s (median) | files/s | speech s per s "
        "| speed-up |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for w in counts:
        med = statistics.median(walls[w])
        print(
            f"| {w} | {med:.1f} | {min(walls[w]):.1f} | {max(walls[w]):.1f} | "
            f"{statistics.median(cpus[w]):.1f} | {args.files / med:.3f} | {speech / med:.2f} | "
            f"{base / med:.2f}x |"
        )


if __name__ == "__main__":
    main()
