"""Keeping a long run's memory flat: a fixed malloc mmap threshold.

glibc's malloc serves a request of at least its mmap threshold (128 kB to start with) with a
mapping of its own, given back to the system when freed; but each time such a block is freed it
raises the threshold to that block's size (up to 32 MB). After the first large temporary is
freed, the buffers that every block of a long run allocates and frees (feature windows, model
activations, frames) come from the heap instead, where freed space fragments and stays resident:
`talkmesh animate` on the bundled model swung between 700 and 805 MB over 6 minutes of audio and
its peak grew with the length. Fixing the threshold (which stops the raising) keeps those buffers
mapped and returned: 640-680 MB, peak 702 MB on the same run (docs/results/long-audio.md).
"""

from __future__ import annotations

import ctypes
import sys

M_MMAP_THRESHOLD = -3  # mallopt's parameter number, from glibc's malloc.h
MMAP_THRESHOLD = 128 * 1024  # glibc's own starting value, now kept


def fix_mmap_threshold(threshold: int = MMAP_THRESHOLD) -> bool:
    """Fix this process's malloc mmap threshold; False where the C library is not glibc."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # musl and others: nothing to fix
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    return bool(mallopt(M_MMAP_THRESHOLD, threshold))


def give_back() -> bool:
    """Return the heap's free memory to the system (glibc's ``malloc_trim``); False where the C
    library is not glibc. A server calls it after a job, so that its idle memory is what it holds,
    not the largest job's freed working set kept in the arena of the thread that ran it."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        malloc_trim = ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return False
    malloc_trim.argtypes = [ctypes.c_size_t]
    return bool(malloc_trim(0))
