"""BLAS threads: one for the small dense kernels of the fits, and no more than a rank's share of
the cores for the full-order model's dense work under MPI.

The fits' matrices are a few hundred wide at most (p, 2 r (r + 1) / 2, the polynomial design):
there OpenBLAS threads cost more than they give, the more so on a busy machine. The entry
points run with one BLAS thread (threadpoolctl) and give the caller's setting back on return.

Under ``mpiexec -n N`` every rank's numpy/scipy BLAS starts as many threads as the machine has
cores, N times too many; OpenBLAS's threads wait by spinning, so the ranks' dense work (the
subspace solver's projections, the streamed POD) fights for the cores. Measured on the 110k-dof
fishtail, 2 ranks on 2 cores, 200 steps: 0.157 s per step (projections 9.9 s) against 0.034 s
(0.39 s) with one BLAS thread per rank. :func:`share_cores_among_ranks` caps it.
"""

from __future__ import annotations

import contextlib
import functools
import os

#: environment variables by which a user has chosen the BLAS threads (left alone then)
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                    "BLIS_NUM_THREADS")
_SHARED: dict = {}


@functools.lru_cache(maxsize=1)
def blas_controller():
    """The process's threadpoolctl controller (built once: it inspects the loaded libraries)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def one_blas_thread():
    """A context manager that limits BLAS to one thread (the caller's setting restored on
    exit); a no-op context when threadpoolctl has no view of the BLAS."""
    try:
        return blas_controller().limit(limits=1, user_api="blas")
    except Exception:  # noqa: BLE001 - no threadpoolctl view of the BLAS: run as is
        return contextlib.nullcontext()


def serial_blas(fn):
    """Decorator: run ``fn`` with one BLAS thread (:func:`one_blas_thread`)."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with one_blas_thread():
            return fn(*args, **kwargs)
    return wrapper


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity; the machine's count off Linux)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def share_cores_among_ranks(comm) -> int | None:
    """Collective on ``comm``. Cap this process's BLAS threads at its share of the node's cores,
    max(1, cores // ranks on the node), for the rest of the process - where ``comm`` has more
    than one rank and the user has not set the threads (:data:`THREAD_VARIABLES`). Returns the
    cap (None where nothing was done). Done once per process; the threadpoolctl limit is kept
    in ``_SHARED`` (``_SHARED["limit"].restore_original_limits()`` undoes it)."""
    if comm.size == 1 or "limit" in _SHARED:
        return _SHARED.get("threads")
    node = comm.Split_type(_comm_type_shared(comm))
    try:
        ranks_here = node.size
    finally:
        node.Free()
    if any(os.environ.get(v, "").strip() for v in THREAD_VARIABLES):
        _SHARED["limit"], _SHARED["threads"] = None, None
        return None
    threads = max(1, usable_cores() // ranks_here)
    try:
        from threadpoolctl import threadpool_limits

        _SHARED["limit"] = threadpool_limits(limits=threads, user_api="blas")
    except Exception:  # noqa: BLE001 - no threadpoolctl view of the BLAS: run as is
        _SHARED["limit"], _SHARED["threads"] = None, None
        return None
    _SHARED["threads"] = threads
    return threads


def _comm_type_shared(comm):
    from mpi4py import MPI

    return MPI.COMM_TYPE_SHARED
