"""The linear solve of a linear time step: one constant SPD matrix, a new right-hand side per step.

Newmark (average acceleration) solves, at every step,

    A a1 = b,      A = M + dt/2 C + dt^2/4 K,

and the linear midpoint step solves A1 dq = r with -A1 = M/dt + dt/4 K (the Jacobian of the
step residual, negative definite; the sign is flipped so that the matrix is SPD). A never
changes, so there are two kinds of solver (``solver=``, :data:`SOLVERS`):

* ``"direct"``: factor A once (MUMPS Cholesky LDL^T; PETSc's own on one rank without MUMPS);
  every step is one forward and one backward substitution through the factor. Per step this
  reads the factor twice - its size, not n, sets the cost; with nested dissection in 3D it
  grows like n^{4/3} (plus the dense top separator).
* ``"direct+blr"``: the same with MUMPS's block low-rank factorisation
  (``mat_mumps_icntl_35`` = 2, dropping threshold ``mat_mumps_cntl_7`` = :data:`BLR_EPSILON`
  = 1e-10; both can be overridden through ``petsc_options``). The factorisation compresses
  the off-diagonal blocks of the fronts to that threshold: on the fishtail, 2 ranks, 24.9 s
  instead of 68.9 s at 392k dofs and 82 s instead of 353 s at 795k, the steps as fast (0.410
  / 0.896 s against 0.400 / 0.993 s) and the output within 8.6e-8 / 4.0e-6 of the exact
  factor's (30 steps; measured in the changelog, with the 2,000-step run). Coarser is not
  safe: with the UCFS variant (``mat_mumps_icntl_36`` = 1) on the 203k-dof mesh the output
  was 2e-6 off at 1e-10, 23 % off at 1e-8, and at 1e-6 the time loop blew up. Nor does a
  single-precision factor (``pc_precision single``) serve: the fishtail's stiffness contrast
  puts A beyond float32. Neither serves as CG's preconditioner either (2-8 iterations of a
  solve nearly as dear as the exact one; changelog).
* iterative (``"cg"``, ``"cg+gamg"``, ``"cg+pmg"``, ``"cg+jacobi"``, ``"chebyshev"``): a
  Krylov method with a preconditioner of O(n) cost per iteration, **warm-started** from the
  caller's guess (the integrators pass the acceleration, or increment, of the displacement
  extrapolated quadratically from the last three steps, q_e = 3 q_k - 3 q_{k-1} + q_{k-2}:
  on the fishtail 12 CG iterations per step instead of 19.5 from the previous acceleration,
  Newmark's own predictor - the nearly massless hull's accelerations alternate from step to
  step, its displacements do not).
  Cost per step: iterations x (one product with A + one preconditioner application).
  ``"cg"`` is ``"cg+gamg"``; ``"cg+pmg"`` is a two-level p-multigrid (Chebyshev-Jacobi
  smoothing on the space, a MUMPS-factored Galerkin coarse problem on the degree-1 Lagrange
  space of the same mesh; the system's space must be Lagrange of degree >= 2).
* ``"auto"``: ``"direct"``, or ``"direct+blr"`` from :data:`BLR_FROM` = 300k global unknowns
  (the default; :func:`resolve` says why): on every mesh we measured
  (the fishtail, 46k-795k dofs, 1 and 2 ranks) the factorisation won per step, by 3-4x
  against the best iterative path (``"cg+pmg"``), and by far more against GAMG, Jacobi or
  Chebyshev - the fishtail's A is not mass-dominated (dt^2/4 K dominates M by 1e6-1e7 in the
  nearly massless hull and the stiff rod), so its condition number is that of an elasticity
  operator with a 1e6 stiffness contrast.

**Stopping test of the iterative solvers (tied to the truncation error).** The quadratic
extrapolation misses the new displacement by the third difference, q1 - q_e = dt^3 q''' +
O(dt^4); the trapezoidal (average acceleration) rule's local truncation error in q is
dt^3 q''' / 12. So the initial residual of the warm start is ~12 local truncation errors,
and the default relative tolerance :data:`RTOL` = 1e-3 *relative to that initial residual*
(``ksp_converged_use_initial_residual_norm``) leaves a solve error of ~1 % of the local
truncation error (without the extrapolation - the first two steps - :data:`RTOL_COLD`) - invisible beside the scheme's own error (measured on the 46k-dof fishtail,
sine input: output within 3e-5 of MUMPS where dt against dt/2 differ by 1.2e-3). The
absolute floor is 1e-12 ||b|| (a warm start that is already exact stops at once). Override
with ``petsc_options={"ksp_rtol": ...}``.

PETSc options (``petsc_options``) go into the global options database under the solver's
prefix, over the defaults of the chosen solver, and are removed once the solver has read them
(as DOLFINx's ``LinearProblem`` does). ``ksp_type`` and ``pc_type`` values are checked against
PETSc's names (:class:`~dolfinx_lopinf.errors.InputError` otherwise).
"""

