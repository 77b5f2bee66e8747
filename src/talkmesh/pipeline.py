"""Speech in, talking face out: the public ``animate`` function the CLI and users call."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from talkmesh.animation import Animation
from talkmesh.arkit import ARKIT_NAMES
from talkmesh.assets import Head, load_head
from talkmesh.audio import SAMPLE_RATE, load_audio
from talkmesh.errors import TalkmeshError
from talkmesh.lipsync import SpeakingStyle, phones_to_weights
from talkmesh.phonemes import Phone, recognize_phones

DEFAULT_FPS = 30.0
MAX_FPS = 240.0
MODELS = ("procedural",)


def num_frames_for(num_samples: int, sr: int, fps: float) -> int:
    """Frames covering the audio (at least one)."""
    return max(1, int(round(num_samples / sr * fps)))


def animate(
    audio: str | Path | np.ndarray,
    *,
    head: Head | None = None,
    text: str | None = None,
    phones: list[Phone] | None = None,
    fps: float = DEFAULT_FPS,
    seed: int = 0,
    style: SpeakingStyle | None = None,
    model: str = "procedural",
) -> Animation:
    """Animate a face from speech.

    Args:
        audio: a speech file (any format ffmpeg reads) or a (S,) float32 waveform at 16 kHz.
        head: the face to animate (default: the bundled default identity).
        text: the transcript, if known: phones are then force-aligned instead of recognised.
        phones: timed phones, if already known (skips recognition).
        fps: output frame rate.
        seed: seed of the audio-independent motion (blinks, brow drift, gaze).
        style: the speaker's style.
        model: the animator (``procedural``; learned models plug in here).

    Returns:
        An :class:`Animation` with vertices (T, V, 3), the audio and the ARKit weights (T, 52).
    """
    if model not in MODELS:
        raise TalkmeshError(f"unknown model '{model}': available models are {', '.join(MODELS)}")
    if not (0 < fps <= MAX_FPS):
        raise TalkmeshError(f"--fps must be in (0, {MAX_FPS:g}], got {fps:g}")
    head = head or load_head()
    wave = load_audio(audio) if isinstance(audio, (str, Path)) else np.asarray(audio, np.float32)
    if wave.ndim != 1 or not len(wave):
        raise TalkmeshError("audio must be a non-empty mono waveform")
    if phones is None:
        phones = recognize_phones(wave, SAMPLE_RATE, text=text)
    num_frames = num_frames_for(len(wave), SAMPLE_RATE, fps)
    weights = phones_to_weights(
        phones, num_frames, fps, audio=wave, sr=SAMPLE_RATE, style=style, seed=seed
    )
    return Animation(
        vertices=head.vertices_from_weights(weights),
        faces=head.faces,
        fps=fps,
        audio=wave,
        sample_rate=SAMPLE_RATE,
        weights=weights,
        weight_names=list(ARKIT_NAMES),
        template=head.template,
        basis=head.blendshapes,
    )
