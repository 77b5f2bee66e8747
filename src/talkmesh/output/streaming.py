"""Writing an :class:`~talkmesh.animation.AnimationBlocks` to files as its frames are made, so that
long audio never holds all its vertices: ``.npz``, ``.weights.npz`` and ``.npy`` stream
(``BLOCK_WRITERS``), the ARKit weight files (``.csv``, ``.json``) keep only the weights; every
other format is written from the collected :class:`~talkmesh.animation.Animation` afterwards."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import replace
from pathlib import Path

import numpy as np

from talkmesh.animation import Animation, AnimationBlocks
from talkmesh.output import write_animation
from talkmesh.output.atomic import remove_stale_temps, temp_prefix, writing
from talkmesh.output.files import exists_error, move_file
from talkmesh.output.media import VIDEO_SIZE
from talkmesh.output.npy import NpyWriter, NpzWriter

WEIGHT_SUFFIXES = (".csv", ".json")  # formats of the ARKit weights alone, (T, 52)
BLOCK_WRITERS: dict[str, Callable[[AnimationBlocks, int, Path], NpzWriter | NpyWriter]] = {
    ".npz": NpzWriter,
    ".npy": NpyWriter,
    ".weights.npz": lambda header, frames, path: NpzWriter(header, frames, path, motion="weights"),
}


def _format(path: Path) -> str:
    """The registry key of ``path``: a compound suffix (``.weights.npz``) or its suffix."""
    compound = "".join(path.suffixes[-2:]).lower()
    return compound if compound in BLOCK_WRITERS else path.suffix.lower()


def save_blocks(
    anim: AnimationBlocks,
    paths: list[Path],
    *,
    overwrite: bool,
    size: int = VIDEO_SIZE,
    camera: str = "front",
    keep: bool = False,
) -> Animation | None:
    """Write ``anim`` to every path (the extension picks the format) in one pass over its blocks.

    Streaming formats are written to a temporary beside the target as blocks arrive and renamed
    into place at the end (never replacing a file unless ``overwrite``); the others are written
    by :func:`~talkmesh.output.write_animation` (videos seen from ``camera``) from the collected
    animation, which is returned (None when every format streamed, unless ``keep``). OSErrors
    are one-line TalkmeshErrors naming the file.
    """
    streamed = [p for p in paths if _format(p) in BLOCK_WRITERS]
    weighted = [p for p in paths if p.suffix.lower() in WEIGHT_SUFFIXES and anim.weight_names]
    others = [p for p in paths if p not in streamed and p not in weighted]
    weights: list[np.ndarray] = []
    poses: list[np.ndarray] = []  # the head's, for the weight formats' head columns
    temps: list[Path] = []
    with ExitStack() as stack:
        writers = []
        for p in streamed:
            with writing(p):
                if p.exists() and not overwrite:
                    raise exists_error(p)
                p.parent.mkdir(parents=True, exist_ok=True)
                remove_stale_temps(p.parent)
                fd, tmp = tempfile.mkstemp(dir=p.parent, prefix=temp_prefix(), suffix=p.suffix)
                os.close(fd)
                os.chmod(tmp, 0o666 & ~_umask())  # mkstemp's 0600 would outlive the rename
            temps.append(Path(tmp))
            stack.callback(Path(tmp).unlink, missing_ok=True)
            with writing(p):  # the header and the audio are written now: disk full names p
                writers.append((p, BLOCK_WRITERS[_format(p)](anim, anim.num_frames, temps[-1])))

        def tee() -> Iterator[Animation]:
            for block in anim.blocks:
                for p, w in writers:
                    with writing(p):
                        w.write(block)
                if weighted and block.weights is not None:
                    weights.append(block.weights)
                if weighted and block.head_pose is not None:
                    poses.append(block.head_pose)
                yield block

        whole = None
        if others or keep:
            whole = replace(anim, blocks=tee()).collect()
        else:
            for _ in tee():
                pass
        for (p, w), tmp in zip(writers, temps, strict=True):
            with writing(p):
                w.close()
                move_file(tmp, p, overwrite)
    for p in others:
        assert whole is not None
        write_animation(whole, p, overwrite=overwrite, size=size, camera=camera)
    if weighted:  # the weight formats read nothing else: no vertices needed
        curves = Animation(
            vertices=np.zeros((anim.num_frames, 0, 3), np.float32),
            faces=np.zeros((0, 3), np.int32),
            fps=anim.fps,
            weights=np.concatenate(weights),
            weight_names=anim.weight_names,
            phones=anim.phones,
            head_pose=np.concatenate(poses) if poses else None,
        )
        for p in weighted:
            write_animation(whole or curves, p, overwrite=overwrite, size=size, camera=camera)
    return whole


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask
