"""``talkmesh serve``: face animation streamed over WebSocket, files over HTTP (starlette + uvicorn).

Streaming
=========

``GET /ws/stream?model=procedural&lookahead_ms=100&offsets=0`` upgrades to a WebSocket: a hello,
16-bit PCM in, one binary message per frame out; the protocol, message by message, is in
:mod:`talkmesh.serve.protocol`.

HTTP
====

* ``GET /``: the browser viewer (``talkmesh/serve/static``), or a 503 page where it is not installed.
* ``GET /health``: ``{"status": "ok", "sessions": n, "max_sessions": m, "jobs": running /animate
  jobs, "queued": waiting ones, "models": [...], "ticks": the streaming scheduler's ticks so far,
  "batched": the session-ticks they computed, "workers": the process ids of the workers that
  compute procedural sessions}`` (batched / ticks: the mean batch).
* ``GET /head.glb``: the bundled head with its 52 ARKit morph targets (named in
  ``meshes[0].extras.targetNames``), a one-frame neutral animation.
* ``GET /avatar.glb``: the ``--avatar`` file as it is (.glb or .vrm), 404 without one; ``/health``
  names it (``"avatar": "my.vrm"``, else null) and the viewer then shows it instead of the head.
* ``POST /animate?format=glb|mp4&model=NAME`` with a wav/flac/mp3/ogg file as the raw body: the
  animated file. 413 for a body over ``--max-upload-mb`` or audio longer than ``--max-seconds``
  (default 300; from the file's header, before anything is decoded), 503 with ``Retry-After``
  when ``--jobs`` slots are busy and ``--max-queue`` jobs wait, 400 with
  ``{"type": "error", "message"}`` for anything wrong with the request or the audio.

Limits on clients (:mod:`talkmesh.serve.limits`, docs/security.md): a request head and then its
body must each arrive within ``--request-timeout`` seconds (default 30) or the connection is dropped
with one log line; a client that leaves mid-upload is one log line; a WebSocket session must send
its first message within ``--first-message-timeout`` seconds (default 2) of the hello.

The sessions' audio is computed in ticks by one scheduler (:mod:`talkmesh.serve.batching`): each
tick runs the ready audio of every session in one worker-thread call, the streams of one model in
shared model steps, so the event loop stays free and a misbehaving client only ends its own
session. Procedural sessions are computed in ``--workers`` processes (:mod:`talkmesh.serve.workers`;
:func:`create_app` computes them in this process unless asked for workers).
"""

from __future__ import annotations

import contextlib
import logging
import math
import signal
import socket
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import anyio
import numpy as np
from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.requests import ClientDisconnect, Request
from starlette.responses import HTMLResponse, JSONResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket, WebSocketDisconnect

from talkmesh.audio.loading import SAMPLE_RATE, AudioTooLong, audio_duration
from talkmesh.errors import MissingDependencyError, TalkmeshError
from talkmesh.face.assets import load_head
from talkmesh.serve import limits as lim
from talkmesh.serve.batching import DEFAULT_BATCH_WAIT_MS, Scheduler, frames_of
from talkmesh.serve.emotion import LiveEmotion
from talkmesh.serve.files import RenderError, animate_file, audio_suffix, neutral_head_glb
from talkmesh.serve.hints import streaming_hint
from talkmesh.serve.limits import JobQueue, QueueFull
from talkmesh.serve.livelink import LiveLinkOut, open_link
from talkmesh.serve.protocol import (
    CLOSE_BUSY,
    CLOSE_GOING_AWAY,
    CLOSE_INTERNAL,
    CLOSE_NORMAL,
    CLOSE_POLICY,
    CLOSE_TOO_BIG,
    encode_frame,
    parse_text,
)
from talkmesh.serve.session import SessionAudio, session_options
from talkmesh.serve.stream import open_stream
from talkmesh.serve.workers import WorkerLost, WorkerPool, default_workers

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).parent / "static"
PROCEDURAL = "procedural"