from __future__ import annotations

import time

import numpy as np

from ._dolfinx import PETSc, dolfinx
from ..errors import InputError

fpetsc = dolfinx.fem.petsc

#: solver names and what they are
SOLVERS = {
    "auto": "chosen at set-up (resolve(): 'direct', or 'direct+blr' from BLR_FROM unknowns)",
    "direct": "MUMPS Cholesky factorisation, one forward/backward substitution per step",
    "direct+blr": "MUMPS block low-rank Cholesky (dropping threshold BLR_EPSILON): the same "
                  "substitutions, a 4x faster factorisation on large meshes",
    "cg": "CG + GAMG (same as 'cg+gamg')",
    "cg+gamg": "CG + GAMG smoothed aggregation (rigid-body near-nullspace when given)",
    "cg+pmg": "CG + two-level p-multigrid (Chebyshev-Jacobi smoothing, MUMPS on degree 1)",
    "cg+jacobi": "CG + Jacobi",
    "chebyshev": "Chebyshev iteration + Jacobi (eigenvalue bounds by CG at set-up)",
}
#: MUMPS's block low-rank dropping threshold (CNTL(7)) of ``"direct+blr"``
BLR_EPSILON = 1e-10
_BLR_OPTIONS = {"mat_mumps_icntl_35": 2, "mat_mumps_cntl_7": BLR_EPSILON}
#: default tolerance of the iterative solvers, relative to the warm start's initial residual
RTOL = 1e-3
#: tolerance (relative to the initial residual) of a solve without the extrapolated warm start
#: (the first two steps, a black-box step): the guess is then no better than the last step's
RTOL_COLD = 1e-8
#: absolute floor of the iterative solvers' residual, relative to ||b||
ATOL_REL = 1e-12
MAX_IT = 5000

_ITERATIVE_DEFAULTS = {
    "cg+gamg": {"ksp_type": "cg", "pc_type": "gamg",
                # the aggregation graph drops couplings below 2 % (measured: a cold solve on
                # the fishtail took 313 CG iterations against 2149 with the default 0)
                "pc_gamg_threshold": 0.02},
    "cg+pmg": {"ksp_type": "cg", "pc_type": "mg", "pc_mg_galerkin": "both",
               "mg_levels_ksp_type": "chebyshev", "mg_levels_pc_type": "jacobi",
               "mg_levels_ksp_max_it": 2, "mg_coarse_ksp_type": "preonly",
               "mg_coarse_pc_type": "cholesky", "mg_coarse_pc_factor_mat_solver_type": "mumps"},
    "cg+jacobi": {"ksp_type": "cg", "pc_type": "jacobi"},
    # as a solver, not a smoother: the whole spectrum (from half the lowest to 1.5 x the highest
    # eigenvalue 100 CG steps find; PETSc's smoother default 0.1 - 1.1 x the highest diverged
    # to NaN on a stiff bar) and many iterations
    "chebyshev": {"ksp_type": "chebyshev", "pc_type": "jacobi", "ksp_chebyshev_esteig": "0.5,0,0,1.5",
                  "ksp_chebyshev_esteig_steps": 100, "ksp_max_it": 50000,
                  # its residual is not minimised as CG's is: 10x tighter to land at the same
                  # fraction of the truncation error
                  "ksp_rtol": 0.1 * RTOL},
}


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


def _type_names(cls) -> set[str]:
    return {str(getattr(cls, name)) for name in dir(cls) if not name.startswith("_")}


def check_solver(solver) -> str:
    """``solver`` as one of :data:`SOLVERS` (case and surrounding blanks ignored), else an
    :class:`~dolfinx_lopinf.errors.InputError` listing them."""
    name = solver.strip().lower() if isinstance(solver, str) else None
    if name not in SOLVERS:
        raise InputError(f"solver must be one of {', '.join(repr(s) for s in SOLVERS)}, got {solver!r} "
                         "(the preconditioner of 'cg' is chosen by name, e.g. 'cg+pmg'; further "
                         "settings through petsc_options)")
    return name


