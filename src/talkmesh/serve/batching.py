"""The server's scheduler: the streaming sessions' work in ticks, one computation call per tick.

Each session's receiving coroutine hands its audio to the :class:`Scheduler` as it arrives
(:meth:`Scheduler.submit`) and keeps reading. The scheduler's loop takes the audio of every
session that has some and computes all of it in one call of
:func:`talkmesh.serve.stream.push_together` in a worker thread: the streams of one model step
together, one model step per frame index for all sessions with that frame due. While a tick
computes, the next chunks of every session queue up for the next one, so the batches grow with
the load: a busy server runs fewer, larger steps instead of falling behind. Each session's frames
come back through its own queue (:class:`Work`), which its sending coroutine drains.

Knobs (``talkmesh serve`` flags): ``--batch-wait-ms`` (default ``DEFAULT_BATCH_WAIT_MS``, 15)
waits that long after the first ready chunk before a tick, to gather more sessions into it (more
throughput, that much latency); ``--torch-threads`` sets the threads of the batched model steps.

Procedural sessions opened in worker processes (:mod:`talkmesh.serve.workers`, ``--workers``)
are computed there. Each place the sessions compute (the server process, each worker) has its
own :class:`Lane`, a loop that ticks over its sessions alone: a worker's sessions never wait for
another worker's tick or for the model steps, and they tick without ``--batch-wait-ms`` (their
recognisers gain nothing from a batch), each tick taking the audio that arrived while the
previous one computed. With the worker replies awaited on the event loop, 32 procedural
sessions on 2 cores went from p95 217 to 113 ms (docs/results/serve-batching-2026-11-25.md).
"""

from __future__ import annotations

import asyncio
import logging
import math

import anyio
import numpy as np

from talkmesh.serve.stream import Streamer, StreamFrame, push_together
from talkmesh.serve.workers import RemoteStream, Worker, WorkerLost

log = logging.getLogger(__name__)

# A tick waits this long after the first ready chunk (``--batch-wait-ms``). Clients send a chunk
# every 10-40 ms (the viewer and bench/serve_load.py: 20 ms) at unrelated phases, so a wait of
# most of one chunk period gathers most sessions' next chunks into the same tick: fewer, larger
# model steps (a streaming CodeTalker frame costs about 5x less CPU in a batch of 16 than alone,
# docs/results/serve-batching-2026-11-25.md) for at most 15 ms more latency, a tenth of the
# 150 ms budget. 0 computes whatever has arrived at once (lowest latency on an idle server).
DEFAULT_BATCH_WAIT_MS = 15.0
MAX_TICK_S = 0.25  # audio of one session computed per tick at most: ticks stay short
MAX_PENDING_S = 5.0  # a session that sends faster than it is computed waits at this backlog


class Work:
    """One session's place in the scheduler: audio waiting to be computed, the frames computed.

    The outbox carries, in order: lists of frames, then ``None`` after the last frames of an
    ended stream; or an exception that ends the session."""

    def __init__(self, stream: Streamer) -> None:
        self.stream = stream
        self.inbox: list[np.ndarray] = []
        self.pending = 0  # samples in the inbox
        self.end = False  # the end message came: flush after the inbox
        self.taken_end = False
        self.send, self.outbox = anyio.create_memory_object_stream(math.inf)
        self.drained = anyio.Event()
        self.lane: Lane | None = None  # set by Scheduler.join

    def take(self) -> tuple[list[np.ndarray], bool]:
        """The chunks for this tick (at most ``MAX_TICK_S`` of audio) and whether the stream ends
        with them."""
        chunks, n = [], 0
        while self.inbox and (not chunks or n + len(self.inbox[0]) <= MAX_TICK_S * 16_000):
            chunk = self.inbox.pop(0)
            chunks.append(chunk)
            n += len(chunk)
        self.pending -= n
        end = self.end and not self.inbox
        self.taken_end = self.taken_end or end
        if self.pending <= MAX_PENDING_S * 16_000:
            self.drained.set()
        return chunks, end

    @property
    def ready(self) -> bool:
        return bool(self.inbox) or (self.end and not self.taken_end)


