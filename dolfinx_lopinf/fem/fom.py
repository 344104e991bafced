"""Run the full-order model in time and record what the scene needs.

One time loop, :func:`run_loop` (also reached as ``run(integrator, n_steps, sinks=...)``),
steps any :class:`~dolfinx_lopinf.fem.integrators.Integrator` (midpoint, Newmark) and hands every
step to pluggable sinks: :class:`StateRecorder`, :class:`OutputProbe`, :class:`EnergyProbe`,
:class:`FieldSnapshots`, :class:`Every` (e.g. a :class:`~dolfinx_lopinf.fem.streaming.StreamingPOD`),
:class:`CheckpointSink`, :class:`Progress`.

``run(system, q0, v0, dt, t_end, ...)`` integrates a :class:`LagrangianSystem` from (q0, v0) with the midpoint variational
integrator and returns :class:`~dolfinx_lopinf.core.snapshots.Snapshots`: states (and velocities,
energies) every ``record_every`` steps up to ``state_until``, outputs y = E q every
``record_every`` steps up to ``t_end``. States are recorded in *state coordinates*
given by a :class:`StateMap` (for Hermite beams: nodal deflection w and rotation theta), and
gathered to rank 0 (other ranks get ``None``) - each rank only ever touches its owned dofs.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ._dolfinx import MPI, dolfinx
from ..errors import InputError
from .agreement import agree, check, together
from .checkpoint import (_FORMAT, _add_state_sketches, _checkpoint_files, _CheckpointFiles, _crc,
                         _fingerprint, _resume)
from .integrators import MidpointIntegrator, NewmarkIntegrator, _check_dt
from ..core.io_atomic import atomic_savez
from .lagrangian import LagrangianSystem
from ..core.snapshots import Snapshots

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
            raise InputError("several dofs share a coordinate (not a Lagrange-type space): pass "
                             "an explicit StateMap (see dolfinx_lopinf.scenes.beam for Hermite)")
        order = (G[perm][:, None] * bs + np.arange(bs)[None, :]).ravel()
        return cls(order, np.ones(len(order)), {})

    def to_dofs(self, states: np.ndarray) -> np.ndarray:
        """Global dof vectors (n, K) from states (n, K) (inverse map)."""
        dofs = np.zeros_like(states)
        dofs[self.order] = states / self.scale[:, None] if states.ndim == 2 else states / self.scale
        return dofs

    def to_local_dofs(self, V, states: np.ndarray) -> np.ndarray:
        """States (n, K) or (n,) as this rank's local dof rows of V: owned, then ghosts
        (the layout of ``Function.x.array``); ``states`` on every rank."""
        imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
        blocks = imap.local_to_global(np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32))
        return self.to_dofs(states)[(blocks.astype(np.int64)[:, None] * bs + np.arange(bs)[None, :]).ravel()]


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
    n_local = (imap.size_local + imap.num_ghosts) * bs

    def local():
        E = np.asarray(E_local)
        if E.ndim != 2 or E.shape[1] != n_local or E.dtype.kind not in "fiu":
            raise InputError(f"E_local must be a real (p, n_local) array with n_local = {n_local} "
                             f"on this rank (from point_output_matrix), got shape {E.shape}")
        if not np.all(np.isfinite(E)):
            raise InputError("E_local contains NaN or inf")
        return E.shape[0]

    p = check(comm, "output_matrix_in_state", local, state_map=_map_key(state_map))
    agree(comm, "output_matrix_in_state", None, outputs=p)
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
    if not isinstance(V, dolfinx.fem.FunctionSpace):
        raise InputError(f"V must be a dolfinx FunctionSpace, got {type(V).__name__}")
    msh = V.mesh
    comm = msh.comm
    bs = V.dofmap.index_map_bs
    problem, points, comp = None, _points(points, msh.geometry.dim), None
    if isinstance(points, str):
        problem, points = points, None
    value_size = int(np.prod(V.value_shape)) if len(V.value_shape) else 1
    if problem is None and value_size > 1 and component is None:
        problem = f"the space has {value_size} components: pass component=0..{value_size - 1}"
    elif problem is None:
        if component is not None and (isinstance(component, (bool, np.bool_))
                                      or not isinstance(component, (int, np.integer))):
            problem = f"component must be an integer in 0..{value_size - 1}, got {component!r}"
        else:
            comp = 0 if component is None else int(component)
            if not 0 <= comp < value_size:
                problem = f"component must be in 0..{value_size - 1}, got {component}"
    agree(comm, "point_output_matrix", problem, points=points, component=comp)
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
        raise InputError(f"points {points[owner == comm.size].tolist()} lie outside the mesh "
                         "(or on no owned cell of any rank): move them inside")
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


def _points(points, gdim: int):
    """Points as a finite (p, 3) array (columns beyond those given are 0), or a message."""
    try:
        P = np.asarray(points, dtype=float)
    except (TypeError, ValueError):
        return (f"points must be an array of coordinates (p, {gdim}) or (p, 3), got "
                f"{type(points).__name__} {str(points)[:60]}")
    if P.ndim == 1:
        P = P[None, :]
    if P.ndim != 2 or P.shape[0] == 0 or not gdim <= P.shape[1] <= 3:
        return (f"points must have shape (p, {gdim}) or (p, 3) - one row of coordinates per "
                f"point on this {gdim}-D mesh - got shape {np.shape(points)}")
    if not np.all(np.isfinite(P)):
        return f"points contain NaN or inf (rows {np.flatnonzero(~np.all(np.isfinite(P), axis=1)).tolist()})"
    return np.hstack([P, np.zeros((P.shape[0], 3 - P.shape[1]))])


def _map_key(state_map):
    """What identifies a state map across ranks (for :func:`agree`): its dof order (exactly)
    and its scales."""
    if not isinstance(state_map, StateMap):
        return state_map
    return (np.asarray(state_map.order), np.asarray(state_map.scale, dtype=float))


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


# -- the time loop ---------------------------------------------------------------------------
#
# One loop for every integrator (dolfinx_lopinf.fem.integrators.Integrator: midpoint, linear or
# Newton, and Newmark): it steps and hands each step to its sinks, which record what the scene
# needs (states, outputs, energies, streaming POD, fields, checkpoints, a progress bar).


class LoopState:
    """What a sink sees at step ``k`` of :func:`run_loop`: the integrator, the step number,
    and the velocity and energy at this step (each computed once, on first request, and
    shared by every sink)."""

    def __init__(self, integrator, n_steps: int, comm):
        self.integrator, self.n_steps, self.comm = integrator, int(n_steps), comm
        self.k = 0
        self.t_loop_start = time.perf_counter()
        self._v = None
        self._v_step = self._e_step = -1
        self._e = None

    @property
    def t(self) -> float:
        return self.integrator.t

    @property
    def q(self):
        return self.integrator.q

    def velocity(self):
        """The velocity at this step (a Function owned by the loop state; do not keep it)."""
        if self._v_step != self.k:
            if self._v is None:
                self._v = dolfinx.fem.Function(self.integrator.q.function_space)
            self.integrator.velocity(self._v)
            self._v_step = self.k
        return self._v

    def energy(self) -> float:
        """The integrator's energy at this step (collective)."""
        if self._e_step != self.k:
            self._e = self.integrator.energy(self.velocity())
            self._e_step = self.k
        return self._e


