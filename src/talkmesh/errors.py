"""User-facing errors and warnings.

Anything the user can fix (a missing file, a wrong sample rate, a mesh with the wrong vertex count)
raises :class:`TalkmeshError` with one line that says what is wrong and what to do. The CLI prints
that line and exits non-zero; it never shows a traceback for these.
"""

import errno
from pathlib import Path


class TalkmeshError(Exception):
    """An error caused by the user's input, with a one-line message that says how to fix it."""


class MissingDependencyError(TalkmeshError):
    """An optional dependency is not installed."""

    def __init__(self, package: str, extra: str, purpose: str):
        super().__init__(
            f"{purpose} needs the '{package}' package: install it with "
            f"`pip install 'talkmesh[{extra}]'` (or `make setup`)."
        )


class TalkmeshWarning(UserWarning):
    """Something was skipped or approximated; the run goes on (the CLI prints one line)."""


def os_error_message(e: OSError, path: object = None, action: str = "write") -> str:
    """One line for an OSError: the path it concerns, the system's reason and what to do."""
    where = path if path is not None else (e.filename if e.filename is not None else "")
    reason = e.strerror or str(e) or type(e).__name__
    hint = {
        "ENOSPC": "free some space or write elsewhere",
        "EACCES": "check the folder's permissions or write elsewhere",
        "EPERM": "check the folder's permissions or write elsewhere",
        "EROFS": "the file system is read-only: write elsewhere",
        "ENOTDIR": "a part of the path is a file, not a folder: choose another path",
        "EEXIST": "a part of the path is a file, not a folder: choose another path",
    }.get(errno.errorcode.get(e.errno or 0, ""), "check the path")
    return f"{where}: cannot {action} it ({reason}): {hint}" if where else f"{reason}: {hint}"


def resolved(path: Path) -> Path:
    """``path.resolve()``, with a symbolic link loop (which pathlib reports as a RuntimeError or
    an OSError) as a one-line :class:`TalkmeshError` naming the path."""
    try:
        return path.resolve()
    except (RuntimeError, OSError) as e:
        if isinstance(e, OSError) and e.errno != errno.ELOOP:
            raise
        raise TalkmeshError(
            f"{path}: a symbolic link loop (the link leads back to itself): fix or remove the link"
        ) from None


def warning_line(message: object, category: type[Warning]) -> str:
    """A warning as the CLI prints it: ``talkmesh: warning: <message>``, one line; a warning
    from a library names its category (``... (UserWarning)``)."""
    lines = str(message).strip().splitlines()
    text = lines[0] if lines else category.__name__
    if issubclass(category, TalkmeshWarning):
        return f"talkmesh: warning: {text}"
    return f"talkmesh: warning: {text} ({category.__name__})"


def show_warnings(every: bool = False) -> None:
    """Print :class:`TalkmeshWarning` s as one ``talkmesh: warning:`` line each, whatever the
    Python warning filters say (they are part of the answer, not noise); with ``every``, other
    libraries' warnings too (one line, without Python's file name and source line)."""
    import sys
    import warnings

    warnings.filterwarnings("always", category=TalkmeshWarning)
    previous = warnings.showwarning
    if getattr(previous, "talkmesh", False):
        previous = previous.previous

    def show(message, category, filename, lineno, file=None, line=None):
        if every or issubclass(category, TalkmeshWarning):
            print(warning_line(message, category), file=sys.stderr, flush=True)
        else:
            previous(message, category, filename, lineno, file, line)

    show.talkmesh = True
    show.previous = previous
    warnings.showwarning = show
