"""Full states back in the user's dolfinx space: into a Function, and into a VTX (.bp) file
that opens in ParaView next to the FOM's own output.

    Q = basis.reconstruct(traj.Qh)                     # (n, K) in the recorder's state order
    write_vtx("rom.bp", V, Q, traj.times)              # collective; Q needed on rank 0 only

    rows = state_rows(V, lambda x: np.isclose(x[2], 1.0))   # the state rows on a face
    write_vtx("top.bp", V, basis.reconstruct(traj.Qh, rows=rows), traj.times, rows=rows)

A state vector has the layout of :class:`~dolfinx_lopinf.fem.state.StateMap`: state[i] =
scale[i] * dofs[order[i]] in global dof numbering, as :class:`~dolfinx_lopinf.fem.recorder.
SnapshotRecorder` and :func:`~dolfinx_lopinf.fem.state.gather_states` gather it. The functions here
apply the exact inverse (dofs[order] = state / scale), then give each rank its owned dofs and
update the ghosts, so SnapshotRecorder -> states -> :func:`write_vtx` round-trips for any number
of ranks (the default state map is the recorder's default, ``StateMap.identity``: row i is
global dof i; pass ``state_map=rec.state_map`` for another, and ``info["state_map"]`` for
``lo.run``'s snapshots, which are ordered by dof coordinates).

Partial states (``rows=``): ``states`` holds only the listed state rows (what
``Basis.reconstruct(Qh, rows=rows)`` returns); the other state rows are written as
``fill`` (0 by default; ``np.nan`` makes ParaView leave them blank).

MPI: every function here is collective over ``V.mesh.comm``. ``path``, ``states``, ``times`` and
``rows`` are taken from rank 0 (other ranks may pass ``None`` or the same arrays; theirs are
ignored); ``name``, ``engine``, ``fill`` and ``overwrite`` must be the same on every rank
(checked), and every rank raises the same :class:`~dolfinx_lopinf.errors.InputError` on bad
input before anything is written.

What :func:`write_vtx` never does: write a space VTX cannot show (Hermite, Nedelec, ... - VTX
would write their derivative or edge dofs as point values: refused), delete a folder it did not
write (an existing ``path`` must be a VTX ``.bp`` folder - ADIOS2 files with VTX's ``vtk.xml``
schema - or empty, unless ``overwrite=True``), leave ``path`` missing at any instant (the swap
of :func:`~dolfinx_lopinf.core.io_atomic.swap_folder`), or let ADIOS2 run out of disk space (it
aborts the process then): the free space is checked against the file's size before the first
step and before every step, and a shortfall raises
:class:`~dolfinx_lopinf.errors.OutOfSpaceError` with nothing written. Temporary folders of a
killed write are removed by the next write of the same path.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np

from ..core._checks import as_real_array
from ..core.io_atomic import (recover_folder, remove_stale_temporaries, swap_folder,
                              temporary_prefix)
from ._dolfinx import MPI, dolfinx
from ..errors import InputError, OutOfSpaceError
from .agreement import agree, together
from .state import StateMap, _map_key, owned_global_dofs

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


def _verdict(comm, problem, where="write_vtx"):
    """Rank 0's problem (or any rank's), raised as InputError on every rank."""
    agree(comm, where, problem)


def _lagrange_problem(V) -> str | None:
    """Why VTX cannot show this space's dofs as point values (None for (discontinuous)
    Lagrange, scalar or blocked)."""
    element = V.ufl_element()
    if getattr(element, "is_mixed", False):
        return ("V is a mixed space: VTX writes one (discontinuous) Lagrange field; write each "
                "sub-space's collapsed field separately")
    family = getattr(element, "element_family", None)
    if family is not None and getattr(family, "name", str(family)) != "P":
        name = getattr(family, "name", str(family))
        return (f"V is a {name} space, which VTX cannot show: it writes every dof as a point "
                "value, so derivative (Hermite) or edge/face (Nedelec, Raviart-Thomas) dofs would "
                "come out as wrong values. Interpolate the states into a Lagrange space first "
                "(e.g. the nodal values of a Hermite beam into P1) and write that")
    return None


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
        state_map: the order of the state rows (default: row i is global dof i, a
            SnapshotRecorder's default; ``rec.state_map`` for another recorder order, and for
            ``lo.run``'s snapshots its ``info["state_map"]``, by dof coordinates - without it
            the field is scrambled).
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
    _verdict(comm, problem, "states_to_function")
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
    _verdict(comm, _map_problem(V, state_map), "state_rows")
    imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
    blocks = dolfinx.fem.locate_dofs_geometrical(V, marker)
    blocks = blocks[blocks < imap.size_local]
    glob = imap.local_to_global(blocks.astype(np.int32))
    dofs = (glob[:, None] * bs + np.arange(bs)[None, :]).ravel()
    dofs = np.concatenate(comm.allgather(dofs)) if comm.size > 1 else dofs
    inverse = np.empty(len(state_map.order), dtype=np.int64)
    inverse[np.asarray(state_map.order)] = np.arange(len(state_map.order))
    return np.sort(inverse[dofs])


_BP_ENTRY = re.compile(r"^(data\.\d+|md\.\d+|md\.idx|mmd\.\d+|profiling\.json)$")


def _not_vtx(folder: Path) -> str | None:
    """None when the existing ``folder`` is a VTX .bp (only ADIOS2 files, an index, and VTX's
    vtk.xml schema in its metadata) or empty; else what it holds."""
    try:
        entries = sorted(os.listdir(folder))
    except OSError as exc:
        return f"it cannot be listed ({exc})"
    if not entries:
        return None
    others = [e for e in entries if not _BP_ENTRY.match(e) or (folder / e).is_symlink()
              or not (folder / e).is_file()]
    if others:
        shown = ", ".join(others[:3]) + (f" and {len(others) - 3} more" if len(others) > 3 else "")
        return f"it holds {len(others)} entries that are not ADIOS2 files ({shown})"
    if "md.idx" not in entries or "md.0" not in entries:
        return "it has no ADIOS2 index (md.idx, md.0)"
    with open(folder / "md.0", "rb") as f:
        head = f.read(1 << 22)
    if b"vtk.xml" not in head:
        return "it is an ADIOS2 file but not a VTX one (no vtk.xml schema in md.0)"
    return None


def _path_problem(path, overwrite: bool) -> str | None:
    """Rank 0's checks of the target (after finishing an interrupted replacement of it)."""
    p = Path(path)
    if p.suffix != ".bp":
        return f"the VTX path must end in .bp (a folder ParaView opens), got {str(path)!r}"
    if not p.parent.is_dir():
        return f"the folder {str(p.parent)!r} of the VTX path does not exist; create it first"
    try:
        recover_folder(p)  # a kill between the two renames of a replacement: put it right
    except OSError as exc:
        return f"{str(path)!r}: an interrupted earlier replacement could not be finished ({exc})"
    if p.is_symlink() or (p.exists() and not p.is_dir()):
        return (f"{str(path)!r} exists and is not a .bp folder (a file or a link); refusing to "
                "replace it - delete it yourself or choose another path")
    if p.is_dir() and not overwrite:
        why = _not_vtx(p)
        if why is not None:
            return (f"{str(path)!r} exists and is not a VTX .bp folder: {why}. Refusing to replace "
                    "it (its contents would be deleted); choose another path, or pass "
                    "overwrite=True to replace it anyway")
    if not os.access(p.parent, os.W_OK | os.X_OK):
        return f"the folder {str(p.parent)!r} is not writable"
    return None