class Sink:
    """A sink of the time loop: :meth:`start` at step 0 (the initial state), :meth:`after`
    after every step, :meth:`finish` once the loop ends. Override what you need; by default
    :meth:`start` does what :meth:`after` does."""

    def start(self, s: LoopState) -> None:
        self.after(s)

    def after(self, s: LoopState) -> None:
        pass

    def finish(self, s: LoopState) -> None:
        pass


class Every(Sink):
    """Call ``fn(state)`` at every ``every``-th step k (k = 0 included) up to ``until_step``,
    or exactly at ``steps`` when given."""

    def __init__(self, fn, *, every: int = 1, until_step: int | None = None, steps=None):
        self.fn, self.every, self.until_step = fn, _count(every, "every", 1), until_step
        self.steps = None if steps is None else set(int(k) for k in steps)

    def after(self, s):
        if self.steps is not None:
            if s.k in self.steps:
                self.fn(s)
        elif s.k % self.every == 0 and (self.until_step is None or s.k <= self.until_step):
            self.fn(s)


class OutputProbe(Sink):
    """y = sum over ranks of E q_local every ``every`` steps (``values``: list of (p,) arrays,
    ``times``: their times)."""

    def __init__(self, output_matrix, *, every: int = 1):
        self.E, self.every = output_matrix, every
        self.values, self.times = [], []

    def after(self, s):
        if s.k % self.every == 0:
            self.values.append(s.comm.allreduce(self.E @ s.q.x.array))
            self.times.append(s.t)


