"""Work spread over a Ray cluster: the files of a batch on actors that each load the model once
(:func:`run_on_cluster`), and independent tasks such as the benchmark's method x seed cells
(:func:`map_tasks`).

``address`` is what ``ray start --head`` prints (``HOST:PORT``), ``ray://HOST:PORT`` for Ray
Client, ``auto`` for the cluster this machine is a node of, or ``local`` for a cluster of this
machine alone, started here and stopped at the end. Every node needs the same talkmesh installed
and, for file outputs, the same paths (a shared file system): workers read the speech and write
the outputs where the driver names them.
"""

from __future__ import annotations

import logging
import socket
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from talkmesh.batch.library import FAILED, AnimateSettings, Animator, Job, Row
from talkmesh.errors import MissingDependencyError, TalkmeshError

CONNECT_TIMEOUT_S = 5.0  # a head that does not answer a TCP connect in this time is unreachable


def import_ray():
    try:
        import ray
    except ImportError:
        raise MissingDependencyError("ray", "cluster", "--cluster") from None
    return ray


def check_reachable(address: str) -> None:
    """A one-line error for an address that is malformed or whose head does not answer, before
    Ray spends a minute retrying it."""
    if address in ("local", "auto"):
        return
    hostport = address.removeprefix("ray://")
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        raise TalkmeshError(
            f"--cluster {address}: give HOST:PORT as `ray start --head` prints it, "
            "ray://HOST:PORT, auto or local"
        )
    try:
        socket.create_connection((host.strip("[]"), int(port)), CONNECT_TIMEOUT_S).close()
    except OSError as e:
        reason = e.strerror or type(e).__name__
        raise TalkmeshError(
            f"--cluster {address}: cannot reach a Ray head there ({reason}): start one with "
            "`ray start --head` or check the address"
        ) from None


@contextmanager
def connected(address: str, num_cpus: int | None = None) -> Iterator[Any]:
    """Ray, connected to ``address`` (``local``: a new cluster of ``num_cpus`` CPUs on this
    machine); disconnected (and a local cluster stopped) at the end. Where this process is
    already connected, that connection is used and kept."""
    ray = import_ray()
    if ray.is_initialized():
        yield ray
        return
    check_reachable(address)
    quiet = {"logging_level": logging.ERROR, "log_to_driver": False}
    try:
        if address == "local":
            ray.init(num_cpus=num_cpus, include_dashboard=False, **quiet)
        else:
            ray.init(address=address, **quiet)
    except Exception as e:  # Ray's own errors (ConnectionError, RuntimeError, ...): one line
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise TalkmeshError(f"--cluster {address}: cannot connect to Ray ({first})") from None
    try:
        yield ray
    finally:
        ray.shutdown()


def cluster_cpus(ray) -> int:
    return max(1, int(ray.cluster_resources().get("CPU", 1)))


class _Worker:
    """A Ray actor around an :class:`Animator` (one CPU, one torch thread)."""

    def __init__(self, settings: AnimateSettings):
        self.animator = Animator(settings, threads=1)

    def run(self, job: Job) -> Row:
        return self.animator(job)


def run_on_cluster(
    jobs: list[Job], settings: AnimateSettings, address: str, workers: int | None = None
) -> Iterator[Row]:
    """Animate ``jobs`` on ``workers`` actors (default: one per CPU of the cluster), each file
    on the next free actor; rows come in the order files finish. An actor that dies fails its
    file; its share goes to the others."""
    if not jobs:
        return
    with connected(address, num_cpus=workers) as ray:
        n = min(len(jobs), workers or cluster_cpus(ray))
        actor = ray.remote(num_cpus=1)(_Worker)
        free = [actor.remote(settings) for _ in range(n)]
        queue = list(reversed(jobs))
        pending: dict[Any, tuple[Any, Job]] = {}
        while queue or pending:
            while free and queue:
                a, job = free.pop(), queue.pop()
                pending[a.run.remote(job)] = (a, job)
            if not pending:  # every actor is dead: the rest cannot run
                for job in reversed(queue):
                    yield _lost(job, "no Ray worker is left")
                return
            (ref,), _ = ray.wait(list(pending), num_returns=1)
            a, job = pending.pop(ref)
            try:
                row = ray.get(ref)
            except ray.exceptions.RayActorError as e:
                yield _lost(job, f"its Ray worker died ({_first_line(e)})")
                continue
            except ray.exceptions.RayError as e:
                row = _lost(job, _first_line(e))
            free.append(a)
            yield row


def _lost(job: Job, why: str) -> Row:
    return Row(str(job.audio), None, None, 0.0, FAILED, f"{job.audio}: {why}: rerun to resume")


def _first_line(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


def map_tasks(
    fn: Callable[..., Any],
    calls: list[tuple],
    address: str,
    *,
    num_cpus: float = 1,
    workers: int | None = None,
) -> Iterator[tuple[tuple, Any]]:
    """``fn(*args)`` for every ``args`` of ``calls`` as Ray tasks of ``num_cpus`` CPUs each;
    yields ``(args, result)`` as they finish. A failed task does not stop the others: once all
    have finished, the first error is raised as itself (a :class:`TalkmeshError` stays one line)."""
    if not calls:
        return
    with connected(address, num_cpus=workers) as ray:
        remote = ray.remote(num_cpus=num_cpus)(fn)
        pending = {remote.remote(*args): args for args in calls}
        error: BaseException | None = None
        while pending:
            (ref,), _ = ray.wait(list(pending), num_returns=1)
            args = pending.pop(ref)
            try:
                result = ray.get(ref)
            except ray.exceptions.RayTaskError as e:
                cause = e.cause if isinstance(e.cause, BaseException) else None
                error = error or cause or TalkmeshError(f"a cluster task failed: {_first_line(e)}")
                continue
            except ray.exceptions.RayError as e:
                error = error or TalkmeshError(f"a cluster task was lost: {_first_line(e)}")
                continue
            yield args, result
        if error is not None:
            raise error