class Lane:
    """The sessions computed in one place (the server process, or one worker process) and the
    loop that ticks over them. Lanes tick independently: a worker's sessions never wait for
    another worker's tick or for the server's model steps."""

    def __init__(self, scheduler: Scheduler, key: Worker | None, batch_wait_s: float) -> None:
        self.scheduler = scheduler
        self.key = key  # the worker computing its sessions (None: the server process)
        self.batch_wait_s = batch_wait_s
        self.works: list[Work] = []
        self.wake = anyio.Event()
        self.runner: asyncio.Task | None = None

    def join(self, work: Work) -> None:
        self.works.append(work)
        if self.runner is None or self.runner.done():
            self.runner = asyncio.get_running_loop().create_task(self._run())

    async def _run(self) -> None:
        while self.works:
            await self.wake.wait()
            self.wake = anyio.Event()
            if self.batch_wait_s:
                await anyio.sleep(self.batch_wait_s)
            ready = [w for w in self.works if w.ready]
            if not ready:
                continue
            jobs = [(w.stream, *w.take()) for w in ready]
            results = await compute(jobs)
            self.scheduler.ticks += 1
            self.scheduler.stepped += len(ready)
            for work, (_, _, end), result in zip(ready, jobs, results):
                work.send.send_nowait(result)
                if end and not isinstance(result, Exception):
                    work.send.send_nowait(None)
            if any(w.ready for w in self.works):
                self.wake.set()


class Scheduler:
    """Ticks over the sessions' work (module docstring), in one :class:`Lane` per place the
    sessions compute; runs while sessions are open."""

    def __init__(self, batch_wait_s: float = DEFAULT_BATCH_WAIT_MS / 1000) -> None:
        self.batch_wait_s = batch_wait_s
        self.lanes: dict[Worker | None, Lane] = {}
        self.ticks = 0
        self.stepped = 0  # session-ticks computed (their mean per tick: the batch size)

    @property
    def works(self) -> list[Work]:
        return [w for lane in self.lanes.values() for w in lane.works]

    def join(self, stream: Streamer) -> Work:
        work = Work(stream)
        worker = stream.worker if isinstance(stream, RemoteStream) else None
        if worker not in self.lanes:
            # a worker's procedural sessions gain nothing from waiting for each other (their
            # recognisers run one after another whatever the batch): they tick at once, each
            # tick taking what arrived while the previous one computed
            wait = self.batch_wait_s if worker is None else 0.0
            self.lanes[worker] = Lane(self, worker, wait)
        work.lane = self.lanes[worker]
        work.lane.join(work)
        return work

    def leave(self, work: Work) -> None:
        lane = work.lane
        if work in lane.works:
            lane.works.remove(work)
        if isinstance(work.stream, RemoteStream):
            work.stream.leave()
        lane.wake.set()  # the lane's loop ends once no session is left in it
        if not lane.works and self.lanes.get(lane.key) is lane:
            del self.lanes[lane.key]

    async def submit(self, work: Work, audio: np.ndarray | None) -> None:
        """Queue a session's audio (None: its end); waits while its backlog is too long."""
        if audio is None:
            work.end = True
        else:
            work.inbox.append(audio)
            work.pending += len(audio)
        work.lane.wake.set()
        while work.pending > MAX_PENDING_S * 16_000:
            work.drained = anyio.Event()
            await work.drained.wait()


async def compute(jobs: list[tuple]) -> list:
    """One tick's (streamer, chunks, end) jobs -> :func:`push_together`'s results, the sessions
    in worker processes computed there, every worker and the local streams at the same time."""
    groups: dict[Worker | None, list[int]] = {}
    for i, (stream, _, _) in enumerate(jobs):
        groups.setdefault(stream.worker if isinstance(stream, RemoteStream) else None, []).append(i)
    results: list = [None] * len(jobs)

    async def run(worker: Worker | None, members: list[int]) -> None:
        group = [jobs[i] for i in members]
        try:
            if worker is None:
                out = await anyio.to_thread.run_sync(push_together, group)
            else:
                out = await worker.tick(group)
        except WorkerLost as e:  # its sessions end with the reason
            out = [e] * len(group)
        except Exception as e:  # a bug: end the sessions of this tick, keep serving
            log.exception("a streaming tick failed")
            out = [e] * len(group)
        for i, result in zip(members, out):
            results[i] = result

    async with anyio.create_task_group() as tasks:
        for worker, members in groups.items():
            tasks.start_soon(run, worker, members)
    return results


async def frames_of(work: Work):
    """A session's computed frames, list by list, until its stream ends; raises what ended it
    (the receiving side's error, or the computation's)."""
    async for item in work.outbox:
        if item is None:
            return
        if isinstance(item, BaseException):
            raise item
        frames: list[StreamFrame] = item
        yield frames