class EnergyProbe(Sink):
    """The integrator's energy every ``every`` steps (``values``, ``times``)."""

    def __init__(self, *, every: int = 1):
        self.every = every
        self.values, self.times = [], []

    def after(self, s):
        if s.k % self.every == 0:
            self.values.append(s.energy())
            self.times.append(s.t)


class FieldSnapshots(Sink):
    """Copies of the local dof array (owned + ghosts) at the given steps: ``fields[k]``."""

    def __init__(self, steps):
        self.steps = set(int(k) for k in steps)
        self.fields = {}

    def after(self, s):
        if s.k in self.steps:
            self.fields[s.k] = s.q.x.array.copy()


class Progress(Sink):
    """A tqdm bar on rank 0 (updated every ``every`` steps)."""

    def __init__(self, *, every: int = 1000, desc: str = "FOM"):
        self.every, self.desc, self.bar, self._shown = every, desc, None, 0

    def _open(self, s):
        if self.bar is None and s.comm.rank == 0:
            from tqdm.auto import tqdm
            self.bar = tqdm(total=s.n_steps, desc=self.desc, unit="step", mininterval=0.5,
                            leave=False)
            if s.k:
                self.bar.update(s.k)
                self._shown = s.k

    def start(self, s):
        self._open(s)

    def after(self, s):
        self._open(s)
        if self.bar is not None and s.k % self.every == 0:
            self.bar.update(s.k - self._shown)
            self._shown = s.k

    def finish(self, s):
        if self.bar is not None:
            self.bar.close()


class StateRecorder(Sink):
    """The FOM recorder of :func:`run`: owned states (and velocities) every ``record_every``
    steps up to ``state_steps``, the energy every ``energy_every`` recorded samples up to
    ``energy_steps``."""

    def __init__(self, n_owned: int, *, record_every: int, state_steps: int, energy_steps: int,
                 energy_every: int, record_velocity: bool):
        self.record_every, self.state_steps, self.energy_steps = record_every, state_steps, energy_steps
        self.energy_every, self.n_owned = energy_every, n_owned
        n_rec = state_steps // record_every + 1
        self.Q = np.empty((n_owned, n_rec))
        self.Vel = np.empty((n_owned, n_rec)) if record_velocity else None
        self.energies, self.energy_times = [], []
        self.filled = 0  # state columns recorded so far
        self.seconds_states = 0.0

    def _record(self, s, j):
        n = self.n_owned
        self.Q[:, j] = s.q.x.array[:n]
        if self.Vel is not None:
            self.Vel[:, j] = s.velocity().x.array[:n]
        if self.energy_every and j % self.energy_every == 0:
            self.energies.append(s.energy())
            self.energy_times.append(s.t)
        self.filled = j + 1

    def start(self, s):
        self._record(s, 0)

    def after(self, s):
        k = s.k
        if k % self.record_every:
            return
        j = k // self.record_every
        if k <= self.state_steps:
            self._record(s, j)
            if k == self.state_steps:
                self.seconds_states = time.perf_counter() - s.t_loop_start
        elif k <= self.energy_steps and self.energy_every and j % self.energy_every == 0:
            self.energies.append(s.energy())
            self.energy_times.append(s.t)


