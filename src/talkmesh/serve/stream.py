"""Real-time streaming: audio chunks in, face frames out, with a bounded look-ahead.

``open_stream(model, lookahead_ms=...)`` returns a streamer; ``push(pcm)`` takes 16 kHz mono audio
of any length (a microphone's 10-200 ms chunks) and returns the frames whose look-ahead has
arrived; ``flush()`` ends the stream. Each frame carries the 52 ARKit weights and, optionally, the
vertex offsets from the neutral face. State is bounded (windowed caches, the last seconds of
audio), so a stream can run for hours at a constant cost per frame.

Two animators stream:

* ``procedural``: incremental phone recognition (PocketSphinx's all-phone search with the cheaper
  settings :data:`talkmesh.audio.phonemes.ALLPHONE_STREAM`, its current best path read after every
  chunk; the utterance restarts at pauses, at the latest every
  ``MAX_UTTERANCE_S``) and the dominance-function lip sync on the phones heard so far. Blinks, gaze
  and brow drift come from a seeded schedule; brow raises on pitch accents need the audio after
  the accent and are left out.
* a learned model's release that streams (:meth:`talkmesh.models.base.MotionModel.open_frame_stream`;
  a CodeTalker with a causal VQ decoder: a streaming one, ``configs/codetalker_stream.yaml``, whose
  mel speech encoder has a runtime look-ahead, exactly what ``generate`` computes offline; or the
  bundled one, whose Whisper features come a block of frames at a time,
  :mod:`talkmesh.models.whisper_stream`, exactly what ``generate_streamed`` computes): one frame
  per step with key/value caches. On the model's own topology (``head`` a face of another topology
  than the bundled head's), its ARKit weights are solved from its motion as offline
  (:mod:`talkmesh.face.solve`, the face rigged once per mesh), each push continuing the last
  frame, and its eye motion is its own.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from talkmesh.audio.loading import SAMPLE_RATE
from talkmesh.audio.phonemes import (
    ALLPHONE_STREAM,
    FRAME_RATE,
    SILENCE_RMS,
    AllphoneSearch,
    Phone,
)
from talkmesh.constants import MOTION_FPS
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES, WeightFitter
from talkmesh.face.assets import Head, load_head
from talkmesh.face.lipsync import (
    BLINK_GAZE,
    INDEX,
    SpeakingStyle,
    add_mouth,
    mouth_curves,
    replace_eye_motion,
    upper_face_curves,
)
from talkmesh.models.bundled import MODELS_DIR
from talkmesh.models.framestream import FrameRequest, next_frames

DEFAULT_LOOKAHEAD_MS = 100.0
MAX_LOOKAHEAD_MS = 300.0
MAX_UTTERANCE_S = 20.0  # the phone recogniser restarts at least this often (bounded search)
MIN_UTTERANCE_S = 6.0  # ... and at a pause once the utterance is this long
PAUSE_S = 0.3
UPPER_FACE_SEGMENT_S = 30.0  # blinks, gaze and drift are drawn this many seconds at a time
PHONE_MEMORY_S = 2.0  # finished phones kept for coarticulation
FRAME_SAMPLES = SAMPLE_RATE // FRAME_RATE
EYES = [INDEX[n] for n in BLINK_GAZE]  # the ARKit channels of procedural blinks and gaze
PIECE = SAMPLE_RATE // 5  # longer pushes are processed 200 ms at a time


@dataclass
class StreamFrame:
    index: int  # frames since the start of the stream
    time: float  # seconds: index / fps
    weights: np.ndarray  # (52,) float32 ARKit weights, in ARKIT_NAMES order
    offsets: np.ndarray | None  # (V, 3) float32 vertex offsets from the neutral face
    head_pose: np.ndarray | None = None  # (6,) float32 pitch, yaw, roll, translation (head_motion)


def as_audio(pcm: np.ndarray) -> np.ndarray:
    """An audio chunk (float in [-1, 1], or int16) -> (S,) float32, non-finite samples zeroed."""
    audio = np.asarray(pcm)
    if audio.ndim != 1:
        raise TalkmeshError(f"audio chunks must be 1-D mono samples, got shape {audio.shape}")
    if audio.dtype == np.int16:
        audio = audio.astype(np.float32) / 32768.0
    elif audio.dtype.kind != "f":
        raise TalkmeshError(f"audio chunks must be float or int16 samples, got {audio.dtype}")
    return np.nan_to_num(audio.astype(np.float32, copy=False), nan=0.0, posinf=0.0, neginf=0.0)


class Streamer:
    """Common part: audio bookkeeping and the emission schedule. Subclasses say how far past a
    frame's time the audio must reach (:meth:`_audio_needed`) and compute frames."""

    sample_rate = SAMPLE_RATE
    names = ARKIT_NAMES

    def __init__(self, fps: float, lookahead_ms: float, head: Head, offsets: bool) -> None:
        self.fps = float(fps)
        self.lookahead_ms = float(lookahead_ms)
        self.head = head
        self.offsets = offsets
        self.samples = 0  # audio received so far
        self.next_frame = 0
        self.closed = False
        self.basis = (  # None on another topology (a model's own): weights are solved there
            None
            if head.blendshapes is None
            else np.ascontiguousarray(head.blendshapes.reshape(len(ARKIT_NAMES), -1), np.float32)
        )

    def push(self, pcm: np.ndarray) -> list[StreamFrame]:
        """16 kHz mono audio (float in [-1, 1], or int16) -> the frames it completes."""
        if self.closed:
            raise TalkmeshError("this stream was flushed: open a new one to stream more audio")
        audio = as_audio(pcm)
        frames: list[StreamFrame] = []
        for i in range(0, len(audio), PIECE):  # long pushes in pieces: state stays bounded
            piece = audio[i : i + PIECE]
            self._receive(piece)
            self.samples += len(piece)
            frames += self._emit(self._ready(), final=False)
        return frames

    def _ready(self) -> int:
        """The frame after the last one whose audio has arrived."""
        ready = self.next_frame
        while self._audio_needed(ready) <= self.samples:
            ready += 1
        return ready

    def _total(self) -> int:
        """Frames of the whole stream once it ends (at least one)."""
        return max(1, int(round(self.samples / SAMPLE_RATE * self.fps)), self.next_frame)

    def flush(self) -> list[StreamFrame]:
        """End of the stream: every remaining frame of the audio received (at least one)."""
        if self.closed:
            return []
        self.closed = True
        return self._emit(self._total(), final=True)

    def _emit(self, end: int, final: bool) -> list[StreamFrame]:
        if end <= self.next_frame:
            return []
        start, self.next_frame = self.next_frame, end
        weights, offsets = self._frames(start, end, final)
        return [
            StreamFrame(t, t / self.fps, weights[k], None if offsets is None else offsets[k])
            for k, t in enumerate(range(start, end))
        ]

    def _weights_to_offsets(self, weights: np.ndarray) -> np.ndarray:
        return (weights @ self.basis).reshape(len(weights), -1, 3)

    # -- for subclasses
    def _receive(self, audio: np.ndarray) -> None:
        raise NotImplementedError

    def _audio_needed(self, frame: int) -> float:
        """Samples that must have arrived before ``frame`` can be computed."""
        raise NotImplementedError

    def _frames(self, start: int, end: int, final: bool) -> tuple[np.ndarray, np.ndarray | None]:
        raise NotImplementedError


