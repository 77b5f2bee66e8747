"""Headless rendering of talking faces to images, mp4 videos and contact sheets.

:class:`~talkmesh.output.raster.Renderer` draws frames with one OpenGL context (EGL; Mesa's llvmpipe
is enough); :mod:`talkmesh.output.video` encodes them with ffmpeg; :mod:`talkmesh.output.labels`
draws the captions. This module puts them together: :func:`render_video`,
:func:`render_side_by_side`, :func:`contact_sheet`, and :func:`render_avatar_video` for a user's
avatar (:class:`~talkmesh.output.scene.AvatarScene`: all its meshes, in their base colours).

The camera looks down -z at the bounding box of a reference mesh (the template or the first frame)
so the face fills the image.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from talkmesh.animation import Animation
from talkmesh.blas import one_blas_thread  # posing: many small products (talkmesh.blas)
from talkmesh.constants import SAMPLE_RATE
from talkmesh.errors import TalkmeshError
from talkmesh.face.geometry import winding_sign
from talkmesh.face.head_motion import pose_vertices
from talkmesh.output.labels import TextOverlay, import_pil
from talkmesh.output.media import VIDEO_SIZE, VIDEO_SUFFIXES, video_size
from talkmesh.output.raster import Renderer, create_context, head_vertex_colors
from talkmesh.output.scene import AvatarScene
from talkmesh.output.video import VIDEO_CRF, atomic_output, check_output, write_video

if TYPE_CHECKING:
    import moderngl

__all__ = [
    "Renderer",
    "contact_sheet",
    "create_context",
    "head_vertex_colors",
    "render_avatar_video",
    "render_side_by_side",
    "render_video",
    "winding_sign",
]

SHEET_GUTTER = 4  # pixels between contact sheet cells


def posed(anim: Animation, t: int) -> np.ndarray:
    """(V, 3) vertices of frame ``t`` where the head is: moved by its ``head_pose``, if any."""
    if anim.head_pose is None:
        return anim.vertices[t]
    return pose_vertices(anim.vertices[t : t + 1], anim.head_pose[t : t + 1], anim.pose_frame)[0]


def _renderer_for(
    anim: Animation,
    size: int | tuple[int, int],
    vertex_colors: np.ndarray | None = None,
    ctx: moderngl.Context | None = None,
    camera: str = "front",
) -> Renderer:
    """A renderer aimed at the animation's template (or first frame), in the head's colours."""
    template = anim.template
    reference = (
        template if template is not None and template.shape == anim.vertices.shape[1:] else None
    )
    if vertex_colors is None:
        vertex_colors = head_vertex_colors(anim.num_vertices)
    return Renderer(
        anim.faces,
        size,
        vertex_colors=vertex_colors,
        reference=anim.vertices[0] if reference is None else reference,
        ctx=ctx,
        camera=camera,
    )


def render_video(
    anim: Animation,
    path: str | os.PathLike,
    size: int | tuple[int, int] = VIDEO_SIZE,
    *,
    vertex_colors: np.ndarray | None = None,
    inputs: Iterable[str | os.PathLike] = (),
    crf: int = VIDEO_CRF,
    progress: bool = False,
    camera: str = "front",
) -> Path:
    """Renders an animation to an mp4 (H.264 yuv420p, with AAC audio if it has audio).

    Args:
        anim: the animation; its audio is padded or trimmed to the duration of its frames.
        path: output .mp4 (or .m4v/.mov); replaced only once the video is complete.
        size: frame size in pixels (even): an int for a square, or (width, height).
        vertex_colors: optional (V, 3) sRGB colours; default the bundled head's part colours
            when the mesh is that head, else skin.
        inputs: files the caller read from; writing over one of them is refused.
        crf: H.264 quality (lower is better; 18 is visually lossless).
        progress: show a progress bar on stderr.
        camera: "front" or "three-quarter" (``raster.CAMERAS``).

    Returns:
        The path written.
    """
    size, inputs = video_size(size), list(inputs)
    check_output(path, VIDEO_SUFFIXES, inputs)
    with _renderer_for(anim, size, vertex_colors, camera=camera) as renderer:
        frames = (renderer.draw(posed(anim, t)) for t in range(anim.num_frames))
        return write_video(
            frames,
            anim.num_frames,
            size,
            anim.fps,
            path,
            audio=anim.audio,
            sample_rate=anim.sample_rate,
            audio_file=anim.audio_file,
            inputs=inputs,
            crf=crf,
            progress=progress,
        )


def avatar_renderer(
    scene: AvatarScene,
    size: int | tuple[int, int],
    ctx: moderngl.Context | None = None,
    camera: str = "front",
) -> Renderer:
    """A renderer of the avatar's triangles in its colours, aimed at its head at rest."""
    return Renderer(
        scene.faces,
        size,
        vertex_colors=scene.colors,
        reference=scene.vertices(0),
        ctx=ctx,
        camera=camera,
        focus=scene.focus,
    )


