"""``talkmesh serve`` under load: N concurrent real-time WebSocket sessions, one table.

    python bench/serve_load.py --sessions 16,32 --model procedural --minutes 5
    python bench/serve_load.py --sessions 16 --model codetalker-stream --minutes 5
    python bench/serve_load.py --sessions 1,2 --minutes 0.2               # quick look
    python bench/serve_load.py --sessions 1,16 --model codetalker-stream --compute-only
    python bench/serve_load.py --sessions 1,4,16 --model codetalker-synth --lookahead-ms 300 \
        --compute-only --one-window-at-a-time --torch-threads 1

For each session count a fresh ``talkmesh serve`` starts on a free loopback port in a subprocess
(``--max-sessions`` = the count). Each client streams speech (the pocketsphinx test recordings,
looped; or ``--wav``) paced in real time, ``--chunk-ms`` at a time, starting at a random moment
of the first ``--stagger-s`` seconds, and records when every frame arrives.

``--model``: ``procedural``, a streaming release (.safetensors), a bundled model that streams
(``codetalker-synth``), or ``codetalker-stream``: a
model of ``configs/codetalker_stream.yaml``'s size and the bundled head's vertices with untrained
weights (a streaming step costs the same whatever the weights; no trained one is bundled).

Per row:

* dropped: frames expected (the audio's duration x fps) minus frames received in order;
* end-to-end latency: when a frame arrives minus when the audio at its own time was captured
  (the client's clock: the stream's start + the frame's time), so it includes the look-ahead,
  the wait for the chunk, queueing and compute; frames only the final flush releases are not
  timed;
* drift: per session, the median latency of the last ``EDGE`` of the run minus that of the first
  (after the first second); the worst session's. A backlog that grows shows here;
* peak RSS: the server process's high-water mark (VmHWM) over the run, and the largest of its
  worker processes' (``talkmesh serve --workers``, by default one per core, compute the
  procedural sessions; "-" without workers); per session: the server's and the workers' peaks
  minus their RSS before the sessions came, divided by the sessions;
* batch: the mean sessions per scheduler tick; the CPU use in cores over the run of the server
  and its workers together, and their CPU time per second of one session's audio (what a
  session costs, whatever else runs: on a quiet machine with C cores about C / that many
  sessions fit, less what the clients take).

``--compute-only`` leaves out the server and the clients: the sessions' computation alone, in
this process, timed in CPU seconds (what batching saves, measurable on a busy machine). For
``procedural`` it runs twice: with the offline phone recogniser's settings
(``talkmesh.audio.phonemes.ALLPHONE``) and with the server's (``ALLPHONE_STREAM``); the
"recogniser" column says which (for a model it is always "stream").
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import random
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
EDGE = 0.2  # drift compares the first and last fifth of a run (at most 60 s each)
MAX_EDGE_S = 60.0
SETTLE_S = 1.0  # the first second (start-up) is left out of the drift's first window
ROOT = Path(__file__).resolve().parent.parent
STAGGER_MS = 100.0  # --compute-only: the streams start this far apart at most (a Whisper block)


@dataclass
class StreamResult:
    expected: int
    received: int
    gaps: int  # frame indices missing or out of order
    latencies: np.ndarray  # (frames timed,) seconds, end to end
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


def untrained_stream_model(out: Path) -> Path:
    """A streaming CodeTalker of configs/codetalker_stream.yaml's size, untrained weights."""
    import torch

    from talkmesh.config import read_yaml
    from talkmesh.face.assets import load_head
    from talkmesh.models.codetalker.model import CodeTalker
    from talkmesh.models.release import save_model
    from talkmesh.training.codetalker import build_config
    from talkmesh.training.trainer import DatasetInfo

    torch.manual_seed(0)
    recipe = read_yaml(ROOT / "configs" / "codetalker_stream.yaml")["model"]
    subjects = tuple(f"s{k}" for k in range(8))
    cfg = build_config(recipe, DatasetInfo(load_head().num_vertices, 30.0, subjects))
    return save_model(CodeTalker(cfg).eval(), out / "codetalker-stream.safetensors")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(port: int, model: str, max_sessions: int, extra: list[str]) -> subprocess.Popen:
    command = [sys.executable, "-m", "talkmesh", "serve", "--port", str(port), "-q"]
    command += ["--model", model, "--max-sessions", str(max_sessions), *extra]
    proc = subprocess.Popen(command, env=dict(os.environ, HF_HUB_OFFLINE="1"))
    import httpx

    deadline = time.monotonic() + 300
    while True:
        try:
            httpx.get(f"http://127.0.0.1:{port}/health").raise_for_status()
            return proc
        except httpx.TransportError:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise SystemExit("the server did not start") from None
            time.sleep(0.2)


