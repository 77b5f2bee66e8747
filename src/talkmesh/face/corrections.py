"""A learned model's mouth corrected by the phone recogniser: what ``animate`` outputs by default.

Models trained on clean synthetic speech keep the mouth open through the noisy and reverberant
pauses of real recordings, miss lip closures and open less on vowels than the procedural animator
(docs/results/real-speech.md). The phone recogniser, and the procedural animator driven by its
phones, supply what the model lacks. Five corrections, each with its own switch
(:class:`Corrections`), move the mouth region (``Regions.mouth_weight``) only:

* ``pause_gate``: the mouth shuts in pauses (:mod:`talkmesh.face.pauses`), their starts moved
  back over a reverberant tail; the pauses come from a voice activity detector trained on many
  languages (``pauses="vad"``, :mod:`talkmesh.audio.vad`, the default) or from the English phone
  recogniser (``pauses="recognizer"``, the default until 2026-11-27);
* ``mix``: a share of the procedural animator's mouth everywhere except at the model's own lip
  closures (so it does not lift them): the mouth follows the loudness more closely;
* ``gain``: the model's mouth opens further where the audio is loud (its displacement from the
  closed mouth scaled by ``1 + gain x`` the loudness, :func:`loudness_curve`), except at its lip
  closures and where the pause gate closes the mouth: models trained to the mean open less on
  vowels than the procedural animator;
* ``bilabial``: the model's near-closures (dips of the lip opening to within
  ``NEAR_CLOSED_MM`` of rest: :func:`near_closures` with ``REOPEN_MM``) shut fully within
  ``BILABIAL_PAD`` frames of a /p b m/ the recogniser finds;
* ``lip_closure`` (on by default since the multilingual model): every near-closure in speech
  shuts fully. Real /p b m/ then close, but so does every near-closure the synthetic truth
  leaves a little open: it costs synthetic LVE (docs/results/real-speech.md).

Closing the lips on the /p b m/ the recogniser finds, wherever the model's lips are, does not
work: it misses most of them in noise, and places some that are not there; ``bilabial`` only
finishes the closures the model starts there.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from talkmesh.audio.phonemes import BILABIALS, Phone
from talkmesh.errors import TalkmeshError
from talkmesh.face.assets import Head, lip_opening
from talkmesh.face.lipsync import SpeakingStyle, phones_to_weights
from talkmesh.face.pauses import (
    HOP_S,
    SPEECH_LEVEL_PERCENTILE,
    frame_db,
    gate_mouth,
    speech_gate,
    tail_pauses,
)

# The defaults (2026-11-27) need no English: the pause gate from voice activity and the model's
# near-closures in speech shut to met lips. With the bundled model retrained on the teacher's
# truth in 16 languages they give /p b m/ closure 1.00 on real clips (clean and 10 dB) and 0.89
# on the multilingual benchmark's unseen voices, where the recogniser's corrections (the mix, the
# gain, the recognised bilabials: ``PREVIOUS``) gave 0.12 (docs/results/multilingual.md).
# ``PREVIOUS`` (the defaults until 2026-11-27, for the English-only model) and ``FAITHFUL`` (until
# 2026-11-26) stay one set of flags away.
MIX = 0.0  # share of the procedural animator's mouth in the default output
NEAR_CLOSED_MM = 3.0  # an opening minimum this close to rest is the model closing the lips
# a near-closure must be a dip: the lips this much further apart the next frame and in one of
# DIP_FRAMES frames before it. Lips that rest near closed (in a pause the gate misses, or a /m/
# the model left at rest) are still: shut at whichever of their frames noise made a minimum,
# they moved in the pause (real clips' smallest speech/pause lip speed 1.5; 5-10 with dips only)
REOPEN_MM = 0.5
DIP_FRAMES = 3
BILABIAL_PAD = 2  # frames either side of a recognised /p b m/ where a near-closure shuts
BILABIAL = False  # the recognised /p b m/ (English): off, the near-closures in speech shut instead
LIP_CLOSURE = True  # every near-closure in speech shuts (to met lips): closure 0.65 -> 1.00 (real)
GAIN = 0.0  # the loudest speech opens the model's mouth this much further (off: the new model
# opens its open vowels 11.0 mm alone, the procedural animator 10.4)
LOUDNESS_SPAN_DB = 30.0  # from this far under the clip's speech level (no gain) up to it (full)
LOUDNESS_SMOOTH_S = 0.1  # the loudness is a moving average over this long
BLOCK = 2048  # frames of procedural vertices built at once (ten minutes would not fit)
PAUSE_SOURCES = ("vad", "recognizer")
PAUSE_SOURCE = "vad"  # any language; "recognizer": the English phone recogniser's pauses


@dataclass(frozen=True)
class Corrections:
    """Which corrections :func:`correct_mouth` applies (the defaults: what ``animate`` does).

    Attributes:
        pause_gate: shut the mouth in recognised pauses.
        lip_closure: shut the lips fully at every one of the model's near-closures.
        mix: share of the procedural animator's mouth, in [0, 1] (0: none).
        gain: how much further the loudest speech opens the mouth, in [0, 2] (0: none).
        bilabial: shut the lips fully at the model's near-closures by a recognised /p b m/.
        pauses: where the pause gate finds pauses: ``vad`` (voice activity, any language) or
            ``recognizer`` (the English phone recogniser's silences).
        met_lips: near-closures that shut (``lip_closure``, ``bilabial``) shut to met lips (the
            teacher's /p b m/ closure on this head, :func:`closed_lips`) instead of the rest
            face, whose lips are a little apart.
    """

    pause_gate: bool = True
    lip_closure: bool = LIP_CLOSURE
    mix: float = MIX
    gain: float = GAIN
    bilabial: bool = BILABIAL
    pauses: str = PAUSE_SOURCE
    met_lips: bool = True

    @property
    def needs_phones(self) -> bool:
        """Whether a correction reads the recognised phones (not only the pauses)."""
        return self.mix > 0 or self.bilabial or (self.pause_gate and self.pauses == "recognizer")

    def __post_init__(self):
        if self.pauses not in PAUSE_SOURCES:
            raise TalkmeshError(
                f"--pause-source must be one of {', '.join(PAUSE_SOURCES)}, got {self.pauses!r}"
            )
        if not 0.0 <= self.mix <= 1.0:
            raise TalkmeshError(f"--procedural-mix must be in [0, 1], got {self.mix:g}")
        if not 0.0 <= self.gain <= 2.0:
            raise TalkmeshError(f"--loudness-gain must be in [0, 2], got {self.gain:g}")


NONE = Corrections(pause_gate=False, lip_closure=False, mix=0.0, gain=0.0, bilabial=False)
# the defaults until 2026-11-27 (for the English-only model): ``--pause-source recognizer
# --no-lip-closure --procedural-mix 0.25 --loudness-gain 0.7 --bilabial-closure``
PREVIOUS = Corrections(
    lip_closure=False, mix=0.25, gain=0.7, bilabial=True, pauses="recognizer", met_lips=False
)
# closest to the old synthetic truth within the real-speech pause targets: ``--pause-source
# recognizer --no-lip-closure --procedural-mix 0.2 --loudness-gain 0.2``
FAITHFUL = Corrections(
    lip_closure=False, mix=0.2, gain=0.2, bilabial=False, pauses="recognizer", met_lips=False
)


def loudness_curve(wave: np.ndarray, num_frames: int, fps: float) -> np.ndarray:
    """(T,) float32 in [0, 1]: the loudness of (S,) ``wave`` at 16 kHz at each frame's centre, 0
    at ``LOUDNESS_SPAN_DB`` or more under the clip's speech level, 1 at it, in dB in between,
    averaged over ``LOUDNESS_SMOOTH_S``."""
    db = frame_db(wave)
    if not len(db):
        return np.zeros(num_frames, np.float32)
    level = np.percentile(db, SPEECH_LEVEL_PERCENTILE)
    loud = np.clip((db - (level - LOUDNESS_SPAN_DB)) / LOUDNESS_SPAN_DB, 0.0, 1.0)
    k = max(1, round(LOUDNESS_SMOOTH_S / HOP_S))
    loud = np.convolve(loud, np.ones(k) / k, mode="same")
    at = ((np.arange(num_frames) + 0.5) / fps / HOP_S).astype(int)
    return loud[np.clip(at, 0, len(loud) - 1)].astype(np.float32)


def closed_lips(head: Head) -> np.ndarray:
    """(V, 3) the head's rest face with its lips met, as the teacher closes them for /p b m/
    (:func:`talkmesh.face.teacher.close_lips` on the rest weights)."""
    from talkmesh.face.teacher import close_lips

    w = np.zeros((1, len(head.blendshape_names)), np.float32)
    close_lips(w, [Phone("M", 0.0, 1.0)], 1.0, head, ease_frames=0)
    return head.vertices_from_weights(w)[0]


def find_pauses(wave: np.ndarray, corrections: Corrections, phones: list[Phone]) -> list[Phone]:
    """The pause gate's segments: voice activity (any language) or the recognised ``phones``."""
    if corrections.pauses == "vad":
        from talkmesh.audio.vad import speech_pauses

        return speech_pauses(wave)
    return phones


def near_closures(
    opening: np.ndarray,
    rest: float,
    within: float = NEAR_CLOSED_MM,
    reopen: float = 0.0,
    before: int = DIP_FRAMES,
) -> np.ndarray:
    """(T,) bool: frames where the (T,) lip ``opening`` has a local minimum less than ``within``
    above ``rest`` (same unit). With ``reopen`` > 0 only dips count: the opening is at least that
    much larger the next frame and in one of the ``before`` frames before (lips that rest in a
    pause, or close into one, are still; a frame at either end of ``opening`` is no dip)."""
    prev = np.concatenate([[np.inf], opening[:-1]])
    nxt = np.concatenate([opening[1:], [np.inf]])
    found = (opening <= prev) & (opening <= nxt) & (opening < rest + within)
    if reopen > 0:
        lower = np.concatenate([np.full(before, -np.inf), opening])
        earlier = np.lib.stride_tricks.sliding_window_view(lower[:-1], before).max(axis=1)
        after = np.concatenate([opening[1:], [-np.inf]])
        found &= (earlier >= opening + reopen) & (after >= opening + reopen)
    return found


def bilabial_frames(
    phones: list[Phone], num_frames: int, fps: float, pad: int = BILABIAL_PAD
) -> np.ndarray:
    """(T,) bool: the frames of each /p b m/ in ``phones``, and ``pad`` frames either side."""
    near = np.zeros(num_frames, bool)
    for p in phones:
        if p.label in BILABIALS:
            lo = max(0, int(p.start * fps) - pad)
            near[lo : max(lo, min(num_frames, int(np.ceil(p.end * fps)) + pad))] = True
    return near


def _blend(vertices: np.ndarray, target, pull: np.ndarray, mouth: np.ndarray) -> None:
    """vertices += pull (T,) x mouth (V,) x (target - vertices), in blocks of frames; ``target``
    maps a slice of frames to their (t, V, 3) target vertices."""
    for lo in range(0, len(pull), BLOCK):
        block = slice(lo, lo + BLOCK)
        if not pull[block].any():
            continue
        w = pull[block, None, None] * mouth[None, :, None]
        vertices[block] += w * (target(block) - vertices[block])


def correct_mouth(
    vertices: np.ndarray,
    head: Head,
    phones: list[Phone],
    wave: np.ndarray,
    fps: float,
    corrections: Corrections = Corrections(),
    *,
    style: SpeakingStyle | None = None,
    seed: int = 0,
    pauses: list[Phone] | None = None,
) -> np.ndarray:
    """(T, V, 3) ``vertices`` of a learned model with their mouth corrected, in place.

    ``phones`` are recognised from ``wave`` ((S,) at 16 kHz); ``head`` is the face the vertices
    animate (its template is the closed mouth, its blendshapes make the procedural animator's
    mouth); ``style`` and ``seed`` as in :func:`phones_to_weights`. ``pauses``: the pause gate's
    ``SIL`` segments (default: found as ``corrections.pauses`` says).
    """
    T, V, _ = vertices.shape
    assert V == head.num_vertices, (V, head.num_vertices)
    chunks = correct_mouth_chunks(
        iter([vertices]),
        T,
        head,
        phones,
        wave,
        fps,
        corrections,
        style=style,
        seed=seed,
        pauses=pauses,
    )
    for _ in chunks:
        pass
    return vertices


def correct_mouth_chunks(
    chunks: Iterator[np.ndarray],
    num_frames: int,
    head: Head,
    phones: list[Phone],
    wave: np.ndarray,
    fps: float,
    corrections: Corrections = Corrections(),
    *,
    style: SpeakingStyle | None = None,
    seed: int = 0,
    pauses: list[Phone] | None = None,
) -> Iterator[np.ndarray]:
    """:func:`correct_mouth` on consecutive (t, V, 3) chunks of ``num_frames`` frames, each
    corrected in place and yielded in order: the same frames as the whole clip at once.

    The (T,) lip openings, loudness gain, procedural weights (T, 52) and pause gate (T,) are
    small and kept for the clip; vertices are not. A near-closure compares a frame's opening with
    its neighbours', and the mix and gain spare a frame either side of one, so a chunk is held
    back until the openings of the two frames after it are known (with any correction but the
    pause gate).
    """
    rest = float(lip_opening(head.template[None], head.regions)[0])
    shut = corrections.lip_closure or corrections.bilabial
    look = 2 if corrections.mix > 0 or corrections.gain > 0 or shut else 0
    weights = gate = loud = None
    shut_at = np.ones(num_frames, bool) if corrections.lip_closure else None
    if corrections.bilabial and not corrections.lip_closure:
        shut_at = bilabial_frames(phones, num_frames, fps)
    closed = None  # where shut lips go: met (solved once per clip) or the rest face
    if shut_at is not None:
        closed = closed_lips(head) if corrections.met_lips else head.template
    if corrections.gain > 0:
        loud = corrections.gain * loudness_curve(wave, num_frames, fps)
    if corrections.mix > 0:
        weights = phones_to_weights(phones, num_frames, fps, audio=wave, style=style, seed=seed)
    if corrections.pause_gate:
        if pauses is None:
            pauses = find_pauses(wave, corrections, phones)
        gate = speech_gate(tail_pauses(pauses, wave), num_frames, fps)
    curves = (loud, weights, shut_at, gate, closed)
    opening: np.ndarray | None = None
    pending: list[np.ndarray] = []
    done = known = 0  # frames yielded, frames whose opening is known
    for chunk in chunks:
        if look:
            o = lip_opening(chunk, head.regions)
            if opening is None:  # the chunks' dtype, so the comparisons are the whole clip's
                opening = np.full(num_frames, np.nan, o.dtype)  # NaN: not known yet
            opening[known : known + len(chunk)] = o
        known += len(chunk)
        pending.append(chunk)
        while pending and done + len(pending[0]) + look <= known:
            chunk = pending.pop(0)
            _correct(chunk, done, opening, rest, curves, head, corrections)
            done += len(chunk)
            yield chunk
    assert known == num_frames, (known, num_frames)
    for chunk in pending:
        _correct(chunk, done, opening, rest, curves, head, corrections)
        done += len(chunk)
        yield chunk


def _correct(
    chunk: np.ndarray,
    start: int,
    opening: np.ndarray | None,
    rest: float,
    curves: tuple[np.ndarray | None, ...],
    head: Head,
    corrections: Corrections,
) -> None:
    """Frames ``start``.. of the clip (``chunk``) corrected in place: ``opening`` is known from
    two frames before to two frames after them (or to the clip's ends); ``curves`` are the
    clip's (T,) gain, (T, 52) procedural weights, (T,) frames where near-closures shut, (T,)
    pause gate (None: not applied) and the (V, 3) face shut lips go to."""
    loud, weights, shut_at, gate, closed = curves
    mouth = head.regions.mouth_weight
    end = start + len(chunk)
    if opening is not None:  # closures from a frame before to a frame after the chunk
        lo, hi = max(0, start - 2 - DIP_FRAMES), min(len(opening), end + 2)
        # the window's first and last frames lack neighbours (unless at the clip's ends): they
        # only decide kept frames outside the chunk
        near = near_closures(opening[lo:hi], rest, NEAR_CLOSED_MM / 1000.0, REOPEN_MM / 1000.0)
        closures = near[start - lo : end - lo]
        kept = near.copy()  # the model's closures (and a frame either side) keep their lips
        kept[1:] |= near[:-1]
        kept[:-1] |= near[1:]
        kept = kept[start - lo : end - lo]
    if loud is not None:  # displacement from the closed mouth x (1 + gain x loudness)
        push = np.where(kept, 0.0, -loud[start:end])
        if gate is not None:  # no gain where the gate closes the mouth, nor on its ramps
            push = push * gate[start:end]
        push = push.astype(np.float32)
        _blend(chunk, lambda b: head.template[None], push, mouth)
    if corrections.mix > 0:
        pull = np.where(kept, 0.0, corrections.mix).astype(np.float32)
        w = weights[start:end]
        _blend(chunk, lambda b: head.vertices_from_weights(w[b]), pull, mouth)
    if shut_at is not None:
        shut = closures & shut_at[start:end]
        if gate is not None and corrections.met_lips:  # in speech only: a pause is at rest
            shut &= gate[start:end] >= 1.0
        shut = shut.astype(np.float32)
        _blend(chunk, lambda b: closed[None], shut, mouth)
    if gate is not None:
        gate_mouth(chunk, head.template, mouth, gate[start:end])
