"""Motion out of talkmesh: video (:mod:`.render`) and the animators' file formats (:mod:`.formats`)."""

from __future__ import annotations

from pathlib import Path

from talkmesh.errors import TalkmeshError

VIDEO_SUFFIXES = (".mp4",)


def write_animation(anim, path: Path, *, overwrite: bool, size: int = 512) -> None:
    """Write ``anim`` to ``path``: a video for .mp4, else the exporter for the extension."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() in VIDEO_SUFFIXES:
        from talkmesh.output.render import render_video

        if path.exists() and not overwrite:
            raise TalkmeshError(f"{path} already exists: choose another -o or pass --overwrite")
        render_video(anim, path, size=size)
    else:
        from talkmesh.output.formats import save_animation

        save_animation(anim, path, overwrite=overwrite)
