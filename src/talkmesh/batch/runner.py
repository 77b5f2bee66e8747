"""A batch from start to end: what is done is skipped, the rest runs on local processes or a
Ray cluster, and every file ends as a row (:func:`animate_batch`)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import NamedTuple

from talkmesh.batch.library import (
    FAILED,
    AnimateSettings,
    Row,
    check_settings,
    plan_jobs,
    run_local,
)


class BatchResult(NamedTuple):
    """Every file's row (done, skipped and failed) and the batch's wall time in seconds."""

    rows: list[Row]
    seconds: float

    @property
    def failed(self) -> list[Row]:
        return [r for r in self.rows if r.status == FAILED]


def animate_batch(
    audio: list[Path],
    outputs: list[list[Path]],
    settings: AnimateSettings,
    *,
    workers: int = 1,
    cluster: str | None = None,
    on_row: Callable[[Row], None] | None = None,
) -> BatchResult:
    """Animate every file of ``audio`` into its ``outputs``, skipping those already done.

    ``cluster`` (a Ray address, or ``local``) runs the files on Ray actors instead of local
    processes; ``on_row`` sees each row as its file finishes (a progress bar). A failed file is
    a row, never an exception: the batch always goes to the end.
    """
    start = time.perf_counter()
    check_settings(settings)
    jobs, rows = plan_jobs(audio, outputs, settings.overwrite)
    for r in rows:
        if on_row:
            on_row(r)
    if cluster is not None:
        from talkmesh.batch.cluster import run_on_cluster

        stream: Iterable[Row] = run_on_cluster(jobs, settings, cluster, workers)
    else:
        stream = run_local(jobs, settings, workers)
    for row in stream:
        rows.append(row)
        if on_row:
            on_row(row)
    order = {str(a): k for k, a in enumerate(audio)}
    rows.sort(key=lambda r: order.get(r.file, len(order)))
    return BatchResult(rows, time.perf_counter() - start)
