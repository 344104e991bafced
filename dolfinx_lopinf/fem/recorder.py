"""Record snapshots from an existing dolfinx time loop (no need for our FOM).

    recorder = SnapshotRecorder(u)                  # u: the dolfinx Function your loop updates
    for n in range(num_steps):
        ...  your solve ...
        recorder.record(t, u, inputs=[load(t)])     # once per step (or every k-th step)
    snaps = recorder.snapshots()                    # Snapshots on rank 0, None elsewhere

Rows. ``snaps.Q[i]`` is dof ``i`` of your space (``u.x.array[i]`` in serial; the global dof
number, i.e. the row of your own assembled PETSc matrices, in parallel), so anything you build
from your own M or K applies to the snapshots as they are. ``order="coordinates"`` sorts the
rows by dof coordinates instead, which makes the arrays identical for any number of ranks;
``recorder.state_map`` is the map either way (state[i] = dofs[state_map.order[i]]).

Which integrator. If you know it, say so - ``SnapshotRecorder(u, scheme="newmark")`` or
``scheme=lo.schemes.GeneralizedAlpha(rho_inf=0.8)`` - and the snapshots carry it for the fit;
leave it None and ``lo.fit`` identifies it from the data. If your loop keeps its velocity and
acceleration Functions, hand them over (``velocity=v, acceleration=a``): they are recorded at
every call and the fit uses the scheme's (u, v, a) relation directly.

Loads. ``record(t, u, inputs=[p])`` records the load values; a generalised-alpha loop applies
its load at t_{n+1-alpha_f}, not at t: say so with ``input_time=t - alpha_f * dt`` (the time
at which the recorded values act), and a load with jumps costs nothing. Without it the
inputs are taken to act at t and interpolated linearly to where the scheme needs them.

Inner product. The snapshots carry the L2 Gram matrix of your space (``snaps.weight``, sparse,
in the rows' order; ``inner(u, v) * dx``, assembled once when :meth:`snapshots` is first
called), and ``lo.fit`` builds its POD basis in that inner product: it measures a field by
its L2 norm, not by its dof values, so it does not depend on how fine the mesh is where (the
Euclidean POD favours refined regions). ``weight=`` takes your own bilinear form instead
(e.g. ``rho * inner(u, v) * dx``) or your assembled PETSc mass matrix; ``weight=None``
records none (Euclidean POD).

In the package's own time loop the recorder is a sink:
``fom.run(integrator, n, sinks=[rec.sink(velocity=True)])`` (``scheme`` defaults to the
integrator's then).

Each rank stores only its owned dofs; :meth:`SnapshotRecorder.snapshots` gathers them once
into state order on rank 0. Every check is collective: a bad argument on one rank raises the
same :class:`~dolfinx_lopinf.errors.InputError` on every rank.
"""

from __future__ import annotations

import numpy as np

from ._dolfinx import dolfinx
from ..errors import InputError
from .agreement import agree, arrive
from .state import StateMap, gather_states, state_gram, weight_kind
from .lagrangian import _on_space
from ..core._checks import check_blocks
from ..core.snapshots import Snapshots, check_scheme

ORDERS = ("dofs", "coordinates")


def _verdict(comm, problem):
    """Raise the first rank's problem on every rank (collective)."""
    for m in (comm.allgather(problem) if comm.size > 1 else [problem]):
        if m is not None:
            raise InputError(m)


