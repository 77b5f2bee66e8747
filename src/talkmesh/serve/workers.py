"""Procedural sessions computed in worker processes, so that ``talkmesh serve`` uses every core.

A procedural session's cost is its phone recogniser (PocketSphinx's search, C code that holds the
GIL, and the Python that reads and tidies its phones): one server process tops out at one core
(docs/results/serve-batching-2026-11-25.md). ``talkmesh serve --workers N`` (default: one per
core) starts N processes; each owns the :class:`~talkmesh.serve.stream.ProceduralStreamer` of the
sessions assigned to it (a new session goes to the worker with the fewest) and makes its share
of ``--max-sessions`` recognisers before it is ready, so that opening a session (65 ms of
reading the acoustic model) does not stall the others. The server's scheduler
(:mod:`talkmesh.serve.batching`) ticks each worker's sessions in a lane of their own: one
message with their audio per tick, the reply awaited on the event loop as the pipe becoming
readable (no thread hand-off per tick), the workers computing in parallel while the event
loop serves the sockets. A worker runs :func:`~talkmesh.serve.stream.push_together`, the code a
session runs in the server process, so its frames are those of the session alone.

Why worker processes rather than several server processes on one port (``SO_REUSEPORT``): the
kernel spreads connections by a hash, not by load, so two processes can get 20 and 12 sessions;
``--max-sessions``, ``/health`` and the batched model steps of streaming models would be per
process; and a process that dies takes its sockets with it, where a lost worker here only ends
its sessions, each with a close that says why (1011 and a message), and the next session gets a
fresh worker.

Messages on a worker's pipe, always one request then one reply:

* ``("open", sid, source, lookahead_ms, offsets)`` -> ``("ok", fps, lookahead_ms, names)`` or
  ``("error", message)``;
* ``("tick", closed_sids, [(sid, chunks, end), ...])`` -> one :class:`Packed` frames or error
  message per job, in order.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import signal
from dataclasses import dataclass, field
from typing import NamedTuple

import anyio
import numpy as np

from talkmesh.errors import TalkmeshError
from talkmesh.serve.stream import StreamFrame

log = logging.getLogger(__name__)

REPLY_TIMEOUT_S = 60.0  # a worker that does not answer a tick in this long is taken as lost
START_TIMEOUT_S = 300.0  # a worker has this long to import talkmesh and open a first stream


def default_workers() -> int:
    """One worker per core this process may use: the server process itself mostly waits on
    sockets while the workers compute."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


class WorkerLost(Exception):
    """The worker computing a session stopped: the session ends with this message."""


class Packed(NamedTuple):
    """Frames start..start + T - 1 of one session as arrays (cheaper to pickle than frames)."""

    start: int
    weights: np.ndarray  # (T, 52) float32
    offsets: np.ndarray | None  # (T, V, 3) float32


def pack(frames: list[StreamFrame]) -> Packed:
    if not frames:
        return Packed(0, np.zeros((0, 0), np.float32), None)
    offsets = None if frames[0].offsets is None else np.stack([f.offsets for f in frames])
    return Packed(frames[0].index, np.stack([f.weights for f in frames]), offsets)


def unpack(packed: Packed, fps: float) -> list[StreamFrame]:
    """The frames :func:`pack` took apart (their times as the streamer computes them)."""
    start, weights, offsets = packed
    return [
        StreamFrame(start + k, (start + k) / fps, w, None if offsets is None else offsets[k])
        for k, w in enumerate(weights)
    ]


# ---------------------------------------------------------------------------------------------
# The worker process


