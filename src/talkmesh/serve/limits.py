"""What ``talkmesh serve`` will spend on one client: audio length, job slots, time to send a request.

* ``POST /animate`` is priced by the audio's duration, read from the file's header before anything
  is decoded: over ``max_seconds`` is a 413 at once (a 181 kB FLAC can hold an hour of silence).
* Jobs run in ``jobs`` slots; a job longer than ``short_seconds`` may take all but one of them, so
  a long job never holds up a short one. Up to ``max_queue`` jobs wait; more get 503 + Retry-After.
* A connection must deliver a complete request head within ``request_timeout`` seconds and its
  body within the same time after the head, else it is dropped (uvicorn has no such timeout).
* A request head (request line and headers) over ``MAX_HEAD_BYTES`` gets 400 (a WebSocket
  upgrade, 403): h11 bounds only heads that arrive in pieces, not one that comes whole. Access
  log lines cut what a client sent to ``LOG_FIELD_CHARS``: a 100 kB URL is not written out.
"""

from __future__ import annotations

import logging
import math
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import anyio
from starlette.responses import JSONResponse

log = logging.getLogger("talkmesh.serve")

DEFAULT_MAX_SECONDS = 300.0  # 5 min of audio per /animate request (about 1 GB at peak)
DEFAULT_JOBS = 2  # /animate jobs at a time (each uses several cores)
DEFAULT_MAX_QUEUE = 8  # /animate jobs waiting for a slot; more are told to come back
DEFAULT_SHORT_SECONDS = 30.0  # jobs up to this long always find a slot free of long jobs
DEFAULT_REQUEST_TIMEOUT_S = 30.0  # to send a request head, then again to send its body
DEFAULT_FIRST_MESSAGE_TIMEOUT_S = 2.0  # WebSocket: accept -> first message, holding a slot
RETRY_SECONDS_PER_AUDIO_SECOND = 0.1  # rough cost of a job, for Retry-After
MAX_HEAD_BYTES = 16 * 1024  # request line + headers (docs/security.md)
LOG_FIELD_CHARS = 200  # of a path, header or client's text in one log line


def head_bytes(scope: dict) -> int:
    """The size of a request's head as the client sent it (request line and headers)."""
    path = scope.get("raw_path") or scope.get("path", "").encode()
    line = len(scope.get("method", "GET")) + len(path) + len(scope.get("query_string", b"")) + 12
    return line + sum(len(k) + len(v) + 4 for k, v in scope.get("headers", ()))


class HeadLimit:
    """ASGI middleware: 400 for a request head over MAX_HEAD_BYTES (403 for a WebSocket
    upgrade, which cannot be answered otherwise before it is accepted), one log line."""

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] not in ("http", "websocket") or head_bytes(scope) <= MAX_HEAD_BYTES:
            await self.app(scope, receive, send)
            return
        client = scope.get("client")
        who = f"{client[0]}:{client[1]}" if client else "a client"
        log.warning(
            "refused %s: a request head of %d bytes, over %d (%s)",
            who,
            head_bytes(scope),
            MAX_HEAD_BYTES,
            shorten(scope.get("path", "")),
        )
        if scope["type"] == "websocket":
            await send({"type": "websocket.close", "code": 1008})
            return
        message = f"the request head is over {MAX_HEAD_BYTES // 1024} kB: send a shorter URL"
        await JSONResponse({"type": "error", "message": message}, 400)(scope, receive, send)


def shorten(text: str, limit: int = LOG_FIELD_CHARS) -> str:
    """``text`` cut to ``limit`` characters, saying how long it was."""
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