DEFAULT_MAX_SESSIONS = 4
DEFAULT_MAX_MESSAGE_BYTES = 64 * 1024
DEFAULT_MAX_UPLOAD_BYTES = 20 * 2**20
DEFAULT_IDLE_TIMEOUT_S = 10.0
WS_FRAME_LIMIT = 16 * 2**20  # uvicorn drops (1009, no message) what is far over the limit unread
SHUTDOWN_WAIT_S = 3.0  # sessions get this long to close with 1001 before uvicorn takes over
UPLOAD_CHUNK = 1 << 16

ANIMATE_FORMATS = {"glb": "model/gltf-binary", "mp4": "video/mp4"}
# ---------------------------------------------------------------------------------------------
# Models and sessions


def resolve_models(models: Sequence[str]) -> dict[str, str]:
    """``--model`` values -> {the name clients ask for: what :func:`open_stream` loads}.

    ``procedural`` stays itself; a .safetensors file (or a bundled model's name) is exposed by
    its file stem, so clients never see or choose paths on the server.
    """
    out: dict[str, str] = {}
    for value in models:
        if value == PROCEDURAL:
            name, source = PROCEDURAL, PROCEDURAL
        else:
            path = Path(value)
            if path.suffix.lower() != ".safetensors" and not path.exists():
                from talkmesh.models.release import MODELS_DIR

                if (MODELS_DIR / f"{value}.safetensors").is_file():
                    path = MODELS_DIR / f"{value}.safetensors"
            if path.suffix.lower() not in (".safetensors", ".onnx"):
                raise TalkmeshError(
                    f"--model {value}: use procedural, a streaming model's .safetensors file or "
                    "an .onnx file of export-onnx"
                )
            if not path.is_file():
                raise TalkmeshError(f"--model {value}: no such file")
            name, source = path.stem, str(path.resolve())
        if out.get(name, source) != source:
            raise TalkmeshError(f"--model {value}: two models are named {name}; rename one file")
        out[name] = source
    if not out:
        raise TalkmeshError("no models to serve: pass --model procedural or a .safetensors file")
    return out


class ClientError(Exception):
    """Ends one session: the client gets ``message`` and the close ``code``."""

    def __init__(self, code: int, message: str):
        super().__init__(message)
        self.code = code


class Sessions:
    """The open streaming sessions: admission up to ``limit``, and closing them all on shutdown."""

    def __init__(self, limit: int):
        self.limit = limit
        self.scopes: set[anyio.CancelScope] = set()
        self.closing = False

    def __len__(self) -> int:
        return len(self.scopes)

    def admit(self, scope: anyio.CancelScope) -> bool:
        if self.closing or len(self.scopes) >= self.limit:
            return False
        self.scopes.add(scope)
        return True

    def leave(self, scope: anyio.CancelScope) -> None:
        self.scopes.discard(scope)

    async def close_all(self, wait_s: float = SHUTDOWN_WAIT_S) -> None:
        """Refuse new sessions and end the open ones (each closes with 1001)."""
        self.closing = True
        for scope in list(self.scopes):
            scope.cancel()
        with anyio.move_on_after(wait_s):
            while self.scopes:
                await anyio.sleep(0.02)


@dataclass(frozen=True)
class Limits:
    max_sessions: int = DEFAULT_MAX_SESSIONS
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    max_upload_bytes: int = DEFAULT_MAX_UPLOAD_BYTES
    idle_timeout: float = DEFAULT_IDLE_TIMEOUT_S
    max_seconds: float = lim.DEFAULT_MAX_SECONDS
    jobs: int = lim.DEFAULT_JOBS
    max_queue: int = lim.DEFAULT_MAX_QUEUE
    request_timeout: float = lim.DEFAULT_REQUEST_TIMEOUT_S
    first_message_timeout: float = lim.DEFAULT_FIRST_MESSAGE_TIMEOUT_S

    def __post_init__(self) -> None:
        if self.max_sessions < 1:
            raise TalkmeshError(f"--max-sessions must be at least 1, got {self.max_sessions}")
        if self.max_message_bytes < 2:
            raise TalkmeshError(
                f"--max-message-bytes must be at least 2, got {self.max_message_bytes}"
            )
        if self.max_upload_bytes < 1:
            raise TalkmeshError("--max-upload-mb must be positive")
        for flag, value in (
            ("--idle-timeout", self.idle_timeout),
            ("--max-seconds", self.max_seconds),
            ("--request-timeout", self.request_timeout),
            ("--first-message-timeout", self.first_message_timeout),
        ):
            if not value > 0:
                raise TalkmeshError(f"{flag} must be positive, got {value:g}")
        if self.jobs < 1 or self.max_queue < 0:
            raise TalkmeshError("--jobs must be at least 1 and --max-queue at least 0")


