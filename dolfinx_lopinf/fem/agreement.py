"""Every rank agrees, nothing hangs: the collective checks of the DOLFINx layer.

A public function of this layer that runs on a communicator is a sequence of collectives
(allreduces, distributed solves, the VTX writer). A multi-rank run hangs in two ways:

1. *The ranks disagree about an argument.* A check that runs on each rank alone (``dt`` not
   positive, NaN in an array) raises on the rank that has the bad value while the others go
   on into a collective; an argument that differs between ranks (another ``dt``, ``t_end``,
   number of steps on rank 1) makes the ranks take different paths - a hang, or a silently
   wrong result where each rank solves its own problem.
2. *One rank raises while the others go on.* An exception only one rank sees (a user
   callback, a sink, disk trouble on one node) leaves the others inside a collective that
   can never complete.

The remedies, in the order a call meets them:

* :func:`agree` - at the entry of every public collective function, after the local checks:
  ONE allgather of (this rank's problem or None, the digests of the settings that must be
  equal on every rank). Every rank then raises the same error - the lowest failing rank's
  (its rank named), or a :class:`~dolfinx_lopinf.errors.RanksDisagreeError` naming each
  setting that differs and every rank's value - before any collective of the function itself
  is entered. Arrays are compared by a BLAKE2b digest of their bytes (about 1 GB/s), numbers
  by their exact ``repr``. On one rank the call costs nothing; on two it costs one allgather
  of a few hundred bytes (17 us measured on a loaded 2-core machine, against 0.4-1.3 ms for
  one time step of the smallest FOM in the tests).
* :func:`together` - around a region where a rank may raise alone (the time loop with its
  sinks and inputs, writing a file, the black-box probe steps). When an exception leaves the
  region on one rank, that rank asks on a private duplicate of the communicator whether every
  rank failed there (a non-blocking barrier polled against a deadline, ``LOPINF_MPI_TIMEOUT``
  seconds, default 60). If all did, the exception propagates on every rank as usual. If the
  others went on, they are inside a collective that cannot complete: the rank prints its
  traceback and the reason and aborts the job (``MPI_Abort``) - a loud end instead of a hang.
  The region costs one ``Comm.Dup`` and ``Free`` (14 us measured on 2 ranks) and nothing per
  step; the deadline is only ever waited for on the failure path.
* The process-wide safety net, :mod:`dolfinx_lopinf._mpi_abort`: an exception left uncaught
  on one rank (anywhere in the user's program, e.g. ``lo.fit`` refusing one rank's data before
  a barrier) aborts the job after its traceback.

Not done: a deadline on every *entry* (a timed barrier before each function). Measured, it
would cost little (23 us against 17 us for the plain allgather on 2 ranks), but no deadline is
safe there: ranks legitimately reach an entry minutes apart (rank 0 fitting a model alone
while the others wait for the next call), so any default would abort correct programs. A
rank that never reaches an entry because it raised is handled by :func:`together` and the
safety net instead.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import sys
import time
import traceback
from pathlib import PurePath

import numpy as np

from .. import errors
from ..errors import InputError, RanksDisagreeError

__all__ = ["agree", "together", "digest"]

#: seconds a rank that raised alone waits for the others before aborting (LOPINF_MPI_TIMEOUT)
DEFAULT_TIMEOUT = 60.0
_SHOWN = 60  # characters of a value shown in a message


def _timeout() -> float:
    try:
        value = float(os.environ.get("LOPINF_MPI_TIMEOUT", DEFAULT_TIMEOUT))
    except ValueError:
        return DEFAULT_TIMEOUT
    return value if np.isfinite(value) and value > 0 else DEFAULT_TIMEOUT


def _short(text: str) -> str:
    return text if len(text) <= _SHOWN else text[:_SHOWN - 3] + "..."


def digest(value) -> tuple[str, str]:
    """(key, shown): ``key`` equal on two ranks exactly when the values are; ``shown`` a short
    description for messages. Numbers and strings by ``repr``, arrays by shape, dtype and a
    BLAKE2b digest of their bytes, containers element by element, other objects (callables,
    solvers, spaces) by their type only."""
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, int, float, str, PurePath)):
        text = repr(str(value)) if isinstance(value, PurePath) else repr(value)
        return text, _short(text)
    if isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        h = hashlib.blake2b(a.view(np.uint8).reshape(-1) if a.size and a.dtype != object
                            else repr(a.tolist()).encode(), digest_size=12).hexdigest()
        key = f"array{a.shape}{a.dtype.str}:{h}"
        if a.size <= 4 and a.dtype != object:
            return key, _short(f"array({a.tolist()})")
        return key, f"array of shape {a.shape} (digest {h[:8]})"
    if isinstance(value, dict):
        parts = [(digest(k), digest(v)) for k, v in sorted(value.items(), key=lambda kv: repr(kv[0]))]
        key = "{" + ", ".join(f"{k[0]}: {v[0]}" for k, v in parts) + "}"
        return key, _short("{" + ", ".join(f"{k[1]}: {v[1]}" for k, v in parts) + "}")
    if isinstance(value, (list, tuple)):
        parts = [digest(v) for v in value]
        left, right = ("[", "]") if isinstance(value, list) else ("(", ")")
        return (left + ", ".join(k for k, _ in parts) + right,
                _short(left + ", ".join(s for _, s in parts) + right))
    name = f"a {type(value).__name__}"
    return f"<{type(value).__module__}.{type(value).__qualname__}>", name


def _error_class(module: str, name: str):
    if module == errors.__name__:
        cls = getattr(errors, name, None)
        if isinstance(cls, type) and issubclass(cls, BaseException):
            return cls
    return None


def _mark(exc: BaseException) -> BaseException:
    """Mark an exception as raised on every rank at the same point (the safety net then lets
    each rank exit by itself instead of aborting the job)."""
    exc.__lopinf_collective__ = True
    return exc


def _ranks(ranks: list[int]) -> str:
    return ("rank " if len(ranks) == 1 else "ranks ") + ", ".join(map(str, ranks))


def agree(comm, where: str, problem=None, **settings) -> None:
    """The collective verdict at the entry of ``where`` (e.g. ``"run"``): raises the same error
    on every rank when any rank has a ``problem`` (an exception or a message), else when the
    ``settings`` (name -> value, each the same on every rank by contract) differ between
    ranks; returns on every rank otherwise. One allgather; nothing on a single rank.

    The error of a problem keeps its class (any class of :mod:`dolfinx_lopinf.errors`; other
    exceptions become :class:`~dolfinx_lopinf.errors.InputError` with their type named) and
    its message, followed by the rank it was found on when it was not found on all of them.
    """
    if problem is not None and not isinstance(problem, BaseException):
        problem = InputError(str(problem))
    size = comm.size
    if size == 1:
        if problem is not None:
            raise problem
        return
    mine_problem = None
    if problem is not None:
        cls = type(problem)
        mine_problem = (cls.__module__, cls.__name__, str(problem))
    keys = {name: digest(value) for name, value in settings.items()}
    everyone = comm.allgather((mine_problem, keys))
    # 1. a problem found on some rank: raised on all of them (its settings may be missing)
    failed = [r for r, (p, _) in enumerate(everyone) if p is not None]
    if failed:
        module, name, message = everyone[failed[0]][0]
        cls = _error_class(module, name)
        if cls is None:
            cls, message = InputError, f"{name}: {message}"
        if len(failed) < size or any(everyone[r][0][2] != everyone[failed[0]][0][2] for r in failed):
            message = f"{message} [found on {_ranks(failed)} of {size}; raised on every rank]"
        try:
            exc = cls(message)
        except Exception:  # an error class with another constructor: keep the message
            exc = InputError(message)
        if problem is not None and problem.__traceback__ is not None:
            raise _mark(exc) from problem
        raise _mark(exc) from None
    # 2. settings that differ between ranks
    differing = []
    for name in keys:
        values: dict[str, list] = {}
        for r, (_, k) in enumerate(everyone):
            key, shown = k.get(name, ("<absent>", "absent"))
            values.setdefault(key, [shown, []])[1].append(r)
        if len(values) > 1:
            listed = "; ".join(f"{_ranks(rs)}: {shown}" for shown, rs in values.values())
            differing.append(f"{name} ({listed})")
    if differing:
        raise _mark(RanksDisagreeError(
            f"{where}: the ranks passed different arguments - " + ", ".join(differing) +
            ". Every rank must pass the same value (compute it on one rank and broadcast it, "
            "e.g. comm.bcast(value, root=0)); nothing was done")) from None


def check(comm, where: str, local_checks, **settings):
    """``local_checks()`` (which may raise) on this rank, then :func:`agree` on its error and
    the settings; returns what ``local_checks`` returned (on every rank, when no rank failed).
    An exception other than an :class:`~dolfinx_lopinf.errors.LOpInfError` in the checks is
    passed on as a problem too (its type named), so no rank raises alone."""
    result, problem = None, None
    try:
        result = local_checks()
    except Exception as exc:  # noqa: BLE001 - every rank must hear of it
        problem = exc
    agree(comm, where, problem, **settings)
    return result


def _abort(comm, where: str, exc: BaseException, waited: float) -> None:
    traceback.print_exception(type(exc), exc, exc.__traceback__, file=sys.stderr)
    sys.stderr.write(
        f"dolfinx_lopinf: rank {comm.rank} of {comm.size} raised the {type(exc).__name__} above "
        f"in {where}, and the other ranks did not (waited {waited:.0f} s for them): they are "
        "inside a collective that can no longer complete, so the MPI job is aborted "
        "(MPI_Abort) instead of hanging. LOPINF_MPI_TIMEOUT sets the wait.\n")
    sys.stderr.flush()
    comm.Abort(1)


@contextlib.contextmanager
def together(comm, where: str):
    """A region every rank leaves the same way: normally, or by an exception on every rank.
    An exception on this rank alone (the others went on) aborts the job after the traceback
    (see the module docstring); an exception raised by :func:`agree` passes straight through.
    """
    if comm.size == 1:
        yield
        return
    dup = comm.Dup()
    try:
        yield
    except BaseException as exc:
        if not getattr(exc, "__lopinf_collective__", False):
            request = dup.Ibarrier()
            start = time.monotonic()
            limit = _timeout()
            pause = 1e-4
            while not request.Test():
                waited = time.monotonic() - start
                if waited > limit:
                    _abort(comm, where, exc, waited)
                time.sleep(pause)
                pause = min(2 * pause, 0.05)
            _mark(exc)  # every rank failed here: each raises its own and exits by itself
        raise
    finally:
        dup.Free()