class CheckpointSink(Sink):
    """Every ``every`` steps (not at the last one) append what ``recorder`` and ``probe``
    recorded since the previous checkpoint to a chunk file and write the integrator state to
    a head file (each atomically); see the format notes above :func:`_crc`."""

    def __init__(self, files: _CheckpointFiles, fingerprint: dict, recorder: StateRecorder,
                 probe: OutputProbe | None, *, every: int):
        self.files, self.fingerprint, self.every = files, fingerprint, every
        self.recorder, self.probe = recorder, probe
        self.j = self.ne = self.ny = 0
        self.crc, self.bytes, self.seconds = [], 0, 0.0

    def after(self, s):
        if s.k % self.every == 0 and s.k < s.n_steps:
            self.save(s)

    def save(self, s):
        t_save = time.perf_counter()
        rec, probe, it = self.recorder, self.probe, s.integrator
        c = len(self.crc)
        p_out = probe.E.shape[0] if probe is not None else 0
        ys = probe.values if probe is not None else []
        y_times = probe.times if probe is not None else []
        chunk = {"Q": rec.Q[:, self.j:rec.filled],
                 "Vel": rec.Vel[:, self.j:rec.filled] if rec.Vel is not None else np.zeros((0, 0)),
                 "energies": np.array(rec.energies[self.ne:], dtype=float),
                 "energy_times": np.array(rec.energy_times[self.ne:], dtype=float),
                 "ys": (np.array(ys[self.ny:], dtype=float).reshape(-1, p_out) if p_out
                        else np.zeros((0, 0))),
                 "y_times": np.array(y_times[self.ny:], dtype=float)}
        atomic_savez(self.files.chunk(c), **chunk)
        crcs = self.crc + [_crc(chunk)]
        head = self.files.heads[len(crcs) % 2]
        atomic_savez(head, format=np.array(_FORMAT),
                     fingerprint=np.array(json.dumps(self.fingerprint)), k=np.array(s.k),
                     q=it.q.x.array, p=it.p.array, t=np.array(it.t),
                     n_chunks=np.array(len(crcs)), chunk_crc=np.array(crcs, dtype=np.int64),
                     filled=np.array(rec.filled))
        self.j, self.ne, self.ny, self.crc = rec.filled, len(rec.energies), len(ys), crcs
        self.bytes += self.files.chunk(c).stat().st_size + head.stat().st_size
        self.seconds += time.perf_counter() - t_save

    def restore(self, integrator, head, chunks) -> int:
        """Put a resumed checkpoint back into the integrator, recorder and probe; return the
        first step still to take."""
        rec, probe = self.recorder, self.probe
        k_start = int(head["k"]) + 1
        integrator.q.x.array[:] = head["q"]
        integrator.p.array[:] = head["p"]
        integrator.t = float(head["t"])
        integrator.steps_taken = k_start - 1
        j0 = 0
        for data in chunks:
            j1 = j0 + data["Q"].shape[1]
            rec.Q[:, j0:j1] = data["Q"]
            if rec.Vel is not None:
                rec.Vel[:, j0:j1] = data["Vel"]
            j0 = j1
            rec.energies.extend(data["energies"].tolist())
            rec.energy_times.extend(data["energy_times"].tolist())
            if probe is not None:
                probe.values.extend(list(data["ys"]))
                probe.times.extend(data["y_times"].tolist())
        rec.filled = j0
        self.j, self.ne = rec.filled, len(rec.energies)
        self.ny = len(probe.values) if probe is not None else 0
        self.crc = [int(c) for c in head["chunk_crc"]]
        return k_start

    def finish(self, s):
        self.files.remove_all()


