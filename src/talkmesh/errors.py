"""User-facing errors.

Anything the user can fix (a missing file, a wrong sample rate, a mesh with the wrong vertex count)
raises :class:`TalkmeshError` with one line that says what is wrong and what to do. The CLI prints
that line and exits non-zero; it never shows a traceback for these.
"""


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