def _bytes_per_step(V) -> int:
    """An upper estimate of the bytes one VTX step of a function on V takes on disk (all
    ranks; VTX rewrites the mesh every step): per local point 3 coordinates and the values
    (vectors padded to 3), per cell its connectivity, its offset and type, 4 kB of metadata;
    times 1.25, the margin over what was measured (the real size was 0.89x-1.10x the sum
    for P1 scalars on 1D/2D meshes and P2 vectors on tetrahedra, 1 and 2 ranks). Collective."""
    imap = V.dofmap.index_map
    points = imap.size_local + imap.num_ghosts
    value_size = int(np.prod(V.value_shape)) if len(V.value_shape) else 1
    values = 1 if value_size == 1 else max(3, value_size)
    tdim = V.mesh.topology.dim
    cells = V.mesh.topology.index_map(tdim).size_local
    per_cell = V.dofmap.cell_dofs(0).size if cells else 0
    local = 8 * points * (3 + values) + 8 * cells * (per_cell + 2)
    return int(1.25 * (V.mesh.comm.allreduce(local, op=MPI.SUM) + 4096))


def _space_problem(folder: Path, need: int, what: str) -> str | None:
    try:
        free = shutil.disk_usage(folder).free
    except OSError as exc:
        return f"cannot read the free space of {folder} ({exc})"
    if free < need:
        return (f"{what} needs about {need / 1e6:.3g} MB but the file system of {folder} has "
                f"{free / 1e6:.3g} MB free; free some space or write fewer steps (or rows=) - "
                "nothing was written")
    return None


