"""Motion out of talkmesh: video (:mod:`.render`) and the animators' file formats (:mod:`.formats`).

:func:`write_animation` picks between them by the file's extension.
"""

from __future__ import annotations

from pathlib import Path

from talkmesh.errors import TalkmeshError
from talkmesh.output.media import VIDEO_SIZE, VIDEO_SUFFIXES

__all__ = ["VIDEO_SIZE", "VIDEO_SUFFIXES", "output_name", "write_animation"]


def output_name(path: Path, num_frames: int) -> str:
    """How to name what writing ``num_frames`` frames to ``path`` made: the path itself, or for an
    OBJ sequence its first and last files (``talk_00000.obj ... talk_00089.obj``)."""
    if path.suffix.lower() != ".obj" or path.is_dir():
        return str(path)
    from talkmesh.output.obj import obj_frame_path

    first = obj_frame_path(path, 0, num_frames)
    if num_frames < 2:
        return str(first)
    return f"{first} ... {obj_frame_path(path, num_frames - 1, num_frames).name}"


def write_animation(
    anim, path: Path, *, overwrite: bool, size: int = VIDEO_SIZE, camera: str = "front"
) -> None:
    """Write ``anim`` to ``path``: a video for ``VIDEO_SUFFIXES`` (seen from ``camera``: "front"
    or "three-quarter"), else the extension's exporter.

    Any OSError (parent is a file, permission denied, disk full, read-only folder) is a one-line
    :class:`TalkmeshError` naming ``path``; temporaries left in the folder by killed writers go.
    """
    from talkmesh.output.atomic import remove_stale_temps, writing

    with writing(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temps(path.parent)
        _write(anim, path, overwrite=overwrite, size=size, camera=camera)


def _write(anim, path: Path, *, overwrite: bool, size: int, camera: str) -> None:
    if path.suffix.lower() in VIDEO_SUFFIXES:
        from talkmesh.output.render import render_video

        if path.exists() and not overwrite:
            raise TalkmeshError(f"{path} already exists: choose another -o or pass --overwrite")
        render_video(anim, path, size=size, camera=camera)
    else:
        from talkmesh.output.formats import save_animation

        save_animation(anim, path, overwrite=overwrite)