def run_loop(integrator, n_steps: int, sinks=(), *, inputs=None, first_step: int = 1) -> dict:
    """The time loop: ``n_steps`` steps of ``integrator`` (any
    :class:`~dolfinx_lopinf.fem.integrators.Integrator`, already initialised), each handed to the
    ``sinks`` in order.

    Args:
        integrator: midpoint (linear or Newton) or Newmark integrator, initialised.
        n_steps: steps to take.
        sinks: :class:`Sink` objects (``StateRecorder``, ``OutputProbe``, ``EnergyProbe``,
            ``Every`` - e.g. ``StreamingPOD.sink()`` -, ``FieldSnapshots``,
            ``CheckpointSink``, ``Progress``), or plain callables ``f(state)`` called at
            every step including step 0.
        inputs: ``inputs(t) -> values`` at the new time t_k = t_0 + k dt, passed to
            ``integrator.step`` (schemes with input channels, e.g. Newmark); None: no inputs.
        first_step: 1 for a fresh run (the sinks' ``start`` sees step 0); k > 1 to continue
            a run restored to step k - 1 (``start`` is skipped).

    Returns:
        ``{"seconds": wall time of the loop (max over ranks), "steps": n_steps}``.

    Collective: the arguments are checked on every rank and agreed on (n_steps, first_step,
    the kinds of sinks, whether there are inputs, the integrator's dt and t must be the same
    on every rank; the same error on every rank otherwise), the integrator must be open and
    initialised. With inputs, their values are compared at every step (one small allgather;
    on one rank nothing). A sink or input function that raises on one rank only aborts the
    job (the other ranks are inside the next step's solve; see
    :mod:`dolfinx_lopinf.fem.agreement`).
    """
    for name in ("step", "velocity", "energy", "dt", "q"):
        if not hasattr(integrator, name):
            raise InputError(f"run needs an Integrator (midpoint or Newmark, see "
                             f"dolfinx_lopinf.fem.integrators) or a LagrangianSystem, got "
                             f"{type(integrator).__name__} (no '{name}')")
    comm = integrator.q.function_space.mesh.comm
    loop, problem = None, None
    try:
        loop = _loop_plan(integrator, n_steps, sinks, inputs, first_step)
    except Exception as exc:  # noqa: BLE001 - every rank must hear of it
        problem = exc
    agree(comm, "run", problem, **({} if loop is None else loop.pop("settings")))
    n_steps, first_step, sinks = loop["n_steps"], loop["first_step"], loop["sinks"]
    state = LoopState(integrator, n_steps, comm)
    dt = integrator.dt
    t_begin = integrator.t - (first_step - 1) * dt
    state.k = first_step - 1
    if loop["agreed"]:
        integrator._agreed_loop = True  # every rank steps without values: no per-step check
    try:
        with together(comm, "run (the time loop: steps, inputs and sinks)"):
            if first_step == 1:
                for sink in sinks:
                    sink.start(state)
            for k in range(first_step, n_steps + 1):
                if inputs is None:
                    integrator.step()
                else:
                    integrator.step(inputs(t_begin + k * dt))
                state.k = k
                for sink in sinks:
                    sink.after(state)
    finally:
        if loop["agreed"]:
            integrator._agreed_loop = False
    seconds = comm.allreduce(time.perf_counter() - state.t_loop_start, op=MPI.MAX)
    with together(comm, "run (the sinks' finish)"):
        for sink in sinks:
            sink.finish(state)
    return {"seconds": seconds, "steps": n_steps}


