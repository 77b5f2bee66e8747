"""OBJ sequences: one Wavefront OBJ per frame (positions in metres)."""

from __future__ import annotations

from pathlib import Path

from talkmesh.animation import Animation


def obj_frame_path(path: Path, frame: int, num_frames: int) -> Path:
    """Where frame ``frame`` of an OBJ sequence saved as ``path`` goes: ``talk_00042.obj``."""
    width = max(5, len(str(num_frames - 1)))
    return path.with_name(f"{path.stem}_{frame:0{width}d}.obj")


def export_obj(anim: Animation, path: Path) -> None:
    """One OBJ per frame, ``<stem>_00000.obj``... next to ``path`` (positions in metres)."""
    num_vertices = anim.num_vertices
    # One %-format over the whole array runs in C: no per-vertex Python loop.
    faces_text = ("f %d %d %d\n" * len(anim.faces)) % tuple((anim.faces + 1).ravel().tolist())
    vertex_format = "v %.6f %.6f %.6f\n" * num_vertices
    for t in range(anim.num_frames):
        header = f"# talkmesh frame {t} of {anim.num_frames} at {anim.fps:g} fps\n"
        vertices_text = vertex_format % tuple(anim.vertices[t].ravel().tolist())
        obj_frame_path(path, t, anim.num_frames).write_text(header + vertices_text + faces_text)
