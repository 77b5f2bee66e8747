"""``talkmesh serve --livelink HOST:PORT``: every session's frames also go to Unreal as Live Link
Face UDP packets (:mod:`talkmesh.output.livelink`), each session under a subject name of its own
choosing (``/ws/stream?livelink=NAME``; ``livelink=0`` opts a session out), so a MetaHuman moves
with the speech that a client streams in."""

from __future__ import annotations

import logging

from talkmesh.errors import TalkmeshError
from talkmesh.output.livelink import (
    DEFAULT_SUBJECT,
    LiveLinkSender,
    Target,
    check_subject,
    live_link_values,
    parse_target,
)
from talkmesh.serve.stream import StreamFrame

log = logging.getLogger(__name__)


class LiveLinkOut:
    """The server's Live Link target, checked once when the server starts."""

    def __init__(self, target: str) -> None:
        self.target: Target = parse_target(target)
        with LiveLinkSender(self.target) as probe:
            probe.check()  # nothing listening on this machine's port: refused before serving


def open_link(out: LiveLinkOut | None, option: str | None) -> SessionLink | None:
    """A session's Live Link (None: the server has no target, or ``livelink=0``); ``option`` is
    its ``livelink`` query value, the subject name (default ``talkmesh``).

    Raises:
        TalkmeshError: a bad subject name, or a subject asked of a server without a target.
    """
    if out is None:
        if option not in (None, "0"):
            raise TalkmeshError(
                "this server sends no Live Link: start it with --livelink HOST:PORT, or drop "
                "the livelink option"
            )
        return None
    if option == "0":
        return None
    return SessionLink(out.target, check_subject(option or DEFAULT_SUBJECT))


class SessionLink:
    """One session's frames to the target, its socket opened with the first frame; a refused
    packet (Unreal not started yet) is logged once and the session goes on."""

    def __init__(self, target: Target, subject: str) -> None:
        self.target, self.subject = target, subject
        self.sender: LiveLinkSender | None = None
        self.warned = False

    def send(self, frame: StreamFrame, fps: float) -> None:
        if self.sender is None:
            self.sender = LiveLinkSender(self.target, self.subject, fps)
        pose = None if frame.head_pose is None else frame.head_pose[None]
        values = live_link_values(frame.weights[None], pose)[0]
        if not self.sender.send(values, frame.index) and not self.warned:
            log.warning("Live Link %s refused frame %d: nothing listens", self.target, frame.index)
            self.warned = True

    def close(self) -> None:
        if self.sender is not None:
            self.sender.close()