def _serve_requests(conn, spares: int = 1) -> None:
    """A worker's loop (module docstring); returns when the server closes the pipe. ``spares``:
    recognisers made before the worker says it is ready (its share of the server's sessions), so
    that opening a session does not stall the others' ticks."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C stops the server, which stops us
    try:  # one BLAS thread: the workers already use every core between them
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:
        pass
    from talkmesh.face.assets import load_head
    from talkmesh.serve.stream import DecoderPool, open_stream, push_together

    head = load_head()
    decoders = DecoderPool()
    # imports and first-use costs before the first session
    open_stream("procedural", head=head, decoders=decoders).release()
    decoders.fill(spares)
    conn.send(("ready",))
    streams = {}
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        if request[0] == "open":
            _, sid, source, lookahead, offsets = request
            try:
                s = open_stream(
                    source, lookahead_ms=lookahead, head=head, offsets=offsets, decoders=decoders
                )
            except TalkmeshError as e:
                conn.send(("error", str(e)))
                continue
            streams[sid] = s
            conn.send(("ok", s.fps, s.lookahead_ms, list(s.names)))
            continue
        _, closed, jobs = request
        for sid in closed:
            _release(streams.pop(sid, None))
        try:
            results = push_together([(streams[sid], chunks, end) for sid, chunks, end in jobs])
            reply = [r if isinstance(r, Exception) else pack(r) for r in results]
        except Exception as e:  # a bug: this tick's sessions end, the worker goes on
            reply = [e] * len(jobs)
        reply = [TalkmeshError(str(r)) if isinstance(r, Exception) else r for r in reply]
        conn.send(reply)
        for (sid, _, end), r in zip(jobs, reply):
            if end or isinstance(r, Exception):
                _release(streams.pop(sid, None))


def _release(stream) -> None:
    """A closed session's recogniser goes back to the worker's pool."""
    if stream is not None:
        stream.release()


# ---------------------------------------------------------------------------------------------
# The server's side


@dataclass(eq=False)
class RemoteStream:
    """Stands in the scheduler for a session computed by a worker (what a streamer tells the
    server: fps, look-ahead, names, sample rate)."""

    worker: Worker
    sid: int
    fps: float
    lookahead_ms: float
    names: list[str]
    sample_rate: int = 16_000

    def leave(self) -> None:
        """The session ended: its worker drops its streamer with the next tick."""
        if self.sid in self.worker.sessions:
            self.worker.sessions.discard(self.sid)
            self.worker.closed.append(self.sid)


@dataclass(eq=False)
class Worker:
    process: multiprocessing.Process
    conn: object  # the server's end of the pipe
    sessions: set[int] = field(default_factory=set)
    closed: list[int] = field(default_factory=list)  # sessions that left, for the next tick
    lock: asyncio.Lock | None = None  # one request at a time (made in the event loop)
    lost: str | None = None  # why the worker is gone

    async def call(self, message):
        """Send a request and wait for its reply, the event loop serving the sockets meanwhile
        (the reply is awaited as the pipe's readability: no thread per call). A caller that is
        cancelled (its client left) does not leave the reply in the pipe for the next request:
        the exchange runs to its end in a task of its own.

        Raises:
            WorkerLost: the worker died, or did not answer within ``REPLY_TIMEOUT_S``.
        """
        return await asyncio.shield(asyncio.ensure_future(self._exchange(message)))

    async def _exchange(self, message):
        if self.lock is None:
            self.lock = asyncio.Lock()
        async with self.lock:
            if self.lost is None:
                try:
                    self.conn.send(message)
                    if await _readable(self.conn, REPLY_TIMEOUT_S):
                        return self.conn.recv()
                    self.lost = f"did not answer within {REPLY_TIMEOUT_S:g} s"
                    self.process.kill()
                except (EOFError, OSError):
                    self.process.join(1.0)
                    self.lost = f"stopped (exit code {self.process.exitcode})"
                log.error("streaming worker %d %s", self.process.pid, self.lost)
            raise WorkerLost(
                f"the process computing this session {self.lost}: the session ends; "
                "reconnect to start a new one"
            )

    async def tick(self, jobs: list[tuple[RemoteStream, list[np.ndarray], bool]]) -> list:
        """This worker's sessions' audio -> their frames or errors (``push_together``'s)."""
        closed, self.closed = self.closed, []  # sessions that left since the last tick
        reply = await self.call(("tick", closed, [(s.sid, chunks, end) for s, chunks, end in jobs]))
        return [
            r if isinstance(r, Exception) else unpack(r, s.fps) for (s, _, _), r in zip(jobs, reply)
        ]


async def _readable(conn, timeout: float) -> bool:
    """Wait until the pipe has a message (True) or ``timeout`` seconds pass (False)."""
    if conn.poll(0):
        return True
    loop = asyncio.get_running_loop()
    ready = loop.create_future()
    fd = conn.fileno()
    loop.add_reader(fd, lambda: ready.done() or ready.set_result(None))
    try:
        await asyncio.wait_for(ready, timeout)
        return True
    except TimeoutError:
        return False
    finally:
        loop.remove_reader(fd)
        # uvloop (libuv) leaves a watched descriptor non-blocking: the pipe's reads and writes of
        # a message larger than its buffer would fail half-way with BlockingIOError
        os.set_blocking(fd, True)


class WorkerPool:
    """``workers`` processes computing procedural sessions (module docstring); each makes
    ``spares`` recognisers before it is ready (the server passes its share of
    ``--max-sessions``: 32 MB each)."""

    def __init__(self, workers: int, spares: int = 1) -> None:
        if workers < 1:
            raise TalkmeshError(f"--workers must be 0 or more, got {workers}")
        self._context = multiprocessing.get_context("spawn")  # no forked event loop or threads
        self.spares = max(1, spares)
        self.workers = [self._start() for _ in range(workers)]
        for w in self.workers:
            self._wait_ready(w)
        self._next_sid = 0
        self._lock: asyncio.Lock | None = None

    def _start(self) -> Worker:
        ours, theirs = self._context.Pipe()
        process = self._context.Process(
            target=_serve_requests,
            args=(theirs, self.spares),
            daemon=True,
            name="talkmesh-stream-worker",
        )
        process.start()
        theirs.close()
        return Worker(process, ours)

    def _restart(self) -> Worker:
        worker = self._start()
        self._wait_ready(worker)
        return worker

    def _wait_ready(self, worker: Worker) -> None:
        """Wait for a new worker's first message (it is ready to open sessions)."""
        try:
            if worker.conn.poll(START_TIMEOUT_S) and worker.conn.recv() == ("ready",):
                return
        except (EOFError, OSError):
            pass
        worker.process.kill()
        raise TalkmeshError(
            f"a streaming worker process did not start within {START_TIMEOUT_S:g} s "
            f"(exit code {worker.process.exitcode}): see the log above, or serve with --workers 0"
        )

    @property
    def pids(self) -> list[int]:
        return [w.process.pid for w in self.workers]

    async def open(self, source: str, lookahead_ms: float | None, offsets: bool) -> RemoteStream:
        """A session on the least busy worker (a lost one is replaced first).

        Raises:
            TalkmeshError: the stream's options are wrong (as :func:`open_stream` says).
            WorkerLost: the worker died while opening it.
        """
        if self._lock is None:
            self._lock = asyncio.Lock()
        async with self._lock:
            for k, w in enumerate(self.workers):
                if w.lost is not None or not w.process.is_alive():
                    self.workers[k] = await anyio.to_thread.run_sync(self._restart)
            worker = min(self.workers, key=lambda w: len(w.sessions))
            self._next_sid += 1
            sid = self._next_sid
            worker.sessions.add(sid)
        try:
            reply = await worker.call(("open", sid, source, lookahead_ms, offsets))
        except WorkerLost:
            worker.sessions.discard(sid)
            raise
        if reply[0] == "error":
            worker.sessions.discard(sid)
            raise TalkmeshError(reply[1])
        _, fps, lookahead, names = reply
        return RemoteStream(worker, sid, fps, lookahead, names)

    def close(self) -> None:
        for w in self.workers:
            w.conn.close()  # the worker's loop ends at the closed pipe
        for w in self.workers:
            w.process.join(2.0)
            if w.process.is_alive():
                w.process.kill()
                w.process.join(1.0)
