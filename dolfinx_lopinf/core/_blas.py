"""One BLAS thread for the small dense kernels of the fits.

The fits' matrices are a few hundred wide at most (p, 2 r (r + 1) / 2, the polynomial design):
there OpenBLAS threads cost more than they give, the more so on a busy machine. The entry
points run with one BLAS thread (threadpoolctl) and give the caller's setting back on return.
"""

from __future__ import annotations

import contextlib
import functools


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
