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

Both integrators here (:class:`MidpointIntegrator`, :class:`NewmarkIntegrator`) follow one
protocol, :class:`Integrator`: ``step(u=None) -> q``, ``velocity()``, ``energy()``, ``dt``,
``t``, ``q``, ``scheme`` and ``close()`` (also a context manager). The one time loop,
:func:`dolfinx_lopinf.fem.fom.run`, drives any of them. PETSc options go into the global options
database under a prefix unique to the integrator (``lopinf_<scheme>_<n>_`` unless you pass
one) and are removed once the solver has read them, as DOLFINx's ``LinearProblem`` does;
``close()`` destroys the PETSc objects.
"""

from __future__ import annotations

import itertools
import warnings
from typing import Protocol, runtime_checkable

import numpy as np

from ._dolfinx import MPI, PETSc, dolfinx, ufl
from ..errors import InputCorrectedWarning, InputError, StepFailedError
from .agreement import RTOL, agree, check
from .lagrangian import LagrangianSystem, _on_space

fem = dolfinx.fem
fpetsc = dolfinx.fem.petsc


_PREFIX_COUNTER = itertools.count()


def _unique_prefix(scheme: str) -> str:
    """A PETSc options prefix no other integrator of this process uses."""
    return f"lopinf_{scheme}_{next(_PREFIX_COUNTER)}_"


def _push_options(prefix: str, options: dict) -> list[str]:
    """Write ``options`` under ``prefix`` into the global database; return the keys written
    (for :func:`_pop_options`)."""
    opts = PETSc.Options()
    for key, value in options.items():
        opts[f"{prefix}{key}"] = value
    return [f"{prefix}{key}" for key in options]


def _pop_options(keys) -> None:
    """Remove keys written by :func:`_push_options` (those already gone are skipped)."""
    opts = PETSc.Options()
    for key in keys:
        if opts.hasName(key):
            opts.delValue(key)


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


def _direct_solver(A, comm, prefix: str, options: dict | None, *, spd: bool = False):
    """KSP with a direct factorisation: MUMPS when PETSc has it, PETSc's own otherwise.
    ``spd``: A is symmetric positive definite - Cholesky (LDL^T, half the memory of LU).
    The options are removed from the global database once the factorisation has read them."""
    ksp = PETSc.KSP().create(comm)
    if spd:
        A.setOption(PETSc.Mat.Option.SPD, True)
    ksp.setOperators(A)
    ksp.setOptionsPrefix(prefix)
    ksp.setType("preonly")
    pc = ksp.getPC()
    pc.setType("cholesky" if spd else "lu")
    pc.setFactorSolverType("mumps")
    keys = _push_options(prefix, options or {})
    try:
        ksp.setFromOptions()
        try:
            ksp.setUp()
        except PETSc.Error:  # pragma: no cover - a PETSc built without MUMPS
            if comm.size > 1:
                raise
            pc.setFactorSolverType("petsc")
            ksp.setUp()
    finally:
        _pop_options(keys)
    return ksp


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
        prefix: PETSc options prefix (default: ``lopinf_midpoint_<n>_``, unique per
            integrator). The options are removed from the global database once read.

    The current state is ``self.q`` (a dolfinx Function), ``self.p`` (a PETSc Vec) and
    ``self.t``. Use :meth:`initialize` then :meth:`step`, or :meth:`advance` as a
    black box from arbitrary (q, p); :meth:`close` (or ``with``) destroys the PETSc objects.
    """

    scheme = "midpoint"

    def __init__(self, system: LagrangianSystem, dt: float, *, petsc_options: dict | None = None,
                 prefix: str | None = None):
        if not isinstance(system, LagrangianSystem):
            raise InputError(f"system must be a LagrangianSystem, got {type(system).__name__}")
        V, comm = system.V, system.V.mesh.comm
        dt = check(comm, "MidpointIntegrator", lambda: (_check_dt(dt), _check_options(petsc_options))[0])
        agree(comm, "MidpointIntegrator", None, dt=dt, petsc_options=petsc_options)
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
        comm = self.system.V.mesh.comm
        self._A1 = fpetsc.assemble_matrix(self._jacobian, bcs=self._bcs)
        self._A1.assemble()
        self._ksp = _direct_solver(self._A1, comm, self.prefix, options)
        self._rhs = fpetsc.create_vector(self.system.V)
        self._dq = fpetsc.create_vector(self.system.V)

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
                        warnings.warn(
                            f"{name} violates the Dirichlet conditions by up to {off:.3g} "
                            f"(max |{name}| = {scale:.3g}) at {n_bc} dofs; it was set to the bc "
                            "value 0 there before the run", InputCorrectedWarning, stacklevel=3)
        self.q.x.array[:] = sysm.q.x.array
        self._assemble(self._momentum_at, self.p)
        self._zero_bc_rows(self.p)
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
        self._step_agreed()
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
            rhs.scale(-1.0)
            fpetsc.set_bc(rhs, self._bcs)
            self._ksp.solve(rhs, dq)
            if self._ksp.getConvergedReason() <= 0:
                raise StepFailed(f"linear solve failed at step {self.steps_taken + 1}: "
                                 f"KSP reason {self._ksp.getConvergedReason()}")
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
        _destroy(self._ksp, getattr(self, "_A1", None), getattr(self, "_rhs", None),
                 getattr(self, "_dq", None), self._snes, getattr(self, "_J", None),
                 getattr(self, "_b", None), getattr(self, "_x", None),
                 getattr(self, "_p_free", None), getattr(self, "_mass_ksp", None),
                 getattr(self, "_mass", None), getattr(self, "_work", None), getattr(self, "p", None))
        self._ksp = self._snes = self._mass_ksp = self._mass = self.p = None
        for name in ("_A1", "_rhs", "_dq", "_J", "_b", "_x", "_p_free", "_work"):
            if hasattr(self, name):
                setattr(self, name, None)