def _space_verdict(comm, folder: Path, need: int, what: str) -> None:
    """OutOfSpaceError on every rank when rank 0 sees less than ``need`` bytes free."""
    problem = _space_problem(folder, need, what) if comm.rank == 0 else None
    if comm.size > 1:
        problem = comm.bcast(problem, root=0)
    if problem is not None:
        exc = OutOfSpaceError(errno.ENOSPC, problem)
        exc.__lopinf_collective__ = True
        raise exc


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
              rows=None, fill: float = 0.0, engine: str = "BP4", overwrite: bool = False) -> Path:
    """Write a trajectory of full states as a VTX file (an ADIOS2 .bp folder) for ParaView.

    Everything is checked first (the same InputError on every rank, nothing on disk); the
    file is written into a temporary folder beside ``path`` and swapped with ``path`` at the
    end, so ``path`` is either absent/its previous version or the complete new file - never
    half of one, and never missing. An existing VTX .bp folder at ``path`` is replaced; any
    other existing folder is refused unless ``overwrite=True`` (see the module docstring).

    Args:
        path: the .bp folder to write (its parent folder must exist).
        V: the (Lagrange-type) FunctionSpace the states live on, as recorded.
        states: (n, K) full states, e.g. ``basis.reconstruct(Qh)``, in the state map's order,
            on rank 0 (ignored elsewhere; may be None). With ``rows``: (len(rows), K).
        times: (K,) increasing times of the columns (rank 0's are used).
        state_map: the order of the state rows (default: row i is global dof i, a
            SnapshotRecorder's default; ``rec.state_map`` for another recorder order, and for
            ``lo.run``'s snapshots its ``info["state_map"]``, by dof coordinates - without it
            the field is scrambled).
        name: the field's name in ParaView.
        rows: optional state rows that ``states`` holds (see :func:`state_rows`); the other
            rows are written as ``fill``.
        fill: value of the rows not in ``rows`` (0; ``np.nan`` to blank them in ParaView).
        engine: ADIOS2 engine, "BP4" (default), "BP5" or "BPFile".
        overwrite: replace an existing folder at ``path`` even when it is not a VTX .bp.

    Returns:
        the path written (rank 0's, on every rank).

    Raises:
        InputError: bad input, a space VTX cannot show, an existing folder that is not a VTX
            .bp (without ``overwrite``) - on every rank, before anything is written.
        OutOfSpaceError: not enough free disk space (checked before and during the write);
            ``path`` is left as it was.
    """
    V = _space(V)
    comm = V.mesh.comm
    agree(comm, "write_vtx", _lagrange_problem(V), name=name, engine=engine, fill=fill,
          overwrite=overwrite, state_map=_map_key(state_map))
    state_map = _default_map(V, state_map)
    S, t, target = _checked_write(V, path, states, times, state_map, rows, fill, name, engine,
                                  overwrite)
    per_step = _bytes_per_step(V)
    _space_verdict(comm, target.parent, len(t) * per_step + (1 << 20),
                   f"writing {target.name} ({len(t)} steps of about {per_step / 1e3:.3g} kB)")
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
                # ADIOS2 aborts the process when the disk fills: stop before it can
                _space_verdict(comm, bp.parent, 2 * per_step + (1 << 20),
                               f"step {k + 1} of {len(t)} of {target.name}")
                _set(f, local[:, k])
                writer.write(float(tk))

    with together(comm, "write_vtx"):
        return _replace_folder(comm, target, write)