def check_petsc_options(options) -> dict:
    """The PETSc options as a dict of str -> value; ``ksp_type`` and ``pc_type`` must be PETSc
    names (a misspelt name is an :class:`~dolfinx_lopinf.errors.InputError` here, not a PETSc
    error in the middle of a set-up). Keys are given without the prefix and without '-'."""
    if options is None:
        return {}
    if not isinstance(options, dict):
        raise InputError(f"petsc_options must be a dict of PETSc options, got {type(options).__name__}")
    for key in options:
        if not isinstance(key, str) or not key or key.startswith("-"):
            raise InputError(f"petsc_options keys are option names without the prefix and without "
                             f"'-', e.g. 'ksp_rtol'; got {key!r}")
    for key, cls in (("ksp_type", PETSc.KSP.Type), ("pc_type", PETSc.PC.Type)):
        if key in options and str(options[key]) not in _type_names(cls):
            raise InputError(f"petsc_options[{key!r}] = {options[key]!r} is not a PETSc type; "
                             f"choose from {sorted(_type_names(cls))}")
    return dict(options)


#: from this many unknowns (global) ``"auto"`` is ``"direct+blr"``
BLR_FROM = 300_000


def resolve(solver: str, n_global: int | None = None) -> str:
    """The solver ``"auto"`` stands for (others are returned as they are; ``"cg"`` as
    ``"cg+gamg"``). ``"auto"`` is a factorisation: measured on the fishtail from 46k to 795k
    dofs on 1 and 2 ranks, its two substitutions per step cost less than the best iterative
    path (``cg+pmg``, 12 CG iterations per step with the quadratic warm start) at every size;
    the iterative solvers are there for matrices whose factor does not fit in memory (they
    hold A, the preconditioner and a few vectors). From :data:`BLR_FROM` global unknowns
    (``n_global``) it is the block low-rank one, ``"direct+blr"`` (a 3-4x faster
    factorisation at the same cost per step: the module docstring); below it ``"direct"`` (the
    gain at 203k dofs, one rank: 22.3 -> 13.4 s, was not worth a changed result)."""
    name = check_solver(solver)
    if name == "auto":
        return "direct+blr" if n_global is not None and n_global >= BLR_FROM else "direct"
    return "cg+gamg" if name == "cg" else name


def direct_ksp(A, comm, prefix: str, options: dict | None, *, spd: bool = False):
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


def _p1_interpolation(V):
    """The interpolation matrix from the degree-1 Lagrange space of V's mesh (same value
    shape) into V, or an InputError when V is not Lagrange of degree >= 2."""
    try:
        element = V.element.basix_element
        ok = element.family.name == "P" and element.degree >= 2
    except (AttributeError, RuntimeError):  # mixed / blocked without one basix element
        ok = False
    if not ok:
        raise InputError("solver 'cg+pmg' coarsens a Lagrange space of degree >= 2 to degree 1 "
                         f"on the same mesh; the system's space is {V.ufl_element()}: choose "
                         "'cg+gamg' or 'direct'")
    shape = V.ufl_element().reference_value_shape
    V1 = dolfinx.fem.functionspace(V.mesh, ("Lagrange", 1, shape))
    P = fpetsc.interpolation_matrix(V1, V)
    P.assemble()
    return P


