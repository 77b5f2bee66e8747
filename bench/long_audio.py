"""Peak memory and output size of `talkmesh animate` on long audio, and the .npz formats' error.

    python bench/long_audio.py                       # 1, 10 and 60 minutes, both animators
    python bench/long_audio.py --minutes 1 10 --models procedural
    python bench/long_audio.py --minutes --models procedural   # only the formats' error

The long audio is espeak-ng speech (a minute of sentences from the synthetic corpus's grammar,
with pauses) repeated to length, written as 16-bit WAV in a temporary folder. Each run is one
`talkmesh animate LONG.wav -o out.npz` process; its peak resident memory is the kernel's
ru_maxrss for that process (os.wait4). The second table saves a minute of each animator's output
in each .npz form and measures the vertex error of reading it back, in millimetres.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import soundfile as sf

from talkmesh.audio.loading import SAMPLE_RATE, load_audio
from talkmesh.datasets.sentences import generate_sentences

SPEECH = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "official" / "speech.wav"


def speech_minute(folder: Path) -> np.ndarray:
    """About a minute of espeak-ng sentences with 0.4 s pauses (the test clip without espeak-ng)."""
    if shutil.which("espeak-ng") is None:
        return load_audio(SPEECH)
    parts, total = [], 0
    for i, text in enumerate(generate_sentences(40, seed=0)):
        path = folder / f"s{i}.wav"
        subprocess.run(["espeak-ng", "-w", str(path), text], check=True, capture_output=True)
        wave = load_audio(path)
        parts += [wave, np.zeros(int(0.4 * SAMPLE_RATE), np.float32)]
        total += len(wave)
        if total > 60 * SAMPLE_RATE:
            break
    return np.concatenate(parts)


def long_wav(minute: np.ndarray, minutes: float, path: Path) -> Path:
    n = int(minutes * 60 * SAMPLE_RATE)
    reps = -(-n // len(minute))
    with sf.SoundFile(path, "w", SAMPLE_RATE, 1, subtype="PCM_16") as f:
        for _ in range(reps):  # written a piece at a time: the bench holds no hour of audio
            take = min(len(minute), n)
            f.write(minute[:take])
            n -= take
    return path


def run_animate(audio: Path, out: Path, model: str) -> tuple[float, float]:
    """Seconds and peak RSS (MB) of one `talkmesh animate` process."""
    cmd = [sys.executable, "-m", "talkmesh", "animate", str(audio), "-o", str(out)]
    cmd += ["--model", model, "--overwrite", "-q"]
    start = time.perf_counter()
    proc = subprocess.Popen(cmd)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode})")
    return time.perf_counter() - start, usage.ru_maxrss / 1024


def memory_table(minute: np.ndarray, folder: Path, minutes: list[float], models: list[str]):
    from talkmesh.face.assets import load_head

    V = load_head().num_vertices
    print(
        "| model | audio (min) | frames | wall (s) | peak RSS (MB) | .npz (MB) | float32 vertices (MB) |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|")
    for m in minutes:
        audio = long_wav(minute, m, folder / f"long{m:g}.wav")
        for model in models:
            out = folder / f"out_{model}_{m:g}.npz"
            seconds, peak = run_animate(audio, out, model)
            frames = round(m * 60 * 30)
            print(
                f"| {model} | {m:g} | {frames} | {seconds:.0f} | {peak:.0f} | "
                f"{out.stat().st_size / 1e6:.1f} | {frames * V * 12 / 1e6:.0f} |",
                flush=True,
            )
            out.unlink()
        audio.unlink()


def error_table(minute: np.ndarray, folder: Path, models: list[str]) -> None:
    from talkmesh.output.formats import load_animation, save_animation
    from talkmesh.pipeline import animate

    print("\n| model | form | size (MB) | max error (mm) | mean error (mm) |")
    print("|---|---|---:|---:|---:|")
    for model in models:
        anim = animate(minute, model=model)
        old = folder / "v1.npz"  # format 1: float32 vertices, stored
        np.savez(old, vertices=anim.vertices, faces=anim.faces, fps=np.float64(anim.fps),
                 audio=anim.audio, weights=anim.weights)  # fmt: skip
        print(f"| {model} | format 1: float32 vertices | {old.stat().st_size / 1e6:.1f} | 0 | 0 |")
        forms = [
            ("offsets.npz", "format 2: float16 offsets, deflated (default)"),
            ("x.weights.npz", ".weights.npz: ARKit weights only (lossy)"),
        ]
        for form, name in forms:
            path = folder / form
            save_animation(anim, path, overwrite=True)
            err = np.linalg.norm(load_animation(path).vertices - anim.vertices, axis=-1) * 1000
            print(
                f"| {model} | {name} | {path.stat().st_size / 1e6:.1f} | "
                f"{err.max():.4f} | {err.mean():.5f} |",
                flush=True,
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, nargs="*", default=[1, 10, 60])
    ap.add_argument("--models", nargs="+", default=["codetalker-synth", "procedural"])
    ap.add_argument("--no-errors", action="store_true", help="skip the format error table")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        minute = speech_minute(folder)
        print(f"speech: {len(minute) / SAMPLE_RATE:.1f} s repeated to length\n")
        memory_table(minute, folder, args.minutes, args.models)
        if not args.no_errors:
            error_table(minute, folder, args.models)


if __name__ == "__main__":
    main()
