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
  is entered. Integers, strings and integer arrays must be equal; floating-point numbers and
  arrays equal to 1e-10 relative (arrays through 4 x 64 block sums of their entries: rounding
  differences between ranks, 1e-16 to 1e-13, never decide a verdict; a difference shows unless
  it cancels in every block statistic). On one rank the call costs nothing; on two it costs
  one allgather of a few kB, small against one time step of even the smallest FOM in the
  tests.
* :func:`together` - around a region where a rank may raise alone (the time loop with its
  sinks and inputs, writing a file, the black-box probe steps). When an exception leaves the
  region on one rank, that rank asks on a private duplicate of the communicator whether every
  rank failed there (a non-blocking barrier polled against a deadline, ``LOPINF_MPI_TIMEOUT``
  seconds, default 60). If all did, the exception propagates on every rank as usual. If the
  others went on, they are inside a collective that cannot complete: the rank prints its
  traceback and the reason and aborts the job (``MPI_Abort``) - a loud end instead of a hang.
  The region costs one ``Comm.Dup`` and ``Free`` and nothing per step; the deadline is only ever waited for on the failure path.
* The process-wide safety net, :mod:`dolfinx_lopinf._mpi_abort`: an exception left uncaught
  on one rank (anywhere in the user's program, e.g. ``lo.fit`` refusing one rank's data before
  a barrier) aborts the job after its traceback.

