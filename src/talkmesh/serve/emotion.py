"""The emotion of a live session: ``{"type": "emotion", "emotion": "happy:0.6"}`` messages change it
as the frames go out.

A message takes effect at the first frame sent after it arrives: the face blends from the
emotion it had to the new one over ``ONSET_S`` (a raised cosine, as a timeline span's onset,
:mod:`talkmesh.face.performance`), and holds it until the next message. Each frame's ARKit
weights get the emotion composed in with the speech in charge of the lips
(:mod:`talkmesh.face.composition`); its vertex offsets, when the client asked for them, move by
the weights' change through the bundled head's blendshapes.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from talkmesh.errors import TalkmeshError
from talkmesh.face.assets import Head
from talkmesh.face.composition import compose, lip_basis, rest_gap
from talkmesh.face.performance import ONSET_S, Mix, Performance, Span, parse_emotion
from talkmesh.serve.stream import StreamFrame


def parse_emotion_message(message: dict) -> Mix:
    """The mix of an emotion message (``TalkmeshError`` naming what is wrong)."""
    text = message.get("emotion")
    if not isinstance(text, str) or set(message) - {"type", "emotion"}:
        raise TalkmeshError(
            'an emotion message is {"type": "emotion", "emotion": "happy:0.6"} '
            "(neutral happy sad angry surprised fearful disgusted, intensities 0 to 1)"
        )
    return parse_emotion(text, "emotion message")


class LiveEmotion:
    """A session's emotion: :meth:`set` on a message, :meth:`apply` to every frame sent."""

    def __init__(self, head: Head) -> None:
        self.head = head
        self.performance = Performance()
        self.pending: Mix | None = None
        upper, lower = head.regions.lip_pair
        self.rest_lips = (head.template[upper] - head.template[lower]).astype(np.float64)
        self.rest = rest_gap(head.template, head.regions.lip_pair)
        self.lip_basis = lip_basis(head.blendshapes, head.regions.lip_pair)
        self.basis = head.blendshapes.reshape(len(head.blendshapes), -1)

    def set(self, mix: Mix) -> None:
        """The emotion from the next frame sent on."""
        self.pending = mix

    def apply(self, frame: StreamFrame) -> StreamFrame:
        """``frame`` with the emotion composed in (itself while the session is neutral)."""
        if self.pending is not None:
            self._start(self.pending, frame.time)
            self.pending = None
        if self.performance.is_neutral:
            return frame
        emotion = self.performance.weights(np.array([frame.time]))
        weights = frame.weights[None].astype(np.float32)
        if frame.offsets is not None:
            upper, lower = self.head.regions.lip_pair
            lips = self.rest_lips + (frame.offsets[upper] - frame.offsets[lower])
        else:
            lips = self.rest_lips + weights[0].astype(np.float64) @ self.lip_basis
        new = compose(weights, emotion, lips[None], self.lip_basis, self.rest)
        offsets = frame.offsets
        if offsets is not None and new is not weights:
            delta = ((new - weights) @ self.basis).reshape(offsets.shape)
            offsets = offsets + delta.astype(offsets.dtype)
        return replace(frame, weights=new[0], offsets=offsets)

    def _start(self, mix: Mix, time: float) -> None:
        """A span from ``time`` on, blending from what the face shows. The spans never end, so
        the last one fully risen by ``time`` hides all before it: it becomes the base (a
        session's spans stay few however many messages it sends)."""
        base, spans = self.performance.base, list(self.performance.spans)
        risen = [k for k, s in enumerate(spans) if s.start + s.onset <= time]
        if risen:
            base, spans = spans[risen[-1]].mix, spans[risen[-1] + 1 :]
        self.performance = Performance(base, (*spans, Span(time, math.inf, mix, ONSET_S, 0.0)))
