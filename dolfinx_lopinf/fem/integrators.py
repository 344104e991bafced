"""Midpoint variational integrator on PETSc objects (docs/method.md#discrete-euler-lagrange).

One step maps (q0, p0) to (q1, p1) by

    p0 + D1 L_d(q0, q1) + f_d^-(q0, q1) = 0      (solved for q1)
    p1 = D2 L_d(q0, q1) + f_d^+(q0, q1),

with the forms of :class:`~dolfinx_lopinf.fem.lagrangian.LagrangianSystem`, always evaluated
by assembling the forms (never as matrix-vector products with K: for a beam K q is a
fourth difference that loses ~h^-4 of the digits, and the energy then drifts by ~1e-8
over a few thousand steps; the assembled residual keeps it at ~1e-14).

* L quadratic (and forcing affine): the step is linear. One Newton update from q1 = q0
  with the Jacobian A1 = dR/dq1, assembled and factored once (MUMPS, else PETSc LU), is
  exact:  A1 d = -(p0 + R(q0, q0)),  q1 = q0 + d.
* Otherwise: PETSc SNES (Newton) on the same residual, Jacobian from ``ufl.derivative``.

Velocities come from the discrete Legendre transform: M v = p - dL/dq_t(q, 0).
Only homogeneous Dirichlet conditions are supported (checked).

The integrators (:class:`MidpointIntegrator`, and
:class:`~dolfinx_lopinf.fem.newmark.NewmarkIntegrator` in :mod:`~dolfinx_lopinf.fem.newmark`)
follow one protocol, :class:`Integrator`: ``step(u=None) -> q``, ``velocity()``, ``energy()``, ``dt``,
``t``, ``q``, ``scheme`` and ``close()`` (also a context manager). The one time loop,
:func:`dolfinx_lopinf.fem.fom.run`, drives any of them. PETSc options go into the global options
database under a prefix unique to the integrator (``lopinf_<scheme>_<n>_`` unless you pass
one) and are removed once the solver has read them, as DOLFINx's ``LinearProblem`` does;
``close()`` destroys the PETSc objects.
"""

from __future__ import annotations

import itertools
from typing import Protocol, runtime_checkable

import numpy as np

from ._dolfinx import MPI, PETSc, dolfinx
from ..errors import InputCorrectedWarning, InputError, StepFailedError, warn
from .agreement import agree, check
from .lagrangian import LagrangianSystem, _on_space
from . import linsolve
from .linsolve import _pop_options, _push_options  # noqa: F401 - re-exported
from .linsolve import direct_ksp as _direct_solver

fem = dolfinx.fem
fpetsc = dolfinx.fem.petsc


_PREFIX_COUNTER = itertools.count()


def _unique_prefix(scheme: str) -> str:
    """A PETSc options prefix no other integrator of this process uses."""
    return f"lopinf_{scheme}_{next(_PREFIX_COUNTER)}_"


def _destroy(*objects) -> None:
    for obj in objects:
        if obj is not None:
            obj.destroy()


@runtime_checkable
class Integrator(Protocol):
    """What the time loop (:func:`dolfinx_lopinf.fem.fom.run`) needs of an integrator.

    Attributes:
        scheme: ``"midpoint"`` or ``"newmark"`` (the data relation the snapshots obey).
        dt: time step.
        t: current time.
        q: the current configuration (a dolfinx Function; owned + ghost dofs up to date).
    """

    scheme: str
    dt: float
    t: float
    q: "fem.Function"

    def step(self, u=None) -> "fem.Function":
        """Advance one step (``u``: input values at the new time, if the scheme takes any);
        return :attr:`q`."""

    def velocity(self, out=None) -> "fem.Function":
        """The velocity at the current time."""

    def energy(self, v=None) -> float:
        """The mechanical energy at the current time (``v``: the velocity, if at hand)."""

    def close(self) -> None:
        """Destroy the PETSc objects (the integrator is unusable afterwards)."""