class UpperFace:
    """Blinks, gaze and brow drift for any frame range, drawn in seeded 30 s segments."""

    def __init__(self, fps: float, seed: int, style: SpeakingStyle, channels=None) -> None:
        self.fps, self.seed, self.style = fps, seed, style
        self.segment = int(UPPER_FACE_SEGMENT_S * fps)
        self.cache: dict[int, np.ndarray] = {}
        self.channels = channels  # keep only these ARKit indices (None: all)

    def __call__(self, start: int, end: int) -> np.ndarray:
        out = np.empty((end - start, len(ARKIT_NAMES)), np.float32)
        for t in range(start, end):  # frames of at most two segments per call in practice
            k = t // self.segment
            if k not in self.cache:
                self.cache = {k: self._segment(k)}  # one segment at a time: bounded
            out[t - start] = self.cache[k][t - k * self.segment]
        return out

    def _segment(self, k: int) -> np.ndarray:
        times = np.arange(self.segment) / self.fps
        rng = np.random.default_rng([self.seed, k])
        w = upper_face_curves(times, rng, self.style, np.zeros((0, 2)))
        if self.channels is not None:
            keep = np.zeros(len(ARKIT_NAMES), bool)
            keep[self.channels] = True
            w[:, ~keep] = 0.0
        return w


