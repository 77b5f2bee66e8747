"""Frame timing of ``talkmesh livelink``: how evenly the Live Link Face packets arrive.

    python bench/livelink_jitter.py [--seconds 20] [--fps 30,60]

A UDP listener on 127.0.0.1 (a thread of this process, standing in for Unreal) stamps each
packet's arrival with ``time.perf_counter``; the sender is
:func:`talkmesh.output.livelink.play_live_link`, the loop ``talkmesh livelink`` runs, sending an
animation of ``--seconds`` of random ARKit weights. Jitter of packet ``i`` is its arrival minus
its due time, ``i / fps`` after the stream's start (the median of ``arrival - i / fps``, so that
the constant latency is taken out); the table
gives its median, 99th percentile and largest absolute value, and the spread (standard
deviation) of the intervals between packets. Every packet is decoded by ``pylivelinkface`` and
its frame number checked to follow the one before.
"""

from __future__ import annotations

import argparse
import socket
import threading
import time

import numpy as np
from pylivelinkface import PyLiveLinkFace

from talkmesh.animation import Animation
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.output.livelink import LiveLinkSender, Target, play_live_link


def listen(sock: socket.socket, count: int, arrivals: list[float], frames: list[int]) -> None:
    for _ in range(count):
        data = sock.recv(4096)
        arrivals.append(time.perf_counter())
        frames.append(PyLiveLinkFace.decode(data)[1]._frames)


def measure(seconds: float, fps: float) -> dict[str, float]:
    count = int(seconds * fps)
    anim = Animation(
        vertices=np.zeros((count, 3, 3)),
        faces=np.array([[0, 1, 2]]),
        fps=fps,
        weights=np.random.default_rng(0).random((count, 52)).astype(np.float32),
        weight_names=list(ARKIT_NAMES),
    )
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        sock.settimeout(10)
        arrivals: list[float] = []
        frames: list[int] = []
        thread = threading.Thread(target=listen, args=(sock, count, arrivals, frames))
        thread.start()
        with LiveLinkSender(Target("127.0.0.1", sock.getsockname()[1])) as sender:
            played = play_live_link(anim, sender)
        thread.join()
    assert frames == list(range(count)), "frames lost or out of order"
    t = np.array(arrivals)
    offset = t - np.arange(count) / fps
    jitter = np.abs(offset - np.median(offset)) * 1000
    return {
        "fps": fps,
        "frames": count,
        "median_ms": float(np.median(jitter)),
        "p99_ms": float(np.percentile(jitter, 99)),
        "max_ms": float(jitter.max()),
        "interval_sd_ms": float(np.diff(t).std() * 1000),
        "late_mean_ms": float(played.late.mean() * 1000),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--fps", default="30,60")
    args = parser.parse_args()
    print("| fps | frames | jitter median (ms) | p99 (ms) | max (ms) | interval sd (ms) |")
    print("|---:|---:|---:|---:|---:|---:|")
    for fps in (float(f) for f in args.fps.split(",")):
        r = measure(args.seconds, fps)
        print(
            f"| {r['fps']:g} | {r['frames']} | {r['median_ms']:.3f} | {r['p99_ms']:.3f} | "
            f"{r['max_ms']:.3f} | {r['interval_sd_ms']:.3f} |"
        )


if __name__ == "__main__":
    main()