class _Closing:
    """Context-manager support (``with Integrator(...) as it: ...`` closes on exit) and the
    life-cycle checks: a closed integrator, or one never initialised, refuses to step."""

    closed = False
    initialized = False
    _agreed_loop = False  # set by the time loop, which agreed on the step arguments at its entry

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _open_problem(self, what: str) -> str | None:
        if self.closed:
            return (f"{type(self).__name__}.{what}: the integrator was closed (close() or the end "
                    "of its with block) and its PETSc objects destroyed; make a new one")
        return None

    def _check_open(self, what: str) -> None:
        """Refuse a closed integrator (a state every rank shares: close() is collective)."""
        problem = self._open_problem(what)
        if problem is not None:
            raise InputError(problem)

    def _step_problem(self, u, takes_inputs: bool) -> str | None:
        problem = self._open_problem("step")
        if problem is None and not self.initialized:
            problem = (f"{type(self).__name__}.step: the integrator was never initialised - it "
                       "would step from q = 0, p = 0 and return zeros; call initialize(...) first "
                       "(run(system, q0, v0, ...) does it for you)")
        if problem is None and u is not None and not takes_inputs:
            problem = ("MidpointIntegrator.step takes no input values: put the forcing into the "
                       "LagrangianSystem (forcing=..., time=...)")
        return problem


def _check_dt(dt, what="dt"):
    try:
        ok = bool(np.isfinite(float(dt)) and float(dt) > 0)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise InputError(f"{what} must be a positive finite number, got {dt!r}")
    return float(dt)


def _check_options(options):
    if options is not None and not isinstance(options, dict):
        raise InputError(f"petsc_options must be a dict of PETSc options, got {type(options).__name__}")
    return options


def _check_mass(M, bc_dofs, comm):
    """The assembled mass matrix must have a positive diagonal on every free dof (else it is
    singular: no kinetic energy on part of the domain or of the components)."""
    diag = M.getDiagonal()
    d = diag.array.copy()
    diag.destroy()
    lo, hi = M.getOwnershipRange()
    free = np.ones(len(d), dtype=bool)
    owned_bc = bc_dofs[bc_dofs < len(d)]
    free[owned_bc] = False
    bad = int(comm.allreduce(int(np.sum(~(d[free] > 0))), op=MPI.SUM))
    if bad:
        raise InputError(
            f"the mass matrix d^2 L / dq_t^2 has a zero, negative or NaN diagonal at {bad} free "
            "dofs: the kinetic energy does not cover every dof (a term missing on part of the "
            "domain or for some components). Add the kinetic term there, or constrain those dofs")


def _check_homogeneous(bcs, V):
    probe = fpetsc.create_vector(V)
    probe.set(0.0)
    fpetsc.set_bc(probe, list(bcs))
    if probe.norm(PETSc.NormType.NORM_INFINITY) != 0:
        raise NotImplementedError(
            "only homogeneous Dirichlet conditions (value 0) are supported by the integrator; "
            "shift the unknown so the boundary value is zero"
        )
    probe.destroy()


#: A nonlinear FOM step (PETSc SNES) did not converge; the message names the step, time and
#: residual. The same class as the reduced models' Newton failures
#: (:class:`dolfinx_lopinf.errors.StepFailedError`, a RuntimeError).
StepFailed = StepFailedError


