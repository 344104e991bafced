"""Run the full-order model in time and record what the scene needs.

``run`` integrates a :class:`LagrangianSystem` from (q0, v0) with the midpoint variational
integrator and returns :class:`~dolfinx_lopinf.snapshots.Snapshots`: states (and velocities,
energies) every ``record_every`` steps up to ``state_until``, outputs y = E q every
``record_every`` steps up to ``t_end``. States are recorded in *state coordinates*
given by a :class:`StateMap` (for Hermite beams: nodal deflection w and rotation theta), and
gathered to rank 0 (other ranks get ``None``) - each rank only ever touches its owned dofs.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ._dolfinx import MPI, PETSc, dolfinx
from .errors import CheckpointMismatchError, FileFormatError, InputError
from .integrators import MidpointIntegrator, _check_dt
from .io_atomic import atomic_savez
from .lagrangian import LagrangianSystem
from .snapshots import Snapshots

fpetsc = dolfinx.fem.petsc


@dataclass(frozen=True)
class StateMap:
    """state[i] = scale[i] * dofs[order[i]] in global dof numbering.

    Attributes:
        order: (n,) global dof index of each state entry.
        scale: (n,) factor from dof to state value (1 for plain nodal values).
        blocks: name -> state rows of a physical block.
    """

    order: np.ndarray
    scale: np.ndarray
    blocks: dict = field(default_factory=dict)

    @classmethod
    def identity(cls, V) -> "StateMap":
        """Global dof order. Note: DOLFINx numbers dofs per partition, so this order (and
        thus the snapshot rows) changes with the number of ranks; see :meth:`from_coordinates`."""
        imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
        n = imap.size_global * bs
        return cls(np.arange(n), np.ones(n), {})

    @classmethod
    def from_coordinates(cls, V) -> "StateMap":
        """State rows ordered by dof coordinates (x, then y, then z; components of a vector
        field kept together), so the snapshots are the same for any number of ranks.

        Needs one coordinate per dof block (Lagrange-type elements); raises otherwise.
        """
        comm = V.mesh.comm
        imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
        n_owned = imap.size_local
        x = V.tabulate_dof_coordinates()[:n_owned]
        glob = imap.local_to_global(np.arange(n_owned, dtype=np.int32))
        pieces = comm.allgather((glob, x))
        G = np.concatenate([g for g, _ in pieces])
        X = np.vstack([c for _, c in pieces])
        scale = max(np.abs(X).max(), 1e-300)
        key = np.round(X / scale, 10)
        perm = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))
        if len(perm) > 1 and np.any(np.all(np.diff(key[perm], axis=0) == 0, axis=1)):
            raise ValueError("several dofs share a coordinate (not a Lagrange-type space): pass "
                             "an explicit StateMap (see dolfinx_lopinf.scenes.beam for Hermite)")
        order = (G[perm][:, None] * bs + np.arange(bs)[None, :]).ravel()
        return cls(order, np.ones(len(order)), {})

    def to_dofs(self, states: np.ndarray) -> np.ndarray:
        """Global dof vectors (n, K) from states (n, K) (inverse map)."""
        dofs = np.zeros_like(states)
        dofs[self.order] = states / self.scale[:, None] if states.ndim == 2 else states / self.scale
        return dofs

    def operator_to_state(self, A: np.ndarray) -> np.ndarray:
        """A dof-space bilinear form matrix (n, n) expressed in state coordinates:
        S^-T A S^-1 where state = S dofs."""
        As = A[np.ix_(self.order, self.order)]
        return As / np.outer(self.scale, self.scale)


def owned_global_dofs(V) -> np.ndarray:
    """Global indices of this rank's owned dofs (blocked spaces unrolled)."""
    imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
    start = imap.local_range[0]
    n_owned = imap.size_local
    return (np.repeat(np.arange(start, start + n_owned) * bs, bs)
            + np.tile(np.arange(bs), n_owned))


def gather_states(V, local: np.ndarray, state_map: StateMap) -> np.ndarray | None:
    """Gather owned rows (n_owned, K) of every rank into state coordinates on rank 0."""
    comm = V.mesh.comm
    pieces = comm.gather((owned_global_dofs(V), local), root=0)
    if comm.rank != 0:
        return None
    n_global = sum(len(g) for g, _ in pieces)
    dofs = np.empty((n_global,) + local.shape[1:])
    for g, values in pieces:
        dofs[g] = values
    scale = state_map.scale.reshape((-1,) + (1,) * (local.ndim - 1))
    return scale * dofs[state_map.order]