class NewmarkIntegrator(_Closing):
    """Newmark average acceleration (gamma = 1/2, beta = 1/4) for a forced, damped linear
    system  M q_tt + C q_t + K q = sum_j b_j u_j(t)  (docs/method.md#newmark-and-generalised-alpha):

        q* = q + dt v + dt^2/4 a,   v* = v + dt/2 a
        A a1 = sum_j b_j u_j(t1) - C v* - K q*,   A = M + dt/2 C + dt^2/4 K  (factored once)
        q1 = q* + dt^2/4 a1,   v1 = v* + dt/2 a1.

    M and K are the mass and stiffness forms of a quadratic :class:`LagrangianSystem`;
    C = alpha M + beta K (Rayleigh); each b_j is an assembled input form (e.g. a chamber
    pressure). Homogeneous Dirichlet conditions of the system are applied.

    Args:
        system: quadratic Lagrangian system.
        dt: time step.
        rayleigh: (alpha, beta).
        input_forms: linear forms b_j(v), one per input channel.
        solver: ``"direct"`` (MUMPS LU of A) or ``"cg"`` (CG + GAMG with ``near_nullspace``).
        near_nullspace: optional PETSc NullSpace (rigid body modes) for GAMG.
        prefix: PETSc options prefix (default ``lopinf_newmark_<n>_``, unique); the options
            are removed from the global database once the solver is set up.

    An :class:`Integrator`: :meth:`initialize` (from rest), then :meth:`step` with the input
    values at the new time; :meth:`close` (or ``with``) destroys the PETSc objects.
    """

    scheme = "newmark"

    def __init__(self, system: LagrangianSystem, dt: float, *, rayleigh=(0.0, 0.0),
                 input_forms=(), solver: str = "direct", near_nullspace=None,
                 prefix: str | None = None, petsc_options: dict | None = None):
        if not isinstance(system, LagrangianSystem):
            raise InputError(f"system must be a LagrangianSystem, got {type(system).__name__}")
        comm = system.V.mesh.comm

        def local():
            if not system.is_quadratic:
                raise InputError("Newmark here is for linear systems (a quadratic Lagrangian)")
            if solver not in ("direct", "cg"):
                raise InputError(f"solver must be 'direct' or 'cg', got {solver!r}")
            step = _check_dt(dt)
            try:
                a, b = (float(c) for c in rayleigh)
            except (TypeError, ValueError):
                raise InputError(f"rayleigh must be (alpha, beta), got {rayleigh!r}") from None
            if not (np.isfinite(a) and np.isfinite(b) and a >= 0 and b >= 0):
                raise InputError(f"rayleigh = {rayleigh!r}: alpha and beta must be finite and >= 0")
            for j, form in enumerate(input_forms):
                args = form.arguments() if isinstance(form, ufl.Form) else None
                if not args or len(args) != 1 or args[0].ufl_function_space() != system.V:
                    raise InputError(f"input_forms[{j}] must be a UFL 1-form whose test function "
                                     "is on the system's space (the space of q)")
            _check_options(petsc_options)
            return step, a, b

        dt, alpha, beta = check(comm, "NewmarkIntegrator", local)
        agree(comm, "NewmarkIntegrator", None, dt=dt, rayleigh=(alpha, beta), solver=solver,
              input_channels=len(input_forms), petsc_options=petsc_options,
              near_nullspace=near_nullspace is not None)
        _check_homogeneous(system.bcs, system.V)
        prefix = _unique_prefix(self.scheme) if prefix is None else str(prefix)
        self.system, self.dt, self.prefix = system, float(dt), prefix
        self._comm = comm
        V = system.V
        bcs = list(system.bcs)
        self._bcs = bcs
        M = fpetsc.assemble_matrix(fem.form(system.mass_form), bcs=bcs)
        M.assemble()
        K = fpetsc.assemble_matrix(fem.form(system.stiffness_form), bcs=bcs, diag=0.0)
        K.assemble()
        C = M.copy()
        C.scale(alpha)
        C.axpy(beta, K)
        A = M.copy()
        A.axpy(0.5 * self.dt, C)
        A.axpy(0.25 * self.dt**2, K)
        self.M, self.K, self.C, self.A = M, K, C, A
        if solver == "direct":
            # A = M + dt/2 C + dt^2/4 K is SPD: Cholesky
            self._ksp = _direct_solver(A, comm, prefix, petsc_options, spd=True)
        else:
            if near_nullspace is not None:
                A.setNearNullSpace(near_nullspace)
            ksp = PETSc.KSP().create(comm)
            ksp.setOperators(A)
            ksp.setOptionsPrefix(prefix)
            ksp.setType("cg")
            ksp.getPC().setType("gamg")
            ksp.setTolerances(rtol=1e-10, atol=1e-30, max_it=2000)
            keys = _push_options(prefix, petsc_options or {})
            try:
                ksp.setFromOptions()
                ksp.setUp()  # GAMG reads its level options here: before they are removed
            finally:
                _pop_options(keys)
            self._ksp = ksp
        self.inputs = []
        for form in input_forms:
            b = fpetsc.assemble_vector(fem.form(form))
            b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
            fpetsc.set_bc(b, bcs)
            self.inputs.append(b)
        self.q, self.v, self.a = (fem.Function(V) for _ in range(3))
        self._qs, self._vs, self._rhs, self._tmp = (fpetsc.create_vector(V) for _ in range(4))
        self.t = 0.0

    def _values(self, u, what: str):
        """(problem, u as (m,) floats): the input values of one time, checked on this rank."""
        m = len(self.inputs)
        if u is None:
            if m:
                return (f"{what}: this integrator has {m} input channel(s) (input_forms): pass "
                        f"{m} input value(s)"), None
            return None, np.zeros(0)
        try:
            values = np.atleast_1d(np.asarray(u, dtype=float)).reshape(-1)
        except (TypeError, ValueError):
            return f"{what}: input values must be {m} numbers, got {u!r}", None
        if len(values) != m:
            return f"{what}: expected {m} input value(s) (one per input form), got {len(values)}", None
        if not np.all(np.isfinite(values)):
            return f"{what}: input values contain NaN or inf: {values}", None
        return None, values

    def _agreed_values(self, u, what: str, problem=None):
        """The input values, the same on every rank (else the same error on every rank)."""
        found, values = self._values(u, what)
        problem = problem or found
        comm = self._comm
        if comm.size > 1:
            # the common case in one small Allreduce (max of [refused, u, -u]: every rank agrees
            # when no rank refused and max u = min u to RTOL); the full agreement, with its
            # message, only when something is wrong
            m = len(self.inputs)
            ok = problem is None
            buf = np.concatenate([[0.0 if ok else 1.0], values if ok else np.zeros(m),
                                  -values if ok else np.zeros(m)])
            out = np.empty_like(buf)
            comm.Allreduce(buf, out, op=MPI.MAX)
            high, low = out[1:m + 1], -out[m + 1:]
            if out[0] == 0.0 and np.all(high - low <= RTOL * np.max(np.abs(out[1:]), initial=0.0)):
                return values
        agree(comm, f"NewmarkIntegrator.{what}", problem,
              **({"input values": values} if problem is None else {}))
        return values

    def _load(self, values, out):
        out.set(0.0)
        for b, uj in zip(self.inputs, values):
            out.axpy(float(uj), b)
        return out

    def initialize(self, u0=None):
        """Start from rest (q = v = 0) with the consistent acceleration M a0 = B u(0)
        (``u0``: the input values at t = 0; None for zero inputs)."""
        if u0 is None and self.inputs and not self.closed:
            u0 = np.zeros(len(self.inputs))
        u0 = self._agreed_values(u0, "initialize", self._open_problem("initialize"))
        for f in (self.q, self.v, self.a):
            f.x.array[:] = 0.0
        if self.inputs:
            rhs = self._load(u0, self._rhs)
            if rhs.norm() > 0:
                # CG + Jacobi on the mass matrix (no second factorisation: on large meshes the
                # memory of one is all there is)
                ksp = PETSc.KSP().create(self.system.V.mesh.comm)
                ksp.setOperators(self.M)
                ksp.setType("cg")
                ksp.getPC().setType("jacobi")
                ksp.setTolerances(rtol=1e-13, atol=0.0, max_it=5000)
                ksp.solve(rhs, self.a.x.petsc_vec)
                if ksp.getConvergedReason() <= 0:
                    raise StepFailed(f"initial acceleration: CG on the mass matrix did not converge "
                                     f"(reason {ksp.getConvergedReason()})")
                self.a.x.scatter_forward()
                ksp.destroy()
        self.t = 0.0
        self.initialized = True

    def step(self, u1=None) -> "fem.Function":
        """Advance one step with the inputs u(t + dt) (None when there are no input forms);
        return ``self.q``. Collective: the input values must be the same on every rank
        (checked: one small allgather per step on several ranks), a refusal is raised on
        every rank."""
        problem = self._step_problem(None, True)
        if self._agreed_loop and problem is None and u1 is None and not self.inputs:
            return self._step_agreed(np.zeros(0))
        return self._step_agreed(self._agreed_values(u1, "step", problem))

    def _step_agreed(self, values) -> "fem.Function":
        """:meth:`step` with input values every rank agreed on."""
        dt = self.dt
        q, v, a = self.q.x.petsc_vec, self.v.x.petsc_vec, self.a.x.petsc_vec
        qs, vs, rhs, tmp = self._qs, self._vs, self._rhs, self._tmp
        q.copy(qs)
        qs.axpy(dt, v)
        qs.axpy(0.25 * dt**2, a)
        v.copy(vs)
        vs.axpy(0.5 * dt, a)
        self._load(values, rhs)
        self.C.mult(vs, tmp)
        rhs.axpy(-1.0, tmp)
        self.K.mult(qs, tmp)
        rhs.axpy(-1.0, tmp)
        fpetsc.set_bc(rhs, self._bcs)
        self._ksp.solve(rhs, a)
        if self._ksp.getConvergedReason() <= 0:
            raise StepFailed(f"Newmark solve failed at t = {self.t + dt:.6g}: KSP reason "
                             f"{self._ksp.getConvergedReason()}")
        qs.copy(q)
        q.axpy(0.25 * dt**2, a)
        vs.copy(v)
        v.axpy(0.5 * dt, a)
        for f in (self.q, self.v, self.a):
            f.x.scatter_forward()
        self.t += dt
        return self.q

    def velocity(self, out: "fem.Function | None" = None) -> "fem.Function":
        """The current velocity (``self.v``, or a copy in ``out``)."""
        self._check_open("velocity")
        if out is None:
            return self.v
        out.x.array[:] = self.v.x.array
        return out

    def energy(self, v: "fem.Function | None" = None) -> float:
        """1/2 v^T M v + 1/2 q^T K q (mechanical energy; v defaults to the current velocity)."""
        self._check_open("energy")
        q, tmp = self.q.x.petsc_vec, self._tmp
        v = self.v.x.petsc_vec if v is None else v.x.petsc_vec
        self.M.mult(v, tmp)
        e = 0.5 * v.dot(tmp)
        self.K.mult(q, tmp)
        return float(e + 0.5 * q.dot(tmp))

    def close(self) -> None:
        """Destroy the PETSc objects (matrices, solver, work and input vectors)."""
        self.closed = True
        _destroy(self._ksp, self.M, self.K, self.C, self.A, self._qs, self._vs, self._rhs,
                 self._tmp, *self.inputs)
        self._ksp = self.M = self.K = self.C = self.A = None
        self._qs = self._vs = self._rhs = self._tmp = None
        self.inputs = []


