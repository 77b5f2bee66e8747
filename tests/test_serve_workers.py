"""``talkmesh serve --workers``: procedural sessions computed in worker processes
(talkmesh.serve.workers) get the frames of a session alone in the server process, a lost worker
ends only its sessions with a close that says why, and the limits on clients still hold."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest
from starlette.testclient import TestClient
from test_serve import CHUNK, CLIP, assert_error, read_until_close

from talkmesh.serve.protocol import CLOSE_INTERNAL, CLOSE_NORMAL, CLOSE_POLICY, CLOSE_TOO_BIG
from talkmesh.serve.server import create_app


@pytest.fixture(scope="module")
def pcm() -> bytes:
    from talkmesh.audio.loading import load_audio

    assert CLIP.exists(), f"{CLIP} is missing: run `make setup` (pocketsphinx-testdata)"
    return (np.clip(load_audio(CLIP), -1, 1) * 32767).astype("<i2").tobytes()


@pytest.fixture(scope="module")
def pooled():
    app = create_app(workers=2, max_sessions=8, batch_wait_ms=5)
    try:
        with TestClient(app) as client:
            yield client
    finally:
        app.state.service.pool.close()


def stream(client, pcm: bytes, query: str = ""):
    with client.websocket_connect(f"/ws/stream{query}") as ws:
        ws.receive_json()
        for i in range(0, len(pcm), CHUNK):
            ws.send_bytes(pcm[i : i + CHUNK])
        ws.send_json({"type": "end"})
        return read_until_close(ws)


def test_sessions_in_workers_get_the_frames_of_a_session_in_the_server(pooled, pcm):
    with TestClient(create_app()) as local:
        alone = stream(local, pcm, "?offsets=1")
    chunks = [pcm[i : i + CHUNK] for i in range(0, len(pcm), CHUNK)]
    with (
        pooled.websocket_connect("/ws/stream?offsets=1") as a,
        pooled.websocket_connect("/ws/stream?offsets=1") as b,
        pooled.websocket_connect("/ws/stream?offsets=1") as c,
    ):
        for ws in (a, b, c):
            ws.receive_json()
        for k, chunk in enumerate(chunks):  # interleaved, b and c a chunk behind a
            a.send_bytes(chunk)
            for ws in (b, c):
                if k:
                    ws.send_bytes(chunks[k - 1])
        a.send_json({"type": "end"})
        for ws in (b, c):
            ws.send_bytes(chunks[-1])
            ws.send_json({"type": "end"})
        replies = [read_until_close(ws) for ws in (a, b, c)]
    assert len(set(pooled.get("/health").json()["workers"])) == 2
    assert len(alone.frames) == 90
    for reply in replies:
        assert reply.code == CLOSE_NORMAL and reply.texts == alone.texts
        assert [f.index for f in reply.frames] == [f.index for f in alone.frames]
        for x, y in zip(reply.frames, alone.frames):
            assert x.time == y.time
            np.testing.assert_array_equal(x.weights, y.weights)
            np.testing.assert_array_equal(x.offsets, y.offsets)


@pytest.mark.parametrize(
    "query, message, code, fragment",
    [
        ("?lookahead_ms=900", None, CLOSE_POLICY, "out of range"),
        ("", b"\x01" * 70_000, CLOSE_TOO_BIG, "over the limit"),
        ("", b"\x01" * 1001, CLOSE_POLICY, "1001 bytes"),
    ],
)
def test_limits_hold_with_workers(pooled, query, message, code, fragment):
    with pooled.websocket_connect(f"/ws/stream{query}") as ws:
        if message is not None:
            ws.receive_json()
            ws.send_bytes(message)
        assert_error(read_until_close(ws), code, fragment)


def test_a_lost_worker_ends_its_sessions_with_a_reason_and_is_replaced(pcm):
    app = create_app(workers=1, batch_wait_ms=0)
    try:
        with TestClient(app) as client:
            (pid,) = client.get("/health").json()["workers"]
            with client.websocket_connect("/ws/stream") as ws:
                ws.receive_json()
                ws.send_bytes(pcm[:CHUNK])
                os.kill(pid, signal.SIGKILL)
                for i in range(CHUNK, len(pcm), CHUNK):
                    ws.send_bytes(pcm[i : i + CHUNK])
                ws.send_json({"type": "end"})
                reply = read_until_close(ws)
            assert_error(reply, CLOSE_INTERNAL, "stopped", "reconnect")
            again = stream(client, pcm)  # the next session gets a new worker
            assert again.code == CLOSE_NORMAL and len(again.frames) == 90
            assert client.get("/health").json()["workers"] != [pid]
    finally:
        app.state.service.pool.close()


def test_a_negative_worker_count_is_a_one_line_error():
    from talkmesh.errors import TalkmeshError

    with pytest.raises(TalkmeshError, match="--workers must be 0 or more"):
        create_app(workers=-1)


class _Echo:
    """The worker's end of a pipe answered by a thread: each request's reply after ``delay`` s;
    stands in for a worker process (``alive``, ``kill``, ``join``, ``exitcode``, ``pid``)."""

    def __init__(self, conn, delay: float) -> None:
        import threading

        self.conn, self.delay, self.exitcode, self.pid = conn, delay, None, 0
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        import time

        while True:
            try:
                request = self.conn.recv()
            except (EOFError, OSError):
                return
            time.sleep(self.delay)
            self.conn.send(("reply to", request, b"x" * 300_000))  # over a pipe's buffer

    def is_alive(self) -> bool:
        return True

    def kill(self) -> None:
        pass

    def join(self, timeout=None) -> None:
        pass


@pytest.mark.parametrize("loop", ["asyncio", "uvloop"])
def test_worker_calls_on_the_event_loop_keep_the_pipe_whole(loop):
    """The server awaits a worker's reply as its pipe becoming readable (no thread per tick).
    uvloop leaves a watched descriptor non-blocking, which made a reply larger than the pipe's
    buffer fail half-way (the session ended with "the process ... stopped"); and a caller
    cancelled while it waits (its client left) must not leave its reply for the next request."""
    import asyncio
    import multiprocessing

    from talkmesh.serve.workers import Worker

    ours, theirs = multiprocessing.Pipe()
    worker = Worker(_Echo(theirs, delay=0.2), ours)

    async def calls():
        with pytest.raises(TimeoutError):  # cancelled while the worker computes
            await asyncio.wait_for(worker.call("first"), 0.05)
        for k in range(3):
            reply = await worker.call(f"next {k}")
            assert reply[:2] == ("reply to", f"next {k}") and len(reply[2]) == 300_000
        assert os.get_blocking(ours.fileno())

    if loop == "uvloop":
        uvloop = pytest.importorskip("uvloop")  # uvicorn[standard] installs it
        uvloop.run(calls())
    else:
        asyncio.run(calls())
    assert worker.lost is None