def _loop_plan(integrator, n_steps, sinks, inputs, first_step) -> dict:
    """:func:`run_loop`'s checks on this rank alone (raises; no collective): the counts, the
    sinks as :class:`Sink` objects, the step function to call, the settings every rank must
    share."""
    n_steps = _count(n_steps, "n_steps", 0)
    first_step = _count(first_step, "first_step", 1)
    if isinstance(sinks, (Sink, str, bytes)) or callable(sinks) or not hasattr(sinks, "__iter__"):
        raise InputError(f"sinks must be a list of Sink objects or callables f(state), got "
                         f"{type(sinks).__name__}; wrap a single sink in a list: sinks=[sink]")
    sinks = list(sinks)
    for i, s in enumerate(sinks):
        if not isinstance(s, Sink) and not callable(s):
            raise InputError(f"sinks[{i}] = {s!r} is neither a Sink (StateRecorder, OutputProbe, "
                             "EnergyProbe, FieldSnapshots, Every, ...) nor a callable f(state) "
                             "called at every step; pass one of those")
    sinks = [s if isinstance(s, Sink) else Every(s) for s in sinks]
    if inputs is not None and not callable(inputs):
        raise InputError(f"inputs must be a callable inputs(t) -> input values (or None), got "
                         f"{type(inputs).__name__}")
    name = type(integrator).__name__
    if getattr(integrator, "closed", False):
        raise InputError(f"the {name} was closed (close() or the end of its with block) and its "
                         "PETSc objects destroyed; make a new one")
    if not getattr(integrator, "initialized", True):
        raise InputError(f"the {name} was never initialised: it would step from zero and "
                         "record zeros. Call integrator.initialize(...) before run(integrator, "
                         "n_steps) (run(system, q0, v0, dt, t_end) does it for you)")
    agreed = False  # True: the integrator's step need not agree on its arguments every step
    if isinstance(integrator, MidpointIntegrator):
        if inputs is not None:
            raise InputError("a MidpointIntegrator takes no input values (inputs= is for "
                             "schemes with input channels, e.g. Newmark): put the forcing into "
                             "the LagrangianSystem (forcing=..., time=...)")
        agreed = True
    elif isinstance(integrator, NewmarkIntegrator):
        if integrator.inputs and inputs is None:
            raise InputError(f"this NewmarkIntegrator has {len(integrator.inputs)} input "
                             "channel(s): pass inputs=lambda t: values")
        if not integrator.inputs and inputs is not None:
            raise InputError("this NewmarkIntegrator has no input forms: drop inputs= (or build "
                             "it with input_forms=...)")
        agreed = inputs is None  # with inputs, their values are compared at every step
    # a progress bar on rank 0 only is fine (no collective); every other sink must be on all
    settings = {"n_steps": n_steps, "first_step": first_step,
                "sinks": [type(s).__name__ for s in sinks if not isinstance(s, Progress)],
                "inputs": inputs is not None,
                "integrator": name, "dt": float(integrator.dt), "t": float(integrator.t)}
    return {"n_steps": n_steps, "first_step": first_step, "sinks": sinks, "agreed": agreed,
            "settings": settings}


# -- the FOM run of a LagrangianSystem: the time loop with the recorder's sinks -------------

def _check_state_map(state_map, n_global: int) -> None:
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


def _plan(system, dt, t_end, record_every, state_until, output_matrix, state_map, energy_every,
          energy_until, integrator, checkpoint, checkpoint_every, record_velocity,
          checkpoint_restart) -> dict:
    """Every input of :func:`run` checked before any work: on each rank, then one collective
    verdict (:func:`~dolfinx_lopinf.fem.agreement.agree`) - the same error on every rank, also
    when the ranks passed different settings. Returns the derived step counts and sizes."""
    if not isinstance(system, LagrangianSystem):
        raise InputError(f"system must be a LagrangianSystem, got {type(system).__name__}")
    comm = system.V.mesh.comm
    plan, problem = None, None
    try:
        plan = _plan_local(system, dt, t_end, record_every, state_until, output_matrix, state_map,
                           energy_every, energy_until, integrator, checkpoint, checkpoint_every,
                           record_velocity, checkpoint_restart)
    except Exception as exc:  # noqa: BLE001 - every rank must hear of it
        problem = exc
    agree(comm, "run", problem, **({} if plan is None else plan.pop("settings")))
    return plan


