"""MeshTalk's applications (paper Sec. 4.3-4.4) on files: ``talkmesh retarget`` and ``talkmesh dub``.

Both read a MeshTalk expression-space release (``talkmesh train configs/meshtalk_synth.yaml``).
Re-targeting encodes an animation with its audio and decodes the codes on another neutral mesh of
the same topology; dubbing encodes the original animation with new audio, so the upper face
(blinks, brows) comes from the original and the mouth follows the new speech.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from talkmesh.animation import Animation
from talkmesh.audio.loading import SAMPLE_RATE, load_audio
from talkmesh.errors import TalkmeshError


def _inputs(model: str | Path, anim: str | Path, source_template: str | Path | None):
    import torch

    from talkmesh.face.assets import load_head, read_mesh_vertices
    from talkmesh.models.release import load_model
    from talkmesh.output.formats import load_animation

    system = load_model(model, family="meshtalk")
    net = system.model
    V = net.config.num_vertices
    source = load_animation(anim, fps=net.config.fps)
    if source.num_vertices != V:
        raise TalkmeshError(
            f"{anim}: {source.num_vertices} vertices, but the model animates {V}-vertex meshes"
        )
    if source_template is not None:
        template = read_mesh_vertices(source_template)
    elif source.template is not None:
        template = source.template
    else:
        template = load_head().template  # the bundled default face
    if template.shape != (V, 3):
        raise TalkmeshError(f"the source's neutral mesh has {len(template)} vertices, not {V}")
    verts = torch.from_numpy(np.ascontiguousarray(source.vertices, np.float32))[None]
    return torch, net, source, verts, torch.from_numpy(np.asarray(template, np.float32))[None]


def _audio(torch, path: str | Path):
    wave = load_audio(path)
    if len(wave) < SAMPLE_RATE // 10:
        raise TalkmeshError(f"{path}: under 0.1 s of audio: nothing to animate")
    return wave, torch.from_numpy(wave)[None]


def _result(vertices, source: Animation, net, wave: np.ndarray, template: np.ndarray) -> Animation:
    return Animation(
        vertices=vertices,
        faces=source.faces,
        fps=net.config.fps,
        audio=wave,
        sample_rate=SAMPLE_RATE,
        template=template,
    )


def retarget(
    model: str | Path,
    anim: str | Path,
    audio: str | Path,
    template: str | Path,
    *,
    source_template: str | Path | None = None,
) -> Animation:
    """The animation in ``anim`` (spoken in ``audio``) on the neutral mesh in ``template``."""
    from talkmesh.face.assets import read_mesh_vertices

    torch, net, source, verts, src_template = _inputs(model, anim, source_template)
    target = read_mesh_vertices(template)
    if target.shape != (net.config.num_vertices, 3):
        raise TalkmeshError(
            f"{template}: {len(target)} vertices, but the model animates "
            f"{net.config.num_vertices}-vertex meshes"
        )
    wave, audio_t = _audio(torch, audio)
    out = net.retarget(verts, src_template, audio_t, torch.from_numpy(target)[None])[0].numpy()
    return _result(out, source, net, wave, target)


def dub(
    model: str | Path,
    anim: str | Path,
    audio: str | Path,
    *,
    source_template: str | Path | None = None,
) -> Animation:
    """The animation in ``anim`` with its mouth re-driven by the speech in ``audio``."""
    torch, net, source, verts, template = _inputs(model, anim, source_template)
    wave, audio_t = _audio(torch, audio)
    out = net.dub(verts, template, audio_t)[0].numpy()
    return _result(out, source, net, wave, template[0].numpy())
