"""Full states back in the user's dolfinx space: into a Function, and into a VTX (.bp) file
that opens in ParaView next to the FOM's own output.

    Q = basis.reconstruct(traj.Qh)                     # (n, K) in the recorder's state order
    write_vtx("rom.bp", V, Q, traj.times)              # collective; Q needed on rank 0 only

    rows = state_rows(V, lambda x: np.isclose(x[2], 1.0))   # the state rows on a face
    write_vtx("top.bp", V, basis.reconstruct(traj.Qh, rows=rows), traj.times, rows=rows)

A state vector has the layout of :class:`~dolfinx_lopinf.fem.fom.StateMap`: state[i] =
scale[i] * dofs[order[i]] in global dof numbering, as :class:`~dolfinx_lopinf.fem.recorder.
SnapshotRecorder` and :func:`~dolfinx_lopinf.fem.fom.gather_states` gather it. The functions here
apply the exact inverse (dofs[order] = state / scale), then give each rank its owned dofs and
update the ghosts, so SnapshotRecorder -> states -> :func:`write_vtx` round-trips for any number
of ranks (the default state map is the recorder's default, ``StateMap.identity``: row i is
global dof i; pass ``state_map=rec.state_map`` for another).

Partial states (``rows=``): ``states`` holds only the listed state rows (what
``Basis.reconstruct(Qh, rows=rows)`` returns); the other state rows are written as
``fill`` (0 by default; ``np.nan`` makes ParaView leave them blank).

MPI: every function here is collective over ``V.mesh.comm``. ``states``, ``times`` and ``rows``
are taken from rank 0 (other ranks may pass ``None`` or the same arrays; theirs are ignored),
and every rank raises the same :class:`~dolfinx_lopinf.errors.InputError` on bad input before
anything is written.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from ..core._checks import as_real_array
from ._dolfinx import dolfinx
from ..errors import InputError
from .fom import StateMap, owned_global_dofs

__all__ = ["state_rows", "states_to_function", "write_vtx"]

_ENGINES = ("BP4", "BP5", "BPFile")


def _space(V):
    if isinstance(V, dolfinx.fem.Function):
        V = V.function_space
    if not isinstance(V, dolfinx.fem.FunctionSpace):
        raise InputError(f"V must be a dolfinx FunctionSpace (or Function), got {type(V).__name__}")
    return V


def _default_map(V, state_map):
    """The recorder's default: state row i is global dof i."""
    return StateMap.identity(V) if state_map is None else state_map


def _verdict(comm, problem):
    """Rank 0's problem (or any rank's), raised as InputError on every rank."""
    problems = comm.allgather(problem) if comm.size > 1 else [problem]
    for p in problems:
        if p is not None:
            raise InputError(p)


def _map_problem(V, state_map: StateMap) -> str | None:
    n_dofs = V.dofmap.index_map.size_global * V.dofmap.index_map_bs
    order = np.asarray(state_map.order)
    scale = np.asarray(state_map.scale, dtype=float)
    if order.shape != (n_dofs,) or scale.shape != (n_dofs,):
        return (f"the state map has {order.shape[0] if order.ndim else 0} rows but the space has "
                f"{n_dofs} dofs: pass the state map the states were recorded with, for this space")
    if not np.all(np.isfinite(scale)) or np.any(scale == 0):
        return "the state map's scale contains zero, NaN or inf"
    return None


def _root_states(V, states, state_map: StateMap, rows, fill, *, single: bool):
    """(problem, S) on rank 0: S the full (n, K) state matrix in state order."""
    problem = _map_problem(V, state_map)
    if problem is not None:
        return problem, None
    n = len(state_map.order)
    name = "state" if single else "states"
    if states is None:
        return f"{name} is None on rank 0 (pass the reconstructed states on rank 0)", None
    try:
        S = as_real_array(states, name)
    except InputError as exc:
        return str(exc), None
    if S.ndim not in ((1,) if single else (1, 2)):
        return (f"{name} must be {'a 1-d vector (n,)' if single else '(n,) or (n, K)'}, "
                f"got shape {S.shape}"), None
    if S.ndim == 1:
        S = S[:, None]
    if rows is None:
        if S.shape[0] != n:
            return (f"{name} have {S.shape[0]} rows but the space has {n} dofs (state rows); "
                    "pass states of this space (or rows= for a partial state)"), None
    else:
        r = np.asarray(rows)
        if r.dtype.kind not in "iu" or r.ndim != 1:
            return f"rows must be a 1-d array of integer state rows, got {r.dtype} {r.shape}", None
        if r.size and (r.min() < 0 or r.max() >= n):
            return f"rows must lie in 0..{n - 1} (the space's dofs), got {r.min()}..{r.max()}", None
        if len(np.unique(r)) != len(r):
            return "rows contains repeated entries", None
        if S.shape[0] != len(r):
            return (f"{name} have {S.shape[0]} rows but rows lists {len(r)}: pass "
                    "basis.reconstruct(Qh, rows=rows)"), None
    bad = ~np.isfinite(S)
    if bad.any():
        i, k = np.argwhere(bad)[0]
        return (f"{name} contain {int(bad.sum())} NaN/inf entries (first at row {i}, column "
                f"{k}): a ROM that blew up? write only the finite part"), None
    if rows is not None:
        full = np.full((n, S.shape[1]), fill, dtype=float)
        full[np.asarray(rows)] = S
        S = full
    return None, S


