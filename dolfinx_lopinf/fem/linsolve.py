"""The linear solve of a linear time step: one constant SPD matrix, a new right-hand side per step.

Newmark (average acceleration) solves, at every step,

    A a1 = b,      A = M + dt/2 C + dt^2/4 K,

and the linear midpoint step solves A1 dq = r with -A1 = M/dt + dt/4 K (the Jacobian of the
step residual, negative definite; the sign is flipped so that the matrix is SPD). A never
changes, so there are two kinds of solver (``solver=``, :data:`SOLVERS`):

* ``"direct"``: factor A once (MUMPS Cholesky LDL^T; PETSc's own on one rank without MUMPS);
  every step is one forward and one backward substitution through the factor. Per step this
  reads the factor twice - its size, not n, sets the cost; with nested dissection in 3D it
  grows like n^{4/3} (plus the dense top separator). Once factored, the assembled A is no
  longer needed: :meth:`StepSolver.release_matrix` takes its action instead (the Newmark
  integrator passes m M + kappa K, :func:`combination_operator`, and destroys A).
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
* ``"direct+subspace"`` / ``"direct+blr+subspace"``: the factor, and a
  :class:`RecycledSubspace` of its earlier solutions. A time step's solution is close to the
  span of the earlier ones (the response of a driven structure lives in few directions - the
  reason a ROM works), so each step first takes the Galerkin projection onto that span, x_p
  (the A-norm-closest point of the span; one pass over the directions, no product with A),
  and accepts it when its exact residual ||b - A x_p|| is below :data:`SUBSPACE_RTOL` = 1e-2
  of the residual of the extrapolated warm start - the test an iterative solver started
  there would stop at (below) - or below twice the (median) relative residual of the
  factor's latest answers (a block low-rank factor's residual is set by its dropping threshold:
  a projection that good is as good as a substitution). Otherwise the step is one
  substitution through the factor, and that solution's new direction joins the span (at
  most :data:`SUBSPACE_SIZE` = 64; when full, the half that carried the recent projections
  is kept). A step then costs three passes over the directions instead of two passes over
  the factor. The warm start's residual b - A x_e needs A x_e: a caller that builds its
  guess from earlier answers passes their images (``guess_image``; the solver returns each
  answer's A x, which the projection and the extension have at no extra product) - the
  Newmark integrator does - else it costs one product with A. The first steps after
  :meth:`initialize` (no extrapolation yet) are always the factor's. The answer differs
  from the factor's by the tolerance, not by rounding: on the fishtail the output moved by
  5e-7-8e-7 of its maximum over 1,000-2,000 steps, as much as the exact factor's own output
  moves between 1 and 2 ranks.
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
* ``"auto"``: ``"direct"``, with the subspace from :data:`SUBSPACE_FROM` = 100k global
  unknowns, and block low rank from :data:`BLR_FROM` = 300k (the default; :func:`resolve`
  says why): on every mesh we measured
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
from collections import deque

import numpy as np

from ._dolfinx import PETSc, dolfinx
from ..core._blas import share_cores_among_ranks
from ..errors import InputError

fpetsc = dolfinx.fem.petsc

#: solver names and what they are
SOLVERS = {
    "auto": "chosen at set-up (resolve(): 'direct', with the subspace from SUBSPACE_FROM and "
            "block low rank from BLR_FROM unknowns)",
    "direct": "MUMPS Cholesky factorisation, one forward/backward substitution per step",
    "direct+blr": "MUMPS block low-rank Cholesky (dropping threshold BLR_EPSILON): the same "
                  "substitutions, a 4x faster factorisation on large meshes",
    "direct+subspace": "the MUMPS Cholesky, each step first projected onto the factor's earlier "
                       "solutions (RecycledSubspace); a substitution only when that misses",
    "direct+blr+subspace": "the block low-rank Cholesky with the same projection",
    "cg": "CG + GAMG (same as 'cg+gamg')",
    "cg+gamg": "CG + GAMG smoothed aggregation (rigid-body near-nullspace when given)",
    "cg+pmg": "CG + two-level p-multigrid (Chebyshev-Jacobi smoothing, MUMPS on degree 1)",
    "cg+jacobi": "CG + Jacobi",
    "chebyshev": "Chebyshev iteration + Jacobi (eigenvalue bounds by CG at set-up)",
}
#: the factorisations (the rest are iterative)
FACTORED = ("direct", "direct+blr", "direct+subspace", "direct+blr+subspace")
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


def _positive(value, key: str, *, below: float = np.inf) -> float:
    """``value`` as a float in (0, below), else an InputError naming ``petsc_options[key]``."""
    try:
        out = float(value)
    except (TypeError, ValueError):
        out = float("nan")
    if not (0.0 < out < below):
        raise InputError(f"petsc_options[{key!r}] must be a number in (0, {below:g}), got {value!r}")
    return out


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


#: from this many unknowns (global) ``"auto"`` factors with block low rank (``"+blr"``)
BLR_FROM = 300_000
#: from this many unknowns (global) ``"auto"`` recycles the factor's solutions (``"+subspace"``)
SUBSPACE_FROM = 100_000


def resolve(solver: str, n_global: int | None = None) -> str:
    """The solver ``"auto"`` stands for (others are returned as they are; ``"cg"`` as
    ``"cg+gamg"``). ``"auto"`` is a factorisation: measured on the fishtail from 46k to 795k
    dofs on 1 and 2 ranks, its two substitutions per step cost less than the best iterative
    path (``cg+pmg``, 12 CG iterations per step with the quadratic warm start) at every size;
    the iterative solvers are there for matrices whose factor does not fit in memory (they
    hold A, the preconditioner and a few vectors). With ``n_global`` global unknowns:

    * below :data:`SUBSPACE_FROM`: ``"direct"`` - every step its substitutions, the answer
      exact to rounding;
    * from :data:`SUBSPACE_FROM`: ``"direct+subspace"`` - most steps answered by the projection
      onto the factor's earlier solutions, to the iterative solvers' kind of tolerance (module
      docstring);
    * from :data:`BLR_FROM`: ``"direct+blr+subspace"`` - the block low-rank factor (3-4x
      faster to factor; below it the gain, 22.3 -> 13.4 s at 203k dofs on one rank, was not
      worth a changed result)."""
    name = check_solver(solver)
    if name == "auto":
        if n_global is None or n_global < SUBSPACE_FROM:
            return "direct"
        return "direct+blr+subspace" if n_global >= BLR_FROM else "direct+subspace"
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


#: the subspace solvers accept the projection when its residual is below this fraction of the
#: extrapolated warm start's residual (``ksp_rtol`` in ``petsc_options`` overrides)
SUBSPACE_RTOL = 1e-2
#: the acceptance floors: twice the median relative residual of this many latest substitutions,
#: and the median relative residual of this many latest accepted projections (once there are
#: that many; :meth:`StepSolver.solve`)
FACTOR_RESIDUAL_WINDOW = 16
#: the second floor accepts a projection only if its residual is at most this fraction of the
#: warm start's (those it answered on the fishtail improved on it 15-100x)
FLOOR_GAIN = 0.1
#: at most this many directions (``subspace_size`` in ``petsc_options`` overrides); when full,
#: the half that carries the recent solutions is kept
SUBSPACE_SIZE = 64


class RecycledSubspace:
    """The Galerkin projection of A x = b onto the span of earlier solutions.

    Holds k directions as rows of V (the owned entries; A-orthonormal: V A V^T = I) and
    W = V A. The projection of a new right-hand side is

        y = V b,    x_p = V^T y,    r = b - W^T y = b - A x_p,

    the A-norm-closest point of the span to the solution (one pass over V and W each, two
    small all-reduces). Its residual r is exact, so a caller can accept x_p by a residual
    test and fall back to a true solve otherwise; :meth:`extend` then adds that solution's
    part A-orthogonal to the span (two Gram-Schmidt passes in the A inner product, one product
    with A). When ``capacity`` directions are held, :meth:`extend` first keeps the
    ``capacity // 2`` combinations that carried the recent projections (leading left singular
    vectors of their coefficients, computed on rank 0 and broadcast so that every rank rotates
    its rows alike).
    """

    def __init__(self, A, capacity: int):
        self.A = A
        self.comm = A.getComm().tompi4py()
        n = A.getLocalSize()[0]
        self.capacity = int(capacity)
        self.V = np.empty((self.capacity, n))  # pages are touched only as rows are filled
        self.W = np.empty((self.capacity, n))
        self.k = 0
        # coefficient vectors of the latest projections since the last compression
        self._recent = deque(maxlen=2 * self.capacity)
        self._d = A.createVecRight()
        self._Ad = A.createVecLeft()

    def _allsum(self, local):
        from ._dolfinx import MPI

        out = np.empty_like(local)
        self.comm.Allreduce(np.ascontiguousarray(local), out, op=MPI.SUM)
        return out

    def project(self, b, x, tol: float, image=None) -> tuple[bool, float]:
        """x = x_p when ||b - A x_p|| <= tol (the verdict of every rank, combined), else x is
        left alone; returns (accepted, ||b - A x_p||). ``image`` (a Vec, optional): set to
        A x_p = W^T y when accepted."""
        from ._dolfinx import MPI

        k = self.k
        bl = b.array_r
        y = self._allsum(self.V[:k] @ bl)
        Ax = y @ self.W[:k]
        r = bl - Ax
        rho = float(np.sqrt(self._allsum(np.array([r @ r]))[0]))
        accepted = bool(self.comm.allreduce(bool(rho <= tol), op=MPI.LAND))
        self._recent.append(np.pad(y, (0, self.capacity - k)))
        if accepted:
            x.array_w[:] = y @ self.V[:k]
            if image is not None:
                image.array_w[:] = Ax
        return accepted, rho

    def extend(self, x, b, image=None) -> bool:
        """Add the part of the solution x of A x = b that is A-orthogonal to the span; False
        when there is none (below 1e-10 of x in the A norm). ``image`` (a Vec, optional): set
        to A x = A d + W^T c, d = x - V^T c the added part (no second product with A)."""
        from ._dolfinx import MPI

        k = self.k
        d = np.array(x.array_r)
        c = np.zeros(k)
        for _ in range(2):
            if k:
                ck = self._allsum(self.W[:k] @ d)
                d -= ck @ self.V[:k]
                c += ck
        self._d.array_w[:] = d
        self.A.mult(self._d, self._Ad)
        ad = self._Ad.array_r
        if image is not None:
            image.array_w[:] = ad + c @ self.W[:k] if k else ad
        norm2, xax = self._allsum(np.array([d @ ad, x.array_r @ b.array_r]))
        # every rank must agree (k sizes the all-reduces), as on project's verdict
        if not self.comm.allreduce(bool(norm2 > 1e-20 * abs(xax)), op=MPI.LAND):
            return False
        if k == self.capacity:
            k = self._compress()
        scale = 1.0 / np.sqrt(norm2)
        self.V[k] = d * scale
        self.W[k] = ad * scale
        self.k = k + 1
        return True

    def _compress(self) -> int:
        keep = self.capacity // 2
        U = np.empty((self.capacity, keep))
        if self.comm.rank == 0:
            if self._recent:
                U[:] = np.linalg.svd(np.array(self._recent).T, full_matrices=False)[0][:, :keep]
            else:  # no projection since the last compression: the newest directions
                U[:] = np.eye(self.capacity)[:, -keep:]
        self.comm.Bcast(U, root=0)
        self.V[:keep] = U.T @ self.V
        self.W[:keep] = U.T @ self.W
        self._recent.clear()
        self.k = keep
        return keep

    def close(self) -> None:
        for vec in (self._d, self._Ad):
            vec.destroy()
        self.V = self.W = None


class _Combination:
    """The action of c1 A1 + c2 A2 (a PETSc python-shell context)."""

    def __init__(self, terms):
        self.terms = terms
        self.work = terms[0][1].createVecLeft()

    def mult(self, mat, x, y):
        (c1, A1), (c2, A2) = self.terms
        A1.mult(x, y)
        y.scale(c1)
        A2.mult(x, self.work)
        y.axpy(c2, self.work)

    def destroy(self, mat=None):
        self.work.destroy()


def combination_operator(c1, A1, c2, A2):
    """A matrix-free c1 A1 + c2 A2 (a shell: two products per multiplication, no storage)."""
    ctx = _Combination([(float(c1), A1), (float(c2), A2)])
    op = PETSc.Mat().createPython(A1.getSizes(), ctx, comm=A1.getComm())
    op.setUp()
    return op


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
        share_cores_among_ranks(comm)  # the projections' dense work: a rank's share of the cores
        self.name = resolve(solver, A.getSize()[0])
        self.iterative = self.name not in FACTORED
        self.iterations = 0
        self.total_iterations = 0
        self.iteration_history = []
        self.solves = 0
        self.projected = 0
        #: wall seconds in the solver's own parts of the steps (KSP solves; for the subspace
        #: solvers also the projections and the extensions)
        self.seconds = {"solve": 0.0, "projection": 0.0, "extend": 0.0}
        self._P = None
        self.subspace = None
        #: the relative residuals ||b - A x|| / ||b|| of the subspace solvers' substitutions (a
        #: block low-rank factor's are its dropping threshold's, not rounding's): the largest,
        #: and the latest few, whose median sets the acceptance floor
        self.factor_residual_max = 0.0
        self._factor_residuals = deque(maxlen=FACTOR_RESIDUAL_WINDOW)
        #: ... and of the latest accepted projections, whose median is the second floor
        self._projection_residuals = deque(maxlen=FACTOR_RESIDUAL_WINDOW)
        options = check_petsc_options(petsc_options)
        t0 = time.perf_counter()
        if not self.iterative:
            if self.name.endswith("+subspace"):
                self._rtol = _positive(options.pop("ksp_rtol", SUBSPACE_RTOL), "ksp_rtol", below=1.0)
                size = _positive(options.pop("subspace_size", SUBSPACE_SIZE), "subspace_size")
                if size != int(size) or size < 2:
                    raise InputError(f"petsc_options['subspace_size'] must be a whole number >= 2, "
                                     f"got {size!r}")
                self.subspace = RecycledSubspace(A, int(size))
                self._ref = A.createVecLeft()
                self._image = A.createVecLeft()  # A x of a substitution (its true residual)
            blr = _BLR_OPTIONS if "+blr" in self.name else {}
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

    def solve(self, b, x, *, extrapolated: bool = True, guess_image=None, image=None) -> int:
        """Solve A x = b (x: the warm start for the iterative solvers); return the KSP's
        converged reason (> 0: converged). ``extrapolated``: x is the quadratic extrapolation
        (tolerance :data:`RTOL` or ``ksp_rtol``), else a cruder guess (:data:`RTOL_COLD`, or
        ``ksp_rtol`` when that is smaller).

        The subspace solvers (:attr:`returns_image`) also take ``guess_image`` = A x (the
        guess's image, when the caller knows it: the warm start's residual then costs no
        product with A) and fill ``image`` with A x of the answer (the caller's next guess
        image, when it combines earlier answers); the other solvers ignore both."""
        b_norm = b.norm() if self.subspace is not None else None  # the tests' scale (b is kept)
        if self.iterative:
            rtol = self._rtol if extrapolated else min(self._rtol, RTOL_COLD)
            self.ksp.setTolerances(rtol=rtol, atol=ATOL_REL * b.norm(), divtol=self._dtol,
                                   max_it=self._max_it)
        elif self.subspace is not None and extrapolated:
            # the projection is accepted where an iterative solve warm-started at x would stop
            # (an empty span projects to x_p = 0: a zero right-hand side costs no substitution)
            t0 = time.perf_counter()
            if guess_image is None:
                self.subspace.A.mult(x, self._ref)
            else:
                guess_image.copy(self._ref)
            self._ref.aypx(-1.0, b)
            # a projection as close as the factor's own answers is accepted too (without this
            # floor, steps whose tolerance falls below a block low-rank factor's residual
            # would all be substitutions), and one as close as the median of the latest
            # accepted projections (relative to ||b||): where the warm start is very good -
            # twice per period of a smooth input - the first test asks for 1e-2 of its tiny
            # residual and would reject projections more accurate than most it accepts
            # (most of the fishtail's later substitutions were such: docs, benchmarks) - if
            # the projection still improves on the warm start FLOOR_GAIN-fold (after a run of
            # rough transients the median may be loose: it never takes a worse answer)
            start = self._ref.norm()
            tol = max(self._rtol * start, 2.0 * self.factor_residual * b_norm,
                      min(self.projection_residual * b_norm, FLOOR_GAIN * start),
                      ATOL_REL * b_norm)
            accepted, rho = self.subspace.project(b, x, tol, image)
            self.seconds["projection"] += time.perf_counter() - t0
            if accepted:
                if b_norm > 0:
                    self._projection_residuals.append(rho / b_norm)
                self.iterations = 0
                self.iteration_history.append(0)
                self.solves += 1
                self.projected += 1
                return int(PETSc.KSP.ConvergedReason.CONVERGED_RTOL)
        t0 = time.perf_counter()
        self.ksp.solve(b, x)
        self.seconds["solve"] += time.perf_counter() - t0
        if self.subspace is not None and self.ksp.getConvergedReason() > 0:
            t0 = time.perf_counter()
            image = self._image if image is None else image
            self.subspace.extend(x, b, image)
            image.copy(self._ref)
            self._ref.aypx(-1.0, b)  # b - A x
            if b_norm > 0:
                rel = self._ref.norm() / b_norm
                self.factor_residual_max = max(self.factor_residual_max, rel)
                self._factor_residuals.append(rel)
            self.seconds["extend"] += time.perf_counter() - t0
        self.iterations = self.ksp.getIterationNumber()
        self.iteration_history.append(self.iterations)
        self.total_iterations += self.iterations
        self.solves += 1
        return self.ksp.getConvergedReason()

    def release_matrix(self, operator) -> None:
        """Hand the factored solvers an operator with A's action in place of the assembled A
        (e.g. :func:`combination_operator` of M and K), so that the caller can destroy A: the
        factor keeps what the substitutions need, A itself is only multiplied by (the
        subspace's extension). Memory: one matrix the size of M less (386 MB per rank of
        the 795k-dof fishtail on 2 ranks). The factor is kept (never refactored)."""
        if self.iterative:
            raise InputError(f"release_matrix: the iterative solver {self.name!r} multiplies by "
                             "the assembled matrix at every iteration")
        self.ksp.getPC().setReusePreconditioner(True)
        self.ksp.setOperators(operator)
        if self.subspace is not None:
            self.subspace.A = operator

    def describe_failure(self, reason: int) -> str:
        """What to say when a solve did not converge."""
        if not self.iterative:
            return f"direct solve: KSP reason {reason}"
        return (f"{self.name}: KSP reason {reason} after {self.iterations} iterations (tolerance "
                f"{self._rtol:g} relative to the warm start's residual); use solver='direct' or "
                "raise ksp_max_it in petsc_options")

    @property
    def factor_residual(self) -> float:
        """The median relative residual of the factor's latest answers (0 before any): a
        projection within twice it is accepted (a median, so that one odd right-hand side does
        not loosen the test for the whole run)."""
        return float(np.median(self._factor_residuals)) if self._factor_residuals else 0.0

    @property
    def projection_residual(self) -> float:
        """The median relative residual ||b - A x_p|| / ||b|| of the latest accepted
        projections, once FACTOR_RESIDUAL_WINDOW of them are known (0 before: the first steps
        fill the span, and their projections are poor): a projection within it is accepted."""
        recent = self._projection_residuals
        return float(np.median(recent)) if len(recent) == recent.maxlen else 0.0

    @property
    def returns_image(self) -> bool:
        """Whether :meth:`solve` fills ``image`` with A x and reads ``guess_image``."""
        return self.subspace is not None

    @property
    def uses_guess(self) -> bool:
        """Whether :meth:`solve` reads x as a guess (the caller should extrapolate it)."""
        return self.iterative or self.subspace is not None

    def stats(self) -> dict:
        """Solver, set-up seconds, solves, iterations (mean per solve) and, for the subspace
        solvers, the solves the projection answered and the directions held."""
        out = {"solver": self.name, "setup_seconds": self.setup_seconds, "solves": self.solves,
               "iterations_per_solve": (self.total_iterations / self.solves) if self.solves else 0.0}
        if self.subspace is not None:
            out.update(projected_solves=self.projected, subspace_directions=self.subspace.k,
                       factor_residual=self.factor_residual,
                       projection_residual=self.projection_residual,
                       factor_residual_max=self.factor_residual_max)
        out.update({f"{key}_seconds": value for key, value in self.seconds.items()})
        return out

    def close(self) -> None:
        for obj in (self.ksp, self._P, getattr(self, "_ref", None), getattr(self, "_image", None)):
            if obj is not None:
                obj.destroy()
        if self.subspace is not None:
            self.subspace.close()
        self.ksp = self._P = self._ref = self._image = self.subspace = None


def extrapolate(history, out):
    """``out`` = 3 q_k - 3 q_{k-1} + q_{k-2} from ``history`` = [q_{k-2}, q_{k-1}, q_k] (PETSc
    Vecs): the quadratic extrapolation to t_{k+1}, off by dt^3 d^3q/dt^3 + O(dt^4)."""
    out.set(0.0)
    out.maxpy(np.array([1.0, -3.0, 3.0]), list(history))
    return out
