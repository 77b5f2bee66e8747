"""Wall time of the main job, ``talkmesh animate SPEECH -o x.glb``, and of a resume with nothing
left to do, for two versions of talkmesh side by side.

    python bench/latency.py --before /work/old/src --after src --repeats 5
    python bench/latency.py --after src --split      # where one run's time goes (cProfile)

Each run is a fresh process, as a user runs it (start-up and imports included): ``glb`` is
``talkmesh animate SPEECH -o OUT/x.glb --overwrite -q`` (the bundled model, default settings),
with the version's cache folder (``TALKMESH_CACHE``) warmed by one untimed run first (the bundled
model's ONNX graphs are exported there on first use); ``glb-first`` is the same with an empty
cache folder every run (a first run after installing); ``glb-torch`` adds ``--runtime torch``;
``resume`` is ``talkmesh animate LIB/ -o OUT/ -q`` on a folder whose output is already there (a
rerun of a finished library: nothing to animate). The versions alternate run by run (before,
after, before, ...), so that load from other processes falls on both alike; the 1-minute load
average is read before each run. ``SPEECH`` defaults to the demo recording in examples/
(8.3 s of speech). Prints a markdown table: per case and version, the median, minimum and maximum
wall time, the median CPU time (user + system of the process) and the median load average.

``--split`` profiles one ``glb`` run of ``--after`` instead (its cache warmed; ``--torch``: with
``--runtime torch``) and prints its parts: importing torch or ONNX Runtime, loading the model, generation, voice activity, the other mouth corrections, the ARKit fit with
blinks and head pose, the .glb's morph targets, writing it, and the rest (start-up, the other
imports, reading the audio).
"""

from __future__ import annotations

import argparse
import os
import pstats
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SPEECH = ROOT / "examples" / "librivox-sense-and-sensibility.flac"