def _scatter(V, S, state_map: StateMap) -> np.ndarray:
    """Rank 0's state matrix S (n, K) -> this rank's owned dof values (n_owned, K)."""
    comm = V.mesh.comm
    owned = owned_global_dofs(V)
    if comm.size == 1:
        dofs = np.empty_like(S)
        dofs[state_map.order] = S / np.asarray(state_map.scale, dtype=float)[:, None]
        return dofs[owned]
    pieces = comm.gather(owned, root=0)
    chunks = None
    if comm.rank == 0:
        dofs = np.empty_like(S)
        dofs[state_map.order] = S / np.asarray(state_map.scale, dtype=float)[:, None]
        chunks = [np.ascontiguousarray(dofs[g]) for g in pieces]
    return comm.scatter(chunks, root=0)


def _set(f, local_column: np.ndarray) -> None:
    n_owned = len(local_column)
    f.x.array[:n_owned] = local_column
    f.x.scatter_forward()


def states_to_function(V, state, state_map: StateMap | None = None, f=None, *, rows=None,
                       fill: float = 0.0):
    """Put one global state vector into a dolfinx Function (collective).

    Args:
        V: the FunctionSpace the states were recorded on (or a Function of it).
        state: (n,) state in the state map's order, on rank 0 (ignored elsewhere; may be None);
            with ``rows``, only those state rows (len(rows),).
        state_map: the recorder's state map (default ``StateMap.from_coordinates(V)``, the
            recorder's default).
        f: Function on V to fill (default: a new one).
        rows: optional state rows that ``state`` holds; the others get ``fill``.
        fill: value of the state rows not in ``rows``.

    Returns:
        the Function (owned dofs set, ghosts updated) on every rank.
    """
    V = _space(V)
    comm = V.mesh.comm
    state_map = _default_map(V, state_map)
    problem = None
    if f is not None and (not isinstance(f, dolfinx.fem.Function)
                          or f.function_space._cpp_object is not V._cpp_object):
        problem = "f must be a Function on V (the space passed)"
    S = None
    if problem is None and comm.rank == 0:
        problem, S = _root_states(V, state, state_map, rows, fill, single=True)
    _verdict(comm, problem)
    f = dolfinx.fem.Function(V) if f is None else f
    _set(f, _scatter(V, S, state_map)[:, 0])
    return f


def state_rows(V, marker, state_map: StateMap | None = None) -> np.ndarray:
    """The state rows (sorted, on every rank) of the dofs whose coordinates satisfy ``marker``
    (a function of x (3, N) returning (N,) bools, as for ``locate_dofs_geometrical``); every
    component of a vector field. Use them for a partial reconstruction and :func:`write_vtx`.
    Collective; Lagrange-type spaces (one coordinate per dof block)."""
    V = _space(V)
    comm = V.mesh.comm
    state_map = _default_map(V, state_map)
    _verdict(comm, _map_problem(V, state_map))
    imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
    blocks = dolfinx.fem.locate_dofs_geometrical(V, marker)
    blocks = blocks[blocks < imap.size_local]
    glob = imap.local_to_global(blocks.astype(np.int32))
    dofs = (glob[:, None] * bs + np.arange(bs)[None, :]).ravel()
    dofs = np.concatenate(comm.allgather(dofs)) if comm.size > 1 else dofs
    inverse = np.empty(len(state_map.order), dtype=np.int64)
    inverse[np.asarray(state_map.order)] = np.arange(len(state_map.order))
    return np.sort(inverse[dofs])


def _path_problem(path) -> str | None:
    p = Path(path)
    if p.suffix != ".bp":
        return f"the VTX path must end in .bp (a folder ParaView opens), got {str(path)!r}"
    if not p.parent.is_dir():
        return f"the folder {str(p.parent)!r} of the VTX path does not exist; create it first"
    if p.exists() and not p.is_dir():
        return f"{str(path)!r} exists and is not a .bp folder; refusing to replace it"
    if not os.access(p.parent, os.W_OK):
        return f"the folder {str(p.parent)!r} is not writable"
    return None