class StepSolver:
    """Solves A x = b for a constant SPD A, one right-hand side per time step.

    Args:
        A: the assembled SPD matrix (kept, not copied; the caller destroys it).
        comm: its communicator.
        solver: a name of :data:`SOLVERS` (checked by :func:`check_solver`).
        prefix: the PETSc options prefix.
        petsc_options: options under the prefix over the solver's defaults (checked by
            :func:`check_petsc_options`).
        V: the function space of x (needed by ``"cg+pmg"``).
        near_nullspace: a PETSc NullSpace for GAMG (e.g. rigid-body modes).

    :meth:`solve` takes x as the initial guess for the iterative solvers (warm start) and
    ignores it for the direct one. ``name`` is the resolved solver, ``setup_seconds`` the
    factorisation / preconditioner set-up time, ``iterations`` the count of the last solve,
    ``iteration_history`` every solve's and ``total_iterations`` their sum.
    """

    def __init__(self, A, comm, solver: str, prefix: str, petsc_options: dict | None = None, *,
                 V=None, near_nullspace=None):
        self.name = resolve(solver, A.getSize()[0])
        self.iterative = self.name not in ("direct", "direct+blr")
        self.iterations = 0
        self.total_iterations = 0
        self.iteration_history = []
        self.solves = 0
        self._P = None
        options = check_petsc_options(petsc_options)
        t0 = time.perf_counter()
        if not self.iterative:
            blr = _BLR_OPTIONS if self.name == "direct+blr" else {}
            self.ksp = direct_ksp(A, comm, prefix, {**blr, **options}, spd=True)
        else:
            self.ksp = self._iterative(A, comm, prefix, options, V, near_nullspace)
        self.setup_seconds = time.perf_counter() - t0

    def _iterative(self, A, comm, prefix, options, V, near_nullspace):
        A.setOption(PETSc.Mat.Option.SPD, True)
        if self.name == "cg+gamg" and near_nullspace is not None:
            A.setNearNullSpace(near_nullspace)
        ksp = PETSc.KSP().create(comm)
        ksp.setOperators(A)
        ksp.setOptionsPrefix(prefix)
        ksp.setType("cg")
        ksp.setTolerances(rtol=RTOL, atol=0.0, max_it=MAX_IT)
        if self.name == "cg+pmg":
            if V is None:
                raise InputError("solver 'cg+pmg' needs the function space (V=...)")
            self._P = _p1_interpolation(V)
            pc = ksp.getPC()
            pc.setType("mg")
            pc.setMGLevels(2)
            pc.setMGInterpolation(1, self._P)
        defaults = {**_ITERATIVE_DEFAULTS[self.name], "ksp_converged_use_initial_residual_norm": True,
                    "ksp_initial_guess_nonzero": True}
        keys = _push_options(prefix, {**defaults, **options})
        try:
            ksp.setFromOptions()
            ksp.setUp()  # GAMG / MG read their level options here: before they are removed
        finally:
            _pop_options(keys)
        self._rtol, _, self._dtol, self._max_it = ksp.getTolerances()
        return ksp

    def solve(self, b, x, *, extrapolated: bool = True) -> int:
        """Solve A x = b (x: the warm start for the iterative solvers); return the KSP's
        converged reason (> 0: converged). ``extrapolated``: x is the quadratic extrapolation
        (tolerance :data:`RTOL` or ``ksp_rtol``), else a cruder guess (:data:`RTOL_COLD`, or
        ``ksp_rtol`` when that is smaller)."""
        if self.iterative:
            rtol = self._rtol if extrapolated else min(self._rtol, RTOL_COLD)
            self.ksp.setTolerances(rtol=rtol, atol=ATOL_REL * b.norm(), divtol=self._dtol,
                                   max_it=self._max_it)
        self.ksp.solve(b, x)
        self.iterations = self.ksp.getIterationNumber()
        self.iteration_history.append(self.iterations)
        self.total_iterations += self.iterations
        self.solves += 1
        return self.ksp.getConvergedReason()

    def describe_failure(self, reason: int) -> str:
        """What to say when a solve did not converge."""
        if not self.iterative:
            return f"direct solve: KSP reason {reason}"
        return (f"{self.name}: KSP reason {reason} after {self.iterations} iterations (tolerance "
                f"{self._rtol:g} relative to the warm start's residual); use solver='direct' or "
                "raise ksp_max_it in petsc_options")

    def stats(self) -> dict:
        """Solver, set-up seconds, solves and iterations (mean per solve)."""
        return {"solver": self.name, "setup_seconds": self.setup_seconds, "solves": self.solves,
                "iterations_per_solve": (self.total_iterations / self.solves) if self.solves else 0.0}

    def close(self) -> None:
        for obj in (self.ksp, self._P):
            if obj is not None:
                obj.destroy()
        self.ksp = self._P = None


def extrapolate(history, out):
    """``out`` = 3 q_k - 3 q_{k-1} + q_{k-2} from ``history`` = [q_{k-2}, q_{k-1}, q_k] (PETSc
    Vecs): the quadratic extrapolation to t_{k+1}, off by dt^3 d^3q/dt^3 + O(dt^4)."""
    out.set(0.0)
    out.maxpy(np.array([1.0, -3.0, 3.0]), list(history))
    return out
