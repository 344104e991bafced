"""Run the full-order model in time and record what the scene needs.

``run`` integrates a :class:`LagrangianSystem` from (q0, v0) with the midpoint variational
integrator and returns :class:`~dolfinx_lopinf.snapshots.Snapshots`: states (and velocities,
energies) every ``record_every`` steps up to ``state_until``, outputs y = E q every
``record_every`` steps up to ``t_end``. States are recorded in *state coordinates*
given by a :class:`StateMap` (for Hermite beams: nodal deflection w and rotation theta), and
gathered to rank 0 (other ranks get ``None``) - each rank only ever touches its owned dofs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ._dolfinx import MPI, dolfinx
from .integrators import MidpointIntegrator
from .lagrangian import LagrangianSystem
from .snapshots import Snapshots


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


def run(system: LagrangianSystem, q0, v0, dt: float, t_end: float, *, record_every: int = 1,
        state_until: float | None = None, output_matrix: np.ndarray | None = None,
        state_map: StateMap | None = None, record_velocity: bool = True,
        energy_every: int | None = None, energy_until: float | None = None, progress: bool = True,
        integrator: MidpointIntegrator | None = None, checkpoint: str | Path | None = None,
        checkpoint_every: int = 1000) -> tuple[Snapshots | None, dict]:
    """Integrate the FOM and record snapshots.

    Args:
        system: the Lagrangian system.
        q0, v0: initial configuration and velocity (Functions or local dof arrays).
        dt, t_end: time step and final time (t_end / dt steps, rounded).
        record_every: keep every ``record_every``-th step.
        state_until: record full states only while t <= state_until (default t_end);
            outputs are recorded to t_end.
        output_matrix: (p, n_local) from :func:`point_output_matrix` (or any local linear
            output); y = allreduce(E q_local).
        state_map: dof -> state coordinates (default: ordered by dof coordinates, so the
            result does not depend on the number of ranks).
        record_velocity: also record velocities (one mass solve per recorded step).
        energy_until: keep recording the energy (every ``energy_every`` samples) up to this
            time, past ``state_until`` (default: ``state_until``).
        energy_every: record the FOM energy every that many recorded samples (default: each
            recorded state sample; 0 disables).
        progress: show a tqdm progress bar on rank 0.
        integrator: reuse an existing integrator (its dt must match).
        checkpoint: a path prefix; every ``checkpoint_every`` steps each rank writes its part
            of the run (integrator state and everything recorded so far) atomically to
            ``<prefix>.rank<i>.npz``. If such files exist when ``run`` starts with the same
            settings, it resumes from them, and the result equals an unbroken run's. The
            files are removed when the run completes.

    Returns:
        ``(snapshots, info)``: Snapshots on rank 0 (None elsewhere); info has ``seconds``
        (wall time of the time loop), ``steps``, ``energy_drift`` (max |E - E0| / |E0| over
        the recorded energies).
    """
    if t_end <= 0:
        raise ValueError(f"t_end must be positive, got {t_end}")
    n_steps = int(round(t_end / dt))
    if abs(n_steps * dt - t_end) > 1e-9 * t_end:
        raise ValueError(f"t_end = {t_end} is not a whole number of steps dt = {dt}")
    if record_every < 1:
        raise ValueError("record_every must be >= 1")
    state_until = t_end if state_until is None else state_until
    n_state_steps = int(round(state_until / dt))
    n_energy_steps = int(round((state_until if energy_until is None else energy_until) / dt))
    V = system.V
    comm = V.mesh.comm
    state_map = StateMap.from_coordinates(V) if state_map is None else state_map
    stepper = integrator if integrator is not None else MidpointIntegrator(system, dt)
    if abs(stepper.dt - dt) > 1e-15 * dt:
        raise ValueError("the integrator's dt differs from dt")
    stepper.initialize(q0, v0)
    n_owned = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
    n_rec = n_state_steps // record_every + 1
    Q = np.empty((n_owned, n_rec))
    Vel = np.empty((n_owned, n_rec)) if record_velocity else None
    energy_every = 1 if energy_every is None else energy_every
    energies, energy_times = [], []
    ys, y_times = [], []
    v = dolfinx.fem.Function(V)

    ckpt = None if checkpoint is None else Path(f"{checkpoint}.rank{comm.rank}.npz")
    settings = np.array([dt, t_end, record_every, n_state_steps, n_energy_steps, energy_every,
                         float(record_velocity), n_owned, comm.size])
    k_start = 1

    def save_checkpoint(k):
        tmp = ckpt.with_suffix(".tmp.npz")
        np.savez(tmp, k=k, settings=settings, q=stepper.q.x.array, p=stepper.p.array,
                 t=stepper.t, Q=Q, Vel=Vel if Vel is not None else np.zeros(0),
                 energies=np.array(energies), energy_times=np.array(energy_times),
                 ys=np.array(ys).reshape(len(ys), -1) if ys else np.zeros((0, 0)),
                 y_times=np.array(y_times))
        tmp.replace(ckpt)  # atomic: a kill leaves either the old or the new checkpoint

    def record(j):
        Q[:, j] = stepper.q.x.array[:n_owned]
        need_v = record_velocity or (energy_every and j % energy_every == 0)
        if need_v:
            stepper.velocity(v)
            if record_velocity:
                Vel[:, j] = v.x.array[:n_owned]
        if energy_every and j % energy_every == 0:
            energies.append(stepper.energy(v))
            energy_times.append(stepper.t)

    def record_energy():
        stepper.velocity(v)
        energies.append(stepper.energy(v))
        energy_times.append(stepper.t)

    def record_output():
        if output_matrix is not None:
            ys.append(comm.allreduce(output_matrix @ stepper.q.x.array))
            y_times.append(stepper.t)

    bar = None
    if progress and comm.rank == 0:
        from tqdm.auto import tqdm
        bar = tqdm(total=n_steps, desc="FOM", unit="step", mininterval=0.5, leave=False)
    t0 = time.perf_counter()
    seconds_states = 0.0
    resumed = ckpt is not None and comm.allreduce(ckpt.exists(), op=MPI.LAND)
    if resumed:
        with np.load(ckpt) as data:
            if not np.array_equal(data["settings"], settings):
                raise ValueError(f"checkpoint {ckpt} belongs to a run with other settings; "
                                 "delete it or change the checkpoint path")
            k_start = int(data["k"]) + 1
            stepper.q.x.array[:] = data["q"]
            stepper.p.array[:] = data["p"]
            stepper.t = float(data["t"])
            stepper.steps_taken = k_start - 1
            Q[:] = data["Q"]
            if Vel is not None:
                Vel[:] = data["Vel"]
            energies[:] = list(data["energies"])
            energy_times[:] = list(data["energy_times"])
            ys[:] = list(data["ys"])
            y_times[:] = list(data["y_times"])
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
        if ckpt is not None and k % checkpoint_every == 0 and k < n_steps:
            save_checkpoint(k)
    seconds = comm.allreduce(time.perf_counter() - t0, op=MPI.MAX)
    if bar is not None:
        bar.close()
    if ckpt is not None and ckpt.exists():
        ckpt.unlink()
    energies = np.array(energies)
    drift = float(np.max(np.abs(energies - energies[0])) / abs(energies[0])) if len(energies) > 1 \
        and energies[0] != 0 else float("nan")
    info = {"seconds": seconds, "steps": n_steps, "energy_drift": drift,
            "resumed_from_step": k_start - 1,
            "seconds_to_state_until": comm.allreduce(seconds_states, op=MPI.MAX),
            "energy": energies, "energy_times": np.array(energy_times)}
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