class DecoderPool:
    """Spare streaming phone recognisers. Making one reads the acoustic model (about 65 ms and
    32 MB), which would stall every other session of a process that opens a stream while they
    run; a server makes its share up front (:meth:`fill`) and takes a closed stream's back
    (:meth:`give`): reset, it recognises as a new one does (``tests/test_stream.py``)."""

    def __init__(self, search: AllphoneSearch = ALLPHONE_STREAM) -> None:
        self.search = search
        self.spares: list = []

    def fill(self, n: int) -> None:
        from talkmesh.audio import phonemes

        while len(self.spares) < n:
            self.spares.append(phonemes._decoder(align=False, search=self.search))

    def take(self):
        if not self.spares:
            self.fill(1)
        return self.spares.pop()

    def give(self, decoder) -> None:
        try:
            decoder.end_utt()
        except RuntimeError:  # no utterance open
            pass
        decoder.reinit_feat()
        self.spares.append(decoder)


class ProceduralStreamer(Streamer):
    """Incremental phone recognition + the procedural lip sync (module docstring)."""

    def __init__(
        self,
        lookahead_ms: float,
        head: Head,
        offsets: bool,
        fps: float = MOTION_FPS,
        seed: int = 0,
        style: SpeakingStyle | None = None,
        search: AllphoneSearch = ALLPHONE_STREAM,
        decoders: DecoderPool | None = None,
    ) -> None:
        super().__init__(fps, lookahead_ms, head, offsets)
        from talkmesh.audio import phonemes

        self._ps = phonemes
        if decoders is not None and decoders.search != search:
            raise ValueError("the pool's recognisers have other search settings")
        self.decoders = decoders
        self.decoder = decoders.take() if decoders else phonemes._decoder(False, search)
        self.style = style or SpeakingStyle()
        self.upper = UpperFace(self.fps, seed, self.style)
        self.past: list[Phone] = []  # finished utterances' phones (the last seconds), stream time
        self.utt_rms: list[np.ndarray] = []  # RMS of the utterance's complete 10 ms frames
        self.rms_tail = np.zeros(0, np.float32)  # samples of the incomplete frame
        self.utt_start = 0  # stream sample where the current utterance began
        self.utt_samples = 0
        self.tidier = phonemes.PhoneTidier()  # the utterance's phones, re-read incrementally
        self.decoder.start_utt()

    def release(self) -> None:
        """The stream is done with: its recogniser goes back to the pool it came from."""
        if self.decoders is not None and self.decoder is not None:
            self.decoders.give(self.decoder)
        self.decoder = None
        self.closed = True

    def _receive(self, audio: np.ndarray) -> None:
        # 16-bit PCM as phonemes._pcm16 makes it; the audio is finite already (as_audio)
        pcm = np.clip(audio * np.float32(32767.0), -32768, 32767).astype("<i2")
        self.decoder.process_raw(pcm.tobytes())
        self.utt_samples += len(audio)
        tail = np.concatenate([self.rms_tail, audio])
        n = len(tail) // FRAME_SAMPLES * FRAME_SAMPLES
        if n:
            frames = tail[:n].reshape(-1, FRAME_SAMPLES)
            self.utt_rms.append(np.sqrt(np.mean(np.square(frames), axis=1)))
        self.rms_tail = tail[n:]
        seconds = self.utt_samples / SAMPLE_RATE
        if seconds >= MAX_UTTERANCE_S or (seconds >= MIN_UTTERANCE_S and self._pause()):
            self._end_utterance()

    def _rms(self) -> np.ndarray:
        """RMS per 10 ms frame of the utterance so far (the last frame zero-padded)."""
        if len(self.utt_rms) > 1:
            self.utt_rms = [np.concatenate(self.utt_rms)]
        parts = list(self.utt_rms)
        if len(self.rms_tail):
            padded = np.zeros(FRAME_SAMPLES, np.float32)
            padded[: len(self.rms_tail)] = self.rms_tail
            parts.append(np.sqrt(np.mean(np.square(padded)))[None])
        return np.concatenate(parts) if parts else np.zeros(0, np.float32)

    def _pause(self) -> bool:
        tail = self._rms()[-int(PAUSE_S * FRAME_RATE) :]
        return float(np.sqrt(np.mean(np.square(tail)))) < SILENCE_RMS

    def _utterance_phones(self, after: float) -> list[Phone]:
        """The current utterance's phones so far, in stream time, that end after ``after``."""
        if not self.utt_samples:
            return []
        segments = [(s.word, s.start_frame, s.end_frame + 1) for s in self.decoder.seg() or []]
        rms = self._rms()
        complete = len(rms) - (len(self.rms_tail) > 0)  # the zero-padded last frame may change
        offset = self.utt_start / SAMPLE_RATE
        return self.tidier.phones(segments, rms, complete, self.utt_samples, offset, after)

    def _end_utterance(self) -> None:
        self.decoder.end_utt()
        now = (self.utt_start + self.utt_samples) / SAMPLE_RATE
        phones = self._utterance_phones(now - PHONE_MEMORY_S)
        self.past = [p for p in [*self.past, *phones] if p.end > now - PHONE_MEMORY_S]
        self.utt_start += self.utt_samples
        self.utt_rms, self.rms_tail, self.utt_samples = [], np.zeros(0, np.float32), 0
        self.tidier = self._ps.PhoneTidier()
        self.decoder.reinit_feat()
        self.decoder.start_utt()

    def _audio_needed(self, frame: int) -> float:
        # the recogniser's 10 ms frames are centred 12.5 ms into their 25 ms window
        return (
            frame / self.fps + self.lookahead_ms / 1000
        ) * SAMPLE_RATE + 1.5 * SAMPLE_RATE / FRAME_RATE

    def _frames(self, start: int, end: int, final: bool) -> tuple[np.ndarray, np.ndarray | None]:
        if final and self.utt_samples:
            self._end_utterance()
        times = np.arange(start, end) / self.fps
        after = times[0] - PHONE_MEMORY_S
        recent = [p for p in self.past if p.end > after] + self._utterance_phones(after)
        weights = add_mouth(
            self.upper(start, end), mouth_curves(recent, times, self.style), self.style
        )
        return weights, self._weights_to_offsets(weights) if self.offsets else None


