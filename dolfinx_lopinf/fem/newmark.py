"""The Newmark integrator (average acceleration) of a quadratic Lagrangian system on PETSc objects.

For a forced, damped linear system M q_tt + C q_t + K q = sum_j b_j u_j(t) (M, K from a
quadratic :class:`~dolfinx_lopinf.fem.lagrangian.LagrangianSystem`, Rayleigh damping
C = alpha M + beta K, input forms b_j) one step is one solve with the effective matrix
A = M + dt/2 C + dt^2/4 K, factored once (MUMPS; on large meshes most steps answered by the
projection onto the factor's earlier solutions) or solved iteratively, warm-started, to a
tolerance tied to the truncation error (:mod:`~dolfinx_lopinf.fem.linsolve`; GAMG with the
rigid-body near-nullspace, :func:`rigid_body_modes`). :class:`NewmarkIntegrator` follows the protocol of
:class:`~dolfinx_lopinf.fem.integrators.Integrator`, so the one time loop
(:func:`~dolfinx_lopinf.fem.loop.run_loop`) drives it with input values at every step.
"""

from __future__ import annotations

import time

import numpy as np

from ._dolfinx import MPI, PETSc, dolfinx, ufl
from ..errors import InputError
from .agreement import RTOL, agree, check
from . import linsolve
from .integrators import StepFailed, _check_dt, _check_homogeneous, _Closing, _destroy, _unique_prefix
from .lagrangian import LagrangianSystem