def _checked_write(V, path, states, times, state_map, rows, fill, name, engine, overwrite):
    """write_vtx's checks, the same verdict on every rank (an InputError before anything is
    written); returns rank 0's states (with every row), the times and rank 0's absolute path
    (on every rank)."""
    comm = V.mesh.comm
    problem, S, t = None, None, None
    if engine not in _ENGINES:
        problem = f"engine must be one of {_ENGINES}, got {engine!r}"
    elif not isinstance(name, str) or not name:
        problem = f"name must be a non-empty string, got {name!r}"
    elif not isinstance(fill, (int, float, np.floating, np.integer)) or isinstance(fill, bool):
        problem = f"fill must be a number, got {fill!r}"
    elif not isinstance(overwrite, (bool, np.bool_)):
        problem = f"overwrite must be True or False, got {overwrite!r}"
    target = None
    if problem is None and comm.rank == 0:
        try:
            target = Path(path).absolute()
        except TypeError:
            problem = f"path must be a str or Path ending in .bp, got {type(path).__name__}"
        if problem is None:
            problem = _path_problem(target, bool(overwrite))
        if problem is None:
            problem, S = _root_states(V, states, state_map, rows, fill, single=False)
        if problem is None:
            problem, t = _times_problem(times, S.shape[1])
    _verdict(comm, problem)
    if comm.size > 1:
        t, target = comm.bcast((t, target), root=0)
    return S, t, target


def _replace_folder(comm, target: Path, write) -> Path:
    """``write(folder)`` (collective) fills a new folder in a temporary directory beside
    ``target`` (named after its owner, ``.<target>.<host>-<pid>.<random>.tmp``, so the next
    write removes it if this process is killed), which then takes the place of ``target``
    (:func:`~dolfinx_lopinf.core.io_atomic.swap_folder` on rank 0: atomic exchange, or a
    recoverable two-step). On any error nothing of the new folder remains and ``target`` is
    as it was."""
    tmp = None
    if comm.rank == 0:
        remove_stale_temporaries(target.parent, target.name)
        tmp = tempfile.mkdtemp(prefix=temporary_prefix(target.name), suffix=".tmp",
                               dir=target.parent)
    tmp = comm.bcast(tmp, root=0) if comm.size > 1 else tmp
    try:
        bp = Path(tmp) / target.name
        write(bp)
        comm.barrier()
        err = None
        if comm.rank == 0:
            try:
                swap_folder(bp, target)
            except OSError as exc:
                err = f"could not move the written {bp} to {target}: {exc}"
        err = comm.bcast(err, root=0) if comm.size > 1 else err
        if err is not None:
            exc = OSError(err)
            exc.__lopinf_collective__ = True
            raise exc
    finally:
        if comm.rank == 0:
            shutil.rmtree(tmp, ignore_errors=True)  # the new folder on error, else the old one
    return target