# ---------------------------------------------------------------------------------------------
# The application


class Service:
    """The endpoints, sharing the models, the limits and the session registry."""

    def __init__(
        self,
        models: dict[str, str],
        limits: Limits,
        avatar: Path | None = None,
        batch_wait_s: float = DEFAULT_BATCH_WAIT_MS / 1000,
        pool: WorkerPool | None = None,
        livelink: LiveLinkOut | None = None,
    ):
        self.avatar_name, self.avatar_glb = None, None
        if avatar is not None:  # checked now: a bad avatar stops the server before it starts
            from talkmesh.output.avatar import bind_avatar, read_glb

            bind_avatar(read_glb(avatar)[0], str(avatar))
            self.avatar_name, self.avatar_glb = Path(avatar).name, Path(avatar).read_bytes()
        self.models = models
        self.default_model = next(iter(models))
        self.limits = limits
        self.sessions = Sessions(limits.max_sessions)
        self.scheduler = Scheduler(batch_wait_s)
        self.pool = pool  # procedural sessions are computed there (None: in this process)
        self.livelink = livelink  # every session's frames also go there (serve/livelink.py)
        self.head = load_head()
        self.queue = JobQueue(limits.jobs, limits.max_queue, lim.DEFAULT_SHORT_SECONDS)
        self._head_glb: bytes | None = None
        self._head_lock = anyio.Lock()

    # -- WebSocket /ws/stream
    async def stream(self, ws: WebSocket) -> None:
        await ws.accept()
        if self.sessions.closing:  # shutting down: close as the open sessions do
            await _close(ws, CLOSE_GOING_AWAY, None)
            return
        with anyio.CancelScope() as scope:
            try:
                if not self.sessions.admit(scope):
                    raise ClientError(
                        CLOSE_BUSY,
                        f"server busy: all {self.limits.max_sessions} streaming sessions are in "
                        "use; try again later",
                    )
                try:
                    await self._session(ws)
                finally:
                    self.sessions.leave(scope)
            except ClientError as e:
                await _close(ws, e.code, str(e))
            except WorkerLost as e:  # logged where it was found
                await _close(ws, CLOSE_INTERNAL, str(e))
            except WebSocketDisconnect:
                pass  # the client left: nothing to tell it
            except Exception as e:  # a bug: end this session only, and say so
                log.exception("streaming session failed")
                await _close(
                    ws, CLOSE_INTERNAL, f"internal error ({type(e).__name__}); please report it"
                )
        if scope.cancelled_caught:
            await _close(ws, CLOSE_GOING_AWAY, None)

    async def _session(self, ws: WebSocket) -> None:
        """Hello, then audio in and frames out until the client's end message."""
        name, lookahead, offsets = self._parse_query(ws)
        source = self.models[name]
        try:
            options = session_options(ws.query_params)
            link = open_link(self.livelink, ws.query_params.get("livelink"))  # sends frames later
            if source == PROCEDURAL and self.pool is not None:
                stream = await self.pool.open(source, lookahead, offsets)
            else:
                opener = lambda: open_stream(  # noqa: E731
                    source, lookahead_ms=lookahead, head=self.head, offsets=offsets
                )
                stream = await anyio.to_thread.run_sync(opener)
        except TalkmeshError as e:
            raise ClientError(CLOSE_POLICY, str(e)) from None
        assert stream.sample_rate == SAMPLE_RATE, stream.sample_rate  # the protocol's PCM rate
        hello = {
            "type": "hello",
            "fps": stream.fps,
            "sample_rate": stream.sample_rate,
            "lookahead_ms": stream.lookahead_ms,
            "model": name,
            "names": list(stream.names),
        }
        await ws.send_json(hello)
        work, emotion = self.scheduler.join(stream), LiveEmotion(self.head)
        audio = SessionAudio(self.scheduler, work, stream.fps, options)
        failure: Exception | None = None
        try:
            async with anyio.create_task_group() as tasks:
                tasks.start_soon(self._receive_loop, ws, audio, emotion)
                tasks.start_soon(audio.keep_alive)  # idle life: silence when the audio stops
                try:  # errors leave the task group as themselves, not as a group
                    sent = 0
                    async for frames in frames_of(work):
                        for notice in audio.take_notices():  # before the frames after it
                            await ws.send_json(notice)
                        for frame in (emotion.apply(f) for f in audio.pose(frames)):
                            if link is not None:
                                link.send(frame, stream.fps)
                            await ws.send_bytes(encode_frame(frame))
                        sent += len(frames)
                    for notice in audio.take_notices():
                        await ws.send_json(notice)
                    await ws.send_json({"type": "end", "frames": sent})
                    await ws.close(CLOSE_NORMAL)
                except Exception as e:
                    failure = e
                tasks.cancel_scope.cancel()
        finally:
            self.scheduler.leave(work)
            if link is not None:
                link.close()
        if failure is not None:
            raise failure

    async def _receive_loop(self, ws: WebSocket, audio: SessionAudio, emotion: LiveEmotion) -> None:
        """A session's audio into the scheduler until its end message; what ends the session
        early (bad input, silence, the client gone) goes into its frames' queue instead."""
        timeout = self.limits.first_message_timeout  # a silent client frees its slot soon
        try:
            while True:
                pcm = await self._receive_audio(ws, timeout)
                timeout = self.limits.idle_timeout
                if isinstance(pcm, dict):  # the emotion of the frames sent from now on
                    audio.heard()
                    emotion.set(pcm)
                elif pcm is None:
                    await audio.end()
                    return
                else:
                    await audio.feed(pcm)
        except Exception as e:
            audio.work.send.send_nowait(e)

    async def _receive_audio(self, ws: WebSocket, timeout: float) -> np.ndarray | dict | None:
        """The next message: (S,) float32 audio, an emotion message's mix, or None for the end.

        Raises:
            ClientError: the message breaks the protocol, or none came for ``timeout`` seconds.
            WebSocketDisconnect: the client left.
        """
        try:
            with anyio.fail_after(timeout):
                message = await ws.receive()
        except TimeoutError:
            raise ClientError(
                CLOSE_POLICY,
                f"no message for {timeout:g} s: send audio as it is recorded "
                'and {"type": "end"} when it stops',
            ) from None
        if message["type"] == "websocket.disconnect":
            raise WebSocketDisconnect(message.get("code", 1000))
        data, text = message.get("bytes"), message.get("text")
        size = len(data) if data is not None else len((text or "").encode())
        limit = self.limits.max_message_bytes
        if size > limit:
            raise ClientError(
                CLOSE_TOO_BIG,
                f"message of {size} bytes is over the limit of {limit}: send shorter chunks",
            )
        if data is None:
            return _parse_text(text)  # None: the end; a dict: an emotion message's mix
        if len(data) % 2:
            raise ClientError(
                CLOSE_POLICY,
                f"binary message of {len(data)} bytes: audio must be 16-bit PCM, an even "
                "number of bytes",
            )
        return np.frombuffer(data, "<i2").astype(np.float32) / 32768.0

    def _parse_query(self, ws: WebSocket) -> tuple[str, float | None, bool]:
        query = ws.query_params
        name = query.get("model", self.default_model)
        if name not in self.models:
            raise ClientError(
                CLOSE_POLICY,
                f"unknown model '{name[:80]}': this server has {', '.join(self.models)}",
            )
        text = query.get("lookahead_ms")  # None: the model's default (procedural 100 ms)
        try:
            lookahead = None if text is None else float(text)
        except ValueError:
            lookahead = math.nan
        if lookahead is not None and not math.isfinite(lookahead):
            raise ClientError(
                CLOSE_POLICY, f"lookahead_ms must be a number of milliseconds, got '{text[:40]}'"
            )
        flag = query.get("offsets", "0")
        if flag not in ("0", "1"):
            raise ClientError(CLOSE_POLICY, f"offsets must be 0 or 1, got '{flag[:40]}'")
        return name, lookahead, flag == "1"

    # -- HTTP
    async def health(self, request: Request) -> JSONResponse:
        return JSONResponse(
            {
                "status": "ok",
                "sessions": len(self.sessions),
                "max_sessions": self.limits.max_sessions,
                "jobs": len(self.queue.running),
                "queued": len(self.queue.waiting),
                "models": list(self.models),
                "avatar": self.avatar_name,
                "ticks": self.scheduler.ticks,  # the scheduler's ticks, and the sessions they
                "batched": self.scheduler.stepped,  # computed in all (their ratio: batch size)
                "workers": [] if self.pool is None else self.pool.pids,  # process ids
            }
        )

    async def head_glb(self, request: Request) -> Response:
        async with self._head_lock:
            if self._head_glb is None:
                self._head_glb = await anyio.to_thread.run_sync(neutral_head_glb)
        return Response(self._head_glb, media_type=ANIMATE_FORMATS["glb"])

    async def avatar(self, request: Request) -> Response:
        if self.avatar_glb is None:
            return _error(404, "this server has no avatar: start it with --avatar FILE.glb")
        return Response(self.avatar_glb, media_type=ANIMATE_FORMATS["glb"])

    async def animate(self, request: Request) -> Response:
        query = request.query_params
        fmt = query.get("format", "glb")
        if fmt not in ANIMATE_FORMATS:
            return _error(
                400, f"format must be one of {', '.join(ANIMATE_FORMATS)}, got '{fmt[:40]}'"
            )
        name = query.get("model", self.default_model)
        if name not in self.models:
            return _error(
                400, f"unknown model '{name[:80]}': this server has {', '.join(self.models)}"
            )
        declared = request.headers.get("content-length", "")
        if declared.isdigit() and int(declared) > self.limits.max_upload_bytes:
            return self._too_big()  # without reading the body
        with tempfile.TemporaryDirectory(prefix="talkmesh-serve-") as tmp:
            upload = Path(tmp) / "upload"
            refused = await self._receive_upload(request, upload)
            if refused is not None:
                return refused
            with open(upload, "rb") as f:
                suffix = audio_suffix(f.read(16))
            if suffix is None:
                return _error(
                    400,
                    "the request body is not wav, flac, mp3 or ogg audio: send the "
                    "audio file's bytes as the body",
                )
            audio = upload.rename(upload.with_suffix(suffix))
            try:  # priced from the header: nothing is decoded yet
                limit = self.limits.max_seconds  # counted up to it when the header is silent
                seconds = await anyio.to_thread.run_sync(audio_duration, audio, limit)
            except TalkmeshError as e:
                return _error(400, str(e).replace(str(audio), "the audio"))
            if seconds > self.limits.max_seconds:
                return lim.too_long(seconds, self.limits.max_seconds)
            out = Path(tmp) / f"talk.{fmt}"
            try:
                async with self.queue.slot(seconds):
                    await anyio.to_thread.run_sync(
                        animate_file, audio, out, self.models[name], self.limits.max_seconds
                    )
            except QueueFull as e:
                return lim.busy(e.retry_after, self.limits.jobs, self.limits.max_queue)
            except AudioTooLong as e:  # the header understated the length
                return lim.too_long(e.seconds, e.limit)
            except TalkmeshError as e:
                return _error(400, str(e).replace(str(audio), "the audio"))
            except RenderError as e:
                return _error(500, str(e))
            return Response(
                out.read_bytes(),
                media_type=ANIMATE_FORMATS[fmt],
                headers={"Content-Disposition": f'attachment; filename="talk.{fmt}"'},
            )

    def _too_big(self) -> JSONResponse:
        limit = self.limits.max_upload_bytes
        return _error(413, f"the audio is over the upload limit of {limit / 2**20:g} MB")

    async def _receive_upload(self, request: Request, path: Path) -> Response | None:
        """Write the body to ``path``; a response instead when it is too big, too slow or cut off."""
        limit, deadline = self.limits.max_upload_bytes, self.limits.request_timeout
        received = 0
        try:
            with anyio.fail_after(deadline), open(path, "wb") as f:
                async for chunk in request.stream():
                    received += len(chunk)
                    if received > limit:
                        return self._too_big()
                    f.write(chunk)
        except TimeoutError:
            log.warning(
                "dropped %s: upload not complete within %g s (%d bytes)",
                lim.client_name(request),
                deadline,
                received,
            )
            return _error(408, f"the upload took over {deadline:g} s: send it faster or shorter")
        except ClientDisconnect:
            log.warning("%s left during its upload (%d bytes)", lim.client_name(request), received)
            return Response(status_code=400)  # nobody reads it
        return None