class SnapshotRecorder:
    """Collects states (and optional velocities, accelerations, inputs, outputs) of a dolfinx
    Function.

    Args:
        u: the Function (or its FunctionSpace) whose values are recorded.
        order: ``"dofs"`` (default: row i is global dof i) or ``"coordinates"`` (rows sorted
            by dof coordinates, identical for any number of ranks; Lagrange-type spaces).
        state_map: an explicit dof -> state map (overrides ``order``; e.g. a Hermite beam's).
        output_matrix: optional (p, n_local) local output matrix, e.g. from
            :func:`dolfinx_lopinf.point_output_matrix`; y = sum over ranks of E u_local.
        blocks: optional name -> state rows (for block-diagonal POD).
        scheme: the integrator of your loop, if you know it: a name (``"newmark"``,
            ``"midpoint"``, ``"central_difference"``, ``"continuous"``) or a
            :mod:`dolfinx_lopinf.core.schemes` object; None (default) = unknown.
        velocity, acceleration: your loop's velocity and acceleration Functions (same space),
            recorded with u at every :meth:`record` call.
        weight: the inner product of the states recorded as ``Snapshots.weight`` (the POD of
            ``lo.fit`` is built in it): ``"l2"`` (default: the L2 Gram matrix
            ``inner(u, v) * dx`` of the space), a UFL bilinear form on the space (e.g.
            ``rho * inner(u, v) * dx``, assembled without boundary conditions), an assembled
            PETSc Mat in the space's dof layout (e.g. your mass matrix; global size n x n;
            read at the first :meth:`snapshots` call, so keep it until then), or None
            (Euclidean: no weight recorded). Checked now; assembled at the first
            :meth:`snapshots` call.

    Example:
        >>> rec = SnapshotRecorder(u)                                   # doctest: +SKIP
        >>> rec.record(0.0, u, inputs=[0.0])                            # doctest: +SKIP
    """

    def __init__(self, u, *, order: str = "dofs", state_map: StateMap | None = None,
                 output_matrix=None, blocks: dict | None = None, scheme=None, velocity=None,
                 acceleration=None, weight="l2"):
        V = u.function_space if isinstance(u, dolfinx.fem.Function) else u
        if not isinstance(V, dolfinx.fem.FunctionSpace):
            raise InputError("SnapshotRecorder needs a dolfinx Function or FunctionSpace, got "
                             f"{type(u).__name__}")
        comm = V.mesh.comm
        problem, spec = None, None
        try:
            self.scheme = check_scheme(scheme, "SnapshotRecorder(scheme=...)")
            spec = None if self.scheme is None else self.scheme.spec
        except InputError as exc:
            problem = str(exc)
        if problem is None and order not in ORDERS and state_map is None:
            problem = f"order must be one of {ORDERS}, got {order!r}"
        if problem is None and state_map is not None and not isinstance(state_map, StateMap):
            problem = f"state_map must be a StateMap, got {type(state_map).__name__}"
        kind = "none"
        if weight is not None:
            try:
                kind = weight_kind(weight, V)
            except InputError as exc:
                problem = problem or f"SnapshotRecorder(weight=...): {exc}"
        if comm.size > 1:  # one allgather: every rank sees every problem and every setting
            seen = comm.allgather((problem, (spec, order if state_map is None else "explicit"),
                                   kind))
            problem = next((p for p, _, _ in seen if p is not None), None)
            specs, kinds = [s for _, s, _ in seen], [k for _, _, k in seen]
            if problem is None and any(x != specs[0] for x in specs):
                problem = (f"SnapshotRecorder arguments differ between ranks (scheme, order): "
                           f"{specs}; pass the same on every rank")
            if problem is None and any(k != kinds[0] for k in kinds):
                problem = (f"SnapshotRecorder arguments differ between ranks (weight): {kinds}; "
                           "pass the same kind of weight on every rank")
        _verdict(comm, problem)
        self.weight = weight
        self._gram = None  # assembled at the first snapshots() call
        self.V = V
        if state_map is None:
            try:
                state_map = StateMap.identity(V) if order == "dofs" else StateMap.from_coordinates(V)
            except ValueError as exc:
                raise InputError(f"order='coordinates': {exc}") from None
        self.state_map = state_map
        if blocks:  # checked now, not first when the run is over (rec.snapshots())
            problem = None
            try:
                blocks = check_blocks(blocks, V.dofmap.index_map.size_global * V.dofmap.index_map_bs)
            except InputError as exc:
                problem = f"SnapshotRecorder: {exc}"
            _verdict(comm, problem)
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
        self._fields = {}
        for name, f in (("velocity", velocity), ("acceleration", acceleration)):
            if f is None:
                continue
            if not isinstance(f, dolfinx.fem.Function):
                problem = problem or (f"{name} must be your loop's dolfinx Function (recorded at "
                                      f"every record() call), got {type(f).__name__}")
            elif not _on_space(f, V):
                problem = problem or (f"{name} is a Function on another space than u's; the "
                                      "(u, v, a) relation needs them on the same space")
            self._fields[name] = f
        _verdict(comm, problem)
        self.output_matrix = output_matrix
        self._times, self._states, self._velocities, self._inputs, self._outputs = [], [], [], [], []
        self._accelerations, self._input_times = [], []

    def __len__(self) -> int:
        return len(self._times)

    def _local(self, f, name, t=None):
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
        bad = np.flatnonzero(~np.isfinite(arr[: self._n_owned]))
        if bad.size:
            imap, bs = self.V.dofmap.index_map, self.V.dofmap.index_map_bs
            first = int(bad[0])
            where = f"t = {t:g}" if isinstance(t, float) else "this time"
            return None, (f"the {name} recorded at {where} contains {bad.size} NaN or inf "
                          f"value(s) on rank {self.V.mesh.comm.rank}, first at dof "
                          f"{imap.local_range[0] * bs + first} (global, block size {bs}): the "
                          "loop diverged or the solve failed before this step")
        return arr, None

    def record(self, t: float, u, *, velocity=None, inputs=None, input_time=None) -> None:
        """Store the state at time t (times must be increasing and uniformly spaced).

        All or nothing: every argument is checked (collectively: every rank raises the same
        :class:`~dolfinx_lopinf.errors.InputError`, also when the ranks pass different times
        or inputs) before anything is stored, so a refused call leaves the recorder as it was.

        Args:
            t: time of this state.
            u: Function on the recorder's space or local dof array (owned, or owned + ghosts).
            velocity: optional Function/array of the velocity at t (not with the recorder's
                own ``velocity=``).
            inputs: optional sequence of m input values (same m every call).
            input_time: the time at which ``inputs`` act in your loop (default t), e.g.
                ``t - alpha_f * dt`` for a generalised-alpha loop; increasing call to call.
        """
        comm = self.V.mesh.comm
        problem = None
        try:
            t = float(t)
            if not np.isfinite(t):
                problem = f"t must be finite, got {t}"
        except (TypeError, ValueError):
            problem = f"t must be a number, got {t!r}"
        arr, p = self._local(u, "u", t)
        problem = problem or p
        vel = acc = tu = None
        if velocity is not None and "velocity" in self._fields:
            problem = problem or ("velocity was given to the recorder (SnapshotRecorder(u, "
                                  "velocity=v)) and to record(); give it once")
        elif velocity is not None or "velocity" in self._fields:
            vel, p = self._local(self._fields.get("velocity", velocity), "velocity", t)
            problem = problem or p
        if "acceleration" in self._fields:
            acc, p = self._local(self._fields["acceleration"], "acceleration", t)
            problem = problem or p
        problem = problem or self._time_problem(t)
        if inputs is not None and problem is None:
            inputs, tu, p = self._input_problem(t, inputs, input_time)
            problem = problem or p
        elif input_time is not None and problem is None:
            problem = "input_time given without inputs"
        if problem is None and self._times:
            if (inputs is None) != (not self._inputs):
                problem = "pass inputs at every record() call or at none"
            elif (vel is None) != (not self._velocities):
                problem = "pass velocity at every record() call or at none"
        if problem is None and self.output_matrix is not None and arr.shape[0] != self._n_local:
            problem = "outputs need the ghosted array: pass the Function itself"
        if problem is None and comm.size > 1:  # the ranks must record the same time and inputs
            seen = comm.allgather((t, None if inputs is None else inputs.tolist()))
            if any(x != seen[0] for x in seen):
                problem = (f"record() called with different times or inputs on different ranks "
                           f"({seen}); t and inputs are global: pass the same on every rank")
        _verdict(comm, problem)
        y = comm.allreduce(self.output_matrix @ arr) if self.output_matrix is not None else None
        # nothing can fail past this point: store everything
        self._times.append(t)
        self._states.append(arr[: self._n_owned].copy())
        if vel is not None:
            self._velocities.append(vel[: self._n_owned].copy())
        if acc is not None:
            self._accelerations.append(acc[: self._n_owned].copy())
        if inputs is not None and tu is not None:
            self._inputs.append(inputs)
            self._input_times.append(tu)
        if y is not None:
            self._outputs.append(y)

    def _time_problem(self, t):
        if not self._times:
            return None
        if t <= self._times[-1]:
            return f"times must increase: got t = {t} after {self._times[-1]}"
        if len(self._times) >= 2:
            dt = self._times[1] - self._times[0]
            tol = 1e-6 * dt + 4 * np.finfo(float).eps * abs(t)
            if abs((t - self._times[-1]) - dt) > tol:
                return (f"record at a uniform spacing: dt was {dt!r}, now {t - self._times[-1]!r} "
                        f"at t = {t!r} (a skipped or repeated step?)")
        return None

    def _input_problem(self, t, inputs, input_time):
        """(inputs as a float array, the time they act, problem or None)."""
        try:
            inputs = np.atleast_1d(np.asarray(inputs, dtype=float)).ravel()
        except (TypeError, ValueError):
            return None, None, f"inputs must be a sequence of real numbers, got {inputs!r}"
        if not np.all(np.isfinite(inputs)):
            return None, None, f"inputs at t = {t} contain NaN or inf: {inputs}"
        if self._inputs and len(inputs) != len(self._inputs[0]):
            return None, None, f"inputs had {len(self._inputs[0])} entries, now {len(inputs)}"
        tu = t
        if input_time is not None:
            try:
                tu = float(input_time)
            except (TypeError, ValueError):
                return None, None, f"input_time must be a number, got {input_time!r}"
            if not np.isfinite(tu):
                return None, None, f"input_time must be finite, got {input_time!r}"
        if self._input_times and tu <= self._input_times[-1]:
            if tu == self._input_times[-1] and np.array_equal(inputs, self._inputs[-1]):
                return inputs, None, None  # the same load sample again (kept once)
            return None, None, (f"input times must increase: input_time = {tu!r} after "
                                f"{self._input_times[-1]!r}"
                                + (" with another value" if tu == self._input_times[-1] else ""))
        return inputs, tu, None

    def sink(self, *, every: int = 1, until_step: int | None = None, velocity: bool = False,
             inputs=None):
        """A sink of :func:`dolfinx_lopinf.fem.loop.run_loop`: :meth:`record` the integrator's
        state (and ``velocity``, and ``inputs(t)`` if given) at every ``every``-th step up to
        ``until_step``. A recorder made without ``scheme`` takes the integrator's."""
        from .loop import Every

        def record(s):
            if self.scheme is None:
                self.scheme = check_scheme(getattr(s.integrator, "scheme", None), "integrator.scheme")
            self.record(s.t, s.q, velocity=s.velocity() if velocity else None,
                        inputs=None if inputs is None else inputs(s.t))

        return Every(record, every=every, until_step=until_step)

    def snapshots(self) -> Snapshots | None:
        """Gather everything to rank 0 as :class:`Snapshots` (None on the other ranks), with
        the recorder's ``weight`` assembled in state coordinates (the first call only)."""
        if len(self._times) < 2:
            raise InputError("record at least two time steps before asking for snapshots")
        arrive(self.V.mesh.comm, "SnapshotRecorder.snapshots()",
               "snapshots() gathers every rank's rows: call it on every rank (it returns None "
               "off rank 0), not inside `if comm.rank == 0:`")
        agree(self.V.mesh.comm, "SnapshotRecorder.snapshots()",
              scheme="" if self.scheme is None else self.scheme.spec, samples=len(self._times),
              inputs=len(self._inputs), velocities=len(self._velocities),
              accelerations=len(self._accelerations))
        gather = (lambda rows: gather_states(self.V, np.column_stack(rows), self.state_map)
                  if rows else None)
        Q, Vel, Acc = gather(self._states), gather(self._velocities), gather(self._accelerations)
        if self.weight is not None and self._gram is None:  # collective; once (None off rank 0)
            self._gram = (state_gram(self.V, self.state_map, self.weight),)
        if self.V.mesh.comm.rank != 0:
            return None
        U = np.column_stack(self._inputs) if self._inputs else None
        Y = np.column_stack(self._outputs) if self._outputs else None
        ti = np.array(self._input_times) if self._inputs else None
        if ti is not None and len(ti) == len(self._times) and np.array_equal(ti, self._times):
            ti = None  # the inputs act at the state times
        return Snapshots(times=np.array(self._times), Q=Q, blocks=self.state_map.blocks, V=Vel,
                         A=Acc, U=U, Y=Y, scheme=self.scheme, input_times=ti,
                         weight=None if self._gram is None else self._gram[0])
