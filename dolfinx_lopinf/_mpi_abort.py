"""The safety net of a multi-rank run: an uncaught exception on one rank aborts the MPI job.

Without it, a rank that dies of an exception the other ranks do not share (bad data on that
rank only, a bug in a user callback, ``lo.fit`` refusing one rank's snapshots) leaves Python
to exit normally: ``mpi4py`` calls ``MPI_Finalize`` and the other ranks wait forever in their
next collective - the job hangs until the batch system kills it. ``python -m mpi4py`` avoids
that with an ``MPI_Abort`` on an uncaught exception; this module does the same for programs
that import ``dolfinx_lopinf``:

* :func:`install` puts :func:`_hook` into ``sys.excepthook`` when MPI is initialised with more
  than one rank in ``COMM_WORLD``, and only if ``sys.excepthook`` is still Python's own (a
  hook the user installed is left alone). It is called when the package is imported and
  when its DOLFINx layer is (whichever first finds ``mpi4py.MPI`` loaded).
* The hook prints the traceback as Python would, then, unless the exception was raised on
  every rank at once by a collective check (it carries ``__lopinf_collective__``: every rank
  exits by itself), says which rank failed and calls ``MPI_Abort`` on ``COMM_WORLD``.
* ``LOPINF_MPI_ABORT=0`` in the environment disables it.

Cost: none until an exception is uncaught. Inside the package the same situation (one rank
raises inside a collective region while the others go on) is handled earlier, where it
happens: see :mod:`dolfinx_lopinf.fem.agreement`.

This module imports neither dolfinx nor mpi4py (it only looks for ``mpi4py.MPI`` among the
loaded modules), so the numpy core stays free of them.
"""

from __future__ import annotations

import os
import sys


def _mpi():
    """``mpi4py.MPI`` when it is loaded and MPI is running (initialised, not finalised)."""
    MPI = sys.modules.get("mpi4py.MPI")
    if MPI is None:
        return None
    try:
        if not MPI.Is_initialized() or MPI.Is_finalized():
            return None
    except Exception:  # pragma: no cover - a broken MPI: do nothing
        return None
    return MPI


def _hook(exc_type, exc, tb):
    sys.__excepthook__(exc_type, exc, tb)
    MPI = _mpi()
    if MPI is None or getattr(exc, "__lopinf_collective__", False):
        return
    comm = MPI.COMM_WORLD
    if comm.Get_size() == 1:
        return
    sys.stderr.write(
        f"dolfinx_lopinf: rank {comm.Get_rank()} of {comm.Get_size()} stopped on the uncaught "
        f"{exc_type.__name__} above ({_summary(exc)}); the other ranks would wait for it "
        "forever in their next collective, so the MPI job is aborted (MPI_Abort). Set "
        "LOPINF_MPI_ABORT=0 to disable this.\n")
    abort(comm)


def _summary(exc) -> str:
    text = str(exc).replace("\n", " ")
    return text if len(text) <= 300 else text[:297] + "..."


def abort(comm, code: int = 1) -> None:
    """``comm.Abort(code)`` after flushing the output and a short pause, so the launcher
    forwards this rank's last words before it kills the job."""
    import time

    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # pragma: no cover
            pass
    time.sleep(0.3)
    comm.Abort(code)


def install() -> bool:
    """Install the hook if MPI runs on several ranks and ``sys.excepthook`` is Python's own.
    Returns True when the hook is (now or already) in place."""
    if sys.excepthook is _hook:
        return True
    if os.environ.get("LOPINF_MPI_ABORT", "1").strip() == "0":
        return False
    if sys.excepthook is not sys.__excepthook__:
        return False  # the user's own hook (or an IDE's): leave it alone
    MPI = _mpi()
    if MPI is None or MPI.COMM_WORLD.Get_size() == 1:
        return False
    sys.excepthook = _hook
    return True