def _plan_local(system, dt, t_end, record_every, state_until, output_matrix, state_map,
                energy_every, energy_until, integrator, checkpoint, checkpoint_every,
                record_velocity, checkpoint_restart) -> dict:
    """:func:`_plan` on this rank alone (raises on a bad value; no collective)."""
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
    p_out = None
    if output_matrix is not None:
        E = np.asarray(output_matrix)
        if E.ndim != 2 or E.shape[1] != n_local or not np.issubdtype(E.dtype, np.floating):
            raise InputError(f"output_matrix must be a real (p, n_local) array with n_local = "
                             f"{n_local} on this rank (from point_output_matrix), got shape "
                             f"{E.shape}, {E.dtype}")
        if not np.all(np.isfinite(E)):
            raise InputError("output_matrix contains NaN or inf")
        p_out = E.shape[0]
    if state_map is not None:
        _check_state_map(state_map, n_global)
    if integrator is not None:
        if not isinstance(integrator, MidpointIntegrator) or integrator.system is not system:
            raise InputError("integrator must be a MidpointIntegrator of this same system")
        if integrator.closed:
            raise InputError("integrator was closed (close() or the end of its with block): "
                             "pass an open one, or none (run makes its own)")
        if abs(integrator.dt - dt) > 1e-15 * dt:
            raise InputError(f"the integrator's dt = {integrator.dt} differs from dt = {dt}")
    files = None
    if checkpoint is not None:
        checkpoint_every = _count(checkpoint_every, "checkpoint_every", 1)
        files = _checkpoint_files(checkpoint, comm.rank)
    for name, flag in (("record_velocity", record_velocity), ("checkpoint_restart", checkpoint_restart)):
        if not isinstance(flag, (bool, np.bool_)):
            raise InputError(f"{name} must be True or False, got {flag!r}")
    # what every rank must have passed alike (the checkpoint prefix may differ: node-local disks)
    settings = {"dt": dt, "t_end": t_end, "record_every": record_every, "state_until": state_until,
                "energy_every": energy_every, "energy_until": energy_until,
                "output_matrix rows": p_out, "state_map": _map_key(state_map),
                "record_velocity": bool(record_velocity), "integrator": integrator is not None,
                "checkpoint": checkpoint is not None,
                "checkpoint_every": checkpoint_every if checkpoint is not None else None,
                "checkpoint_restart": bool(checkpoint_restart)}
    return dict(dt=dt, t_end=t_end, n_steps=n_steps, record_every=record_every,
                n_state_steps=n_state_steps, n_energy_steps=n_energy_steps,
                energy_every=energy_every, n_owned=n_owned, n_global=n_global, files=files,
                checkpoint_every=checkpoint_every, settings=settings)


def run(system, *args, **kwargs):
    """Two forms of one time loop.

    * ``run(integrator, n_steps, sinks=[...], inputs=None)`` - :func:`run_loop`: step any
      :class:`~dolfinx_lopinf.fem.integrators.Integrator` and feed the sinks.
    * ``run(system, q0, v0, dt, t_end, ...)`` - :func:`run_system`: the midpoint FOM of a
      :class:`LagrangianSystem` with its recorder, output and checkpoint sinks, returning
      ``(Snapshots, info)``.
    """
    if isinstance(system, LagrangianSystem):
        return run_system(system, *args, **kwargs)
    return run_loop(system, *args, **kwargs)