def output_matrix_in_state(V, E_local: np.ndarray, state_map: StateMap) -> np.ndarray:
    """The output matrix (p, n) acting on state coordinates, on every rank.

    ``E_local`` is (p, n_local) over local (owned + ghost) dofs as from
    :func:`point_output_matrix`; y = E_state @ state with state = scale * dofs[order].
    """
    comm = V.mesh.comm
    imap = V.dofmap.index_map
    bs = V.dofmap.index_map_bs
    local_nodes = np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32)
    glob = np.repeat(imap.local_to_global(local_nodes) * bs, bs) + np.tile(np.arange(bs), len(local_nodes))
    n = imap.size_global * bs
    E_dofs = np.zeros((E_local.shape[0], n))
    np.add.at(E_dofs.T, glob, E_local.T)
    E_dofs = comm.allreduce(E_dofs)
    return E_dofs[:, state_map.order] / state_map.scale


def point_output_matrix(V, points: np.ndarray, component: int | None = None) -> np.ndarray:
    """(p, n_local) matrix E with y = sum over ranks of E @ u.x.array (owned + ghost dofs):
    the values at ``points`` (p, 3) of an FE function (one ``component`` of a vector field).
    Each point is handled by one rank.

    Built from ``Function.eval`` on unit dof vectors, so it is exact for any element.
    """
    msh = V.mesh
    comm = msh.comm
    bs = V.dofmap.index_map_bs
    value_size = int(np.prod(V.value_shape)) if len(V.value_shape) else 1
    if value_size > 1 and component is None:
        raise ValueError(f"the space has {value_size} components: pass component=0..{value_size - 1}")
    comp = 0 if component is None else int(component)
    if not 0 <= comp < value_size:
        raise ValueError(f"component must be in 0..{value_size - 1}, got {component}")
    points = np.atleast_2d(np.asarray(points, dtype=float))
    tree = dolfinx.geometry.bb_tree(msh, msh.topology.dim)
    candidates = dolfinx.geometry.compute_collisions_points(tree, points)
    colliding = dolfinx.geometry.compute_colliding_cells(msh, candidates, points)
    n_local = (V.dofmap.index_map.size_local + V.dofmap.index_map.num_ghosts) * bs
    E = np.zeros((len(points), n_local))
    n_owned_cells = msh.topology.index_map(msh.topology.dim).size_local
    found = np.array([comm.rank if len(colliding.links(i)) and colliding.links(i)[0] < n_owned_cells
                      else comm.size for i in range(len(points))])
    owner = comm.allreduce(found, op=MPI.MIN)
    if np.any(owner == comm.size):
        raise ValueError(f"points {points[owner == comm.size].tolist()} lie outside the mesh")
    probe = dolfinx.fem.Function(V)
    for i, point in enumerate(points):
        if owner[i] != comm.rank:
            continue
        cell = colliding.links(i)[0]
        for block in V.dofmap.cell_dofs(cell):
            for k in range(bs):
                dof = block * bs + k
                probe.x.array[:] = 0.0
                probe.x.array[dof] = 1.0
                E[i, dof] = probe.eval(point, np.array([cell], dtype=np.int32))[comp]
    return E


# -- input checks ---------------------------------------------------------------------------

def _number(value, name, remedy="") -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}{remedy}") from None
    if not np.isfinite(x):
        raise InputError(f"{name} must be finite, got {value!r}{remedy}")
    return x