class MidpointIntegrator(_Closing):
    """Midpoint variational integrator for a :class:`LagrangianSystem` (an :class:`Integrator`).

    Args:
        system: the Lagrangian system.
        dt: time step.
        petsc_options: extra options for the linear solver (linear case, prefix
            ``<prefix>``) or for SNES (nonlinear case).
        solver: the linear case's solver, a name of
            :data:`dolfinx_lopinf.fem.linsolve.SOLVERS` (``"auto"``: MUMPS LU of the step
            Jacobian, or on larger problems a Cholesky of its negative with the recycled
            subspace, :func:`~dolfinx_lopinf.fem.linsolve.resolve`; the other solvers work on
            that negative, M/dt + dt/4 K, which is SPD, the iterative and subspace ones
            warm-started from the extrapolated displacement). Newton (SNES) steps keep their direct solve: only
            ``"auto"`` or ``"direct"`` there (KSP/PC via petsc_options).
        prefix: PETSc options prefix (default: ``lopinf_midpoint_<n>_``, unique per
            integrator). The options are removed from the global database once read.

    The current state is ``self.q`` (a dolfinx Function), ``self.p`` (a PETSc Vec) and
    ``self.t``. Use :meth:`initialize` then :meth:`step`, or :meth:`advance` as a
    black box from arbitrary (q, p); :meth:`close` (or ``with``) destroys the PETSc objects.
    """

    scheme = "midpoint"

    def __init__(self, system: LagrangianSystem, dt: float, *, petsc_options: dict | None = None,
                 prefix: str | None = None, solver: str = "auto"):
        if not isinstance(system, LagrangianSystem):
            raise InputError(f"system must be a LagrangianSystem, got {type(system).__name__}")
        V, comm = system.V, system.V.mesh.comm

        def local():
            # "auto" from the problem's size, as Newmark's (the linear case's factor: MUMPS's
            # block low-rank Cholesky of -A1 from BLR_FROM unknowns); Newton steps stay direct
            n_global = V.dofmap.index_map.size_global * V.dofmap.index_map_bs
            name = linsolve.resolve(solver, n_global if system.is_quadratic else None)
            if name != "direct" and not system.is_quadratic:
                raise InputError(f"solver={solver!r}: the nonlinear (Newton, PETSc SNES) midpoint step "
                                 "keeps its direct solve; choose 'auto' or 'direct' and set the "
                                 "Newton step's KSP/PC through petsc_options")
            if name != "direct":
                linsolve.check_petsc_options(petsc_options)
            return _check_dt(dt), _check_options(petsc_options), name

        dt, _, solver = check(comm, "MidpointIntegrator", local)
        agree(comm, "MidpointIntegrator", None, dt=dt, petsc_options=petsc_options, solver=solver)
        self._solver_name = solver
        self.solver = None
        self._history = []
        prefix = _unique_prefix(self.scheme) if prefix is None else str(prefix)
        self.system, self.dt, self.prefix = system, float(dt), prefix
        self._comm = comm
        self._snes = self._ksp = None
        self._pending_options = []
        _check_homogeneous(system.bcs, V)
        self.forms = f = system.step_forms(self.dt)
        self.q = fem.Function(V, name="q")
        self.p = fpetsc.create_vector(V)
        self.p.set(0.0)
        self.t = 0.0
        self.steps_taken = 0
        self._bcs = list(system.bcs)
        self._bc_dofs = np.concatenate([bc.dof_indices()[0] for bc in self._bcs]) if self._bcs else \
            np.zeros(0, dtype=np.int32)
        n_owned = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
        self._bc_dofs_owned_mask = self._bc_dofs < n_owned
        self._residual = fem.form(f.residual)
        self._momentum = fem.form(f.momentum)
        self._jacobian = fem.form(f.d_residual_d_q1)
        # Legendre transform pieces: mass (with bcs) and dL/dq_t at (q, 0).
        self._mass = fpetsc.assemble_matrix(fem.form(system.mass_form), bcs=self._bcs)
        self._mass.assemble()
        _check_mass(self._mass, self._bc_dofs, comm)
        self._mass_ksp = _direct_solver(self._mass, comm, prefix + "mass_", None)
        self._momentum_at = fem.form(system.momentum_form)
        self._energy = fem.form(system.energy_form)
        self._work = fpetsc.create_vector(V)
        self._linear = system.is_quadratic
        if self._linear:
            self._setup_linear(petsc_options)
        else:
            self._setup_snes(petsc_options)

    # -- set-up ---------------------------------------------------------------------------
    def _setup_linear(self, options):
        V, comm = self.system.V, self.system.V.mesh.comm
        if self._solver_name == "direct":
            self._A1 = fpetsc.assemble_matrix(self._jacobian, bcs=self._bcs)
            self._A1.assemble()
            self._ksp = _direct_solver(self._A1, comm, self.prefix, options)
        else:  # -A1 = M/dt + dt/4 K (+ damping) is SPD: bc rows -1 before the sign flip
            self._A1 = fpetsc.assemble_matrix(self._jacobian, bcs=self._bcs, diag=-1.0)
            self._A1.assemble()
            self._A1.scale(-1.0)
            self.solver = linsolve.StepSolver(self._A1, comm, self._solver_name, self.prefix,
                                              options, V=V)
            self._ksp = self.solver.ksp
            if self.solver.uses_guess:  # a plain factor ("direct+blr") takes no warm start
                self._history = [fpetsc.create_vector(V) for _ in range(3)]
        self._n_history = 0
        self._rhs = fpetsc.create_vector(V)
        self._dq = fpetsc.create_vector(V)
        self._dq.set(0.0)

    def _setup_snes(self, options):
        V, comm = self.system.V, self.system.V.mesh.comm
        self._snes = PETSc.SNES().create(comm)
        self._J = fpetsc.create_matrix(self._jacobian)
        self._b = fpetsc.create_vector(V)
        self._x = fpetsc.create_vector(V)
        q1 = self.forms.q1

        def residual(snes, x, b):
            fpetsc.assemble_residual(snes, x, b, q1, self._residual, self._jacobian, self._bcs)
            # add p0 on the free rows (bc rows keep their bc residual)
            b.axpy(1.0, self._p_free)

        self._snes.setFunction(residual, self._b)
        self._snes.setJacobian(fpetsc.assemble_jacobian, self._J, None,
                               kargs={"u": q1, "jacobian": self._jacobian, "preconditioner": None,
                                      "bcs": self._bcs})
        self._snes.setOptionsPrefix(self.prefix)
        defaults = {"snes_type": "newtonls", "snes_linesearch_type": "none", "snes_rtol": 1e-12,
                    "snes_atol": 1e-12, "snes_stol": 0.0, "snes_max_it": 25, "ksp_type": "preonly",
                    "pc_type": "lu"}
        # removed after the first step: the inner KSP/PC read some of them only at set-up
        self._pending_options = _push_options(self.prefix, {**defaults, **(options or {})})
        self._snes.setFromOptions()
        self._p_free = fpetsc.create_vector(V)

    # -- helpers --------------------------------------------------------------------------
    def _assemble(self, form, out):
        with out.localForm() as loc:
            loc.set(0.0)
        fpetsc.assemble_vector(out, form)
        out.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return out

    def _zero_bc_rows(self, vec):
        if len(self._bc_dofs):
            with vec.localForm() as loc:
                loc.array[self._bc_dofs] = 0.0

    def _warm_start(self, dq):
        """dq = q_e - q_k with q_e extrapolated from the last three displacements (returns
        True); until three are known, dq keeps the previous increment (returns False)."""
        q = self.q.x.petsc_vec
        q.copy(self._history[0])
        self._history.append(self._history.pop(0))
        self._n_history = min(self._n_history + 1, 3)
        if self._n_history < 3:
            return False
        linsolve.extrapolate(self._history, dq)
        dq.axpy(-1.0, q)
        return True

    def _set_time(self, t_mid):
        if self.system.time is not None:
            self.system.time.value = t_mid

    # -- public ---------------------------------------------------------------------------
    def initialize(self, q0, v0, t0: float = 0.0):
        """Set (q, p) from an initial configuration and velocity: p0 = dL/dq_t(q0, v0).

        Args:
            q0, v0: dolfinx Functions on the system's space or local dof arrays.
        """
        sysm = self.system
        comm = sysm.V.mesh.comm
        arrays, problem = [], self._open_problem("initialize")
        try:
            t0 = float(t0)
        except (TypeError, ValueError):
            t0 = float("nan")
        if problem is None and not np.isfinite(t0):
            problem = "t0 must be a finite number"
        for target, value, name in ((sysm.q, q0, "q0"), (sysm.q_t, v0, "v0")):
            if self.closed:
                break
            if isinstance(value, fem.Function):
                if not _on_space(value, sysm.V):
                    problem = problem or (f"{name} is a Function on another function space or mesh "
                                          "than the system's; interpolate it onto the space of q")
                arr = value.x.array
            else:
                try:
                    arr = np.asarray(value, dtype=float)
                except (TypeError, ValueError):
                    arr = np.zeros(0)
                    problem = problem or f"{name} must be a Function or an array of floats"
            if arr.shape != target.x.array.shape:
                problem = problem or (
                    f"{name} has shape {arr.shape}, the space has {target.x.array.shape[0]} local "
                    "dofs (owned + ghosts) on this rank: pass a Function on the system's space or "
                    "its x.array")
            elif not np.all(np.isfinite(arr)):
                problem = problem or f"{name} contains NaN or inf"
            arrays.append(arr)
        agree(comm, "MidpointIntegrator.initialize", problem, t0=t0)
        dofs = self._bc_dofs
        for target, arr, name in ((sysm.q, arrays[0], "q0"), (sysm.q_t, arrays[1], "v0")):
            target.x.array[:] = arr
            target.x.scatter_forward()
            if self._bcs:
                off = float(comm.allreduce(np.abs(target.x.array[dofs]).max(initial=0.0), op=MPI.MAX))
                if off > 0:
                    scale = float(comm.allreduce(np.abs(target.x.array).max(initial=0.0), op=MPI.MAX))
                    n_bc = int(comm.allreduce(np.count_nonzero(
                        self._bc_dofs_owned_mask & (target.x.array[dofs] != 0)), op=MPI.SUM))
                    target.x.array[dofs] = 0.0
                    if off > 1e-13 * scale:
                        warn(
                            f"{name} violates the Dirichlet conditions by up to {off:.3g} "
                            f"(max |{name}| = {scale:.3g}) at {n_bc} dofs; it was set to the bc "
                            "value 0 there before the run", InputCorrectedWarning)
        self.q.x.array[:] = sysm.q.x.array
        self._assemble(self._momentum_at, self.p)
        self._zero_bc_rows(self.p)
        self._n_history = 0
        self.t = float(t0)
        self.steps_taken = 0
        self.initialized = True

    @property
    def mass_matrix(self) -> "PETSc.Mat":
        """The assembled mass matrix M (dof space, Dirichlet rows and columns replaced by the
        identity) - what maps a velocity to the momentum p = M v this integrator steps."""
        return self._mass

    def advance(self, q0: np.ndarray, p0: PETSc.Vec):
        """Black-box step: from (q0 local dofs, p0 PETSc Vec) return (q1 array, p1 Vec) copies,
        leaving the integrator's own state untouched."""
        self._check_open("advance")
        saved_q, saved_p, saved_t = self.q.x.array.copy(), self.p.copy(), self.t
        self.q.x.array[:] = q0
        p0.copy(self.p)
        self._n_history = 0  # the warm start's history is not this state's
        self._step_agreed()
        self._n_history = 0
        out = self.q.x.array.copy(), self.p.copy()
        self.q.x.array[:] = saved_q
        saved_p.copy(self.p)
        saved_p.destroy()
        self.t = saved_t
        self.steps_taken -= 1
        return out

    def step(self, u=None) -> "fem.Function":
        """Advance (q, p, t) by one step dt; return ``self.q``. The midpoint scheme takes no
        input values (``u`` must be None): forcing lives in the system's UFL forms. Collective:
        a refusal (closed, never initialised, ``u`` given) is raised on every rank."""
        problem = self._step_problem(u, False)
        if self._agreed_loop and problem is None:
            return self._step_agreed()
        agree(self._comm, "MidpointIntegrator.step", problem)
        return self._step_agreed()

    def _step_agreed(self) -> "fem.Function":
        """:meth:`step` once every rank agreed to take it (the time loop checks at its entry)."""
        try:
            self._step()
        finally:
            if self._pending_options:
                _pop_options(self._pending_options)
                self._pending_options = []
        return self.q

    def _step(self):
        f, t_mid = self.forms, self.t + 0.5 * self.dt
        f.q0.x.array[:] = self.q.x.array
        self._set_time(t_mid)
        if self._linear:
            f.q1.x.array[:] = self.q.x.array
            rhs, dq = self._rhs, self._dq
            self._assemble(self._residual, rhs)  # R(q0, q0) = D1 L_d(q0, q0) + f_d^-
            rhs.axpy(1.0, self.p)
            if self.solver is None:  # A1 dq = -(R + p)
                rhs.scale(-1.0)
                fpetsc.set_bc(rhs, self._bcs)
                self._ksp.solve(rhs, dq)
                reason = self._ksp.getConvergedReason()
                failure = f"KSP reason {reason}"
            else:  # (-A1) dq = R + p (the iterative solvers warm-started)
                fpetsc.set_bc(rhs, self._bcs)
                warm = self._warm_start(dq) if self._history else False
                reason = self.solver.solve(rhs, dq, extrapolated=warm)
                failure = self.solver.describe_failure(reason) if reason <= 0 else ""
                fpetsc.set_bc(dq, self._bcs)  # the constrained rows exactly
            if reason <= 0:
                raise StepFailed(f"linear solve failed at step {self.steps_taken + 1}: {failure}")
            f.q1.x.petsc_vec.axpy(1.0, dq)
            f.q1.x.scatter_forward()
        else:
            self.p.copy(self._p_free)
            self._zero_bc_rows(self._p_free)
            f.q1.x.array[:] = self.q.x.array  # Newton initial guess: previous configuration
            f.q1.x.petsc_vec.copy(self._x)
            self._snes.solve(None, self._x)
            reason = self._snes.getConvergedReason()
            if reason <= 0:
                fnorm = self._snes.getFunctionNorm()
                raise StepFailed(
                    f"Newton (SNES) did not converge at step {self.steps_taken + 1} "
                    f"(t = {self.t + self.dt:.6g}): reason {reason}, residual norm {fnorm:.3e} "
                    f"after {self._snes.getIterationNumber()} iterations; reduce dt"
                )
            self._x.copy(f.q1.x.petsc_vec)
            f.q1.x.scatter_forward()
        self._assemble(self._momentum, self.p)  # p1 = D2 L_d(q0, q1) + f_d^+
        self._zero_bc_rows(self.p)
        self.q.x.array[:] = f.q1.x.array
        self.t += self.dt
        self.steps_taken += 1

    def velocity(self, out: "fem.Function | None" = None) -> "fem.Function":
        """v with M v = p - dL/dq_t(q, 0) (the discrete Legendre transform)."""
        self._check_open("velocity")
        sysm = self.system
        out = fem.Function(sysm.V) if out is None else out
        sysm.q.x.array[:] = self.q.x.array
        sysm.q_t.x.array[:] = 0.0
        rhs = self._assemble(self._momentum_at, self._work)
        rhs.scale(-1.0)
        rhs.axpy(1.0, self.p)
        fpetsc.set_bc(rhs, self._bcs)
        self._mass_ksp.solve(rhs, out.x.petsc_vec)
        if self._mass_ksp.getConvergedReason() <= 0:
            raise StepFailed(f"mass solve (velocity) failed at step {self.steps_taken}: KSP "
                             f"reason {self._mass_ksp.getConvergedReason()}")
        out.x.scatter_forward()
        return out

    def energy(self, v: "fem.Function | None" = None) -> float:
        """E(q, v) = dL/dq_t . v - L, assembled from the UFL energy form (all ranks)."""
        self._check_open("energy")
        sysm = self.system
        v = self.velocity() if v is None else v
        sysm.q.x.array[:] = self.q.x.array
        sysm.q_t.x.array[:] = v.x.array
        local = fem.assemble_scalar(self._energy)
        return float(sysm.V.mesh.comm.allreduce(local))

    def close(self) -> None:
        """Destroy the PETSc objects and remove any options still in the global database."""
        self.closed = True
        _pop_options(self._pending_options)
        self._pending_options = []
        if self.solver is not None:
            self.solver.close()
            self._ksp = self.solver = None
        _destroy(*self._history)
        self._history = []
        _destroy(self._ksp, getattr(self, "_A1", None), getattr(self, "_rhs", None),
                 getattr(self, "_dq", None), self._snes, getattr(self, "_J", None),
                 getattr(self, "_b", None), getattr(self, "_x", None),
                 getattr(self, "_p_free", None), getattr(self, "_mass_ksp", None),
                 getattr(self, "_mass", None), getattr(self, "_work", None), getattr(self, "p", None))
        self._ksp = self._snes = self._mass_ksp = self._mass = self.p = None
        for name in ("_A1", "_rhs", "_dq", "_J", "_b", "_x", "_p_free", "_work"):
            if hasattr(self, name):
                setattr(self, name, None)


