"""Many files at once: a dialogue library animated by local worker processes or on a Ray cluster.

``inputs`` turns folders and lists into speech files; ``library`` animates them (one row per file,
a bad file never stops the batch); ``runner`` skips what is done and picks local processes or Ray;
``summary`` writes the CSV; ``cluster`` talks to Ray.
"""

from talkmesh.batch.inputs import AUDIO_SUFFIXES, Input, find_inputs, is_batch_source
from talkmesh.batch.library import (
    FAILED,
    OK,
    SKIPPED,
    AnimateSettings,
    Animator,
    Job,
    Row,
    plan_jobs,
)
from talkmesh.batch.runner import BatchResult, animate_batch
from talkmesh.batch.summary import read_summary, with_earlier, write_summary

__all__ = [
    "AUDIO_SUFFIXES",
    "FAILED",
    "OK",
    "SKIPPED",
    "AnimateSettings",
    "Animator",
    "BatchResult",
    "Input",
    "Job",
    "Row",
    "animate_batch",
    "find_inputs",
    "is_batch_source",
    "plan_jobs",
    "read_summary",
    "with_earlier",
    "write_summary",
]