def _count(value, name, minimum: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{name} must be an integer >= {minimum}, got {value!r}")
    if value < minimum:
        raise InputError(f"{name} must be >= {minimum}, got {value}")
    return int(value)


def _collective(comm, problem, cls=InputError):
    """Raise ``cls(problem)`` on every rank when any rank has a problem (same verdict
    everywhere; one allgather)."""
    if comm.size == 1:
        if problem is not None:
            raise cls(problem)
        return
    for p in comm.allgather(problem):
        if p is not None:
            raise cls(p)


# -- checkpoints ----------------------------------------------------------------------------
#
# Per rank r and prefix P: two head files P.rank<r>.npz and P.rank<r>.b.npz written in turn
# (the previous head stays valid while the next one is written, so the ranks can always agree
# on a step all of them have), and append-only chunk files P.rank<r>.part<c>.npz holding what
# was recorded between checkpoint c-1 and c (state and velocity columns, energies, outputs).
# A head holds the integrator state (q, p, t, k), the run's fingerprint and a CRC of every
# chunk it refers to. Each checkpoint writes one chunk and one head, each atomically.

_FORMAT = "dolfinx_lopinf checkpoint 2"
_CHUNK_KEYS = ("Q", "Vel", "energies", "energy_times", "ys", "y_times")


def _crc(arrays: dict) -> int:
    crc = 0
    for key in _CHUNK_KEYS:
        a = np.ascontiguousarray(arrays[key])
        crc = zlib.crc32(repr((key, a.dtype.str, a.shape)).encode(), crc)
        crc = zlib.crc32(a.view(np.uint8).reshape(-1) if a.size else b"", crc)
    return crc


class _CheckpointFiles:
    """The files of one rank's checkpoint under a prefix."""

    def __init__(self, prefix, rank: int):
        prefix = Path(prefix)
        self.dir = prefix.parent
        self.base = f"{prefix.name}.rank{rank}"
        self.heads = (self.dir / f"{self.base}.npz", self.dir / f"{self.base}.b.npz")

    def chunk(self, c: int) -> Path:
        return self.dir / f"{self.base}.part{c:05d}.npz"

    def remedy(self) -> str:
        return (f"delete the files {self.dir / self.base}*.npz, use another checkpoint prefix, "
                "or pass checkpoint_restart=True to start the run over")

    def existing(self) -> list[Path]:
        pattern = re.compile(rf"^\.?{re.escape(self.base)}\.(npz|b\.npz|part\d+\.npz)(\..*\.tmp)?$")
        try:
            return [self.dir / n for n in os.listdir(self.dir) if pattern.match(n)]
        except OSError:
            return []

    def remove_all(self):
        for path in self.existing():
            try:
                path.unlink()
            except OSError:
                pass


def _load_npz(path: Path, remedy: str) -> dict:
    """Every array of an .npz, or FileFormatError naming the file and the remedy."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except Exception as exc:  # BadZipFile, EOFError, zlib.error, ValueError, OSError, ...
        raise FileFormatError(f"checkpoint file {path} is truncated or corrupt "
                              f"({type(exc).__name__}: {exc}); {remedy}") from None


def _probe_vectors(V):
    """Two deterministic probe states (local arrays, owned + ghosts) that depend only on the
    global dof numbers, and the owned rows' global numbers."""
    imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
    nodes = np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32)
    g = (np.repeat(imap.local_to_global(nodes) * bs, bs) + np.tile(np.arange(bs), len(nodes))) \
        .astype(float)
    return 1e-3 * np.sin(1.3 * g + 0.1), 1e-3 * np.cos(0.77 * g + 0.2), g[: imap.size_local * bs]


def _sketch(comm, owned: np.ndarray, g: np.ndarray) -> list:
    """Four random projections and the squared norm of a distributed vector (allreduced):
    equal vectors give equal sketches; any real change of the vector changes them."""
    R = np.cos(np.outer(g, [0.7548776662, 0.5698402910, 0.3247179572, 0.2207440846]) + np.arange(4))
    local = np.append(owned @ R, owned @ owned)
    return [float(x) for x in comm.allreduce(local)]


