"""The batch's summary CSV: one row per speech file (file, duration, frames, seconds, status,
error), written atomically at the end of every run. A file skipped because an earlier run did it
keeps that run's duration, frames and seconds, so the summary of a resumed batch is complete."""

from __future__ import annotations

import csv
import io
import os
import tempfile
from pathlib import Path

from talkmesh.batch.library import SKIPPED, Row
from talkmesh.errors import TalkmeshError, os_error_message
from talkmesh.output.atomic import temp_prefix

COLUMNS = ("file", "duration", "frames", "seconds", "status", "error")


def read_summary(path: Path) -> dict[str, Row]:
    """The rows of an earlier summary by file (empty when there is none or it is not ours)."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            if tuple(reader.fieldnames or ()) != COLUMNS:
                return {}
            return {r["file"]: _row(r) for r in reader}
    except (OSError, ValueError, csv.Error, UnicodeDecodeError):
        return {}


def _row(r: dict[str, str]) -> Row:
    return Row(
        r["file"],
        float(r["duration"]) if r["duration"] else None,
        int(r["frames"]) if r["frames"] else None,
        float(r["seconds"] or 0.0),
        r["status"],
        r["error"],
    )


def with_earlier(rows: list[Row], earlier: dict[str, Row]) -> list[Row]:
    """Skipped rows filled in with what the earlier run measured for the same file."""
    out = []
    for r in rows:
        old = earlier.get(r.file)
        if r.status == SKIPPED and old is not None and old.frames is not None:
            r = r._replace(duration=old.duration, frames=old.frames, seconds=old.seconds)
        out.append(r)
    return out


def write_summary(path: Path, rows: list[Row]) -> None:
    """Write ``rows`` to ``path`` (a temporary renamed into place: never half a summary)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    for r in rows:
        w.writerow(
            [
                r.file,
                "" if r.duration is None else f"{r.duration:.3f}",
                "" if r.frames is None else r.frames,
                f"{r.seconds:.3f}",
                r.status,
                r.error,
            ]
        )
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(), suffix=".csv", dir=path.parent)
        try:
            with os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
                f.write(buf.getvalue())
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    except OSError as e:
        raise TalkmeshError(os_error_message(e, path)) from None