class ShortLogFields(logging.Filter):
    """Cut the long strings of a log record's arguments (uvicorn's access log writes the path
    a client sent verbatim)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple):
            record.args = tuple(shorten(a) if isinstance(a, str) else a for a in record.args)
        return True


class QueueFull(Exception):
    """No slot and no room to wait: come back after ``retry_after`` seconds."""

    def __init__(self, retry_after: int):
        super().__init__(f"retry after {retry_after} s")
        self.retry_after = retry_after


class JobQueue:
    """Admission for /animate jobs priced by their audio duration (see the module docstring)."""

    def __init__(self, jobs: int, max_queue: int, short_seconds: float):
        self.jobs, self.max_queue, self.short_seconds = jobs, max_queue, short_seconds
        self.long_slots = max(1, jobs - 1)
        self.running: list[float] = []
        self.waiting: list[float] = []
        self._changed = anyio.Condition()

    def _fits(self, seconds: float) -> bool:
        if len(self.running) >= self.jobs:
            return False
        if seconds <= self.short_seconds:
            return True
        return sum(s > self.short_seconds for s in self.running) < self.long_slots

    def retry_after(self) -> int:
        work = sum(self.running) + sum(self.waiting)
        return max(1, math.ceil(work * RETRY_SECONDS_PER_AUDIO_SECOND / self.jobs))

    @asynccontextmanager
    async def slot(self, seconds: float) -> AsyncIterator[None]:
        """Hold a job slot for a job of ``seconds`` of audio; raises :class:`QueueFull`."""
        async with self._changed:
            if not self._fits(seconds):
                if len(self.waiting) >= self.max_queue:
                    raise QueueFull(self.retry_after())
                self.waiting.append(seconds)
                try:
                    while not self._fits(seconds):
                        await self._changed.wait()
                finally:
                    self.waiting.remove(seconds)
            self.running.append(seconds)
        try:
            yield
        finally:
            with anyio.CancelScope(shield=True):
                async with self._changed:
                    self.running.remove(seconds)
                    self._changed.notify_all()


def head_timeout_protocol(seconds: float):
    """uvicorn's h11 protocol, closing connections whose request head is not complete within
    ``seconds`` of the connection opening or of the previous response (a half-sent request)."""
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class HeadTimeoutProtocol(H11Protocol):
        head_timer = None
        upgraded = False  # a WebSocket now: its own timeouts apply

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            self._arm()

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            if self._waiting_for_head():
                if self.head_timer is None:
                    self._arm()
            elif self.head_timer is not None:
                self.head_timer.cancel()
                self.head_timer = None

        def connection_lost(self, exc) -> None:
            if self.head_timer is not None:
                self.head_timer.cancel()
            super().connection_lost(exc)

        def handle_websocket_upgrade(self, event) -> None:
            self.upgraded = True
            if self.head_timer is not None:
                self.head_timer.cancel()
                self.head_timer = None
            super().handle_websocket_upgrade(event)

        def _waiting_for_head(self) -> bool:
            if self.upgraded:
                return False
            return self.cycle is None or self.cycle.response_complete

        def _arm(self) -> None:
            self.head_timer = self.loop.call_later(seconds, self._expire)

        def _expire(self) -> None:
            self.head_timer = None
            if self._waiting_for_head() and not self.transport.is_closing():
                log.warning("dropped %s: no complete request within %g s", _who(self), seconds)
                self.transport.close()

    return HeadTimeoutProtocol


def _who(protocol) -> str:
    client = getattr(protocol, "client", None)
    return f"{client[0]}:{client[1]}" if client else "a client"


def client_name(request) -> str:
    """``host:port`` of a request's client, for one-line logs."""
    client = request.client
    return f"{client.host}:{client.port}" if client else "a client"


def too_long(seconds: float, limit: float) -> JSONResponse:
    """413: the audio is longer than the server's ``--max-seconds``."""
    # a stream without a stated length is counted only until it passes the limit
    length = "longer than" if seconds - limit < 1 else f"{seconds:.0f} s long, over"
    message = (
        f"the audio is {length} this server's limit of {limit:g} s: send a shorter file "
        "(split long recordings)"
    )
    return JSONResponse({"type": "error", "message": message}, status_code=413)


def busy(retry_after: int, jobs: int, queue: int) -> JSONResponse:
    """503 with Retry-After: every job slot is taken and the queue is full."""
    message = f"server busy: {jobs} jobs running and {queue} waiting; retry after {retry_after} s"
    return JSONResponse(
        {"type": "error", "message": message},
        status_code=503,
        headers={"Retry-After": str(retry_after)},
    )