def proc_status(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM in bytes, and the CPU seconds used (utime + stime)."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0]) * 1024
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    out["cpu"] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return out


async def one_stream(url: str, pcm: bytes, chunk_ms: float, delay: float) -> StreamResult:
    from websockets.asyncio.client import connect

    await asyncio.sleep(delay)
    chunk = 2 * int(SAMPLE_RATE * chunk_ms / 1000)
    arrivals: list[tuple[int, float]] = []
    # no keep-alive pings from the client: a loaded machine must not end sessions by itself
    async with connect(url, max_size=None, open_timeout=120, ping_interval=None) as ws:
        hello = json.loads(await ws.recv())
        fps, lookahead = hello["fps"], hello["lookahead_ms"] / 1000
        start = time.perf_counter()  # sample 0 is "captured" now

        async def send() -> None:
            for k, i in enumerate(range(0, len(pcm), chunk)):
                wait = start + (k + 1) * chunk_ms / 1000 - time.perf_counter()
                if wait > 0:  # the chunk's audio has been "recorded"
                    await asyncio.sleep(wait)
                await ws.send(pcm[i : i + chunk])
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
    gaps = sum(1 for k, (i, _) in enumerate(arrivals) if i != k)
    timed = [(i, t) for i, t in arrivals if (i / fps + lookahead) * SAMPLE_RATE <= total - 2000]
    latencies = np.array([t - (start + i / fps) for i, t in timed])
    return StreamResult(
        expected, len(arrivals), gaps, latencies, np.array([i / fps for i, _ in timed])
    )


async def run_streams(url: str, pcm: bytes, n: int, chunk_ms: float, stagger: float):
    rng = random.Random(n)
    return list(
        await asyncio.gather(
            *(one_stream(url, pcm, chunk_ms, rng.uniform(0, stagger)) for _ in range(n))
        )
    )


def drift_ms(r: StreamResult, seconds: float) -> float:
    """Median latency of the run's last ``EDGE`` minus that of its first (after start-up), ms."""
    edge = min(MAX_EDGE_S, EDGE * seconds)
    first = r.latencies[(r.frame_times >= SETTLE_S) & (r.frame_times < SETTLE_S + edge)]
    last = r.latencies[r.frame_times > r.frame_times.max() - edge]
    return 1000 * float(np.median(last) - np.median(first))


def run_config(args, model: str, name: str, n: int, pcm: bytes) -> str:
    extra = [] if args.batch_wait_ms is None else ["--batch-wait-ms", str(args.batch_wait_ms)]
    if args.torch_threads:
        extra += ["--torch-threads", str(args.torch_threads)]
    if args.workers is not None:
        extra += ["--workers", str(args.workers)]
    port = free_port()
    proc = start_server(port, model, n, extra)
    import httpx

    try:
        health0 = httpx.get(f"http://127.0.0.1:{port}/health").json()
        pids = [proc.pid, *health0.get("workers", [])]
        idle = [proc_status(pid) for pid in pids]
        url = f"ws://127.0.0.1:{port}/ws/stream?model={name}&lookahead_ms={args.lookahead_ms:g}"
        wall = time.perf_counter()
        results = asyncio.run(run_streams(url, pcm, n, args.chunk_ms, args.stagger_s))
        wall = time.perf_counter() - wall
        used = [proc_status(pid) for pid in pids]
        health = httpx.get(f"http://127.0.0.1:{port}/health").json()
    finally:
        proc.terminate()
        proc.wait(timeout=60)
    lat = 1000 * np.concatenate([r.latencies for r in results])
    expected = sum(r.expected for r in results)
    received = sum(r.received for r in results)
    dropped = expected - received + sum(r.gaps for r in results)
    drift = max(drift_ms(r, len(pcm) / 2 / SAMPLE_RATE) for r in results)
    ticks = max(1, health.get("ticks", 0) - health0.get("ticks", 0))
    batch = (health.get("batched", 0) - health0.get("batched", 0)) / ticks
    if health.get("workers", []) != pids[1:]:
        raise SystemExit(f"a worker was replaced during the run: {pids[1:]} -> {health['workers']}")
    cpu_s = sum(u["cpu"] - i["cpu"] for u, i in zip(used, idle))
    split = ", ".join(f"{(u['cpu'] - i['cpu']) / wall:.2f}" for u, i in zip(used, idle))
    print(f"{n} sessions: CPU in cores of the server, then each worker: {split}", file=sys.stderr)
    cpu, per_cpu = cpu_s / wall, 100 * cpu_s / (n * len(pcm) / 2 / SAMPLE_RATE)
    peak = used[0]["VmHWM"] / 2**20
    worker_peak = f"{max(u['VmHWM'] for u in used[1:]) / 2**20:.0f}" if used[1:] else "-"
    per = sum(u["VmHWM"] - i["VmRSS"] for u, i in zip(used, idle)) / 2**20 / n
    return (
        f"| {n} | {expected} / {received} | {dropped} | {np.median(lat):.0f} "
        f"| {np.percentile(lat, 95):.0f} | {lat.max():.0f} | {drift:+.0f} | {peak:.0f} "
        f"| {worker_peak} | {per:.1f} | {batch:.1f} | {cpu:.2f} | {per_cpu:.1f} |"
    )


def compute_only(
    model: str,
    n: int,
    pcm: bytes,
    chunk_ms: float,
    lookahead_ms: float,
    search: str = "stream",
    together: bool = True,
) -> str:
    """The server's computation without the server: ``n`` streams pushed together
    (:func:`talkmesh.serve.stream.push_together`) in ticks of two chunks, in this process ->
    a table row of CPU time per frame and per second of one session's audio. ``search``:
    the procedural recogniser's settings, ``stream`` (the server's) or ``offline``. Stream
    ``k`` starts with ``k / n`` of :data:`STAGGER_MS` of silence, so the streams' frames fall
    at different moments of a tick, as those of sessions that start at random moments do.
    ``together`` False: each Whisper stream encodes its own windows (what a step did before
    :meth:`talkmesh.models.whisper_stream.WhisperFeatureStream.prepare`), the reference."""
    from talkmesh.audio.phonemes import ALLPHONE, ALLPHONE_STREAM
    from talkmesh.face.assets import load_head
    from talkmesh.serve.stream import ProceduralStreamer, open_stream, push_together

    head = load_head()
    if model == "procedural":
        settings = {"stream": ALLPHONE_STREAM, "offline": ALLPHONE}[search]
        streams = [
            ProceduralStreamer(lookahead_ms, head, False, seed=k, search=settings) for k in range(n)
        ]
    else:
        streams = [
            open_stream(model, lookahead_ms=lookahead_ms, head=head, seed=k) for k in range(n)
        ]
    from talkmesh.models.whisper_stream import WhisperFeatureStream

    speech = np.frombuffer(pcm, "<i2").astype(np.float32) / 32768.0
    lead = [np.zeros(round(SAMPLE_RATE * STAGGER_MS / 1000 * k / n), np.float32) for k in range(n)]
    audios = [np.concatenate([silence, speech]) for silence in lead]
    step = int(SAMPLE_RATE * chunk_ms / 1000)
    prepare = WhisperFeatureStream.__dict__["prepare"]  # the staticmethod itself
    if not together:
        WhisperFeatureStream.prepare = None  # FrameBatch.step then calls window() per stream
    try:
        frames, cpu = 0, time.process_time()
        for i in range(0, len(speech), 2 * step):
            work = [
                (s, [a[i : i + step], a[i + step : i + 2 * step]], False)
                for s, a in zip(streams, audios)
            ]
            frames += sum(len(r) for r in push_together(work))
        cpu = time.process_time() - cpu
    finally:
        WhisperFeatureStream.prepare = prepare
    seconds = len(speech) / SAMPLE_RATE
    return f"| {n} | {frames} | {1000 * cpu / frames:.2f} | {100 * cpu / (n * seconds):.1f} |"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument(
        "--sessions", "--streams", default="1,2,4,8", help="sessions per run (default 1,2,4,8)"
    )
    p.add_argument("--minutes", type=float, help="audio per session in minutes (default 1/3)")
    p.add_argument(
        "--seconds", type=float, help="audio per session in seconds (instead of --minutes)"
    )
    p.add_argument("--chunk-ms", type=float, default=20.0, help="audio per message (default 20)")
    p.add_argument("--lookahead-ms", type=float, default=50.0, help="each session's (default 50)")
    p.add_argument(
        "--stagger-s", type=float, default=1.0, help="sessions start within this (default 1)"
    )
    p.add_argument(
        "--model",
        default="procedural",
        help="procedural, a streaming .safetensors, a bundled model that streams (codetalker-synth) "
        "or codetalker-stream (untrained, see above)",
    )
    p.add_argument("--batch-wait-ms", type=float, help="the server's (default: its default, 15)")
    p.add_argument("--torch-threads", type=int, help="the server's (default PyTorch's)")
    p.add_argument("--workers", type=int, help="the server's (default: its default, one per core)")
    p.add_argument("--wav", help="speech to stream (default: the pocketsphinx test recordings)")
    p.add_argument(
        "--compute-only",
        action="store_true",
        help="no server, no clients: the sessions' computation in this process, CPU time only",
    )
    p.add_argument(
        "--one-window-at-a-time",
        action="store_true",
        help="--compute-only with a Whisper model: also each stream's encoder windows on their "
        "own (the reference for encoding a step's windows together)",
    )
    args = p.parse_args()
    seconds = args.seconds or 60 * (args.minutes or 1 / 3)
    counts = [int(s) for s in args.sessions.split(",")]
    pcm = speech(seconds, args.wav)
    with tempfile.TemporaryDirectory() as tmp:
        model = args.model
        if model == "codetalker-stream":
            model = str(untrained_stream_model(Path(tmp)))
        if args.compute_only:
            if args.torch_threads:
                import torch

                torch.set_num_threads(args.torch_threads)
            searches = ["offline", "stream"] if model == "procedural" else ["stream"]
            ways = [False, True] if args.one_window_at_a_time else [True]
            rows = [
                f"| {search} | {'together' if together else 'one at a time'} "
                + compute_only(model, n, pcm, args.chunk_ms, args.lookahead_ms, search, together)
                for search in searches
                for n in counts
                for together in ways
            ]
            print(
                f"\n{args.model}, {seconds:g} s per session, look-ahead {args.lookahead_ms:g} ms, "
                "computed in ticks of two chunks\n"
            )
            print(
                "| recogniser | encoder windows | sessions | frames | CPU per frame (ms) "
                "| CPU per session (% of a core) |"
            )
            print("|---|---|---|---|---|---|")
            print("\n".join(rows))
            return
        name = "procedural" if model == "procedural" else Path(model).stem
        rows = []
        for n in counts:
            rows.append(run_config(args, model, name, n, pcm))
            print(f"{n} sessions: {rows[-1]}", file=sys.stderr, flush=True)
    wait = "default (15)" if args.batch_wait_ms is None else f"{args.batch_wait_ms:g}"
    print(
        f"\n{args.model}, {seconds:g} s per session in {args.chunk_ms:g} ms chunks, look-ahead "
        f"{args.lookahead_ms:g} ms, --batch-wait-ms {wait}, torch threads "
        f"{args.torch_threads or 'default'}, --workers "
        f"{'default' if args.workers is None else args.workers}, {os.cpu_count()} CPU cores\n"
    )
    print(
        "| sessions | frames expected / received | dropped | latency p50 (ms) | p95 (ms) "
        "| max (ms) | worst drift (ms) | server peak RSS (MB) | per worker (MB) "
        "| per session (MB) | batch | server + workers CPU (cores) "
        "| CPU per session (% of a core) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
