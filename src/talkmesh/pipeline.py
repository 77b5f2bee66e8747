"""Speech in, talking face out: the public ``animate`` function the CLI and users call."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from talkmesh.animation import Animation, AnimationBlocks
from talkmesh.audio.loading import SAMPLE_RATE, load_audio
from talkmesh.audio.phonemes import Phone, recognize_phones, word_starts
from talkmesh.audio.resamplers import POLYPHASE
from talkmesh.audio.waveform import Waveform, open_audio
from talkmesh.constants import INT8_LAYERS, MOTION_FPS
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES, WeightFitter
from talkmesh.face.assets import Head, load_head
from talkmesh.face.composition import compose, compose_vertices, lip_basis, rest_gap
from talkmesh.face.corrections import (
    BILABIAL,
    GAIN,
    LIP_CLOSURE,
    MIX,
    NONE,
    PAUSE_SOURCE,
    Corrections,
    correct_mouth_chunks,
)
from talkmesh.face.head_motion import NATURAL, check_amount, head_pose
from talkmesh.face.lipsync import (
    SpeakingStyle,
    blink_gaze_weights,
    phones_to_weights,
    replace_eye_motion,
)
from talkmesh.face.performance import Performance, split_tags, tag_spans

if TYPE_CHECKING:
    from talkmesh.models.base import MotionModel

DEFAULT_FPS = MOTION_FPS
MIN_FPS, MAX_FPS = 1.0, 240.0  # fewer frames a second is no animation; more, no display shows
MAX_SEED = 2**32 - 1  # numpy's seeds
MAX_STYLE_WEIGHT = 1e6  # --style weights are normalised to add up to 1: any finite share will do
INT8_MODES = INT8_LAYERS  # animate(int8=...): CodeTalker layers run in int8
MODELS = ("procedural",)
BLOCK = 256  # frames made at once: 15 MB of float32 vertices on the bundled head (V=4766)


DEFAULT_MODEL = "codetalker-synth"  # the bundled CodeTalker (src/talkmesh/data/models/)


def default_model() -> str:
    """The bundled CodeTalker when it is installed (and torch with it), else ``procedural``."""
    from importlib.util import find_spec

    if find_spec("torch") is None or find_spec("safetensors") is None:
        return "procedural"
    return DEFAULT_MODEL if DEFAULT_MODEL in available_models() else "procedural"


def available_models() -> list[str]:
    """``procedural`` plus the bundled learned models (``talkmesh/data/models/*.safetensors``)."""
    from talkmesh.models.bundled import bundled_models

    return [*MODELS, *bundled_models()]


def num_frames_for(num_samples: int, sr: int, fps: float) -> int:
    """Frames covering the audio (at least one)."""
    return max(1, int(round(num_samples / sr * fps)))


def animate(
    audio: str | Path | np.ndarray,
    *,
    head: Head | None = None,
    text: str | None = None,
    phones: list[Phone] | None = None,
    fps: float | None = None,
    seed: int = 0,
    style: SpeakingStyle | None = None,
    model: str | MotionModel | None = None,
    style_mix: dict[str, float] | None = None,
    blinks: bool = True,
    int8: str | None = None,
    pause_gate: bool = True,
    lip_closure: bool = LIP_CLOSURE,
    procedural_mix: float = MIX,
    loudness_gain: float = GAIN,
    bilabial_closure: bool = BILABIAL,
    pause_source: str = PAUSE_SOURCE,
    performance: Performance | None = None,
    head_motion: float = NATURAL,
    runtime: str = "auto",
) -> Animation:
    """Animate a face from speech.

    Args:
        audio: a speech file (any format ffmpeg reads) or a (S,) float32 waveform at 16 kHz.
        head: the face to animate (default: the bundled default identity); a face of another
            topology (:func:`talkmesh.face.assets.plain_head`, a learned model's own) is animated
            by the model alone: no pause gate, blinks or ARKit weights, which need the bundled
            blendshapes and regions.
        text: the transcript, if known: phones are then force-aligned instead of recognised
            (procedural animator; with ``model`` None it selects it).
        phones: timed phones, if already known (skips recognition).
        fps: output frame rate (default: a learned model's own, e.g. 25 for BIWI models; 30 for
            the procedural animator).
        seed: seed of the audio-independent motion (blinks, brow drift, gaze).
        style: the speaker's style.
        model: ``procedural`` or a learned model: a bundled name, a ``.safetensors`` release or
            a model already loaded with ``load_model`` (so that many files load it once)
            (default: the bundled CodeTalker, ``codetalker-synth``; ``procedural`` without it).
        style_mix: learned models: weights over the training speakers (``{"A": 0.7, "B": 0.3}``);
            default the mean of all of them (the model has never heard this speaker).
        blinks: learned models: replace the model's own eye motion (its fitted blink and gaze
            channels) with the procedural animator's blinks and gaze saccades (seeded by
            ``seed``), which speech cannot predict.
        int8: CodeTalker models: run these layers in int8 on the CPU (``speech``: the speech
            encoder, ``decoders``: the per-frame decoder layers, ``all``: both); faster, not
            exact (its effect on accuracy: docs/results/codetalker.md).
        pause_gate: learned models: close the mouth in pauses (voice activity, any language;
            :mod:`talkmesh.face.pauses`), where noisy real recordings keep it open otherwise.
        lip_closure: learned models: shut the lips (met) where the model nearly closes them in
            speech (:mod:`talkmesh.face.corrections`; on by default).
        procedural_mix: learned models: share of the procedural animator's mouth (recognised
            phones) mixed into the model's except at its lip closures, in [0, 1]; 0: off.
        loudness_gain: learned models: the loudest speech opens the mouth ``1 + gain`` times as
            far (not at its lip closures), in [0, 2]; 0: off.
        bilabial_closure: learned models: shut the lips fully where the model nearly closes them
            by a /p b m/ that the phone recogniser finds.
        pause_source: learned models: the pause gate's pauses, ``vad`` or ``recognizer``.
        performance: the emotion over the clip (:mod:`talkmesh.face.performance`), composed with
            the speech so that the speech keeps the lips' opening
            (:mod:`talkmesh.face.composition`); ``[happy]`` tags in ``text`` add spans to it.
        head_motion: how much the head moves with the speech's prosody, 0 (still) to 1
            (:mod:`talkmesh.face.head_motion`; the bundled topology only), as ``head_pose``.
        runtime: what runs a learned model named by ``model`` (:mod:`talkmesh.models.runtime`):
            ``auto`` (ONNX Runtime for the bundled model and .onnx files, torch otherwise),
            ``torch`` or ``onnxruntime``.

    Returns:
        An :class:`Animation` with vertices (T, V, 3), the audio and the ARKit weights (T, 52).
    """
    options = {k: v for k, v in locals().items() if k != "audio"}  # the arguments, forwarded
    return animate_blocks(audio, **options).collect()


def check_fps_seed(fps: float | None, seed: int = 0) -> None:
    """One-line errors for a frame rate outside [MIN_FPS, MAX_FPS] or a seed numpy refuses."""
    if fps is not None and not (MIN_FPS <= fps <= MAX_FPS):  # NaN fails too
        raise TalkmeshError(f"--fps {fps:g}: give {MIN_FPS:g} to {MAX_FPS:g} frames per second")
    if not 0 <= seed <= MAX_SEED:
        raise TalkmeshError(f"--seed {seed}: give a whole number from 0 to {MAX_SEED}")


def _checked_wave(
    audio: str | Path | np.ndarray, fps: float | None, block: int, seed: int = 0
) -> np.ndarray | Waveform:
    """The (S,) waveform of ``audio`` once ``fps`` and ``block`` are checked (one-line errors):
    a file libsndfile reads is a :class:`Waveform`, read from the file a slice at a time."""
    check_fps_seed(fps, seed)
    if block < 1:
        raise TalkmeshError(f"block must be at least 1 frame, got {block}")
    wave = open_audio(audio) if isinstance(audio, (str, Path)) else np.asarray(audio, np.float32)
    if wave.ndim != 1 or not len(wave):
        raise TalkmeshError("audio must be a non-empty mono waveform")
    return wave


def animate_blocks(
    audio: str | Path | np.ndarray,
    *,
    head: Head | None = None,
    text: str | None = None,
    phones: list[Phone] | None = None,
    fps: float | None = None,
    seed: int = 0,
    style: SpeakingStyle | None = None,
    model: str | MotionModel | None = None,
    style_mix: dict[str, float] | None = None,
    blinks: bool = True,
    int8: str | None = None,
    pause_gate: bool = True,
    lip_closure: bool = LIP_CLOSURE,
    procedural_mix: float = MIX,
    loudness_gain: float = GAIN,
    bilabial_closure: bool = BILABIAL,
    pause_source: str = PAUSE_SOURCE,
    block: int = BLOCK,
    performance: Performance | None = None,
    head_motion: float = NATURAL,
    runtime: str = "auto",
) -> AnimationBlocks:
    """:func:`animate` ``block`` frames at a time (arguments as there; the same frames): memory
    does not grow with the audio when the model generates in chunks (the procedural animator,
    causal CodeTalker models); :func:`talkmesh.output.streaming.save_blocks` writes it. A file
    libsndfile reads is read a slice at a time (``audio`` is then a ``Waveform``)."""
    wave = _checked_wave(audio, fps, block, seed)
    check_amount(head_motion)
    source = Path(audio) if isinstance(audio, (str, Path)) else None  # videos mux its sound
    head = head or load_head()
    if model is None:  # a transcript or phones ask for the phone-driven animator
        model = "procedural" if text is not None or phones is not None else default_model()
    _check_options(int8, model, text, phones)
    if model == "procedural":
        made = animate_procedural(
            wave,
            head,
            text=text,
            phones=phones,
            fps=fps,
            seed=seed,
            style=style,
            block=block,
            performance=performance,
            head_motion=head_motion,
        )
        made.audio_file = source
        return made
    mouth = (pause_gate, lip_closure, procedural_mix, loudness_gain, bilabial_closure)
    corrections = Corrections(*mouth, pause_source)
    net, weights = _learned_model(model, head, style_mix, int8, runtime)
    wave = _wave_for(net, wave, source)
    fps = net.motion_fps if fps is None else fps
    frames = net.default_frames(len(wave))  # imported official models count as the official code
    if abs(fps - net.motion_fps) > 1e-6:
        frames = num_frames_for(len(wave), SAMPLE_RATE, fps)
    chunks = _learned_chunks(net, wave, head, weights, fps, frames, seed, block)
    if not head.rigged:  # another topology (the model's own): the model's motion as it is
        return _plain_blocks(chunks, head, fps, frames, wave, source)
    if corrections != NONE:  # voice activity (and the English recogniser, if asked): the mouth
        found = recognize_phones(wave, SAMPLE_RATE) if corrections.needs_phones else []
        chunks = correct_mouth_chunks(
            chunks, frames, head, found, wave, fps, corrections, seed=seed, style=style
        )
    eyes = blink_gaze_weights(frames, fps, seed=seed, style=style) if blinks else None
    pose = _pose(wave, frames, fps, head_motion, seed)
    return AnimationBlocks(
        blocks=_finish_learned(chunks, head, fps, eyes, _rigged_only(performance, head), pose),
        num_frames=frames,
        faces=head.faces,
        fps=fps,
        audio=wave,
        sample_rate=SAMPLE_RATE,
        weight_names=list(ARKIT_NAMES),
        template=head.template,
        basis=head.blendshapes,
        audio_file=source,
    )


def _wave_for(net: MotionModel, wave: np.ndarray | Waveform, source: Path | None):
    """The waveform ``net`` hears: an imported official model reads a file resampled as its
    official code did it (``net.resampler``), not by the polyphase filter."""
    if source is None or net.resampler == POLYPHASE:
        return wave
    return load_audio(source, resampler=net.resampler)


def _plain_blocks(chunks, head: Head, fps: float, frames: int, wave, source) -> AnimationBlocks:
    return AnimationBlocks(
        blocks=(Animation(vertices=c, faces=head.faces, fps=fps) for c in chunks),
        num_frames=frames,
        faces=head.faces,
        fps=fps,
        audio=wave,
        sample_rate=SAMPLE_RATE,
        template=head.template,
        audio_file=source,
    )


def _rigged_only(performance: Performance | None, head: Head) -> Performance | None:
    """``performance`` when it adds anything (None when neutral); the emotion moves the bundled
    blendshapes, so a face of another topology cannot take it."""
    if performance is None or performance.is_neutral:
        return None
    if not head.rigged:
        raise TalkmeshError(
            f"--emotion moves the bundled head's blendshapes, not {head.name}'s "
            f"{head.num_vertices} vertices: animate the bundled topology"
        )
    return performance


def _check_options(int8: str | None, model, text: str | None, phones) -> None:
    """One-line errors for options the model cannot take."""
    if model != "procedural" and (text is not None or phones is not None):
        raise TalkmeshError(
            f"--text and phones drive the procedural animator, not {model_name(model)}: drop "
            "them or pass --model procedural"
        )
    if int8 is not None and int8 not in INT8_MODES:
        raise TalkmeshError(f"--int8 {int8}: use one of {', '.join(INT8_MODES)}")
    if model == "procedural" and int8 is not None:
        raise TalkmeshError("--int8 applies to CodeTalker models, not the procedural animator")


def _torch_chunks(net, wave, head: Head, weights, n_in: int, seed: int, block: int):
    import torch

    return (
        c[0].numpy().astype(np.float32, copy=False)
        for c in net.generate_chunks(
            wave if isinstance(wave, Waveform) else torch.from_numpy(wave)[None],
            torch.from_numpy(head.template)[None],
            style_weights=None if weights is None else torch.from_numpy(weights)[None],
            num_frames=n_in,
            seed=seed,
            chunk=block,
        )
    )


def _finish_learned(
    chunks: Iterator[np.ndarray],
    head: Head,
    fps: float,
    eyes: np.ndarray | None,
    performance: Performance | None = None,
    pose: np.ndarray | None = None,
) -> Iterator[Animation]:
    """A learned model's vertices (their mouth corrected), a chunk at a time, made into
    :func:`animate`'s frames: ARKit weights fitted (so ARKit exports work for learned models),
    the model's own eye motion replaced by procedural ``eyes`` and the ``performance``'s emotion
    composed in as blendshape offsets; ``pose`` (T, 6) is the head's motion."""
    fitter = WeightFitter(head.blendshapes)
    basis = head.blendshapes.reshape(len(ARKIT_NAMES), -1)
    t = 0
    for verts in chunks:
        n = len(verts)
        weights = fitter(np.asarray(verts, np.float64) - head.template.astype(np.float64))
        if eyes is not None:
            replace_eye_motion(verts, weights, eyes[t : t + n], basis)
        if performance is not None:
            emotion = performance.weights((t + np.arange(n)) / fps)
            rest = rest_gap(head.template, head.regions.lip_pair)
            weights = compose_vertices(
                verts, weights, emotion, head.blendshapes, head.regions.lip_pair, rest
            )
        yield Animation(
            vertices=verts,
            faces=head.faces,
            fps=fps,
            weights=weights,
            weight_names=list(ARKIT_NAMES),
            template=head.template,
            basis=head.blendshapes,
            head_pose=None if pose is None else pose[t : t + n],
        )
        t += n


def animate_procedural(
    wave: np.ndarray,
    head: Head,
    *,
    text: str | None,
    phones: list[Phone] | None,
    fps: float | None,
    seed: int,
    style: SpeakingStyle | None,
    block: int = BLOCK,
    performance: Performance | None = None,
    head_motion: float = NATURAL,
    runtime: str = "auto",
) -> AnimationBlocks:
    """The phone-driven animator on ``head`` (arguments as in :func:`animate_blocks`): the weight
    curves (T, 52) at once, the vertices a block at a time."""
    fps = DEFAULT_FPS if fps is None else fps
    if not head.rigged:
        raise TalkmeshError(
            f"the procedural animator drives the bundled head's topology, not {head.name}'s "
            f"{head.num_vertices} vertices: pass a learned model of this topology (--model)"
        )
    text, tags = split_tags(text) if text else (text, [])
    if phones is None:
        phones = recognize_phones(wave, SAMPLE_RATE, text=text)
    num_frames = num_frames_for(len(wave), SAMPLE_RATE, fps)
    weights = phones_to_weights(
        phones, num_frames, fps, audio=wave, sr=SAMPLE_RATE, style=style, seed=seed
    )
    if tags:
        spans = tag_spans(tags, word_starts(phones, text), len(wave) / SAMPLE_RATE)
        performance = (performance or Performance()).with_spans(spans)
    performance = _rigged_only(performance, head)
    if performance is not None:
        weights = _compose_weights(weights, performance.weights(np.arange(num_frames) / fps), head)
    pose = _pose(wave, num_frames, fps, head_motion, seed)

    def blocks() -> Iterator[Animation]:
        for t in range(0, num_frames, block):
            w = weights[t : t + block]
            yield Animation(
                vertices=head.vertices_from_weights(w),
                faces=head.faces,
                fps=fps,
                weights=w,
                weight_names=list(ARKIT_NAMES),
                head_pose=None if pose is None else pose[t : t + block],
            )

    return AnimationBlocks(
        blocks=blocks(),
        num_frames=num_frames,
        faces=head.faces,
        fps=fps,
        audio=wave,
        sample_rate=SAMPLE_RATE,
        weight_names=list(ARKIT_NAMES),
        template=head.template,
        basis=head.blendshapes,
        phones=[(str(p[0]), float(p[1]), float(p[2])) for p in phones],
    )


def _pose(wave, frames: int, fps: float, amount: float, seed: int) -> np.ndarray | None:
    """(T, 6) head motion of the bundled head, None when still (``amount`` 0)."""
    return head_pose(wave, frames, fps, amount=amount, seed=seed) if amount > 0 else None


def _compose_weights(weights: np.ndarray, emotion: np.ndarray, head: Head) -> np.ndarray:
    """The procedural animator's (T, 52) ``weights`` with the (T, 52) ``emotion`` composed in."""
    upper, lower = head.regions.lip_pair
    basis = lip_basis(head.blendshapes, head.regions.lip_pair)
    lips = (head.template[upper] - head.template[lower]).astype(np.float64) + weights @ basis
    return compose(weights, emotion, lips, basis, rest_gap(head.template, head.regions.lip_pair))


def parse_style(text: str | None) -> dict[str, float] | None:
    """``A:0.7,B:0.3`` -> {"A": 0.7, "B": 0.3}; a bare name means weight 1."""
    if not text:
        return None
    out: dict[str, float] = {}
    for item in text.split(","):
        name, _, weight = item.strip().partition(":")
        try:
            out[name] = float(weight) if weight else 1.0
        except ValueError:
            raise TalkmeshError(f"--style {text}: '{item}' must look like NAME:WEIGHT") from None
        if not 0 <= out[name] <= MAX_STYLE_WEIGHT:  # NaN fails too
            raise TalkmeshError(
                f"--style {text}: the weight of '{name}' must be 0 to {MAX_STYLE_WEIGHT:g} "
                "(the weights are shares: A:0.7,B:0.3)"
            )
    return out


def model_name(model: str | Path | MotionModel) -> str:
    """How messages name ``model``: its name or path, or its class for a loaded model."""
    return str(model) if isinstance(model, (str, Path)) else type(model).__name__


def _learned_model(
    model: str | Path | MotionModel,
    head: Head,
    style_mix: dict[str, float] | None,
    int8: str | None,
    runtime: str = "auto",
) -> tuple[Any, np.ndarray | None]:
    """A released learned model (any family of talkmesh.models.registry; ``model``: a name, a
    release file or a loaded model) on ``runtime`` (:mod:`talkmesh.models.runtime`) for ``head``
    and its style weights (K,) over the training speakers (None: the model has none)."""
    from talkmesh.models.onnx import OnnxModel
    from talkmesh.models.runtime import open_model

    net = open_model(model, runtime, int8=int8)
    if not isinstance(net, OnnxModel):
        import torch

        torch.set_num_threads(max(1, torch.get_num_threads()))
    if net.num_vertices != head.num_vertices:
        raise TalkmeshError(
            f"model {model_name(model)} animates {net.num_vertices}-vertex meshes but the face "
            f"has {head.num_vertices}: pass --template with a neutral face of the model's topology "
            "(e.g. VOCASET's templates.pkl:SUBJECT or FLAME_sample.ply, BIWI's BIWI.ply)"
        )
    styles = list(net.styles)
    weights = None
    if styles:
        weights = np.full(len(styles), 1.0 / len(styles), np.float32)
    if style_mix:
        if not styles:
            raise TalkmeshError(f"--style: model {model_name(model)} has no speaker styles")
        unknown = sorted(set(style_mix) - set(styles))
        if unknown:
            raise TalkmeshError(
                f"--style: unknown speaker {unknown[0]}; the model knows {', '.join(styles)}"
            )
        total = sum(style_mix.values())
        if total <= 0:
            raise TalkmeshError("--style weights must add up to more than 0")
        weights = np.array([style_mix.get(s, 0.0) / total for s in styles], np.float32)
    return net, weights


def _learned_chunks(
    net: Any,
    wave: np.ndarray,
    head: Head,
    weights: np.ndarray | None,
    fps: float,
    frames: int,
    seed: int,
    block: int,
) -> Iterator[np.ndarray]:
    """The model's vertices (t, V, 3) in consecutive chunks, resampled from its frame rate to
    ``frames`` frames at ``fps`` (linear interpolation) when they differ."""
    from talkmesh.models.onnx import OnnxModel

    n_in = net.default_frames(len(wave))
    if isinstance(net, OnnxModel):  # numpy in and out: no torch
        chunks = net.frames(np.asarray(wave), head.template, weights, n_in, block)
    else:
        chunks = _torch_chunks(net, wave, head, weights, n_in, seed, block)
    if abs(fps - net.motion_fps) <= 1e-6:
        yield from chunks
        return
    pos = np.clip(np.arange(frames) / fps * net.motion_fps, 0, n_in - 1)
    i0 = np.floor(pos).astype(int)
    i1 = np.minimum(i0 + 1, n_in - 1)
    w = (pos - i0)[:, None, None].astype(np.float32)
    buf, start, j = np.empty((0, head.num_vertices, 3), np.float32), 0, 0  # buf: frames start..
    for c in chunks:
        buf = np.concatenate([buf, c])
        known = start + len(buf)
        end = frames if known >= n_in else int(np.searchsorted(i1, known, "left"))
        if end > j:
            a, b, x = i0[j:end] - start, i1[j:end] - start, w[j:end]
            yield buf[a] * (1 - x) + buf[b] * x
            j = end
        if j < frames:
            buf, start = buf[i0[j] - start :], int(i0[j])
