"""numpy's BLAS on one thread where a team of threads costs more than it gives.

OpenBLAS starts a thread per core and meets them after every product. For small products in a
loop (the ARKit fit's 200 steps of (T, 52) @ (52, 52)) the meetings are the whole cost; for the
medium ones of a .glb's morph targets (a (249, 14298) Gram matrix, its eigenvectors, a QR) a
second core saves a few hundredths of a second on an idle machine. With the cores busy (other
processes, a batch's workers) every meeting waits for a descheduled thread: the fit of 8 s of
motion took 4 s instead of 0.1 s, the morph targets 4 s instead of 0.3 s. :func:`one_blas_thread`
runs a body on one thread, as :mod:`talkmesh.models.threads` runs PyTorch's step loops.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """numpy's BLAS on one thread for the body (threadpoolctl), its count restored after."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # a dependency, but the body works without it
        yield
        return
    with threadpool_limits(1, user_api="blas"):
        yield