def _fingerprint(stepper, settings: dict, output_matrix, probe_times) -> dict:
    """Everything that determines the trajectory: settings (exact), and sketches of the
    assembled forms at probe states (mass/momentum, step residual and momentum, forcing at
    two times, energy), the bcs' global dofs, the output matrix (compared with a tolerance)."""
    system = stepper.system
    V, comm = system.V, system.V.mesh.comm
    fp = dict(settings)
    a, b, g = _probe_vectors(V)
    n_owned = len(g)
    f = stepper.forms
    saved = [(fn, fn.x.array.copy()) for fn in (f.q0, f.q1, system.q, system.q_t)]
    saved_time = None if system.time is None else np.array(system.time.value, copy=True)
    vec = fpetsc.create_vector(V)

    def assembled(form):
        with vec.localForm() as loc:
            loc.set(0.0)
        fpetsc.assemble_vector(vec, form)
        vec.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return _sketch(comm, vec.array[:n_owned], g)

    try:
        for fn, x in ((f.q0, a), (f.q1, b), (system.q, a), (system.q_t, b)):
            fn.x.array[:] = x
        fp["mass and momentum dL/dq_t at a probe state"] = assembled(stepper._momentum_at)
        fp["energy at a probe state"] = [float(comm.allreduce(
            dolfinx.fem.assemble_scalar(stepper._energy)))]
        for i, t in enumerate(probe_times):
            stepper._set_time(t)
            tag = f" (t = {t:.6g})" if system.time is not None else ""
            fp[f"step residual at a probe state{tag} (stiffness, potential, forcing)"] = \
                assembled(stepper._residual)
            fp[f"step momentum at a probe state{tag}"] = assembled(stepper._momentum)
            if system.forcing is not None:
                fp[f"forcing at a probe state{tag}"] = assembled(dolfinx.fem.form(system.forcing))
            if system.time is None:
                break
    finally:
        for fn, x in saved:
            fn.x.array[:] = x
        if saved_time is not None:
            system.time.value = saved_time
        vec.destroy()
    # Dirichlet conditions: the sorted global numbers of the constrained dofs
    bs = V.dofmap.index_map_bs
    owned_bc = stepper._bc_dofs[stepper._bc_dofs_owned_mask]
    glob = V.dofmap.index_map.local_to_global((owned_bc // bs).astype(np.int32)) * bs + owned_bc % bs
    all_bc = np.sort(np.concatenate(comm.allgather(np.asarray(glob, dtype=np.int64))))
    fp["Dirichlet dofs (global numbers)"] = f"{len(all_bc)} dofs, sha256 " + \
        hashlib.sha256(all_bc.tobytes()).hexdigest()[:16]
    if output_matrix is not None:
        E = np.asarray(output_matrix, dtype=float)
        fp["output matrix"] = [float(x) for x in comm.allreduce(
            np.concatenate([E @ a, E @ b]))] + [float(E.shape[0])]
    return fp


def _add_state_sketches(fp: dict, stepper) -> None:
    system = stepper.system
    comm = system.V.mesh.comm
    g = _probe_vectors(system.V)[2]
    n_owned = len(g)
    fp["initial state q0 (after the bcs)"] = _sketch(comm, stepper.q.x.array[:n_owned], g)
    fp["initial velocity v0 (after the bcs)"] = _sketch(comm, system.q_t.x.array[:n_owned], g)


def _differences(stored: dict, current: dict, n_global: int) -> list[str]:
    out = []
    for key in sorted(set(stored) | set(current)):
        old, new = stored.get(key), current.get(key)
        if key not in stored or key not in current:
            out.append(f"{key}: {'absent' if old is None else old!r} in the checkpoint, "
                       f"{'absent' if new is None else new!r} in this run")
        elif isinstance(old, list) and isinstance(new, list) and len(old) == len(new):
            o, n = np.array(old, dtype=float), np.array(new, dtype=float)
            # sketch entries: equal up to rounding (the same run reproduces them bit for bit;
            # the tolerance only keeps a harmless last-bit difference from refusing a resume)
            scale = np.sqrt(abs(o[-1])) + np.sqrt(abs(n[-1])) if len(o) == 5 else np.abs(o).max()
            tol = 1e-9 * max(scale * np.sqrt(max(n_global, 1)), np.abs(o).max(initial=0.0), 1e-300)
            same = np.all((np.abs(o - n) <= tol) | (np.isnan(o) & np.isnan(n)))
            if not same:
                rel = float(np.nanmax(np.abs(o - n)) / max(np.nanmax(np.abs(o)), 1e-300))
                out.append(f"{key} (differs by {rel:.2g} relative)")
        elif old != new:
            out.append(f"{key}: {old!r} in the checkpoint, {new!r} in this run")
    return out


def _resume(files: _CheckpointFiles, comm, fingerprint: dict, n_global: int):
    """Read this rank's newest head that every rank has, check its fingerprint, load its
    chunks. Collective: every rank returns the same kind of answer or raises the same error.
    Returns None (no checkpoint: start from step 0) or (head, chunks)."""
    heads, problem = {}, None
    for path in files.heads:
        if path.exists():
            try:
                data = _load_npz(path, files.remedy())
                if str(data.get("format", "")) != _FORMAT or "k" not in data:
                    raise FileFormatError(f"{path} is not a checkpoint of this version of "
                                          f"dolfinx_lopinf (no '{_FORMAT}' header); "
                                          f"{files.remedy()}")
                heads[int(data["k"])] = (path, data)
            except FileFormatError as exc:
                problem = problem or str(exc)
    _collective(comm, problem, FileFormatError)
    steps = comm.allgather(sorted(heads))
    if not any(steps):
        return None
    common = set(steps[0]).intersection(*map(set, steps[1:]))
    if not common:
        missing = [r for r, s in enumerate(steps) if not s]
        raise CheckpointMismatchError(
            f"the checkpoint under prefix {files.dir / files.base.rsplit('.rank', 1)[0]} is "
            f"incomplete: ranks {missing or 'all'} have no head at a step the others have "
            f"(steps per rank: {steps}); it comes from a run on another number of ranks or was "
            f"left by another run. {files.remedy()}")
    k = max(common)
    path, head = heads[k]
    try:
        stored = json.loads(str(head["fingerprint"]))
    except (KeyError, ValueError) as exc:
        stored, problem = {}, f"checkpoint file {path} has no readable fingerprint ({exc})"
    _collective(comm, problem, FileFormatError)
    diffs = _differences(stored, fingerprint, n_global)
    all_diffs = comm.allgather(diffs) if comm.size > 1 else [diffs]
    union = list(dict.fromkeys(d for ds in all_diffs for d in ds))
    if union:
        raise CheckpointMismatchError(
            f"checkpoint {path} belongs to another run, so resuming it would silently continue "
            "that run's trajectory. What differs: " + "; ".join(union) + f". {files.remedy()}")
    chunks, problem = [], None
    crcs = np.asarray(head["chunk_crc"], dtype=np.int64)
    for c in range(int(head["n_chunks"])):
        try:
            data = _load_npz(files.chunk(c), files.remedy())
            if any(key not in data for key in _CHUNK_KEYS) or _crc(data) != int(crcs[c]):
                raise FileFormatError(f"checkpoint chunk {files.chunk(c)} does not match its head "
                                      f"{path} (checksum); {files.remedy()}")
            chunks.append(data)
        except FileNotFoundError:
            problem = problem or f"checkpoint chunk {files.chunk(c)} is missing; {files.remedy()}"
            break
        except FileFormatError as exc:
            problem = problem or str(exc)
            break
    _collective(comm, problem, FileFormatError)
    return head, chunks


# -- the FOM run ----------------------------------------------------------------------------

def run(system: LagrangianSystem, q0, v0, dt: float, t_end: float, *, record_every: int = 1,
        state_until: float | None = None, output_matrix: np.ndarray | None = None,
        state_map: StateMap | None = None, record_velocity: bool = True,
        energy_every: int | None = None, energy_until: float | None = None, progress: bool = True,
        integrator: MidpointIntegrator | None = None, checkpoint: str | Path | None = None,
        checkpoint_every: int = 1000, checkpoint_restart: bool = False
        ) -> tuple[Snapshots | None, dict]:
    """Integrate the FOM and record snapshots.

    Every argument is checked before the first step (all ranks reach the same verdict);
    bad values raise :class:`~dolfinx_lopinf.errors.InputError` naming the argument.

    Args:
        system: the Lagrangian system.
        q0, v0: initial configuration and velocity (Functions on the system's space or local
            dof arrays, owned + ghosts). Values that violate the (homogeneous) Dirichlet
            conditions are set to 0 on the constrained dofs, with an
            :class:`~dolfinx_lopinf.errors.InputCorrectedWarning` saying by how much.
        dt, t_end: time step and final time (t_end / dt steps, must be a whole number).
        record_every: keep every ``record_every``-th step (1 <= record_every <= steps).
        state_until: record full states only while t <= state_until (default t_end; at least
            two samples, at most t_end); outputs are recorded to t_end.
        output_matrix: (p, n_local) from :func:`point_output_matrix` (or any local linear
            output); y = allreduce(E q_local).
        state_map: dof -> state coordinates (default: ordered by dof coordinates, so the
            result does not depend on the number of ranks).
        record_velocity: also record velocities (one mass solve per recorded step).
        energy_until: keep recording the energy (every ``energy_every`` samples) up to this
            time, past ``state_until`` (default: ``state_until``; at most t_end).
        energy_every: record the FOM energy every that many recorded samples (default: each
            recorded state sample; 0 disables).
        progress: show a tqdm progress bar on rank 0.
        integrator: reuse an existing integrator of ``system`` (its dt must match).
        checkpoint: a path prefix in an existing directory; every ``checkpoint_every`` steps
            each rank appends what it recorded since the last checkpoint to
            ``<prefix>.rank<i>.part<c>.npz`` and writes its integrator state to
            ``<prefix>.rank<i>.npz`` / ``.b.npz`` (alternately), each file atomically. When
            ``run`` starts and such files exist, it resumes from the newest step every rank
            has - only if the checkpoint's fingerprint (initial state, assembled forms at
            probe states, forcing, bcs, dt, t_end, record settings, output matrix, scheme,
            ranks) equals this run's; otherwise it raises
            :class:`~dolfinx_lopinf.errors.CheckpointMismatchError` naming what differs.
            A truncated or corrupt file raises :class:`~dolfinx_lopinf.errors.FileFormatError`
            naming it. The result of a resumed run equals an unbroken run's bit for bit. The
            files are removed when the run completes.
        checkpoint_every: steps between checkpoints (>= 1).
        checkpoint_restart: discard any existing checkpoint under ``checkpoint`` and start
            from step 0.

    Returns:
        ``(snapshots, info)``: Snapshots on rank 0 (None elsewhere); info has ``seconds``
        (wall time of the time loop), ``steps``, ``energy_drift`` (max |E - E0| / |E0| over
        the recorded energies), ``resumed_from_step``, ``checkpoint_bytes`` (bytes this rank
        wrote to checkpoint files) and ``checkpoint_seconds`` (time spent writing them).
    """
    # -- every input checked before any work ------------------------------------------------
    if not isinstance(system, LagrangianSystem):
        raise InputError(f"system must be a LagrangianSystem, got {type(system).__name__}")
    dt = _check_dt(dt)
    t_end = _number(t_end, "t_end")
    if t_end <= 0:
        raise InputError(f"t_end must be positive, got {t_end}")
    n_steps = int(round(t_end / dt))
    if n_steps < 1 or abs(n_steps * dt - t_end) > 1e-9 * t_end:
        raise InputError(f"t_end = {t_end} is not a whole number of steps dt = {dt}; choose "
                         "t_end = n * dt")
    record_every = _count(record_every, "record_every", 1)
    if record_every > n_steps:
        raise InputError(f"record_every = {record_every} is more than the {n_steps} steps of the "
                         "run: nothing but the initial state would be recorded; lower it")
    min_until = record_every * dt
    if state_until is None:
        n_state_steps = n_steps
    else:
        state_until = _number(state_until, "state_until")
        if not min_until * (1 - 1e-9) <= state_until <= t_end * (1 + 1e-9):
            raise InputError(
                f"state_until = {state_until} must lie in [record_every * dt, t_end] = "
                f"[{min_until:g}, {t_end:g}] (at least two recorded states, none after the run)")
        n_state_steps = min(int(round(state_until / dt)), n_steps)
    if energy_until is None:
        n_energy_steps = n_state_steps
    else:
        energy_until = _number(energy_until, "energy_until")
        if not 0 <= energy_until <= t_end * (1 + 1e-9):
            raise InputError(f"energy_until = {energy_until} must lie in [0, t_end = {t_end:g}]")
        n_energy_steps = min(int(round(energy_until / dt)), n_steps)
    energy_every = 1 if energy_every is None else _count(energy_every, "energy_every", 0)
    V = system.V
    comm = V.mesh.comm
    imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
    n_owned = imap.size_local * bs
    n_local = (imap.size_local + imap.num_ghosts) * bs
    n_global = imap.size_global * bs
    problem = None
    if output_matrix is not None:
        E = np.asarray(output_matrix)
        if E.ndim != 2 or E.shape[1] != n_local or not np.issubdtype(E.dtype, np.floating):
            problem = (f"output_matrix must be a real (p, n_local) array with n_local = {n_local} "
                       f"on this rank (from point_output_matrix), got shape {E.shape}, {E.dtype}")
        elif not np.all(np.isfinite(E)):
            problem = "output_matrix contains NaN or inf"
    _collective(comm, problem)
    if state_map is not None:
        if not isinstance(state_map, StateMap):
            raise InputError(f"state_map must be a StateMap, got {type(state_map).__name__}")
        order = np.asarray(state_map.order)
        scale = np.asarray(state_map.scale, dtype=float)
        if order.shape != (n_global,) or scale.shape != (n_global,):
            raise InputError(f"state_map has {order.shape} rows and {scale.shape} scales; the "
                             f"space has {n_global} dofs")
        if not np.array_equal(np.sort(order), np.arange(n_global)):
            raise InputError("state_map.order is not a permutation of the global dofs 0..n-1")
        if not np.all(np.isfinite(scale) & (scale != 0)):
            raise InputError("state_map.scale must be finite and nonzero")
    if integrator is not None:
        if not isinstance(integrator, MidpointIntegrator) or integrator.system is not system:
            raise InputError("integrator must be a MidpointIntegrator of this same system")
        if abs(integrator.dt - dt) > 1e-15 * dt:
            raise InputError(f"the integrator's dt = {integrator.dt} differs from dt = {dt}")
    files = None
    if checkpoint is not None:
        checkpoint_every = _count(checkpoint_every, "checkpoint_every", 1)
        prefix = Path(checkpoint)
        directory = prefix.parent
        problem = None
        if not directory.is_dir():
            problem = (f"checkpoint = {str(checkpoint)!r}: the directory {directory} does not exist "
                       "(create it first)")
        elif not os.access(directory, os.W_OK | os.X_OK):
            problem = f"checkpoint = {str(checkpoint)!r}: the directory {directory} is not writable"
        _collective(comm, problem)
        files = _CheckpointFiles(prefix, comm.rank)

    # -- set-up ------------------------------------------------------------------------------
    state_map = StateMap.from_coordinates(V) if state_map is None else state_map
    stepper = integrator if integrator is not None else MidpointIntegrator(system, dt)
    fingerprint = None
    if files is not None:
        settings = {"dt": repr(dt), "t_end": repr(t_end), "steps": n_steps,
                    "record_every": record_every, "state steps": n_state_steps,
                    "energy steps": n_energy_steps, "energy_every": energy_every,
                    "record_velocity": bool(record_velocity), "ranks": comm.size,
                    "global dofs": n_global, "owned dofs on this rank": n_owned,
                    "scheme": f"midpoint variational ({'linear' if stepper._linear else 'Newton'})"}
        fingerprint = _fingerprint(stepper, settings, output_matrix,
                                   (0.5 * dt, 0.6180339887 * t_end + 0.5 * dt))
    stepper.initialize(q0, v0)
    if fingerprint is not None:
        _add_state_sketches(fingerprint, stepper)
    n_rec = n_state_steps // record_every + 1
    Q = np.empty((n_owned, n_rec))
    Vel = np.empty((n_owned, n_rec)) if record_velocity else None
    energies, energy_times = [], []
    ys, y_times = [], []
    v = dolfinx.fem.Function(V)
    filled = 0  # state columns recorded so far
    k_start = 1
    saved = {"j": 0, "ne": 0, "ny": 0, "crc": [], "bytes": 0, "seconds": 0.0}

    def save_checkpoint(k):
        t_save = time.perf_counter()
        c = len(saved["crc"])
        p_out = output_matrix.shape[0] if output_matrix is not None else 0
        chunk = {"Q": Q[:, saved["j"]:filled],
                 "Vel": Vel[:, saved["j"]:filled] if Vel is not None else np.zeros((0, 0)),
                 "energies": np.array(energies[saved["ne"]:], dtype=float),
                 "energy_times": np.array(energy_times[saved["ne"]:], dtype=float),
                 "ys": (np.array(ys[saved["ny"]:], dtype=float).reshape(-1, p_out) if p_out
                        else np.zeros((0, 0))),
                 "y_times": np.array(y_times[saved["ny"]:], dtype=float)}
        atomic_savez(files.chunk(c), **chunk)
        crcs = saved["crc"] + [_crc(chunk)]
        head = files.heads[len(crcs) % 2]
        atomic_savez(head, format=np.array(_FORMAT), fingerprint=np.array(json.dumps(fingerprint)),
                      k=np.array(k), q=stepper.q.x.array, p=stepper.p.array, t=np.array(stepper.t),
                      n_chunks=np.array(len(crcs)), chunk_crc=np.array(crcs, dtype=np.int64),
                      filled=np.array(filled))
        saved.update(j=filled, ne=len(energies), ny=len(ys), crc=crcs)
        saved["bytes"] += files.chunk(c).stat().st_size + head.stat().st_size
        saved["seconds"] += time.perf_counter() - t_save

    def record(j):
        nonlocal filled
        Q[:, j] = stepper.q.x.array[:n_owned]
        need_v = record_velocity or (energy_every and j % energy_every == 0)
        if need_v:
            stepper.velocity(v)
            if record_velocity:
                Vel[:, j] = v.x.array[:n_owned]
        if energy_every and j % energy_every == 0:
            energies.append(stepper.energy(v))
            energy_times.append(stepper.t)
        filled = j + 1

    def record_energy():
        stepper.velocity(v)
        energies.append(stepper.energy(v))
        energy_times.append(stepper.t)

    def record_output():
        if output_matrix is not None:
            ys.append(comm.allreduce(output_matrix @ stepper.q.x.array))
            y_times.append(stepper.t)

    resumed = None
    if files is not None:
        if checkpoint_restart:
            files.remove_all()
        else:
            resumed = _resume(files, comm, fingerprint, n_global)
            if resumed is None:
                files.remove_all()  # stray chunks of a run that never wrote a head
    bar = None
    if progress and comm.rank == 0:
        from tqdm.auto import tqdm
        bar = tqdm(total=n_steps, desc="FOM", unit="step", mininterval=0.5, leave=False)
    t0 = time.perf_counter()
    seconds_states = 0.0
    if resumed is not None:
        head, chunks = resumed
        k_start = int(head["k"]) + 1
        stepper.q.x.array[:] = head["q"]
        stepper.p.array[:] = head["p"]
        stepper.t = float(head["t"])
        stepper.steps_taken = k_start - 1
        j0 = 0
        for data in chunks:
            j1 = j0 + data["Q"].shape[1]
            Q[:, j0:j1] = data["Q"]
            if Vel is not None:
                Vel[:, j0:j1] = data["Vel"]
            j0 = j1
            energies.extend(data["energies"].tolist())
            energy_times.extend(data["energy_times"].tolist())
            ys.extend(list(data["ys"]))
            y_times.extend(data["y_times"].tolist())
        filled = j0
        saved.update(j=filled, ne=len(energies), ny=len(ys),
                     crc=[int(c) for c in head["chunk_crc"]])
        if bar is not None:
            bar.update(k_start - 1)
    else:
        record(0)
        record_output()
    for k in range(k_start, n_steps + 1):
        stepper.step()
        if k % record_every == 0:
            j = k // record_every
            if k <= n_state_steps:
                record(j)
                if k == n_state_steps:
                    seconds_states = time.perf_counter() - t0
            elif k <= n_energy_steps and energy_every and j % energy_every == 0:
                record_energy()
            record_output()
        if bar is not None and k % 1000 == 0:
            bar.update(1000)
        if files is not None and k % checkpoint_every == 0 and k < n_steps:
            save_checkpoint(k)
    seconds = comm.allreduce(time.perf_counter() - t0, op=MPI.MAX)
    if bar is not None:
        bar.close()
    if files is not None:
        files.remove_all()
    energies = np.array(energies)
    drift = float(np.max(np.abs(energies - energies[0])) / abs(energies[0])) if len(energies) > 1 \
        and energies[0] != 0 else float("nan")
    info = {"seconds": seconds, "steps": n_steps, "energy_drift": drift,
            "resumed_from_step": k_start - 1,
            "seconds_to_state_until": comm.allreduce(seconds_states, op=MPI.MAX),
            "energy": energies, "energy_times": np.array(energy_times),
            "checkpoint_bytes": saved["bytes"], "checkpoint_seconds": saved["seconds"]}
    Qg = gather_states(V, Q, state_map)
    Vg = gather_states(V, Vel, state_map) if record_velocity else None
    if comm.rank != 0:
        return None, info
    times = dt * record_every * np.arange(n_rec)
    energy_full = energies if energy_every == 1 else None
    Y = np.array(ys).T if ys else None
    snaps = Snapshots(times=times, Q=Qg, blocks=state_map.blocks, V=Vg, energy=energy_full,
                      Y=Y, output_times=np.array(y_times) if ys else None)
    return snaps, info