def rigid_body_modes(V):
    """The six rigid-body modes of a 3D vector space as a PETSc NullSpace (orthonormalised):
    the near-nullspace GAMG needs to coarsen elasticity well."""
    bs = V.dofmap.index_map_bs
    if bs != 3 or V.mesh.geometry.dim != 3:
        raise ValueError("rigid_body_modes needs a 3D vector function space (block size 3)")
    n_own = V.dofmap.index_map.size_local
    x = V.tabulate_dof_coordinates()[:n_own]
    modes = np.zeros((6, n_own, 3))
    for i in range(3):
        modes[i, :, i] = 1.0
    modes[3, :, 0], modes[3, :, 1] = -x[:, 1], x[:, 0]
    modes[4, :, 0], modes[4, :, 2] = x[:, 2], -x[:, 0]
    modes[5, :, 2], modes[5, :, 1] = x[:, 1], -x[:, 2]
    vecs = []
    comm = V.mesh.comm
    for m in modes.reshape(6, -1):
        v = PETSc.Vec().createMPI((len(m), PETSc.DECIDE), bsize=3, comm=comm)
        v.array[:] = m
        vecs.append(v)
    # modified Gram-Schmidt (collective dot products)
    for i, v in enumerate(vecs):
        for w in vecs[:i]:
            v.axpy(-v.dot(w), w)
        v.scale(1.0 / v.norm())
    return PETSc.NullSpace().create(vectors=vecs, comm=comm)
