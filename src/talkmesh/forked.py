"""Work in a forked child: its memory given back when it exits, its library state left behind.

:func:`in_child` runs ``fn(*args)`` in a child forked from this process and brings back the tuple
of plain arrays it returns (``np.save`` without pickles through a pipe). The dense rig's mesh
simplification runs there so that its working set does not stay in the parent's heap; espeak-ng's
synthesis runs there because its wave generator keeps state from one text to the next.
"""

from __future__ import annotations

import io
import os

import numpy as np


def in_child(fn, *args) -> tuple[np.ndarray, ...] | None:
    """``fn(*args)`` (a tuple of plain arrays) computed in a forked child; None where there is
    no fork (not POSIX) or the child failed."""
    if not hasattr(os, "fork"):
        return None
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: compute, send the arrays, exit at once (no cleanup of the parent's)
        code = 1
        try:
            os.close(read)
            buffer = io.BytesIO()  # np.save needs a file it can seek: a pipe is none
            for array in fn(*args):
                np.save(buffer, np.ascontiguousarray(array), allow_pickle=False)
            with os.fdopen(write, "wb") as f:
                f.write(buffer.getbuffer())
            code = 0
        finally:
            os._exit(code)
    os.close(write)
    with os.fdopen(read, "rb") as f:
        data = f.read()
    _, status = os.waitpid(pid, 0)
    if status != 0:
        return None
    stream = io.BytesIO(data)
    out = []
    while stream.tell() < len(data):
        out.append(np.load(stream, allow_pickle=False))
    return tuple(out)
