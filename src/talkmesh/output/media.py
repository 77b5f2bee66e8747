"""What the renderer writes: the video suffixes, the default size and the size checks.

A leaf module (it imports only :mod:`talkmesh.errors`), so that :mod:`talkmesh.output` can name the
video suffixes without loading the renderer.
"""

from __future__ import annotations

from talkmesh.errors import TalkmeshError

VIDEO_SUFFIXES = (".mp4", ".m4v", ".mov")  # written by the renderer (H.264 + AAC in MP4)
VIDEO_SIZE = 512  # pixels a side of rendered videos unless asked otherwise
MIN_SIZE, MAX_SIZE = 16, 4096  # pixels a side of any rendered image


def size_pair(size: int | tuple[int, int]) -> tuple[int, int]:
    """``size`` (an int for a square, or (width, height)) -> (width, height), checked."""
    width, height = (size, size) if isinstance(size, int) else (int(size[0]), int(size[1]))
    if not (MIN_SIZE <= width <= MAX_SIZE and MIN_SIZE <= height <= MAX_SIZE):
        raise TalkmeshError(
            f"image size must be {MIN_SIZE} to {MAX_SIZE} pixels a side, got {width}x{height}"
        )
    return width, height


def video_size(size: int | tuple[int, int]) -> tuple[int, int]:
    """:func:`size_pair`, also checking both sides are even, as H.264 needs."""
    width, height = size_pair(size)
    if width % 2 or height % 2:
        raise TalkmeshError(f"video width and height must be even for H.264, got {width}x{height}")
    return width, height