fem = dolfinx.fem
fpetsc = dolfinx.fem.petsc
#: let PETSc compare the sparsity of M and K (same pattern: the fast entry-wise sum)
_UNKNOWN_PATTERN = PETSc.Mat.Structure.UNKNOWN_NONZERO_PATTERN
#: the warm start a_e = a_{k-2} + a_{k-1} - a_k (coefficients of the history, oldest first)
_EXTRAPOLATION = np.array([1.0, 1.0, -1.0])


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
        solver: a name of :data:`dolfinx_lopinf.fem.linsolve.SOLVERS`: ``"auto"`` (default,
            :func:`~dolfinx_lopinf.fem.linsolve.resolve`), ``"direct"`` (MUMPS Cholesky of A,
            factored once), ``"direct+blr"`` (its block low-rank variant: a faster
            factorisation on large meshes), ``"direct+subspace"`` / ``"direct+blr+subspace"``
            (the factor, most steps answered by the projection onto its earlier solutions:
            ``auto`` from 100k unknowns) or an iterative one (``"cg"`` = ``"cg+gamg"`` with
            ``near_nullspace``, ``"cg+pmg"``, ``"cg+jacobi"``, ``"chebyshev"``), warm-started
            from the displacement extrapolated over the last three steps (as the
            acceleration a_e = a_{k-1} + a_{k-2} - a_k, which it is for Newmark states) and
            stopped at a tolerance tied to the truncation error (see
            :mod:`~dolfinx_lopinf.fem.linsolve`).
        near_nullspace: optional PETSc NullSpace (rigid body modes) for GAMG.
        prefix: PETSc options prefix (default ``lopinf_newmark_<n>_``, unique); the options
            are removed from the global database once the solver is set up.
        petsc_options: options of the solver under the prefix (e.g. ``{"ksp_rtol": 1e-6}``).

    An :class:`Integrator`: :meth:`initialize` (from rest), then :meth:`step` with the input
    values at the new time; :meth:`close` (or ``with``) destroys the PETSc objects.
    C is never stored: C v = alpha M v + beta K v (one matrix less in memory); :attr:`C`
    builds it on request. ``timings`` holds the set-up seconds (assembly, solver set-up),
    ``solver`` the :class:`~dolfinx_lopinf.fem.linsolve.StepSolver` (its ``stats()``).
    """

    scheme = "newmark"

    def __init__(self, system: LagrangianSystem, dt: float, *, rayleigh=(0.0, 0.0),
                 input_forms=(), solver: str = "auto", near_nullspace=None,
                 prefix: str | None = None, petsc_options: dict | None = None):
        if not isinstance(system, LagrangianSystem):
            raise InputError(f"system must be a LagrangianSystem, got {type(system).__name__}")
        comm = system.V.mesh.comm

        def local():
            if not system.is_quadratic:
                raise InputError("Newmark here is for linear systems (a quadratic Lagrangian)")
            name = linsolve.check_solver(solver)
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
            linsolve.check_petsc_options(petsc_options)
            return step, a, b, name

        dt, alpha, beta, solver = check(comm, "NewmarkIntegrator", local)
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
        t0 = time.perf_counter()
        M = fpetsc.assemble_matrix(fem.form(system.mass_form), bcs=bcs)
        M.assemble()
        K = fpetsc.assemble_matrix(fem.form(system.stiffness_form), bcs=bcs, diag=0.0)
        K.assemble()
        # A = M + dt/2 (alpha M + beta K) + dt^2/4 K (PETSc finds out that M and K share
        # their sparsity - the same space and cells - and adds them entry by entry)
        m, kappa = 1.0 + 0.5 * self.dt * alpha, 0.5 * self.dt * beta + 0.25 * self.dt**2
        A = M.copy()
        A.scale(m)
        A.axpy(kappa, K, structure=_UNKNOWN_PATTERN)
        self.M, self.K, self.A = M, K, A
        self.rayleigh = (alpha, beta)
        self._C = None
        self.timings = {"assemble_seconds": time.perf_counter() - t0}
        self.solver = linsolve.StepSolver(A, comm, solver, prefix, petsc_options, V=V,
                                          near_nullspace=near_nullspace)
        self._ksp = self.solver.ksp
        self.timings["solver_setup_seconds"] = self.solver.setup_seconds
        if not self.solver.iterative:
            # the factor holds what the solves need: the assembled A (as large as M) gives way
            # to its action m M + kappa K, two products where A is multiplied (at initialize
            # and, for the subspace solvers, at a substitution)
            self.A = linsolve.combination_operator(m, M, kappa, K)
            self.solver.release_matrix(self.A)
            A.destroy()
        self.inputs = []
        for form in input_forms:
            b = fpetsc.assemble_vector(fem.form(form))
            b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
            fpetsc.set_bc(b, bcs)
            self.inputs.append(b)
        self.q, self.v, self.a = (fem.Function(V) for _ in range(3))
        self._qs, self._vs, self._rhs, self._tmp, self._w = (fpetsc.create_vector(V) for _ in range(5))
        # the last three solved accelerations, oldest first (the warm start of the iterative
        # and subspace solvers) and, for the subspace solvers, their images A a (the warm
        # start's residual b - A a_e then costs no product with A)
        self._history = [fpetsc.create_vector(V) for _ in range(3)] if self.solver.uses_guess else []
        n_images = 4 if self.solver.returns_image else 0  # three and the guess's
        self._images = [fpetsc.create_vector(V) for _ in range(n_images)]
        self._n_history = 0
        self.t = 0.0

    @property
    def C(self) -> "PETSc.Mat":
        """The Rayleigh damping matrix alpha M + beta K, assembled on first request (the time
        loop never needs it; destroyed by :meth:`close`)."""
        self._check_open("C")
        if self._C is None:
            alpha, beta = self.rayleigh
            C = self.M.copy()
            C.scale(alpha)
            C.axpy(beta, self.K, structure=_UNKNOWN_PATTERN)
            self._C = C
        return self._C

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
        self._n_history = 0
        if self._history:  # a_0 starts the warm start's history (and A a_0 its images')
            self.a.x.petsc_vec.copy(self._history[2])
            if self._images:
                self.A.mult(self.a.x.petsc_vec, self._images[2])
            self._n_history = 1
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
        # rhs -= C v* + K q* = K (q* + beta v*) + alpha M v*: one product with K, one with M
        alpha, beta = self.rayleigh
        qs.copy(self._w)
        self._w.axpy(beta, vs)
        self.K.mult(self._w, tmp)
        rhs.axpy(-1.0, tmp)
        if alpha:
            self.M.mult(vs, tmp)
            rhs.axpy(-alpha, tmp)
        fpetsc.set_bc(rhs, self._bcs)
        # warm start: a1 = 4/dt^2 (q_e - q*) with q_e = 3 q_k - 3 q_{k-1} + q_{k-2}, which for
        # Newmark states is a_e = a_{k-1} + a_{k-2} - a_k (the average-acceleration update
        # gives q_e - q* = dt^2/4 (a_{k-1} + a_{k-2} - a_k)); its image A a_e is the same
        # combination of the answers' images, so the subspace solvers' acceptance test needs
        # no product with A. Until three accelerations are solved, the previous acceleration
        # (Newmark's own predictor).
        extrapolated = self._n_history == 3
        guess_image = image = None
        if extrapolated:
            a.set(0.0)
            a.maxpy(_EXTRAPOLATION, self._history)
        if self._images:
            image = self._images[0]  # the oldest slot, refilled with this answer's image
            if extrapolated:
                guess_image = self._images[3]
                guess_image.set(0.0)
                guess_image.maxpy(_EXTRAPOLATION, self._images[:3])
        reason = self.solver.solve(rhs, a, extrapolated=extrapolated, guess_image=guess_image,
                                   image=image)
        if reason <= 0:
            raise StepFailed(f"Newmark solve failed at t = {self.t + dt:.6g}: "
                             f"{self.solver.describe_failure(reason)}")
        if self._history:
            fpetsc.set_bc(a, self._bcs)  # the constrained rows exactly (a guess-based answer's)
            a.copy(self._history[0])  # the oldest slot becomes the newest
            self._history.append(self._history.pop(0))
            if self._images:
                self._images[:3] = self._images[1:3] + self._images[:1]
            self._n_history = min(self._n_history + 1, 3)
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
        if self.solver is not None:
            self.solver.close()
        _destroy(self.M, self.K, self._C, self.A, self._qs, self._vs, self._rhs, self._tmp,
                 self._w, *self.inputs, *self._history, *self._images)
        self._ksp = self.solver = self.M = self.K = self._C = self.A = None
        self._qs = self._vs = self._rhs = self._tmp = self._w = None
        self.inputs, self._history, self._images = [], [], []


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