def _times_problem(times, K: int):
    try:
        t = np.atleast_1d(as_real_array(times, "times"))
    except InputError as exc:
        return str(exc), None
    if t.ndim != 1 or len(t) != K:
        return f"times must be 1-d with one time per state column ({K}), got shape {t.shape}", None
    if not np.all(np.isfinite(t)):
        return "times contain NaN or inf", None
    if K > 1 and np.any(np.diff(t) <= 0):
        i = int(np.argmax(np.diff(t) <= 0))
        return f"times must increase: times[{i + 1}] = {t[i + 1]} after times[{i}] = {t[i]}", None
    return None, t


def write_vtx(path, V, states, times, *, state_map: StateMap | None = None, name: str = "u",
              rows=None, fill: float = 0.0, engine: str = "BP4") -> Path:
    """Write a trajectory of full states as a VTX file (an ADIOS2 .bp folder) for ParaView.

    Everything is checked first (the same InputError on every rank, nothing on disk); the
    file is written into a temporary folder beside ``path`` and renamed to ``path`` at the end,
    so ``path`` is either absent/its previous version or the complete new file - never half of
    one. An existing .bp folder at ``path`` is replaced.

    Args:
        path: the .bp folder to write (its parent folder must exist).
        V: the (Lagrange-type) FunctionSpace the states live on, as recorded.
        states: (n, K) full states, e.g. ``basis.reconstruct(Qh)``, in the state map's order,
            on rank 0 (ignored elsewhere; may be None). With ``rows``: (len(rows), K).
        times: (K,) increasing times of the columns (rank 0's are used).
        state_map: the recorder's state map (default ``StateMap.from_coordinates(V)``).
        name: the field's name in ParaView.
        rows: optional state rows that ``states`` holds (see :func:`state_rows`); the other
            rows are written as ``fill``.
        fill: value of the rows not in ``rows`` (0; ``np.nan`` to blank them in ParaView).
        engine: ADIOS2 engine, "BP4" (default), "BP5" or "BPFile".

    Returns:
        the path written.
    """
    V = _space(V)
    comm = V.mesh.comm
    state_map = _default_map(V, state_map)
    S, t = _checked_write(V, path, states, times, state_map, rows, fill, name, engine)
    local = _scatter(V, S, state_map)
    del S

    def write(bp: Path):
        f = dolfinx.fem.Function(V, name=name)
        try:
            writer = dolfinx.io.VTXWriter(comm, bp, [f], engine=engine)
        except RuntimeError as exc:
            raise InputError(f"VTX cannot write this space ({exc}); VTX writes (discontinuous) "
                             "Lagrange spaces only - interpolate into one first") from None
        with writer:
            for k, tk in enumerate(t):
                _set(f, local[:, k])
                writer.write(float(tk))

    return _replace_folder(comm, Path(path).absolute(), write)


def _checked_write(V, path, states, times, state_map, rows, fill, name, engine):
    """write_vtx's checks, the same verdict on every rank (an InputError before anything is
    written); returns rank 0's (states with every row, times) and the times on every rank."""
    comm = V.mesh.comm
    problem, S, t = None, None, None
    if engine not in _ENGINES:
        problem = f"engine must be one of {_ENGINES}, got {engine!r}"
    elif not isinstance(name, str) or not name:
        problem = f"name must be a non-empty string, got {name!r}"
    elif not isinstance(fill, (int, float, np.floating, np.integer)) or isinstance(fill, bool):
        problem = f"fill must be a number, got {fill!r}"
    if problem is None and comm.rank == 0:
        problem = _path_problem(path)
        if problem is None:
            problem, S = _root_states(V, states, state_map, rows, fill, single=False)
        if problem is None:
            problem, t = _times_problem(times, S.shape[1])
    _verdict(comm, problem)
    return S, (comm.bcast(t, root=0) if comm.size > 1 else t)


def _replace_folder(comm, target: Path, write) -> Path:
    """``write(folder)`` (collective) fills a new folder in a temporary directory beside
    ``target``, which then replaces ``target`` (one ``os.replace`` on rank 0; a previous
    version is moved aside first and put back if the move fails). On any error nothing of the
    new folder remains and ``target`` is as it was."""
    tmp = None
    if comm.rank == 0:
        tmp = tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    tmp = comm.bcast(tmp, root=0) if comm.size > 1 else tmp
    try:
        bp = Path(tmp) / target.name
        write(bp)
        comm.barrier()
        err = None
        if comm.rank == 0:
            old = Path(tmp) / ".previous"
            try:
                if target.exists():
                    os.replace(target, old)
                os.replace(bp, target)
            except OSError as exc:
                err = f"could not move the written {bp} to {target}: {exc}"
                if old.exists() and not target.exists():
                    os.replace(old, target)  # put the previous version back
        err = comm.bcast(err, root=0) if comm.size > 1 else err
        if err is not None:
            raise OSError(err)
    finally:
        if comm.rank == 0:
            shutil.rmtree(tmp, ignore_errors=True)
    return target
