"""What an oversized upload costs ``talkmesh serve``: time to the refusal and the server's memory.

    python bench/serve_limits.py                       # 60 and 20 min of silent FLAC, default limits
    python bench/serve_limits.py --minutes 60,180 --max-seconds 300

Starts ``talkmesh serve`` on a free loopback port in a subprocess, posts each silent FLAC (an hour
of silence compresses to a few hundred kB, well under the upload limit) to ``/animate`` and
prints, per file: its size, the status and the time to the answer, and the server's resident
memory (``VmRSS``) and its peak so far (``VmHWM``, from /proc) before and after the request; the
last column is how much the request raised the peak. Linux only.
"""

from __future__ import annotations

import argparse
import io
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import soundfile as sf


def silent_flac(minutes: float) -> bytes:
    buf = io.BytesIO()
    with sf.SoundFile(buf, "w", 16_000, 1, format="FLAC") as f:
        block = np.zeros(16_000 * 60, np.int16)
        for _ in range(int(minutes)):
            f.write(block)
    return buf.getvalue()


def memory_mb(pid: int) -> dict[str, float]:
    """VmRSS and VmHWM of a process, MB."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0]) / 1024
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", default="60,20", help="comma-separated lengths of silence")
    ap.add_argument("--max-seconds", type=float, default=None, help="the server's limit")
    args = ap.parse_args()
    port = free_port()
    cmd = [sys.executable, "-m", "talkmesh", "serve", "--port", str(port), "-q"]
    if args.max_seconds:
        cmd += ["--max-seconds", str(args.max_seconds)]
    proc = subprocess.Popen(cmd, env=dict(os.environ, HF_HUB_OFFLINE="1"))
    url = f"http://127.0.0.1:{port}"
    try:
        while True:
            try:
                httpx.get(f"{url}/health")
                break
            except httpx.TransportError:
                time.sleep(0.2)
        print(
            f"{'audio':>8} {'upload kB':>10} {'status':>6} {'answer s':>9} {'RSS MB':>15} "
            f"{'peak MB':>15} {'peak growth':>12}"
        )
        for minutes in (float(m) for m in args.minutes.split(",")):
            body = silent_flac(minutes)
            before = memory_mb(proc.pid)
            start = time.perf_counter()
            response = httpx.post(f"{url}/animate?model=procedural", content=body, timeout=3600)
            took = time.perf_counter() - start
            after = memory_mb(proc.pid)
            print(
                f"{minutes:>6.0f} m {len(body) / 1024:>10.0f} {response.status_code:>6} "
                f"{took:>9.3f} {before['VmRSS']:>6.0f} -> {after['VmRSS']:<6.0f} "
                f"{before['VmHWM']:>6.0f} -> {after['VmHWM']:<6.0f} "
                f"{after['VmHWM'] - before['VmHWM']:>9.1f} MB"
            )
            if response.status_code != 200:
                print(f"         {response.json()['message']}")
    finally:
        proc.terminate()
        proc.wait()


if __name__ == "__main__":
    main()