def run(src: Path, args: list[str], cache: Path) -> tuple[float, float, float]:
    """(wall s, CPU s, load average) of ``python -m talkmesh ARGS`` with ``src`` first on the
    path and ``cache`` as its cache folder."""
    env = {
        **os.environ,
        "PYTHONPATH": str(src),
        "HF_HUB_OFFLINE": "1",
        "TALKMESH_CACHE": str(cache),
    }
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "talkmesh", *args], env=env, capture_output=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        sys.exit(f"talkmesh {' '.join(args)} failed:\n{res.stderr.decode()}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, load


def cases(speech: Path, work: Path) -> dict[str, list[str]]:
    """The commands measured, with a library whose output already exists for ``resume``."""
    lib, done = work / "lib", work / "done"
    lib.mkdir()
    done.mkdir()
    (lib / speech.name).symlink_to(speech.resolve())
    (done / f"{speech.stem}.mp4").write_bytes(b"an earlier run's output")  # what resume checks
    glb = ["animate", str(speech), "-o", str(work / "x.glb"), "--overwrite", "-q"]
    return {
        "glb": glb,
        "glb-first": glb,
        "glb-torch": [*glb, "--runtime", "torch"],
        "resume": ["animate", str(lib), "-o", f"{done}/", "-q"],
    }


def compare(versions: dict[str, Path], speech: Path, repeats: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        commands = cases(speech, work)
        caches = {name: work / f"cache-{name}" for name in versions}
        for name, src in versions.items():  # warm each version's cache
            run(src, commands["glb"], caches[name])
        times: dict[tuple[str, str], list[tuple[float, float, float]]] = {}
        for i in range(repeats):
            for case, args in commands.items():
                for name, src in versions.items():
                    cache = work / f"empty-{name}-{i}" if case == "glb-first" else caches[name]
                    times.setdefault((case, name), []).append(run(src, args, cache))
    print("| case | version | wall median (s) | min | max | CPU median (s) | load avg |")
    print("|---|---|---|---|---|---|---|")
    for (case, name), rows in times.items():
        wall = [r[0] for r in rows]
        print(
            f"| {case} | {name} | {statistics.median(wall):.2f} | {min(wall):.2f} | "
            f"{max(wall):.2f} | {statistics.median(r[1] for r in rows):.2f} | "
            f"{statistics.median(r[2] for r in rows):.2f} |"
        )


# (label, function as pstats names it: file suffix and name); parts are made disjoint below
PARTS = {
    "torch": ("torch/__init__.py", "<module>"),
    "onnxruntime": ("onnxruntime/__init__.py", "<module>"),
    "load": ("talkmesh/models/release.py", "load_model"),
    "open": ("talkmesh/models/runtime.py", "open_model"),
    "generation": ("talkmesh/pipeline.py", "_learned_chunks"),
    "vad": ("talkmesh/audio/vad.py", "speech_pauses"),
    "corrections": ("talkmesh/face/corrections.py", "correct_mouth_chunks"),
    "finish": ("talkmesh/pipeline.py", "_finish_learned"),
    "glb": ("talkmesh/output/gltf.py", "export_glb"),
    "morph": ("talkmesh/output/morph.py", "morph_rig"),
}


def split(src: Path, speech: Path, extra: list[str]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        prof = Path(tmp) / "run.prof"
        args = ["animate", str(speech), "-o", f"{tmp}/x.glb", "-q", *extra]
        env = {**os.environ, "PYTHONPATH": str(src), "HF_HUB_OFFLINE": "1"}
        env["TALKMESH_CACHE"] = f"{tmp}/cache"
        run(src, [*args, "--overwrite"], Path(f"{tmp}/cache"))  # the cache warmed
        Path(f"{tmp}/x.glb").unlink()
        load = os.getloadavg()[0]
        start = time.perf_counter()
        cmd = [sys.executable, "-m", "cProfile", "-o", str(prof), "-m", "talkmesh", *args]
        subprocess.run(cmd, env=env, check=True)
        wall = time.perf_counter() - start
        stats = pstats.Stats(str(prof)).stats
    cum = {label: 0.0 for label in PARTS}
    for (file, _, name), (_, _, _, total, _) in stats.items():
        for label, (suffix, fn) in PARTS.items():
            if file.endswith(suffix) and name == fn:
                cum[label] = max(cum[label], total)
    parts = {
        "importing torch": cum["torch"],
        "importing onnxruntime": cum["onnxruntime"],
        "loading the model": max(cum["load"], cum["open"] - cum["onnxruntime"] - cum["torch"]),
        "generation": cum["generation"],
        "voice activity (Silero VAD)": cum["vad"],
        "other mouth corrections": cum["corrections"] - cum["generation"] - cum["vad"],
        "ARKit fit, blinks, emotion": cum["finish"] - cum["corrections"],
        "the .glb's morph targets": cum["morph"],
        "writing the .glb": cum["glb"] - cum["morph"],
    }
    parts["the rest (start-up, other imports, audio, head pose)"] = wall - sum(parts.values())
    print(f"one profiled run (load average {load:.2f}): {wall:.2f} s wall\n")
    print("| part | s |\n|---|---|")
    for label, seconds in parts.items():
        print(f"| {label} | {seconds:.2f} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--before", type=Path, help="the src/ folder of the version to compare with")
    p.add_argument("--after", type=Path, default=ROOT / "src", help="src/ of this version")
    p.add_argument("--speech", type=Path, default=SPEECH)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--split", action="store_true", help="profile one run of --after instead")
    p.add_argument("--torch", action="store_true", help="--split: the run with --runtime torch")
    a = p.parse_args()
    if a.split:
        split(a.after.resolve(), a.speech, ["--runtime", "torch"] if a.torch else [])
        return
    versions = {"after": a.after.resolve()}
    if a.before is not None:
        versions = {"before": a.before.resolve(), **versions}
    compare(versions, a.speech, a.repeats)


if __name__ == "__main__":
    main()
