"""What ``POST /animate`` and ``GET /head.glb`` of ``talkmesh serve`` compute: the audio's kind
from its first bytes, an animated file as ``talkmesh animate`` writes it, the neutral head."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import load_head

# The first bytes of the audio files /animate takes, and the suffix the audio reader needs.
AUDIO_SIGNATURES = (
    (b"RIFF", ".wav"),
    (b"RF64", ".wav"),
    (b"fLaC", ".flac"),
    (b"OggS", ".ogg"),
    (b"ID3", ".mp3"),
)


def audio_suffix(head: bytes) -> str | None:
    """The file suffix of wav/flac/ogg/mp3 audio from its first bytes; None for anything else."""
    for magic, suffix in AUDIO_SIGNATURES:
        if head.startswith(magic):
            return suffix
    if len(head) >= 2 and head[0] == 0xFF and head[1] & 0xE0 == 0xE0:  # an MPEG frame sync
        return ".mp3"
    return None


class RenderError(Exception):
    """Writing the result failed: the server's fault (e.g. no renderer), not the upload's."""


def animate_file(audio: Path, out: Path, model: str, max_seconds: float | None = None) -> None:
    """Animate ``audio`` with ``model`` into ``out`` (.glb or .mp4), as ``talkmesh animate``;
    audio longer than ``max_seconds`` is refused (:class:`AudioTooLong`) while it is decoded."""
    from talkmesh.heap import give_back

    try:
        _animate_file(audio, out, model, max_seconds)
    finally:
        give_back()  # the job's freed memory back to the system: an idle server holds its own


def _animate_file(audio: Path, out: Path, model: str, max_seconds: float | None) -> None:
    from talkmesh.audio.loading import load_audio
    from talkmesh.output import write_animation
    from talkmesh.pipeline import animate

    anim = animate(load_audio(audio, max_seconds=max_seconds), model=model)
    anim.audio_file = audio  # an .mp4 keeps the upload's own sound, not the 16 kHz copy
    try:
        write_animation(anim, out, overwrite=True)
    except TalkmeshError as e:
        raise RenderError(str(e)) from None


def neutral_head_glb() -> bytes:
    """The bundled head as .glb: its 52 ARKit blendshapes as morph targets, one neutral frame,
    and the video renderer's colours as vertex colours (irises and pupils, lips, teeth)."""
    from talkmesh.animation import Animation
    from talkmesh.face.look import head_colors
    from talkmesh.output.formats import save_animation

    head = load_head()
    anim = Animation(
        vertices=head.template[None],
        faces=head.faces,
        fps=30.0,
        weights=np.zeros((1, len(ARKIT_NAMES)), np.float32),
        weight_names=list(ARKIT_NAMES),
        template=head.template,
        basis=head.blendshapes,
        colors=head_colors(head),
    )
    with tempfile.TemporaryDirectory(prefix="talkmesh-serve-") as tmp:
        (path,) = save_animation(anim, Path(tmp) / "head.glb")
        return path.read_bytes()
