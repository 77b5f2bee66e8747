"""Head-motion statistics over a minute and more of speech the motion was never tuned on: the
range (standard deviation, 5th-95th percentile spread) and speed (mean and 95th percentile of
the absolute angular speed) of pitch, yaw and roll, offline and live.

    python bench/head_stats.py [--amount 0.5] [--seeds 0,1,2] [--wavs DIR] [--gap 0.6]

The speech: the synthetic corpus's voices (``talkmesh synth --subjects 4 --sentences 8``, made in
a temporary folder: four MBROLA/Festival voices, about 100 s) and the recording in
``examples/``, joined with ``--gap`` seconds of silence; ``--wavs DIR`` takes a folder's .wav
files instead. Never the real-speech benchmark's recordings (those judge, they do not tune).

"offline" is :func:`talkmesh.face.head_motion.head_pose` as ``talkmesh animate`` makes it;
"live" is :class:`talkmesh.face.head_stream.HeadMotionStream` as a ``talkmesh serve`` session
makes it (20 ms chunks, each frame asked once its audio and 100 ms more have come).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from talkmesh.audio.loading import SAMPLE_RATE, load_audio
from talkmesh.face.head_motion import NATURAL, POSE_COLUMNS, head_pose
from talkmesh.face.head_stream import HeadMotionStream

FPS = 30.0
ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "librivox-sense-and-sensibility.flac"
CHUNK = SAMPLE_RATE // 50  # 20 ms, as the viewer sends
LOOKAHEAD_FRAMES = 3  # 100 ms


def synth_wavs(folder: Path) -> list[Path]:
    """The synthetic corpus's utterances, made by the ``talkmesh synth`` command."""
    cmd = [sys.executable, "-m", "talkmesh", "synth", "--out", str(folder), "--subjects", "4"]
    cmd += ["--sentences", "8", "--workers", "1", "--seed", "0", "-q"]
    subprocess.run(cmd, check=True, stderr=subprocess.DEVNULL)
    return sorted((folder / "wav").glob("*.wav"))


def joined(paths: list[Path], gap: float) -> np.ndarray:
    pause = np.zeros(int(gap * SAMPLE_RATE), np.float32)
    return np.concatenate([part for p in paths for part in (load_audio(p), pause)])


def live_poses(wave: np.ndarray, frames: int, amount: float, seed: int) -> np.ndarray:
    motion = HeadMotionStream(FPS, amount=amount, seed=seed)
    out, done = [], 0
    for i in range(0, len(wave), CHUNK):
        motion.receive(wave[i : i + CHUNK])
        ready = min(frames, int((i + CHUNK) / SAMPLE_RATE * FPS) - LOOKAHEAD_FRAMES)
        if ready > done:
            out.append(motion.poses(done, ready))
            done = ready
    out.append(motion.poses(done, frames))
    return np.concatenate(out)


def rows(name: str, seed: int, pose: np.ndarray) -> list[str]:
    out = []
    for k, angle in enumerate(POSE_COLUMNS[:3]):
        deg = np.degrees(pose[:, k].astype(np.float64))
        speed = np.abs(np.diff(deg)) * FPS
        spread = np.percentile(deg, 95) - np.percentile(deg, 5)
        out.append(
            f"| {name} | {seed} | {angle} | {deg.std():.2f} | {spread:.2f} | "
            f"{speed.mean():.2f} | {np.percentile(speed, 95):.2f} |"
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--amount", type=float, default=NATURAL)
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--gap", type=float, default=0.6, help="silence between utterances (s)")
    ap.add_argument("--wavs", type=Path, help="a folder of .wav files instead of the corpus")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        if args.wavs is not None:
            paths = sorted(args.wavs.glob("*.wav"))
        else:
            paths = synth_wavs(Path(tmp) / "synth") + [EXAMPLE]
        wave = joined(paths, args.gap)
    frames = int(len(wave) / SAMPLE_RATE * FPS)
    print(
        f"{len(paths)} utterances, {len(wave) / SAMPLE_RATE:.1f} s, amount {args.amount:g}, "
        f"{FPS:g} fps\n"
    )
    print(
        "| motion | seed | angle | std (deg) | p5-p95 (deg) | mean speed (deg/s) | p95 speed (deg/s) |"
    )
    print("|---|---|---|---|---|---|---|")
    for seed in (int(s) for s in args.seeds.split(",")):
        offline = head_pose(wave, frames, FPS, amount=args.amount, seed=seed)
        live = live_poses(wave, frames, args.amount, seed)
        for line in rows("offline", seed, offline) + rows("live", seed, live):
            print(line)


if __name__ == "__main__":
    main()
