"""Safe writes: temporary names that say who made them, stale ones cleared, OSErrors as one line.

Every writer puts its work in a hidden ``.talkmesh-<pid>-*`` file or folder next to the target and
renames it at the end. A process killed in between (kill -9, power loss) leaves that temporary
behind; the next write into the same folder removes the ones whose process is gone.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from talkmesh.errors import TalkmeshError, os_error_message

TEMP_MARK = ".talkmesh-"
# A temporary without a process id in its name is stale once it is this old (seconds).
ANONYMOUS_STALE_S = 3600.0


def temp_prefix() -> str:
    """The prefix of this process's temporary names (``.talkmesh-<pid>-``)."""
    return f"{TEMP_MARK}{os.getpid()}-"


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return pid < 2**22  # another user's process (or a pid no system hands out)
    return True


def _stale(entry: Path, now: float) -> bool:
    pid_text = entry.name[len(TEMP_MARK) :].split("-", 1)[0]
    if pid_text.isdigit():
        return not _alive(int(pid_text))
    try:
        return now - entry.lstat().st_mtime > ANONYMOUS_STALE_S
    except OSError:
        return False


def remove_stale_temps(folder: Path) -> list[Path]:
    """Delete the ``.talkmesh-*`` temporaries in ``folder`` left by processes that no longer run.

    Returns what was removed; anything that cannot be inspected or removed is left alone.
    """
    removed: list[Path] = []
    try:
        entries = [e for e in Path(folder).iterdir() if e.name.startswith(TEMP_MARK)]
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        if not _stale(entry, now):
            continue
        try:
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()
        except OSError:
            continue
        removed.append(entry)
    return removed


@contextmanager
def writing(path: Path) -> Iterator[None]:
    """Turn any OSError inside the block into a one-line :class:`TalkmeshError` naming ``path``
    (parent is a file, permission denied, disk full, read-only file system)."""
    try:
        yield
    except OSError as e:
        raise TalkmeshError(os_error_message(e, path)) from None