class ModelStreamer(Streamer):
    """A learned model's release that streams (:meth:`talkmesh.models.base.MotionModel.open_frame_stream`),
    one frame per step; its eye motion becomes procedural blinks and gaze (module docstring).
    :func:`push_together` computes the frames of many such streams in shared model steps."""

    def __init__(
        self,
        path: str | Path,
        lookahead_ms: float | None,
        head: Head,
        offsets: bool,
        seed: int = 0,
        style_weights: np.ndarray | None = None,
        blinks: bool = True,
    ) -> None:
        net = _load_streaming_model(path)
        if net.num_vertices != head.num_vertices:
            raise TalkmeshError(
                f"{path} animates {net.num_vertices}-vertex meshes but the face has {head.num_vertices}"
            )
        try:
            self.stream = net.open_frame_stream(style_weights, lookahead_ms, head.template)
        except TalkmeshError as e:
            raise TalkmeshError(f"{path}: {e}") from None
        super().__init__(self.stream.fps, self.stream.lookahead_ms, head, offsets)
        if head.rigged:
            self.fitter = _weight_fitter(head)
        else:  # the model's own topology: its weights solved, its eyes its own (as offline)
            self.fitter, blinks = _SolvingFitter(head), False
        self.blinks = UpperFace(self.fps, seed, SpeakingStyle(), EYES) if blinks else None
        self.buffer = np.zeros(0, np.float32)
        self.buffer_start = 0  # stream sample of buffer[0]

    def _receive(self, audio: np.ndarray) -> None:
        self.buffer = np.concatenate([self.buffer, audio])

    def _audio_needed(self, frame: int) -> float:
        return self.stream.audio_needed(frame)

    def _frames(self, start: int, end: int, final: bool) -> tuple[np.ndarray, np.ndarray | None]:
        motion = np.stack([self.stream.frame(*self._request(t)[1:]) for t in range(start, end)])
        weights = self.fitter(motion)
        if self.basis is not None:
            replace_eye_motion(motion, weights, self._eyes(start, end, weights), self.basis)
        return self._finish(start, end, motion, weights)

    def _eyes(self, start: int, end: int, weights: np.ndarray) -> np.ndarray:
        """The eyes frames start..end-1 get: procedural blinks and gaze, or the model's own
        (``weights``, the ARKit weights fitted to its motion) without blinks."""
        return weights if self.blinks is None else self.blinks(start, end)

    def _request(self, frame: int):
        return FrameRequest(self.stream, self.buffer, self.buffer_start, frame)

    def _take(self, chunks: list[np.ndarray], end: bool) -> range:
        """Receive ``chunks`` (and the end of the stream) -> the frames now due, for the caller
        to compute (:func:`push_together`)."""
        if self.closed:
            raise TalkmeshError("this stream was flushed: open a new one to stream more audio")
        for audio in map(as_audio, chunks):
            self._receive(audio)
            self.samples += len(audio)
        self.closed = end
        start, self.next_frame = self.next_frame, self._total() if end else self._ready()
        return range(start, self.next_frame)

    def _finish(
        self, start: int, end: int, motion: np.ndarray, weights: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Frames start..end-1 from their motion (T, V * 3) and ARKit weights, the eye motion
        replaced: the audio no later frame reads is dropped."""
        drop = self.stream.first_sample(end) - self.buffer_start
        if drop > 0:
            self.buffer = self.buffer[drop:]
            self.buffer_start += drop
        offsets = motion.reshape(len(motion), -1, 3) if self.offsets else None
        return weights, offsets


def push_together(
    work: list[tuple[Streamer, list[np.ndarray], bool]],
) -> list[list[StreamFrame] | TalkmeshError]:
    """Many streams' new audio at once: for each (streamer, chunks, end) the frames that pushing
    each chunk in turn (then flushing, if ``end``) would return, or the TalkmeshError that ended
    it. The streams of one model compute their frames together: one model step per frame index
    for all streams that have that many frames due (:func:`_model_frames`), each stream's frames
    what it computes alone. The procedural animator has no shared model: its streams run one
    after another."""
    out: list = [None] * len(work)
    due: dict[int, range] = {}  # model streams: the frames to compute
    for i, (streamer, chunks, end) in enumerate(work):
        try:
            if isinstance(streamer, ModelStreamer):
                due[i] = streamer._take(chunks, end)
            else:
                frames = [f for chunk in chunks for f in streamer.push(chunk)]
                out[i] = frames + (streamer.flush() if end else [])
        except TalkmeshError as e:
            out[i] = e
    groups: dict[int, list[int]] = {}  # model streams that share a face fit their weights together
    for i, frames in due.items():
        if len(frames):
            groups.setdefault(id(work[i][0].fitter), []).append(i)
        else:
            out[i] = []
    for members in groups.values():
        computed = _model_frames([work[i][0] for i in members], [due[i] for i in members])
        for i, frames in zip(members, computed):
            out[i] = frames
    return out


def _model_frames(streamers: list[ModelStreamer], due: list[range]) -> list[list[StreamFrame]]:
    """The frames ``due`` of model streams that share a face: one model step per frame index,
    one weight fit, one eye replacement for them all."""
    first = streamers[0]
    # without vertex offsets to send, the model gives only the frames' projections onto the
    # blendshapes, all the weight fit needs (and cheaper than the V * 3 coordinates)
    basis = None if any(s.offsets for s in streamers) or first.basis is None else first.fitter.basis
    rows: list[list[np.ndarray]] = [[] for _ in streamers]
    for k in range(max(map(len, due))):
        active = [j for j, frames in enumerate(due) if k < len(frames)]
        requests = [streamers[j]._request(due[j][k]) for j in active]
        for j, row in zip(active, next_frames(requests, basis)):
            rows[j].append(row)
    stacked = np.concatenate([np.stack(r) for r in rows])
    weights = first.fitter(stacked) if basis is None else first.fitter.from_projection(stacked)
    cuts = np.cumsum([len(frames) for frames in due])[:-1]
    eyes = np.concatenate(
        [s._eyes(r.start, r.stop, w) for s, r, w in zip(streamers, due, np.split(weights, cuts))]
    )
    if first.basis is None:  # another topology: the model's own eyes, nothing replaced
        pass
    elif basis is None:
        replace_eye_motion(stacked, weights, eyes, first.basis)
    else:  # what replace_eye_motion does to the weights
        weights[:, EYES] = eyes[:, EYES]
    out = []
    for s, r, part, w in zip(streamers, due, np.split(stacked, cuts), np.split(weights, cuts)):
        w, offsets = s._finish(r.start, r.stop, part, w)
        out.append(
            [
                StreamFrame(t, t / s.fps, w[k], None if offsets is None else offsets[k])
                for k, t in enumerate(r)
            ]
        )
    return out


_FITTERS: dict[int, tuple[Head, WeightFitter]] = {}


class _SolvingFitter:
    """The weight fit of one stream on another topology than the bundled head's: the bounded,
    smooth solve of :mod:`talkmesh.face.solve` (the face rigged once per mesh), each call
    continuing from the last frame of the one before. One per stream (it keeps that frame)."""

    def __init__(self, head: Head) -> None:
        from talkmesh.face.solve import solver_for_mesh

        self.solver = solver_for_mesh(head.template, head.faces, head.name)
        self.previous: np.ndarray | None = None

    def __call__(self, motion: np.ndarray) -> np.ndarray:
        """(T, V * 3) offsets -> (T, 52) weights."""
        offsets = np.asarray(motion).reshape(len(motion), -1, 3)
        weights = self.solver.solve(offsets, self.previous).weights
        if len(weights):
            self.previous = weights[-1].astype(np.float64)
        return weights


def _weight_fitter(head: Head) -> WeightFitter:
    """One fitter per face (its factorised basis is megabytes), shared by the streams."""
    if id(head) not in _FITTERS:
        if len(_FITTERS) >= 4:
            _FITTERS.clear()
        _FITTERS[id(head)] = (head, WeightFitter(head.blendshapes, iterations=50))
    return _FITTERS[id(head)][1]


_MODELS: dict[tuple[str, float], object] = {}


def _load_streaming_model(path: str | Path):
    """A release (or an ONNX export, run without torch) loaded once per process (per file
    version) and shared read-only by streams."""
    path = Path(path).resolve()
    key = (str(path), path.stat().st_mtime)
    if key not in _MODELS:
        if len(_MODELS) >= 4:  # bounded: a server holds a few models
            _MODELS.clear()
        if path.suffix.lower() == ".onnx":
            from talkmesh.models.onnx import OnnxModel

            _MODELS[key] = OnnxModel(path)
        else:
            from talkmesh.models.release import load_model

            _MODELS[key] = load_model(path).eval()
    return _MODELS[key]


def open_stream(
    model: str | Path | None = "procedural",
    *,
    lookahead_ms: float | None = None,
    head: Head | None = None,
    offsets: bool = False,
    seed: int = 0,
    fps: float = MOTION_FPS,
    style_weights: np.ndarray | None = None,
    blinks: bool = True,
    decoders: DecoderPool | None = None,
) -> Streamer:
    """A streamer for ``model``: ``procedural``, a bundled model's name, the path of a release
    that streams (a CodeTalker with a causal VQ decoder: the bundled ``codetalker-synth``, a
    streaming one of ``configs/codetalker_stream.yaml``) or an ``.onnx`` file of export-onnx
    (run by ONNX Runtime without torch, :mod:`talkmesh.models.onnx_stream`).

    ``lookahead_ms``: audio after a frame's time that it waits for, 0-300 ms (None: the
    model's default, procedural 100 ms, the bundled CodeTalker 300 ms, a mel streaming release
    the largest it was trained for, which is the range it accepts). ``offsets``: also return vertex
    offsets per frame. ``fps`` applies to the procedural animator (a model has its own), and
    ``decoders`` (a :class:`DecoderPool` its recogniser comes from and goes back to, by
    ``release()``).
    """
    lookahead = None if lookahead_ms is None else float(lookahead_ms)
    if lookahead is not None and not 0.0 <= lookahead <= MAX_LOOKAHEAD_MS:
        raise TalkmeshError(
            f"look-ahead {lookahead:g} ms is out of range: use 0 to {MAX_LOOKAHEAD_MS:g} ms"
        )
    head = head or load_head()
    if head.rigged and tuple(head.blendshape_names) != tuple(ARKIT_NAMES):
        raise TalkmeshError("the face's blendshapes are not the 52 ARKit shapes in ARKit order")
    name = "procedural" if model is None else str(model)
    if name == "procedural" and not head.rigged:
        raise TalkmeshError(
            f"the procedural animator streams the bundled head's topology, not {head.name}'s "
            f"{head.num_vertices} vertices: stream a learned model of this topology"
        )
    if name == "procedural":
        if not 1.0 <= fps <= 240.0:
            raise TalkmeshError(f"fps {fps:g} is out of range: use 1 to 240")
        return ProceduralStreamer(
            DEFAULT_LOOKAHEAD_MS if lookahead is None else lookahead,
            head,
            offsets,
            fps=fps,
            seed=seed,
            decoders=decoders,
        )
    path = Path(name)
    if not path.is_file() and (MODELS_DIR / f"{name}.safetensors").is_file():
        path = MODELS_DIR / f"{name}.safetensors"  # a bundled model by its name
    if path.suffix.lower() not in (".safetensors", ".onnx") or not path.is_file():
        raise TalkmeshError(
            f"unknown streaming model '{name}': use procedural, a bundled model, a streaming "
            "model's .safetensors file or an .onnx file of export-onnx"
        )
    return ModelStreamer(
        path, lookahead, head, offsets, seed=seed, style_weights=style_weights, blinks=blinks
    )
