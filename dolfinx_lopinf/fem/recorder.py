"""Record snapshots from an existing dolfinx time loop (no need for our FOM).

    recorder = SnapshotRecorder(u)                  # u: the dolfinx Function your loop updates
    for n in range(num_steps):
        ...  your solve ...
        recorder.record(t, u, inputs=[load(t)])     # once per step (or every k-th step)
    snaps = recorder.snapshots()                    # Snapshots on rank 0, None elsewhere

If you know your loop's integrator, say so - ``SnapshotRecorder(u, scheme="newmark")`` - and
the snapshots carry it (``snaps.scheme``) for the fit; leave it None when you do not know.

In the package's own time loop the recorder is a sink:
``fom.run(integrator, n, sinks=[rec.sink(velocity=True)])`` (``scheme`` defaults to the
integrator's then).

Each rank stores only its owned dofs; :meth:`SnapshotRecorder.snapshots` gathers them once
into global dof order, so the arrays are identical for any number of ranks.
"""

from __future__ import annotations

import numpy as np

from ._dolfinx import dolfinx
from ..errors import InputError
from .fom import StateMap, gather_states
from .lagrangian import _on_space
from ..core.snapshots import Snapshots, check_scheme


class SnapshotRecorder:
    """Collects states (and optional velocities, inputs, outputs) of a dolfinx Function.

    Args:
        u: the Function (or its FunctionSpace) whose values are recorded.
        state_map: dof -> state coordinates (default: ordered by dof coordinates, identical
            for any number of ranks; Lagrange-type spaces).
        output_matrix: optional (p, n_local) local output matrix, e.g. from
            :func:`dolfinx_lopinf.point_output_matrix`; y = sum over ranks of E u_local.
        blocks: optional name -> state rows (for block-diagonal POD).
        scheme: the integrator of your loop, if you know it: ``"newmark"`` (average
            acceleration, gamma = 1/2, beta = 1/4), ``"midpoint"`` (midpoint variational
            integrator) or ``"continuous"`` (anything else); None (default) = unknown. Stored
            as ``Snapshots.scheme``.

    Example:
        >>> rec = SnapshotRecorder(u)                                   # doctest: +SKIP
        >>> rec.record(0.0, u, inputs=[0.0])                            # doctest: +SKIP
    """

    def __init__(self, u, *, state_map: StateMap | None = None, output_matrix=None,
                 blocks: dict | None = None, scheme: str | None = None):
        self.scheme = check_scheme(scheme, "SnapshotRecorder(scheme=...)")
        V = u.function_space if isinstance(u, dolfinx.fem.Function) else u
        if not isinstance(V, dolfinx.fem.FunctionSpace):
            raise InputError("SnapshotRecorder needs a dolfinx Function or FunctionSpace, got "
                             f"{type(u).__name__}")
        self.V = V
        self.state_map = StateMap.from_coordinates(V) if state_map is None else state_map
        if blocks:
            self.state_map = StateMap(self.state_map.order, self.state_map.scale, blocks)
        self._n_owned = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
        self._n_local = (V.dofmap.index_map.size_local + V.dofmap.index_map.num_ghosts) \
            * V.dofmap.index_map_bs
        problem = None
        if output_matrix is not None:
            output_matrix = np.asarray(output_matrix)
            if output_matrix.ndim != 2 or output_matrix.shape[1] != self._n_local:
                problem = (f"output_matrix must be (p, {self._n_local}) on this rank (owned + ghost "
                           f"dofs, from point_output_matrix), got shape {output_matrix.shape}")
            elif not np.all(np.isfinite(output_matrix)):
                problem = "output_matrix contains NaN or inf"
        for m in (V.mesh.comm.allgather(problem) if V.mesh.comm.size > 1 else [problem]):
            if m is not None:
                raise InputError(m)
        self.output_matrix = output_matrix
        self._times, self._states, self._velocities, self._inputs, self._outputs = [], [], [], [], []

    def __len__(self) -> int:
        return len(self._times)

    def _local(self, f, name):
        """(array, problem): the local dof array of a Function/array, or why it is refused."""
        if isinstance(f, dolfinx.fem.Function):
            W = f.function_space
            if not _on_space(f, self.V):
                where = "another mesh" if W.mesh._cpp_object is not self.V.mesh._cpp_object \
                    else "another function space (element or dof layout)"
                return None, (f"{name} is a Function on {where} than the recorder's; record "
                              "Functions of the space the recorder was created with")
            arr = f.x.array
        else:
            try:
                arr = np.asarray(f, dtype=float)
            except (TypeError, ValueError):
                return None, f"{name} must be a Function or an array of floats, got {type(f).__name__}"
            if arr.ndim != 1:
                return None, f"{name} must be a 1-d local dof array, got shape {arr.shape}"
        if arr.shape[0] not in (self._n_owned, self._n_local):
            return None, (f"{name} has {arr.shape[0]} local entries; expected {self._n_owned} "
                          f"(owned) or {self._n_local} (owned + ghosts)")
        if not np.all(np.isfinite(arr[: self._n_owned])):
            return None, f"the {name} recorded at this time contains NaN or inf"
        return arr, None

    def record(self, t: float, u, *, velocity=None, inputs=None) -> None:
        """Store the state at time t (times must be increasing and uniformly spaced).

        All or nothing: every argument is checked (collectively: every rank raises the same
        :class:`~dolfinx_lopinf.errors.InputError`) before anything is stored, so a refused
        call leaves the recorder as it was.

        Args:
            t: time of this state.
            u: Function on the recorder's space or local dof array (owned, or owned + ghosts).
            velocity: optional Function/array of the velocity at t.
            inputs: optional sequence of m input values at t (same m every call).
        """
        comm = self.V.mesh.comm
        problem = None
        try:
            t = float(t)
            if not np.isfinite(t):
                problem = f"t must be finite, got {t}"
        except (TypeError, ValueError):
            problem = f"t must be a number, got {t!r}"
        arr, p = self._local(u, "u")
        problem = problem or p
        vel = None
        if velocity is not None:
            vel, p = self._local(velocity, "velocity")
            problem = problem or p
        if problem is None and self._times:
            if t <= self._times[-1]:
                problem = f"times must increase: got t = {t} after {self._times[-1]}"
            elif len(self._times) >= 2:
                dt = self._times[1] - self._times[0]
                if abs((t - self._times[-1]) - dt) > 1e-6 * dt:
                    problem = (f"record at a uniform spacing: dt was {dt}, now "
                               f"{t - self._times[-1]} at t = {t}")
        if inputs is not None and problem is None:
            try:
                inputs = np.atleast_1d(np.asarray(inputs, dtype=float)).ravel()
                if not np.all(np.isfinite(inputs)):
                    problem = f"inputs at t = {t} contain NaN or inf: {inputs}"
                elif self._inputs and len(inputs) != len(self._inputs[0]):
                    problem = f"inputs had {len(self._inputs[0])} entries, now {len(inputs)}"
            except (TypeError, ValueError):
                problem = f"inputs must be a sequence of numbers, got {inputs!r}"
        if problem is None and self._times:
            if (inputs is None) != (not self._inputs):
                problem = "pass inputs at every record() call or at none"
            elif (velocity is None) != (not self._velocities):
                problem = "pass velocity at every record() call or at none"
        if problem is None and self.output_matrix is not None and arr.shape[0] != self._n_local:
            problem = "outputs need the ghosted array: pass the Function itself"
        messages = comm.allgather(problem) if comm.size > 1 else [problem]
        for m in messages:
            if m is not None:
                raise InputError(m)
        y = comm.allreduce(self.output_matrix @ arr) if self.output_matrix is not None else None
        # nothing can fail past this point: store everything
        self._times.append(t)
        self._states.append(arr[: self._n_owned].copy())
        if vel is not None:
            self._velocities.append(vel[: self._n_owned].copy())
        if inputs is not None:
            self._inputs.append(inputs)
        if y is not None:
            self._outputs.append(y)

    def sink(self, *, every: int = 1, until_step: int | None = None, velocity: bool = False,
             inputs=None):
        """A sink of :func:`dolfinx_lopinf.fem.fom.run_loop`: :meth:`record` the integrator's
        state (and ``velocity``, and ``inputs(t)`` if given) at every ``every``-th step up to
        ``until_step``. A recorder made without ``scheme`` takes the integrator's."""
        from .fom import Every

        def record(s):
            if self.scheme is None:
                self.scheme = check_scheme(getattr(s.integrator, "scheme", None), "integrator.scheme")
            self.record(s.t, s.q, velocity=s.velocity() if velocity else None,
                        inputs=None if inputs is None else inputs(s.t))

        return Every(record, every=every, until_step=until_step)

    def snapshots(self) -> Snapshots | None:
        """Gather everything to rank 0 as :class:`Snapshots` (None on the other ranks)."""
        if len(self._times) < 2:
            raise InputError("record at least two time steps before asking for snapshots")
        Q = gather_states(self.V, np.column_stack(self._states), self.state_map)
        Vel = gather_states(self.V, np.column_stack(self._velocities), self.state_map) \
            if self._velocities else None
        if self.V.mesh.comm.rank != 0:
            return None
        U = np.column_stack(self._inputs) if self._inputs else None
        Y = np.column_stack(self._outputs) if self._outputs else None
        return Snapshots(times=np.array(self._times), Q=Q, blocks=self.state_map.blocks, V=Vel,
                         U=U, Y=Y, scheme=self.scheme)
