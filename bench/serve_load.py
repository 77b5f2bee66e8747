"""``talkmesh serve`` under load: N concurrent real-time streams, per-frame latency, one table.

    python bench/serve_load.py                                # 1, 2, 4, 8 streams of 20 s
    python bench/serve_load.py --streams 1,2 --seconds 10     # quicker
    python bench/serve_load.py --model path/to/streaming.safetensors

Starts ``talkmesh serve`` on a free loopback port in a subprocess. Each client streams speech
(the pocketsphinx test recordings, looped; or ``--wav``) paced in real time, ``--chunk-ms`` at a
time, and records when every frame arrives. A frame's latency runs from sending the chunk that
completed its audio (its time plus the look-ahead) to receiving it, so it includes waiting for
the compute of other sessions and at most one chunk of the animator's own extra context (the
procedural recogniser reads 15 ms past the look-ahead). Frames that only the final flush
releases are counted but not timed. A stream keeps up with real time when the median latency of
its last two seconds is at most ``KEEP_UP_MS`` above that of its first two: no growing backlog.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from talkmesh.audio.loading import SAMPLE_RATE, load_audio
from talkmesh.serve.protocol import decode_frame

LIBRIVOX = Path("/usr/share/pocketsphinx/test/data/librivox")
TEXT = (
    "The quick brown fox jumps over the lazy dog. She sells sea shells by the sea shore. "
    "Peter Piper picked a peck of pickled peppers, and then he went home to rest."
)
KEEP_UP_MS = 100.0
EDGE_S = 2.0  # the start and the end of a stream compared for a growing backlog


@dataclass
class StreamResult:
    expected: int
    received: int
    gaps: int  # frame indices missing or out of order
    latencies: np.ndarray  # (frames timed,) seconds
    frame_times: np.ndarray  # (frames timed,) seconds of stream time of those frames


def speech(seconds: float, wav: str | None) -> bytes:
    """``seconds`` of speech as 16 kHz int16 little-endian PCM."""
    if wav:
        wave = load_audio(wav)
    elif LIBRIVOX.is_dir():
        wave = np.concatenate([load_audio(p) for p in sorted(LIBRIVOX.glob("*.wav"))])
    else:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "speech.wav"
            subprocess.run(["espeak-ng", "-v", "en-us", "-w", str(path), TEXT], check=True)
            wave = load_audio(path)
    n = int(seconds * SAMPLE_RATE)
    wave = np.tile(wave, math.ceil(n / len(wave)))[:n]
    return (np.clip(wave, -1, 1) * 32767).astype("<i2").tobytes()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(port: int, model: str, max_sessions: int) -> subprocess.Popen:
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "talkmesh",
            "serve",
            "--port",
            str(port),
            "-q",
            "--model",
            model,
            "--max-sessions",
            str(max_sessions),
        ],
        env=dict(os.environ, HF_HUB_OFFLINE="1"),
    )
    import httpx

    deadline = time.monotonic() + 120
    while True:
        try:
            httpx.get(f"http://127.0.0.1:{port}/health").raise_for_status()
            return proc
        except httpx.TransportError:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise SystemExit("the server did not start") from None
            time.sleep(0.2)


async def one_stream(url: str, pcm: bytes, chunk_ms: float) -> StreamResult:
    from websockets.asyncio.client import connect

    chunk = 2 * int(SAMPLE_RATE * chunk_ms / 1000)
    sent_at: list[float] = []  # time each chunk was sent
    arrivals: list[tuple[int, float]] = []
    async with connect(url, max_size=None) as ws:
        hello = json.loads(await ws.recv())
        fps, lookahead = hello["fps"], hello["lookahead_ms"] / 1000

        async def send() -> None:
            start = time.perf_counter()
            for k, i in enumerate(range(0, len(pcm), chunk)):
                delay = start + (k + 1) * chunk_ms / 1000 - time.perf_counter()
                if delay > 0:  # the chunk's audio has been "recorded"
                    await asyncio.sleep(delay)
                await ws.send(pcm[i : i + chunk])
                sent_at.append(time.perf_counter())
            await ws.send(json.dumps({"type": "end"}))

        sender = asyncio.create_task(send())
        async for message in ws:
            if isinstance(message, bytes):
                arrivals.append((decode_frame(message).index, time.perf_counter()))
            elif (reply := json.loads(message))["type"] == "error":
                raise SystemExit(f"the server refused a stream: {reply['message']}")
            else:
                break  # {"type": "end"}
        await sender
    total = len(pcm) // 2
    expected = max(1, round(total / SAMPLE_RATE * fps))
    indices = [i for i, _ in arrivals]
    gaps = sum(1 for k, i in enumerate(indices) if i != k)
    latencies, times = [], []
    for index, arrived in arrivals:
        needed = math.ceil((index / fps + lookahead) * SAMPLE_RATE)
        k = math.ceil(needed / (chunk // 2)) - 1  # the chunk that completes the frame's audio
        if needed <= total and k < len(sent_at):  # later frames wait for the flush: not timed
            latencies.append(arrived - sent_at[max(k, 0)])
            times.append(index / fps)
    return StreamResult(expected, len(arrivals), gaps, np.array(latencies), np.array(times))


async def run_streams(url: str, pcm: bytes, n: int, chunk_ms: float) -> list[StreamResult]:
    return list(await asyncio.gather(*(one_stream(url, pcm, chunk_ms) for _ in range(n))))


def keeps_up(r: StreamResult) -> tuple[bool, float]:
    """(no growing backlog, median latency of the end minus that of the start in ms)."""
    first = r.latencies[r.frame_times < EDGE_S]
    last = r.latencies[r.frame_times > r.frame_times.max() - EDGE_S]
    drift = 1000 * (np.median(last) - np.median(first))
    return drift <= KEEP_UP_MS, drift


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument(
        "--streams", default="1,2,4,8", help="concurrent streams per run (default 1,2,4,8)"
    )
    p.add_argument("--seconds", type=float, default=20.0, help="audio per stream (default 20)")
    p.add_argument("--chunk-ms", type=float, default=20.0, help="audio per message (default 20)")
    p.add_argument("--model", default="procedural", help="procedural or a streaming .safetensors")
    p.add_argument("--wav", help="speech to stream (default: the pocketsphinx test recordings)")
    args = p.parse_args()
    counts = [int(s) for s in args.streams.split(",")]
    pcm = speech(args.seconds, args.wav)
    port = free_port()
    proc = start_server(port, args.model, max(counts))
    name = "procedural" if args.model == "procedural" else Path(args.model).stem
    url = f"ws://127.0.0.1:{port}/ws/stream?model={name}"
    rows = []
    try:
        for n in counts:
            results = asyncio.run(run_streams(url, pcm, n, args.chunk_ms))
            lat = 1000 * np.concatenate([r.latencies for r in results])
            ups = [keeps_up(r) for r in results]
            expected = sum(r.expected for r in results)
            received = sum(r.received for r in results)
            rows.append(
                f"| {n} | {expected} / {received} | {expected - received + sum(r.gaps for r in results)} "
                f"| {np.median(lat):.0f} | {np.percentile(lat, 95):.0f} "
                f"| {max(d for _, d in ups):+.0f} | {'yes' if all(u for u, _ in ups) else 'no'} |"
            )
            print(f"{n} streams: done", file=sys.stderr, flush=True)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    print(
        f"\n{args.model}, {args.seconds:g} s per stream in {args.chunk_ms:g} ms chunks, "
        f"{os.cpu_count()} CPU cores\n"
    )
    print(
        "| streams | frames expected / received | dropped | median latency (ms) "
        "| p95 latency (ms) | worst drift end-start (ms) | kept up |"
    )
    print("|---|---|---|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