def run_system(system: LagrangianSystem, q0, v0, dt: float, t_end: float, *, record_every: int = 1,
               state_until: float | None = None, output_matrix: np.ndarray | None = None,
               state_map: StateMap | None = None, record_velocity: bool = True,
               energy_every: int | None = None, energy_until: float | None = None,
               progress: bool = True, integrator: MidpointIntegrator | None = None,
               checkpoint: str | Path | None = None, checkpoint_every: int = 1000,
               checkpoint_restart: bool = False) -> tuple[Snapshots | None, dict]:
    """Integrate the FOM and record snapshots.

    Every argument is checked before the first step (all ranks reach the same verdict);
    bad values raise :class:`~dolfinx_lopinf.errors.InputError` naming the argument, on every
    rank, also when only one rank has them. On several ranks dt, t_end, record_every,
    state_until, energy_every, energy_until, record_velocity, the state map, the number of
    outputs and the checkpoint settings must be the same on every rank (else
    :class:`~dolfinx_lopinf.errors.RanksDisagreeError` on every rank, naming each rank's value;
    the checkpoint prefix may differ, e.g. node-local disks). An exception on one rank alone
    during the run aborts the job instead of hanging (:mod:`dolfinx_lopinf.fem.agreement`).

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
        integrator: reuse an existing integrator of ``system`` (its dt must match; it is
            left open). Without it, ``run`` makes one and closes it at the end.
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
    plan = _plan(system, dt, t_end, record_every, state_until, output_matrix, state_map,
                 energy_every, energy_until, integrator, checkpoint, checkpoint_every,
                 record_velocity, checkpoint_restart)
    state_map = StateMap.from_coordinates(system.V) if state_map is None else state_map
    stepper = integrator if integrator is not None else MidpointIntegrator(system, plan["dt"])
    try:
        with together(system.V.mesh.comm, "run"):
            return _run_recorded(system, stepper, q0, v0, plan, output_matrix, state_map,
                                 record_velocity, progress, checkpoint_restart)
    finally:
        if integrator is None:
            stepper.close()


def _run_recorded(system, stepper, q0, v0, plan, output_matrix, state_map, record_velocity,
                  progress, checkpoint_restart):
    """:func:`run_system` after the checks: the sinks, the resume, the loop, the gather."""
    V, comm = system.V, system.V.mesh.comm
    dt, n_steps, files = plan["dt"], plan["n_steps"], plan["files"]
    record_every, energy_every = plan["record_every"], plan["energy_every"]
    fingerprint = None
    if files is not None:
        settings = {"dt": repr(dt), "t_end": repr(plan["t_end"]), "steps": n_steps,
                    "record_every": record_every, "state steps": plan["n_state_steps"],
                    "energy steps": plan["n_energy_steps"], "energy_every": energy_every,
                    "record_velocity": bool(record_velocity), "ranks": comm.size,
                    "global dofs": plan["n_global"], "owned dofs on this rank": plan["n_owned"],
                    "scheme": f"midpoint variational ({'linear' if stepper._linear else 'Newton'})"}
        fingerprint = _fingerprint(stepper, settings, output_matrix,
                                   (0.5 * dt, 0.6180339887 * plan["t_end"] + 0.5 * dt))
    stepper.initialize(q0, v0)
    if fingerprint is not None:
        _add_state_sketches(fingerprint, stepper)
    recorder = StateRecorder(plan["n_owned"], record_every=record_every,
                             state_steps=plan["n_state_steps"], energy_steps=plan["n_energy_steps"],
                             energy_every=energy_every, record_velocity=record_velocity)
    probe = OutputProbe(output_matrix, every=record_every) if output_matrix is not None else None
    sinks = [recorder] + ([probe] if probe is not None else [])
    if progress:
        sinks.append(Progress())
    first_step, checkpointer = 1, None
    if files is not None:
        checkpointer = CheckpointSink(files, fingerprint, recorder, probe,
                                      every=plan["checkpoint_every"])
        sinks.append(checkpointer)
        if checkpoint_restart:
            files.remove_all()
        else:
            resumed = _resume(files, comm, fingerprint, plan["n_global"])
            if resumed is None:
                files.remove_all()  # stray chunks of a run that never wrote a head
            else:
                first_step = checkpointer.restore(stepper, *resumed)
    loop = run_loop(stepper, n_steps, sinks, first_step=first_step)
    energies = np.array(recorder.energies)
    drift = float(np.max(np.abs(energies - energies[0])) / abs(energies[0])) if len(energies) > 1 \
        and energies[0] != 0 else float("nan")
    info = {"seconds": loop["seconds"], "steps": n_steps, "energy_drift": drift,
            "resumed_from_step": first_step - 1,
            "seconds_to_state_until": comm.allreduce(recorder.seconds_states, op=MPI.MAX),
            "energy": energies, "energy_times": np.array(recorder.energy_times),
            "checkpoint_bytes": checkpointer.bytes if checkpointer else 0,
            "checkpoint_seconds": checkpointer.seconds if checkpointer else 0.0}
    Qg = gather_states(V, recorder.Q, state_map)
    Vg = gather_states(V, recorder.Vel, state_map) if record_velocity else None
    if comm.rank != 0:
        return None, info
    times = dt * record_every * np.arange(recorder.Q.shape[1])
    energy_full = energies if energy_every == 1 else None
    ys = probe.values if probe is not None else []
    Y = np.array(ys).T if ys else None
    snaps = Snapshots(times=times, Q=Qg, blocks=state_map.blocks, V=Vg, energy=energy_full,
                      Y=Y, output_times=np.array(probe.times) if ys else None)
    return snaps, info
