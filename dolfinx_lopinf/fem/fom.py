"""The full-order model of a :class:`~dolfinx_lopinf.fem.lagrangian.LagrangianSystem`, recorded.

``run(system, q0, v0, dt, t_end, ...)`` (:func:`run_system`) integrates the system from
(q0, v0) with the midpoint variational integrator in the one time loop
(:func:`~dolfinx_lopinf.fem.loop.run_loop`) with its sinks: the :class:`StateRecorder`, an
:class:`~dolfinx_lopinf.fem.loop.OutputProbe`, a :class:`~dolfinx_lopinf.fem.loop.Progress` bar
and a :class:`~dolfinx_lopinf.fem.checkpoint.CheckpointSink`. It returns
:class:`~dolfinx_lopinf.core.snapshots.Snapshots`: states (and velocities, energies) every
``record_every`` steps up to ``state_until``, outputs y = E q every ``record_every`` steps up to
``t_end``. States are recorded in *state coordinates* given by a
:class:`~dolfinx_lopinf.fem.state.StateMap` (for Hermite beams: nodal deflection w and rotation
theta), and gathered to rank 0 (other ranks get ``None``) - each rank only ever touches its
owned dofs. ``run(integrator, n_steps, sinks=..., inputs=...)`` is the loop itself, for any
integrator.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ._dolfinx import MPI
from ..core._checks import check_int, check_real
from ..core.snapshots import Snapshots
from ..errors import InputError
from .agreement import agree, together
from .checkpoint import CheckpointSink, _add_state_sketches, _checkpoint_files, _fingerprint, _resume
from .integrators import MidpointIntegrator, _check_dt
from .lagrangian import LagrangianSystem
from .loop import OutputProbe, Progress, Sink, run_loop
from .state import StateMap, _check_state_map, _map_key, gather_states, state_gram


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
    t_end = check_real(t_end, "t_end")
    if t_end <= 0:
        raise InputError(f"t_end must be positive, got {t_end}")
    n_steps = int(round(t_end / dt))
    if n_steps < 1 or abs(n_steps * dt - t_end) > 1e-9 * t_end:
        raise InputError(f"t_end = {t_end} is not a whole number of steps dt = {dt}; choose "
                         "t_end = n * dt")
    record_every = check_int(record_every, "record_every", 1)
    if record_every > n_steps:
        raise InputError(f"record_every = {record_every} is more than the {n_steps} steps of the "
                         "run: nothing but the initial state would be recorded; lower it")
    min_until = record_every * dt
    if state_until is None:
        n_state_steps = n_steps
    else:
        state_until = check_real(state_until, "state_until")
        if not min_until * (1 - 1e-9) <= state_until <= t_end * (1 + 1e-9):
            raise InputError(
                f"state_until = {state_until} must lie in [record_every * dt, t_end] = "
                f"[{min_until:g}, {t_end:g}] (at least two recorded states, none after the run)")
        n_state_steps = min(int(round(state_until / dt)), n_steps)
    if energy_until is None:
        n_energy_steps = n_state_steps
    else:
        energy_until = check_real(energy_until, "energy_until")
        if not 0 <= energy_until <= t_end * (1 + 1e-9):
            raise InputError(f"energy_until = {energy_until} must lie in [0, t_end = {t_end:g}]")
        n_energy_steps = min(int(round(energy_until / dt)), n_steps)
    energy_every = 1 if energy_every is None else check_int(energy_every, "energy_every", 0)
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
        checkpoint_every = check_int(checkpoint_every, "checkpoint_every", 1)
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
        ``(snapshots, info)``: Snapshots on rank 0 (None elsewhere), tagged with the
        integrator's scheme (``"midpoint"``: what ``lo.fit`` fits) and carrying the system's
        mass matrix as their inner product (``weight``: ``lo.fit``'s POD is mass-orthonormal,
        the Galerkin projection); info has ``seconds``
        (wall time of the time loop), ``steps``, ``energy_drift`` (max |E - E0| / |E0| over
        the recorded energies), ``resumed_from_step``, ``checkpoint_bytes`` (bytes this rank
        wrote to checkpoint files), ``checkpoint_seconds`` (time spent writing them) and
        ``state_map`` - the order of the snapshots' rows (by dof coordinates unless you passed
        one): pass it to :func:`~dolfinx_lopinf.fem.vtx.write_vtx`,
        :func:`~dolfinx_lopinf.fem.vtx.states_to_function` and
        :func:`~dolfinx_lopinf.fem.vtx.state_rows`, whose default is the recorder's dof order.
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
    weight = state_gram(V, state_map, system.mass_form, strict=False)  # lo.fit's POD: the Galerkin projection
    if comm.rank != 0:
        return None, info
    times = dt * record_every * np.arange(recorder.Q.shape[1])
    energy_full = energies if energy_every == 1 else None
    ys = probe.values if probe is not None else []
    Y = np.array(ys).T if ys else None
    snaps = Snapshots(times=times, Q=Qg, blocks=state_map.blocks, V=Vg, energy=energy_full,
                      Y=Y, output_times=np.array(probe.times) if ys else None,
                      scheme=stepper.scheme, weight=weight)  # lo.fit fits that relation
    info["state_map"] = state_map  # the rows' order: write_vtx & co default to dof order
    return snaps, info