def render_avatar_video(
    scene: AvatarScene,
    path: str | os.PathLike,
    size: int | tuple[int, int] = VIDEO_SIZE,
    *,
    audio: np.ndarray | None = None,
    sample_rate: int = SAMPLE_RATE,
    audio_file: str | os.PathLike | None = None,
    inputs: Iterable[str | os.PathLike] = (),
    crf: int = VIDEO_CRF,
    progress: bool = False,
    camera: str = "front",
) -> Path:
    """Renders an avatar's clip (:class:`~talkmesh.output.scene.AvatarScene`) to an mp4: every
    frame of the clip, all its meshes morphed and skinned as a glTF viewer poses them, with
    ``audio`` (or ``audio_file``) muxed as :func:`render_video` does.

    Returns:
        The path written.
    """
    size, inputs = video_size(size), list(inputs)
    check_output(path, VIDEO_SUFFIXES, inputs)
    with one_blas_thread(), avatar_renderer(scene, size, camera=camera) as renderer:
        frames = (renderer.draw(scene.vertices(t)) for t in range(scene.num_frames))
        return write_video(
            frames,
            scene.num_frames,
            size,
            scene.fps,
            path,
            audio=audio,
            sample_rate=sample_rate,
            audio_file=audio_file,
            inputs=inputs,
            crf=crf,
            progress=progress,
        )


def render_side_by_side(
    anims: Sequence[Animation],
    labels: Sequence[str],
    path: str | os.PathLike,
    size: int | tuple[int, int] = VIDEO_SIZE,
    *,
    inputs: Iterable[str | os.PathLike] = (),
    crf: int = VIDEO_CRF,
    progress: bool = False,
    camera: str = "front",
) -> Path:
    """Renders animations next to each other, each labelled, into one mp4.

    Every panel is ``size`` and is sampled at the first animation's frame rate; shorter animations
    hold their last frame until the longest ends. The audio is that of the first animation that
    has audio, padded or trimmed to the video.

    Args:
        anims: the N animations, left to right (their meshes may differ).
        labels: N labels drawn at the top of the panels.
        path: output .mp4 (or .m4v/.mov); replaced only once the video is complete.
        size: panel size in pixels (even): an int for a square, or (width, height).
        inputs: files the caller read from; writing over one of them is refused.
        crf: H.264 quality.
        progress: show a progress bar on stderr.
        camera: "front" or "three-quarter" (``raster.CAMERAS``).

    Returns:
        The path written; the video is (N * width) x height.
    """
    if not anims or len(anims) != len(labels):
        raise TalkmeshError(f"need one label per animation, got {len(anims)} and {len(labels)}")
    (width, height), inputs = video_size(size), list(inputs)
    check_output(path, VIDEO_SUFFIXES, inputs)
    fps = anims[0].fps
    num_frames = max(max(1, round(a.duration * fps)) for a in anims)
    overlays = [TextOverlay(label, width, height, top=True) for label in labels]
    sound = next((a for a in anims if a.audio is not None), None)
    ctx = create_context()
    renderers: list[Renderer] = []
    try:
        renderers = [_renderer_for(a, (width, height), ctx=ctx, camera=camera) for a in anims]
        canvas = np.empty((height, width * len(anims), 4), dtype=np.uint8)

        def frames() -> Iterator[np.ndarray]:
            for i in range(num_frames):
                for j, (anim, renderer) in enumerate(zip(anims, renderers, strict=True)):
                    t = min(round(i * anim.fps / fps), anim.num_frames - 1)
                    panel = canvas[:, j * width : (j + 1) * width]
                    panel[:] = renderer.draw(posed(anim, t))
                    overlays[j].draw(panel)
                yield canvas

        return write_video(
            frames(),
            num_frames,
            (canvas.shape[1], height),
            fps,
            path,
            audio=None if sound is None else sound.audio,
            sample_rate=SAMPLE_RATE if sound is None else sound.sample_rate,
            audio_file=None if sound is None else sound.audio_file,
            inputs=inputs,
            crf=crf,
            progress=progress,
        )
    finally:
        for renderer in renderers:
            renderer.close()
        ctx.release()


def contact_sheet(
    anim: Animation,
    path: str | os.PathLike,
    n: int = 8,
    cols: int = 4,
    size: int = 256,
    *,
    inputs: Iterable[str | os.PathLike] = (),
    camera: str = "front",
) -> np.ndarray:
    """Saves a PNG grid of ``n`` evenly spaced frames, each labelled with its time.

    Returns:
        (H, W, 3) uint8 sheet: ceil(n / cols) rows of ``size`` pixel cells, with thin gutters.
    """
    if n < 1 or cols < 1:
        raise TalkmeshError(f"a contact sheet needs n >= 1 and cols >= 1, got n={n}, cols={cols}")
    inputs = list(inputs)
    check_output(path, (".png",), inputs)
    Image, _, _ = import_pil()
    picks = np.linspace(0, anim.num_frames - 1, min(n, anim.num_frames)).round().astype(int)
    cols = min(cols, len(picks))
    rows = -(-len(picks) // cols)
    step = size + SHEET_GUTTER
    sheet = np.full((rows * step + SHEET_GUTTER, cols * step + SHEET_GUTTER, 3), 255, np.uint8)
    image = np.empty((size, size, 3), dtype=np.uint8)
    with _renderer_for(anim, size, camera=camera) as renderer:
        for k, t in enumerate(picks):
            y, x = SHEET_GUTTER + (k // cols) * step, SHEET_GUTTER + (k % cols) * step
            cell = sheet[y : y + size, x : x + size]
            cell[:] = renderer.draw(posed(anim, t), image)
            TextOverlay(f"{t / anim.fps:.2f} s", size, size, top=False).draw(cell)
    with atomic_output(path, (".png",), inputs) as tmp:
        Image.fromarray(sheet).save(tmp, format="PNG")
    return sheet
