"""Does ``talkmesh serve`` keep its memory when clients misbehave? Idle RSS before and after
rounds of bad and good requests.

    PYTHONPATH=src python bench/serve_memory.py [--rounds 3] [--model procedural] [--seconds 3]

Starts ``talkmesh serve`` (the procedural animator unless ``--model``) on a free loopback port and
prints its resident memory and its workers' (``VmRSS``, /proc) idle, then after each round of: WebSocket sessions
sending garbage (text, ``[`` x 30000, odd-length and oversized binary), request heads of 60 kB and
a 100 kB URL, POST /animate of garbage bytes and of ``--seconds`` of speech (3), and streamed sessions of 3 s
of speech; each measured after ``--settle`` seconds idle. Memory that rises once and then stays
is the allocator's working set; memory that rises every round is a leak. Linux only.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import soundfile as sf

LIBRIVOX = Path("/usr/share/pocketsphinx/test/data/librivox")
SAMPLE_RATE = 16_000


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS")


def tree_mb(pid: int) -> tuple[float, float]:
    """RSS of the server process, and of its worker processes together (MB)."""
    children = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        children += [int(c) for c in (task / "children").read_text().split()]
    return rss_mb(pid), sum(rss_mb(c) for c in children)


def speech(seconds: float) -> np.ndarray:
    """(S,) float32 speech at 16 kHz: a LibriVox clip where installed, else a gliding tone."""
    clips = sorted(LIBRIVOX.glob("*.wav"))
    if clips:
        wave, sr = sf.read(clips[0], dtype="float32")
        assert sr == SAMPLE_RATE, sr
    else:
        t = np.arange(int(seconds * SAMPLE_RATE)) / SAMPLE_RATE
        wave = (0.3 * np.sin(2 * np.pi * (150 + 50 * t) * t)).astype(np.float32)
    return np.resize(wave, int(seconds * SAMPLE_RATE))


def wav_bytes(wave: np.ndarray) -> bytes:
    buf = io.BytesIO()
    sf.write(buf, wave, SAMPLE_RATE, format="WAV", subtype="PCM_16")
    return buf.getvalue()


async def garbage_session(url: str, message: bytes | str) -> None:
    from websockets.asyncio.client import connect

    try:
        async with connect(url, max_size=None, open_timeout=60) as ws:
            await ws.recv()  # hello
            await ws.send(message)
            async for _ in ws:
                pass
    except Exception:  # closed by the server: what garbage earns
        pass


async def good_session(url: str, pcm: bytes) -> int:
    from websockets.asyncio.client import connect

    frames = 0
    async with connect(url, max_size=None, open_timeout=60) as ws:
        await ws.recv()
        for i in range(0, len(pcm), 3200):
            await ws.send(pcm[i : i + 3200])
        await ws.send(json.dumps({"type": "end"}))
        async for message in ws:
            if isinstance(message, bytes):
                frames += 1
            else:
                break
    return frames


def raw_request(port: int, head: bytes) -> None:
    """Send a request head as it is (httpx would refuse to send some) and read the answer."""
    with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
        try:
            s.sendall(head)
            s.recv(65536)
        except OSError:  # the server may close on an oversized head before reading it all
            pass


def one_round(port: int, model: str, pcm: bytes, wav: bytes) -> str:
    url = f"ws://127.0.0.1:{port}/ws/stream?model={model}"
    garbage: list[bytes | str] = ["hello", "[" * 30000, b"\x01\x02\x03", b"\0" * 70_000]
    garbage += [json.dumps({"type": "end", "x": [[[]]]}), b"\xff" * 6401]

    async def sessions() -> int:
        for _ in range(5):
            await asyncio.gather(*(garbage_session(url, g) for g in garbage))
        frames = 0
        for _ in range(3):
            frames += sum(await asyncio.gather(*(good_session(url, pcm) for _ in range(2))))
        return frames

    frames = asyncio.run(sessions())
    for size in (40_000, 60_000, 100_000):
        raw_request(port, b"GET /health HTTP/1.1\r\nHost: x\r\nX-Pad: " + b"a" * size + b"\r\n\r\n")
    raw_request(port, b"GET /" + b"a" * 100_000 + b" HTTP/1.1\r\nHost: x\r\n\r\n")
    statuses = []
    with httpx.Client(timeout=300) as client:
        for body in [os.urandom(50_000), b"RIFF" + os.urandom(1000), wav, wav, wav]:
            r = client.post(f"http://127.0.0.1:{port}/animate?model={model}", content=body)
            statuses.append(r.status_code)
    return f"streamed {frames} frames; /animate answered {statuses}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--model", default="procedural")
    ap.add_argument("--seconds", type=float, default=3.0, help="speech posted to /animate")
    ap.add_argument("--settle", type=float, default=5.0, help="idle seconds before measuring")
    args = ap.parse_args()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cmd = [sys.executable, "-m", "talkmesh", "serve", "--port", str(port), "-q"]
    cmd += ["--model", args.model]
    proc = subprocess.Popen(
        cmd, env=dict(os.environ, HF_HUB_OFFLINE="1"), stderr=subprocess.DEVNULL
    )
    try:
        while True:
            try:
                httpx.get(f"http://127.0.0.1:{port}/health")
                break
            except httpx.TransportError:
                if proc.poll() is not None:
                    raise SystemExit("the server did not start") from None
                time.sleep(0.2)
        wave = speech(3.0)
        pcm = (np.clip(wave, -1, 1) * 32767).astype("<i2").tobytes()
        wav = wav_bytes(speech(args.seconds))
        time.sleep(args.settle)
        print("| after | idle RSS MB: server | its workers | what the round did |")
        print("|---|---|---|---|")
        print("| start | {:.0f} | {:.0f} | |".format(*tree_mb(proc.pid)))
        for k in range(args.rounds):
            start = time.perf_counter()
            what = one_round(port, args.model, pcm, wav)
            took = time.perf_counter() - start
            time.sleep(args.settle)
            server, workers = tree_mb(proc.pid)
            print(f"| round {k + 1} | {server:.0f} | {workers:.0f} | {what} ({took:.0f} s) |")
    finally:
        proc.terminate()
        proc.wait()


if __name__ == "__main__":
    main()