async def _close(ws: WebSocket, code: int, message: str | None) -> None:
    """Tell the client why (if there is a message) and close; a client already gone is fine."""
    try:
        if message is not None:
            await ws.send_json({"type": "error", "message": message})
        await ws.close(code)
    except (WebSocketDisconnect, RuntimeError, OSError):
        pass


def _parse_text(text: str | None):
    """None for the end message, a mix for an emotion message, else a ClientError."""
    try:
        return parse_text(text)
    except TalkmeshError as e:
        raise ClientError(CLOSE_POLICY, str(e)) from None


def _error(status: int, message: str) -> JSONResponse:
    return JSONResponse({"type": "error", "message": message}, status_code=status)


def _viewer_missing(request: Request) -> HTMLResponse:
    return HTMLResponse(
        "<!doctype html><title>talkmesh</title><h1>The browser viewer is not installed</h1>"
        f"<p>{STATIC_DIR.name} is missing from this talkmesh installation. The streaming API at "
        "<code>/ws/stream</code> and <code>/health</code>, <code>/head.glb</code> and "
        "<code>/animate</code> still work.</p>",
        status_code=503,
    )


def create_app(
    models: Sequence[str] = (PROCEDURAL,),
    max_sessions: int = DEFAULT_MAX_SESSIONS,
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    max_upload_bytes: int = DEFAULT_MAX_UPLOAD_BYTES,
    idle_timeout: float = DEFAULT_IDLE_TIMEOUT_S,
    static_dir: Path | None = STATIC_DIR,
    avatar: str | Path | None = None,
    batch_wait_ms: float = DEFAULT_BATCH_WAIT_MS,
    workers: int = 0,
    livelink: str | None = None,
    **limit_options,
) -> Starlette:
    """The ASGI app. Every model is opened once here, so a bad one fails now, not per client.

    ``avatar``: a .glb/.vrm with ARKit morph targets that the viewer shows instead of the head;
    ``limit_options``: the other fields of :class:`Limits` (max_seconds, jobs, max_queue,
    request_timeout, first_message_timeout); ``batch_wait_ms``: how long the scheduler waits after
    a session's audio arrives to gather others' into the same tick (:mod:`talkmesh.serve.batching`);
    ``workers``: processes that compute the procedural sessions (:mod:`talkmesh.serve.workers`;
    0: this process); ``livelink``: HOST:PORT to send sessions' frames to (serve/livelink.py).
    With workers, close ``app.state.service.pool`` when done."""
    limits = Limits(
        max_sessions, max_message_bytes, max_upload_bytes, float(idle_timeout), **limit_options
    )
    if not 0.0 <= batch_wait_ms <= 1000.0:
        raise TalkmeshError(f"--batch-wait-ms must be 0 to 1000, got {batch_wait_ms:g}")
    avatar = None if avatar is None else Path(avatar)
    if workers < 0:
        raise TalkmeshError(f"--workers must be 0 or more, got {workers}")
    link = None if livelink is None else LiveLinkOut(livelink)
    service = Service(resolve_models(models), limits, avatar, batch_wait_ms / 1000, livelink=link)
    for name, source in service.models.items():
        try:  # a model that cannot stream this face (or an .onnx of another kind) stops it here
            open_stream(source, head=service.head)
        except TalkmeshError as e:
            raise TalkmeshError(streaming_hint(name, source, e)) from None
    if workers and PROCEDURAL in service.models.values():
        # each worker makes its share of the sessions' recognisers up front (WorkerPool)
        service.pool = WorkerPool(workers, spares=-(-limits.max_sessions // workers))
    routes = [
        WebSocketRoute("/ws/stream", service.stream),
        Route("/health", service.health),
        Route("/head.glb", service.head_glb),
        Route("/avatar.glb", service.avatar),
        Route("/animate", service.animate, methods=["POST"]),
    ]
    if static_dir is not None and Path(static_dir).is_dir():
        routes.append(Mount("/", StaticFiles(directory=static_dir, html=True)))
    else:
        routes.append(Route("/", _viewer_missing))
    app = Starlette(routes=routes, middleware=[Middleware(lim.HeadLimit)])
    app.state.service = service
    return app


# ---------------------------------------------------------------------------------------------
# Running it


def _listen(host: str, port: int) -> socket.socket:
    """A listening socket, so that a port in use is a one-line error and port 0 works."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as e:
        sock.close()
        raise TalkmeshError(
            f"cannot listen on {host}:{port} ({e.strerror or e}): choose another --port or --host"
        ) from None
    sock.listen(128)
    return sock


def serve(
    host: str = "127.0.0.1",
    port: int = 8000,
    *,
    quiet: bool = False,
    torch_threads: int | None = None,
    workers: int | None = None,
    **app_options,
) -> None:
    """Run :func:`create_app` with uvicorn until Ctrl-C or SIGTERM, then close the sessions (1001);
    ``torch_threads``: PyTorch's threads for the model steps (None: this process's share of the
    cores beside the workers, :func:`talkmesh.models.threads.worker_threads`); ``workers``:
    processes for the procedural sessions (None: one per core, :func:`default_workers`)."""
    try:
        import uvicorn
    except ImportError:
        raise MissingDependencyError("uvicorn", "serve", "talkmesh serve") from None
    if not 0 <= port <= 65535:
        raise TalkmeshError(f"--port {port}: give 1 to 65535 (0: any free port)")
    if torch_threads is not None and torch_threads < 1:
        raise TalkmeshError(f"--torch-threads must be at least 1, got {torch_threads}")
    workers = default_workers() if workers is None else workers
    with contextlib.suppress(ImportError):  # without torch: the procedural animator only
        from talkmesh.models.threads import set_process_threads

        set_process_threads(torch_threads, workers + 1)
    app = create_app(workers=workers, **app_options)
    service: Service = app.state.service

    class _Server(uvicorn.Server):
        # uvicorn drops open WebSockets with 1012 (restart); close ours first with 1001 (going away)
        async def shutdown(self, sockets=None):
            await service.sessions.close_all()
            await super().shutdown(sockets)

    config = uvicorn.Config(
        app,
        lifespan="off",
        log_level="warning" if quiet else "info",
        ws_max_size=max(WS_FRAME_LIMIT, 4 * service.limits.max_message_bytes),
        http=lim.head_timeout_protocol(service.limits.request_timeout),
        # PCM chunks and float frames do not compress: deflate would only cost both ends CPU
        ws_per_message_deflate=False,
        timeout_graceful_shutdown=SHUTDOWN_WAIT_S,
    )
    logging.getLogger("uvicorn.access").addFilter(lim.ShortLogFields())  # after Config's setup
    sock = _listen(host, port)
    if not quiet:
        bound = sock.getsockname()[1]
        print(
            f"talkmesh: serving http://{host}:{bound}/ (stream at ws://{host}:{bound}/ws/stream; "
            f"models: {', '.join(service.models)}); Ctrl-C to stop",
            flush=True,
        )
    # uvicorn re-raises the signal that stopped it once it is done; a stop is no error here, so
    # that signal finds a handler that ignores it and the command exits 0.
    stops = (signal.SIGINT, signal.SIGTERM)
    previous = {s: signal.signal(s, lambda *_: None) for s in stops}
    try:
        _Server(config).run(sockets=[sock])
    finally:
        if service.pool is not None:
            service.pool.close()
        for s, handler in previous.items():
            signal.signal(s, handler)
        sock.close()
