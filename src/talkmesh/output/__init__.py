"""Motion out of talkmesh: video (:mod:`.render`) and the animators' file formats (:mod:`.formats`).

:func:`write_animation` picks between them by the file's extension.
"""

from __future__ import annotations

from pathlib import Path

from talkmesh.errors import TalkmeshError

VIDEO_SUFFIXES = (".mp4", ".m4v", ".mov")  # written by the renderer (H.264 + AAC in MP4)
VIDEO_SIZE = 512  # pixels a side of rendered videos unless asked otherwise


def write_animation(anim, path: Path, *, overwrite: bool, size: int = VIDEO_SIZE) -> None:
    """Write ``anim`` to ``path``: a video for ``VIDEO_SUFFIXES``, else the extension's exporter."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() in VIDEO_SUFFIXES:
        from talkmesh.output.render import render_video

        if path.exists() and not overwrite:
            raise TalkmeshError(f"{path} already exists: choose another -o or pass --overwrite")
        render_video(anim, path, size=size)
    else:
        from talkmesh.output.formats import save_animation

        save_animation(anim, path, overwrite=overwrite)