Not done: a deadline on every *entry* (a timed barrier before each function). It would cost
little (about what the plain allgather costs), but no deadline is safe there: ranks legitimately reach an entry minutes apart (rank 0 fitting a model alone
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
from .._mpi_abort import _summary, abort
from ..errors import InputError, RanksDisagreeError

__all__ = ["agree", "arrive", "check", "together", "digest", "same"]

#: seconds a rank that raised alone waits for the others before aborting (LOPINF_MPI_TIMEOUT)
DEFAULT_TIMEOUT = 60.0
#: floating-point settings agree when equal to this relative tolerance (see :func:`same`)
RTOL = 1e-10
#: interleaved blocks of a float array's sketch (:func:`_block_sketch`)
BLOCKS = 64
#: float arrays up to this size are sent and compared entry by entry (to RTOL of their largest)
SMALL = 256
_SHOWN = 100  # characters of a value shown in a message


def _timeout() -> float:
    try:
        value = float(os.environ.get("LOPINF_MPI_TIMEOUT", DEFAULT_TIMEOUT))
    except ValueError:
        return DEFAULT_TIMEOUT
    return value if np.isfinite(value) and value > 0 else DEFAULT_TIMEOUT


def _short(text: str) -> str:
    return text if len(text) <= _SHOWN else text[:_SHOWN - 3] + "..."


def _block_sketch(a: np.ndarray) -> np.ndarray:
    """(4, BLOCKS) statistics of a float array over BLOCKS interleaved blocks of its entries
    (entry i in block i % BLOCKS): sum, position-weighted sum (weights 1 + (i // BLOCKS) % 7,
    so a permutation or a sign flip inside a block shows), sum of squares, sum of magnitudes
    (the scale the others are compared against). Three passes over the data; any change of
    the values beyond rounding changes some statistic."""
    flat = np.ascontiguousarray(a, dtype=float).reshape(-1)
    m = -(-len(flat) // BLOCKS) * BLOCKS
    x = np.zeros(m)
    x[:len(flat)] = flat
    x = x.reshape(-1, BLOCKS)
    w = 1.0 + (np.arange(len(x)) % 7)[:, None]
    return np.vstack([x.sum(axis=0), (w * x).sum(axis=0), (x * x).sum(axis=0), np.abs(x).sum(axis=0)])


def digest(value):
    """(key, shown): what rank-to-rank comparison needs of ``value`` (see :func:`same`), and a
    short description for messages. Integers, strings and integer arrays exactly (an array by
    a BLAKE2b digest of its bytes); floats and float arrays to :data:`RTOL` relative (a float
    array by :func:`_block_sketch`); containers element by element; other objects
    (callables, solvers, spaces) by their type only."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return ("float", value), _short(repr(value))
    if value is None or isinstance(value, (bool, int, str, PurePath)):
        text = repr(str(value)) if isinstance(value, PurePath) else repr(value)
        return text, _short(text)
    if isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        shown = (_short(f"array({a.tolist()})") if a.size <= 4 and a.dtype != object else
                 f"array of shape {a.shape}" + (f" (sum {np.sum(a):.6g}, max |.| {np.max(np.abs(a)):.6g})"
                                                if a.size and a.dtype.kind == "f" else ""))
        if a.dtype.kind == "f":
            if a.size <= SMALL:  # the values themselves: cheaper to send and compare
                return ("values", a.shape, tuple(a.reshape(-1).tolist())), shown
            return ("floats", a.shape, _block_sketch(a)), shown
        h = hashlib.blake2b(a.view(np.uint8).reshape(-1) if a.size and a.dtype != object
                            else repr(a.tolist()).encode(), digest_size=12).hexdigest()
        return f"array{a.shape}{a.dtype.str}:{h}", shown if a.size <= 4 else f"{shown} (digest {h[:8]})"
    if isinstance(value, dict):
        parts = [(digest(k), digest(v)) for k, v in sorted(value.items(), key=lambda kv: repr(kv[0]))]
        return (("dict", tuple((k[0], v[0]) for k, v in parts)),
                _short("{" + ", ".join(f"{k[1]}: {v[1]}" for k, v in parts) + "}"))
    if isinstance(value, (list, tuple)):
        parts = [digest(v) for v in value]
        left, right = ("[", "]") if isinstance(value, list) else ("(", ")")
        return (("seq", left, tuple(k for k, _ in parts)),
                _short(left + ", ".join(s for _, s in parts) + right))
    return f"<{type(value).__module__}.{type(value).__qualname__}>", f"a {type(value).__name__}"


def _close(x: float, y: float) -> bool:
    return x == y or (np.isnan(x) and np.isnan(y)) or abs(x - y) <= RTOL * max(abs(x), abs(y))


def same(k1, k2) -> bool:
    """Whether two keys of :func:`digest` are of equal values: exactly, or to :data:`RTOL`
    relative for floating-point values (rounding differences between ranks - another BLAS,
    thread count or CPU - are 1e-16 to 1e-13 relative; real disagreements are far larger)."""
    if isinstance(k1, tuple) and isinstance(k2, tuple) and k1 and k2 and k1[0] == k2[0]:
        tag = k1[0]
        if tag == "float":
            return _close(k1[1], k2[1])
        if tag == "values":
            if k1[1] != k2[1]:
                return False
            scale = max(max(map(abs, k1[2]), default=0.0), max(map(abs, k2[2]), default=0.0))
            return all(x == y or (x != x and y != y) or abs(x - y) <= RTOL * scale
                       for x, y in zip(k1[2], k2[2]))
        if tag == "floats":
            if k1[1] != k2[1]:
                return False
            s1, s2 = k1[2], k2[2]
            scale = RTOL * np.maximum(s1[3], s2[3])  # sums: against the sum of magnitudes
            both_nan = np.isnan(s1) & np.isnan(s2)
            ok = both_nan | (np.abs(s1 - s2) <= np.vstack([scale, 7 * scale,
                                                            RTOL * np.maximum(s1[2], s2[2]), scale]))
            return bool(np.all(ok))
        if tag == "dict":
            return len(k1[1]) == len(k2[1]) and all(
                same(a[0], b[0]) and same(a[1], b[1]) for a, b in zip(k1[1], k2[1]))
        if tag == "seq":
            return k1[1] == k2[1] and len(k1[2]) == len(k2[2]) and all(
                same(a, b) for a, b in zip(k1[2], k2[2]))
    return k1 == k2


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
    # 2. settings that differ between ranks (ranks grouped by equal values)
    differing = []
    for name in keys:
        groups: list = []  # [key, shown, ranks]
        for r, (_, k) in enumerate(everyone):
            key, shown = k.get(name, ("<absent>", "absent"))
            for group in groups:
                if same(group[0], key):
                    group[2].append(r)
                    break
            else:
                groups.append([key, shown, [r]])
        if len(groups) > 1:
            listed = "; ".join(f"{_ranks(rs)}: {shown}" for _, shown, rs in groups)
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
        f"({_summary(exc)}) in {where}, and the other ranks did not (waited {waited:.0f} s for "
        "them): they are inside a collective that can no longer complete, so the MPI job is "
        "aborted (MPI_Abort) instead of hanging. LOPINF_MPI_TIMEOUT sets the wait.\n")
    abort(comm)


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


def arrive(comm, where: str, hint: str) -> None:
    """Wait until every rank has reached ``where`` (a non-blocking barrier). A rank that waits
    longer than ``LOPINF_MPI_TIMEOUT`` seconds says so on stderr, once, with ``hint`` (how the
    call must be made), and keeps waiting: a collective called on some ranks only - e.g.
    ``if comm.rank == 0: rec.snapshots()`` - is then named instead of hanging silently. It does
    not abort: ranks may legitimately arrive minutes apart."""
    if comm.size == 1:
        return
    # on the communicator itself: a Dup would already block until every rank arrives
    request = comm.Ibarrier()
    start, limit, pause, told = time.monotonic(), _timeout(), 1e-4, False
    while not request.Test():
        if not told and time.monotonic() - start > limit:
            sys.stderr.write(
                f"dolfinx_lopinf: rank {comm.rank} of {comm.size} has waited {limit:.0f} s in "
                f"{where} for the other ranks. {hint}\n")
            sys.stderr.flush()
            told = True
        time.sleep(pause)
        pause = min(2 * pause, 0.05)
