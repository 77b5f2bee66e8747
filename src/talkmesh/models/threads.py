"""How many threads PyTorch runs where: step loops on few, worker processes on their share.

Step-by-step generation (MeshTalk's sampler, CodeTalker's and FaceFormer's autoregressive steps)
runs thousands of small operations one after the other. Handing each to a team of threads costs
more than it saves, and when other processes hold the cores every step waits for the team's
slowest member: with the machine busy, MeshTalk's sampler took 16x longer on PyTorch's default
two threads than on one. :func:`step_threads` runs those loops on :data:`STEP_THREADS` threads;
the speech encoder and the final vertex maps (large matrix products) keep PyTorch's count.
``TALKMESH_STEP_THREADS`` overrides it (0: PyTorch's own count). Processes that share a machine
(the batch runner's and the server's workers) each take :func:`worker_threads`, so that N of them
do not start more threads than there are cores. ``bench/threads.py`` measures both
(docs/results/threads.md).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

from talkmesh.errors import TalkmeshError

STEP_THREADS = 1  # bench/threads.py: the fastest for every family's steps, idle or busy
ENV = "TALKMESH_STEP_THREADS"


def step_thread_count() -> int | None:
    """Threads for step loops: ``TALKMESH_STEP_THREADS`` if set (0: None, PyTorch's own
    count), else :data:`STEP_THREADS`."""
    value = os.environ.get(ENV)
    if value is None:
        return STEP_THREADS
    try:
        n = int(value)
    except ValueError:
        n = -1
    if n < 0:
        raise TalkmeshError(f"{ENV}={value!r}: give a whole number of threads (0: PyTorch's own)")
    return n or None


@contextmanager
def step_threads() -> Iterator[None]:
    """Run the body (a step loop over small tensors) on :func:`step_thread_count` threads, never
    more than PyTorch has now; its count is restored after."""
    import torch

    n, before = step_thread_count(), torch.get_num_threads()
    if n is None or n >= before:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def usable_cpus() -> int:
    """The cores this process may run on (its affinity where the OS tells it)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def worker_threads(processes: int, cpus: int | None = None) -> int:
    """PyTorch threads for each of ``processes`` computing side by side on ``cpus`` cores
    (default: :func:`usable_cpus`): their share, at least one."""
    cpus = usable_cpus() if cpus is None else cpus
    return max(1, cpus // max(1, processes))


def set_process_threads(threads: int | None, processes: int) -> None:
    """PyTorch's threads in this process: ``threads``, else its share of the cores among
    ``processes`` that share them (:func:`worker_threads`: the server beside its workers)."""
    import torch

    torch.set_num_threads(threads or worker_threads(processes))
