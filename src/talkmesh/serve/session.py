"""A streaming session's audio on its way to the scheduler, its head motion, and the idle life
that keeps its face moving when the audio stops.

Every chunk the client sends goes to the session's :class:`~talkmesh.face.head_stream.HeadMotionStream`
(the head pose each frame carries) and to the scheduler, in the same order. From the client's
first message on the session keeps a clock; when no audio has come for ``IDLE_AFTER_S``,
:meth:`SessionAudio.keep_alive` streams silence in the client's place, up to the clock, every
``IDLE_TICK_S``: the frames keep coming with the procedural upper face's blinks and gaze, and
the head's breathing and sway. When the client speaks again its audio follows the silence. A
client sending faster than real time is ahead of the clock and gets no silence until the clock
catches up; ``idle=0`` turns it off.

A client that plays its own audio and times the frames by their index must know where that
silence went: when the client's audio comes again (or its end), the session notes
``{"type": "silence", "sample": S, "samples": N}`` (N samples of silence from the stream's
sample S on), which the server sends before any frame of the audio after it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import anyio
import numpy as np

from talkmesh.audio.loading import SAMPLE_RATE
from talkmesh.errors import TalkmeshError
from talkmesh.face.head_motion import NATURAL, check_amount
from talkmesh.face.head_stream import HeadMotionStream
from talkmesh.serve.batching import Scheduler, Work
from talkmesh.serve.stream import StreamFrame

IDLE_AFTER_S = 0.5  # a client that sent no audio for this long has stopped talking
IDLE_TICK_S = 0.04  # silence is streamed this often (a frame or so at a time)
MAX_IDLE_PIECE_S = 1.0  # at most this much silence at once (a client back after a long stall)


@dataclass(frozen=True)
class SessionOptions:
    head_motion: float = NATURAL
    idle: bool = True


def session_options(query) -> SessionOptions:
    """``head_motion`` (0 to 1) and ``idle`` (0 or 1) of a session's query, checked."""
    text = query.get("head_motion", str(NATURAL))
    try:
        amount = float(text)
    except ValueError:
        amount = math.nan
    try:
        check_amount(amount)
    except TalkmeshError:
        raise TalkmeshError(
            f"head_motion must be 0 (still) to 1 (lively), got '{text[:40]}'"
        ) from None
    flag = query.get("idle", "1")
    if flag not in ("0", "1"):
        raise TalkmeshError(f"idle must be 0 or 1, got '{flag[:40]}'")
    return SessionOptions(amount, flag == "1")


class SessionAudio:
    """A session's audio: the client's chunks (:meth:`feed`), its end (:meth:`end`) and the
    silence of :meth:`keep_alive`, into the scheduler and the head motion (module docstring)."""

    def __init__(
        self, scheduler: Scheduler, work: Work, fps: float, options: SessionOptions
    ) -> None:
        self.scheduler, self.work, self.options = scheduler, work, options
        amount = options.head_motion
        self.motion = HeadMotionStream(fps, amount=amount) if amount > 0 else None
        self.started: float | None = None  # monotonic time of the first message
        self.last_audio: float | None = None
        self.samples = 0
        self.ended = False
        self.idle_from: int | None = None  # the stream's sample where the silence now began
        self.idle_samples = 0
        self.notices: list[dict] = []  # silence messages for the client, oldest first

    def heard(self) -> None:
        """A message came (any kind): the session's clock runs from the first."""
        if self.started is None:
            self.started = time.monotonic()

    async def feed(self, pcm: np.ndarray) -> None:
        """The client's next chunk of (S,) float32 audio."""
        self.heard()
        self.last_audio = time.monotonic()
        self._note_silence()
        await self._submit(pcm)

    async def end(self) -> None:
        self.ended = True
        self._note_silence()
        await self.scheduler.submit(self.work, None)

    def _note_silence(self) -> None:
        """The silence streamed since the client's last audio, as a message (module docstring)."""
        if self.idle_samples:
            notice = {"type": "silence", "sample": self.idle_from, "samples": self.idle_samples}
            self.notices.append(notice)
        self.idle_from, self.idle_samples = None, 0

    def take_notices(self) -> list[dict]:
        """The silence messages noted since the last call, to send before the next frames."""
        notices, self.notices = self.notices, []
        return notices

    async def _submit(self, pcm: np.ndarray) -> None:
        # the head motion and the scheduler get the audio in the same order: nothing awaits
        # between the two (Scheduler.submit queues before it waits for a backlog)
        if self.motion is not None:
            self.motion.receive(pcm)
        self.samples += len(pcm)
        await self.scheduler.submit(self.work, pcm)

    def pose(self, frames: list[StreamFrame]) -> list[StreamFrame]:
        """``frames`` (in order) with their head poses, computed at once (as they are when the
        head is still)."""
        if self.motion is None or not frames:
            return frames
        first = frames[0].index
        poses = self.motion.poses(first, frames[-1].index + 1)
        for frame in frames:
            frame.head_pose = poses[frame.index - first]
        return frames

    async def keep_alive(self) -> None:
        """Silence in the client's place while it sends no audio (module docstring); returns
        at the end of the audio."""
        if not self.options.idle:
            return
        while not self.ended:
            await anyio.sleep(IDLE_TICK_S)
            if self.started is None or self.ended:
                continue
            now = time.monotonic()
            if now - (self.last_audio or self.started) < IDLE_AFTER_S:
                continue
            due = int((now - self.started) * SAMPLE_RATE) - self.samples
            if due > 0:
                piece = min(due, int(MAX_IDLE_PIECE_S * SAMPLE_RATE))
                if self.idle_from is None:
                    self.idle_from = self.samples
                self.idle_samples += piece
                await self._submit(np.zeros(piece, "f4"))
