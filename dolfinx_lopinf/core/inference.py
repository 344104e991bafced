"""Lagrangian operator inference (L-OpInf) and the standard OpInf baseline (METHOD.md s. 4).

Mechanical ROM with reduced mass fixed to I:

    qh_tt + Ch qh_t + Kh qh = Bh u,        y = Eh qh.

L-OpInf solves the constrained least-squares problem

    min  || ddQh + Kh Qh + Ch dQh - Bh U ||_F
    s.t. Kh = Kh^T, Ch = Ch^T, Kh >= eps I, Ch >= eps I   (matrix inequalities),

so the learned ROM is the Euler-Lagrange equation of ``L_h = 1/2 |qh_t|^2 - 1/2 qh^T Kh qh``
(with Rayleigh-like dissipation Ch and input Bh u) by construction.

Compression: write Theta = [Kh, Ch, -Bh] (r, p) and D = [Qh; dQh; U] (p, K). Then

    ||ddQh + Theta D||_F^2 = ||Theta L + Z||_F^2 + ||ddQh||_F^2 - ||Z||_F^2,
    G = D D^T = L L^T,  Z = ddQh D^T L^{-T}  (r, p)   (L from a thin QR of D^T),

so after one pass over the data (cost O(K p^2)) the problem no longer depends on K.
Solvers (:mod:`dolfinx_lopinf.core.lsq`: a :class:`~dolfinx_lopinf.core.lsq.Problem` and strategy
objects). Without damping and inputs, the symmetric-only problem has the closed-form
Lyapunov solution G K + K G = -(X + X^T), X = ddQh Qh^T; if that minimiser already satisfies
K >= eps I it *is* the L-OpInf solution (KKT holds with zero multiplier). Otherwise ADMM in
the eigenbasis of G (K alone) or, for damped fits, a primal-dual interior point method with
a certified duality gap (:class:`~dolfinx_lopinf.core.lsq.Auto`). ``solver="cvxpy"`` (Clarabel on
the compressed problem) is the reference.

Nonlinear-wave ROM (gray box):  qh_tt = Kh qh - Fh,  Fh = V^T f_nl(V qh), Kh = Kh^T:

    min ||ddQh + Fh - Kh Qh||_F   ->   G K + K G = T Qh^T + Qh T^T,  T = ddQh + Fh.

Standard (second-order) OpInf drops every constraint: Theta = -ddQh D^+ by least squares.
"""

from __future__ import annotations

import functools
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from . import lsq
from ._checks import check_matrix
from ..errors import (
    IllConditionedDataWarning,
    InputError,
    RankDeficientDataError,
    SolverFailedError,
    SolverWarning,
    warn,
)
from .lsq.linalg import from_eig, sym


@functools.lru_cache(maxsize=1)
def _blas_controller():
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def _serial_blas(fn):
    """Run ``fn`` with one BLAS thread. Its kernels are small (p, 2 r (r + 1) / 2 <= a few
    hundred) and OpenBLAS threads cost more than they give there: with 2 threads the forced
    r = 20 fit took 180 ms instead of 22 ms on our 2-core machine. The caller's setting is
    restored on return."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with _blas_controller().limit(limits=1, user_api="blas"):
            return fn(*args, **kwargs)
    return wrapper


@dataclass(frozen=True)
class MechanicalOperators:
    """Inferred reduced operators of qh_tt + C qh_t + K qh = B u (None where not fitted).

    Attributes:
        K: (r, r) stiffness.  C: (r, r) damping or None.  B: (r, m) input or None.
        M: (r, r) learned reduced mass (``mass="learned"``), None when it is fixed to I.
        certificate: how the solve went, a dict: ``solver``, ``certified`` (the duality gap
            met its tolerance, 1e-8 by default, and the operators are feasible),
            ``duality_gap`` (relative), ``iterations``, ``seconds``, ``status``, ``objective`` (the
            squared residual norm ||ddQh + K Qh + C dQh - B U||_F^2), ``relative_residual``,
            ``min_eig_K``/``min_eig_C``, ``symmetry_error``, ``seconds``, and the fields of
            the solver's :class:`~dolfinx_lopinf.core.lsq.Certificate` (``iterations``,
            ``duality_gap``, KKT residuals, ...; :meth:`~dolfinx_lopinf.core.lsq.Certificate.as_dict`).
    """

    K: np.ndarray
    C: np.ndarray | None = None
    B: np.ndarray | None = None
    certificate: dict = field(default_factory=dict)
    M: np.ndarray | None = None


#: The relative duality gap below which a fit is ``certified`` (the engine's default).
GAP_TOL = 1e-8
#: Relative Tikhonov parameter of every fit (see :func:`gram_data`): directions of the
#: row-normalised data whose singular value is below ``RIDGE`` times the largest are not
#: determined by double-precision data; the ridge decides them (towards zero) instead of
#: rounding.
RIDGE = 1e-9
#: Singular values below ``RANK_RTOL`` times the largest count as "not determined by the
#: data" in the warning (and the error with ``strict=True``). Five decades above rounding
#: (~1e-16), so a different BLAS cannot move a well-determined problem across it.
RANK_RTOL = 1e-10


@dataclass(frozen=True)
class GramData:
    """The data of the least-squares problem after one pass over K snapshots.

    The problem is the ridge-regularised least squares

        min  ||Theta D + ddQh||_F^2 + gamma^2 ||Theta diag(s)||_F^2,    gamma = ridge * sigma_1,

    with s the row norms of D = [Qh; dQh; U] and sigma_1 the largest singular value of the
    row-normalised data diag(1/s) D. Its normal matrix is G = D D^T + gamma^2 diag(s)^2 = L L^T.

    Attributes:
        L: (p, p) lower-triangular factor of G.
        Z: (r, p) such that the objective is ||Theta L + Z||_F^2 + target_norm2 - ||Z||_F^2.
        target_norm2: ||ddQh||_F^2.
        r, m: reduced and input dimensions; ``has_damping`` tells whether dQh is in D.
        condition: condition number of the row-normalised data matrix (before the ridge).
        rank: number of its singular values above ``RANK_RTOL`` times the largest.
        ridge_weights: (p,) gamma * s, so the ridge term is ||Theta * ridge_weights||_F^2.
    """

    L: np.ndarray
    Z: np.ndarray
    target_norm2: float
    r: int
    m: int
    has_damping: bool
    condition: float = float("nan")
    rank: int = -1
    ridge_weights: np.ndarray | None = None

    def objective(self, theta: np.ndarray) -> float:
        """The objective the solvers minimise: ||Theta D + ddQh||_F^2 + the ridge term."""
        return float(lsq.residual_norm2(theta, self.L, self.Z) + self.target_norm2 - np.sum(self.Z**2))

    def data_objective(self, theta: np.ndarray) -> float:
        """||Theta D + ddQh||_F^2, the misfit without the ridge term."""
        ridge = 0.0 if self.ridge_weights is None else np.sum((theta * self.ridge_weights) ** 2)
        return self.objective(theta) - float(ridge)


def _data_matrix(Qh, dQh, ddQh, U, damping):
    Qh = check_matrix(Qh, "Qh")
    r, K = Qh.shape
    ddQh = check_matrix(ddQh, "ddQh", rows=r, cols=K)
    rows = [Qh]
    if damping:
        if dQh is None:
            raise InputError("damping=True needs the first derivatives dQh")
        rows.append(check_matrix(dQh, "dQh", rows=r, cols=K))
    m = 0
    if U is not None:
        U = check_matrix(np.atleast_2d(U), "U", cols=K)
        m = U.shape[0]
        rows.append(U)
    p = sum(block.shape[0] for block in rows)
    if K < p:
        raise InputError(
            f"{K} snapshots cannot determine {p} unknowns per row; record more "
            "time samples or lower r"
        )
    return rows, ddQh, r, m


def _row_norms(A: np.ndarray) -> np.ndarray:
    """Euclidean row norms without overflow or underflow (data scaled by 1e+-160 included)."""
    big = np.abs(A).max(axis=1)
    safe = np.where(big > 0, big, 1.0)
    return big * np.linalg.norm(A / safe[:, None], axis=1)


def _block_names(r, m, damping):
    names = [f"Qh[{i}]" for i in range(r)]
    names += [f"dQh[{i}]" for i in range(r)] if damping else []
    return names + [f"U[{i}]" for i in range(m)]


def gram_data(Qh, dQh, ddQh, U=None, *, damping=True, ridge: float = RIDGE,
              strict: bool = False) -> GramData:
    """Form the compressed, ridge-regularised least-squares data (one pass over the snapshots).

    Rank and conditioning. POD coordinates span many decades and the paper's block basis makes
    [Qh; dQh] nearly singular (theta ~ w'), so whether the smallest singular value of the data
    lies just above or just below a rank threshold is decided by rounding (the BLAS, the
    thread count, the MPI layout). No result may hinge on that. Hence:

    * the fit always carries the ridge gamma^2 ||Theta diag(s)||^2 with gamma = ``ridge`` *
      sigma_1 (row-normalised data): it changes directions with singular value
      sigma >> gamma by a relative (gamma / sigma)^2 (<= 1e-8 for sigma >= 1e-5 sigma_1 at the
      default 1e-9) and decides the directions the data do not see (sigma <~ gamma) towards
      zero - a unique, stable answer that depends continuously on the data;
    * directions with sigma < ``RANK_RTOL`` sigma_1 are reported: one
      :class:`~dolfinx_lopinf.errors.IllConditionedDataWarning` naming the rank, the condition
      number and what was done; ``strict=True`` raises
      :class:`~dolfinx_lopinf.errors.RankDeficientDataError` instead.

    ``ridge=0`` gives the plain least squares (it fails on singular data).
    """
    if not (np.isfinite(ridge) and 0 <= ridge < 1):
        raise InputError(f"ridge must be a number in [0, 1), got {ridge!r}")
    rows, ddQh, r, m = _data_matrix(Qh, dQh, ddQh, U, damping)
    if not np.any(ddQh):
        raise InputError(
            "the target (ddQh, the second derivatives, plus Fh for waves) is identically zero: "
            "static or empty snapshots carry no dynamics to fit; record a trajectory that moves")
    L, Z, cond, rank, weights = _compress(rows, ddQh, _block_names(r, m, damping), ridge, strict,
                                          "[Qh; dQh; U]")
    return GramData(L, Z, float(np.sum(ddQh**2)), r, m, damping, cond, rank, weights)


def _compress(rows, target, names, ridge, strict, what):
    """(L, Z, condition, rank, ridge weights) of min ||Theta D + target||^2 + gamma^2
    ||Theta diag(s)||^2 with D = vstack(rows); see :func:`gram_data`."""
    scale = np.concatenate([_row_norms(block) for block in rows])
    if np.any(scale == 0):
        zero = [names[i] for i in np.flatnonzero(scale == 0)]
        raise RankDeficientDataError(
            f"data rows {zero} of {what} are identically zero, so the operator entries "
            "that multiply them are not determined by the data; lower r to the rank of the "
            "snapshots (a zero POD coordinate means r exceeds it) or drop the zero input")
    # Row-normalised data Dn = diag(1/s) D (p x K). One Householder QR of the augmented tall
    # matrix [Dn^T, target^T] (K x (p + r)), Q never formed: its leading p x p block is R
    # (Dn^T = Qf R) and the block beside it is Qf^T target^T = Z^T. Then D D^T = L L^T with
    # L = diag(s) R^T - exact for any conditioning (the condition number is never squared;
    # POD coordinates span many decades), one LAPACK call on one Fortran-ordered copy of the
    # data, O(K (p + r)^2). The ridge appends rows gamma I to Dn^T (0 to target^T): one more
    # QR of a (2p) x (p + r) matrix.
    p, r, K = len(scale), target.shape[0], target.shape[1]
    A = np.empty((K, p + r), order="F")
    start = 0
    for block in rows:
        A[:, start:start + block.shape[0]] = block.T / scale[start:start + block.shape[0]]
        start += block.shape[0]
    A[:, p:] = target.T
    R_aug = scipy.linalg.qr(A, mode="r", overwrite_a=True, check_finite=False)[0][:p]
    sv = np.linalg.svd(R_aug[:, :p], compute_uv=False)
    cond = float(sv[0] / max(sv[-1], np.finfo(float).tiny))
    rank = int((sv > RANK_RTOL * sv[0]).sum())
    gamma = ridge * sv[0]
    if gamma > 0:
        R_aug = scipy.linalg.qr(np.vstack([R_aug, np.hstack([gamma * np.eye(p), np.zeros((p, r))])]),
                                mode="r", check_finite=False)[0][:p]
    if rank < p:
        msg = (f"the data matrix {what} ({p} rows, row-normalised) has numerical rank "
               f"{rank} < {p} at relative tolerance {RANK_RTOL:g} (condition number {cond:.3g}):"
               " some operator directions are not determined by the data")
        if strict:
            raise RankDeficientDataError(msg + "; lower r, record a richer trajectory or drop a "
                                         "block (or call without strict=True to regularise)")
        warn(msg + f"; they were fixed by the ridge {ridge:g} * sigma_1 (Tikhonov, towards zero)"
             " with the constraints kept. Pass strict=True to raise instead, or lower r for a fit "
             "the data determine alone.", IllConditionedDataWarning)
    L = scale[:, None] * R_aug[:, :p].T
    return L, R_aug[:, p:].T, cond, rank, (gamma * scale if gamma > 0 else None)


def _split_theta(theta, r, m, has_damping):
    K = theta[:, :r]
    C = theta[:, r : 2 * r] if has_damping else None
    B = -theta[:, theta.shape[1] - m :] if m else None
    return K, C, B


def _certificate(gram, K, C, B, solver, status, seconds, eps):
    theta = np.hstack([K] + ([C] if C is not None else []) + ([-B] if B is not None else []))
    obj = max(gram.objective(theta), 0.0)
    misfit = max(gram.data_objective(theta), 0.0)
    cert = {
        "solver": solver,
        "status": status,
        "objective": obj,
        "data_misfit": misfit,
        "relative_residual": float(np.sqrt(misfit / gram.target_norm2)),
        "data_rank": gram.rank,
        "data_rows": int(gram.L.shape[0]),
        "symmetry_error": float(np.abs(K - K.T).max() / max(np.abs(K).max(), 1e-300)),
        "min_eig_K": float(np.linalg.eigvalsh(0.5 * (K + K.T)).min()),
        "seconds": seconds,
        "eps": eps,
        "data_condition": gram.condition,
    }
    if C is not None:
        cert["min_eig_C"] = float(np.linalg.eigvalsh(0.5 * (C + C.T)).min())
    return cert


#: The names ``solver=`` of :func:`infer_mechanical` accepts.
SOLVERS = ("auto", "lyapunov", "admm", "cvxpy")


def _check_solver(solver):
    if isinstance(solver, str):
        if solver not in SOLVERS:
            raise InputError(f"unknown solver {solver!r}; choose one of "
                             f"{', '.join(repr(s) for s in SOLVERS)}, or pass a strategy object "
                             "with a solve(problem) method (e.g. dolfinx_lopinf.core.lsq.PSDBlocks())")
    elif not callable(getattr(solver, "solve", None)):
        raise InputError(f"solver must be one of {', '.join(repr(s) for s in SOLVERS)} or an "
                         f"object with a solve(problem) method, not a {type(solver).__name__}")


@_serial_blas
def infer_mechanical(Qh, dQh, ddQh, U=None, *, eps: float = 1e-8, damping: bool = True,
                     solver: str | lsq.Strategy = "auto", ridge: float = RIDGE,
                     strict: bool = False, mass: str = "identity") -> MechanicalOperators:
    """L-OpInf for Mh qh_tt + Ch qh_t + Kh qh = Bh u with Kh, Ch symmetric, >= eps I and
    Mh = I (``mass="identity"``) or learned too (``mass="learned"``, :mod:`dolfinx_lopinf.core.mass`).

    Args:
        Qh, dQh, ddQh: (r, K) reduced states and their first/second time derivatives on
            the same grid (see :func:`dolfinx_lopinf.core.ddt.derivatives`). ``dQh`` may be None
            when ``damping=False``.
        U: (m, K) inputs, or None for an unforced system.
        eps: lower bound on the eigenvalues of Kh (and Ch).
        damping: fit Ch too; ``False`` gives the conservative form (Kh, and Bh with inputs).
        solver: ``"auto"`` (:class:`~dolfinx_lopinf.core.lsq.Auto`); ``"lyapunov"`` (the
            symmetric minimiser, unconstrained: the conservative unforced fit only);
            ``"admm"`` (the ADMM strategies without the interior point, a comparison
            path); ``"cvxpy"`` (Clarabel on the compressed problem, the reference); or a
            strategy object whose ``solve(problem)`` returns ``(Theta, Certificate)`` for
            a :class:`~dolfinx_lopinf.core.lsq.Problem` (e.g. ``lsq.PSDBlocks(gap_tol=1e-10)``).
        ridge: relative Tikhonov parameter that decides the directions the data do not
            determine (see :func:`gram_data`); 0 turns it off.
        strict: raise :class:`~dolfinx_lopinf.errors.RankDeficientDataError` when the data
            do not determine every operator entry, instead of warning and regularising, and
            :class:`~dolfinx_lopinf.errors.SolverFailedError` when the fit is not certified
            (duality gap above its tolerance) instead of returning it with a warning.
        mass: ``"identity"`` (Mh = I: right in a mass-orthonormal basis) or ``"learned"``
            (Mh symmetric positive definite, fitted with the others by a convex problem
            whose answer does not depend on the coordinates of the reduced space - use it
            in a Euclidean, black-box basis).

    Returns:
        :class:`MechanicalOperators` with a certificate; warns if the solver did not reach
        optimality.

    Example:
        >>> t = np.linspace(0, 10, 2001); w = np.array([[1.0], [2.0]])
        >>> Q = np.vstack([np.cos(t), 0.5 * np.sin(2 * t)])
        >>> from dolfinx_lopinf.core.ddt import derivatives
        >>> ops = infer_mechanical(*derivatives(Q, t), damping=False)
        >>> bool(np.allclose(ops.K, np.diag([1.0, 4.0]), atol=1e-5))
        True
    """
    _check_solver(solver)
    if not (np.isfinite(eps) and eps >= 0):
        raise InputError(f"eps must be a finite number >= 0, got {eps}")
    if mass not in ("identity", "learned"):
        raise InputError(f"mass must be 'identity' or 'learned', got {mass!r}")
    (Qh, dQh, ddQh, U), c_state, c_input = _unit_scaled(Qh, dQh, ddQh, U)
    if mass == "learned":
        from .mass import infer_with_mass

        ops = infer_with_mass(Qh, dQh if damping else None, ddQh, U, damping=damping, eps=eps,
                              ridge=ridge, strict=strict, solver=solver)
        return _unscaled(ops, c_state, c_input)
    gram = gram_data(Qh, dQh, ddQh, U, damping=damping, ridge=ridge, strict=strict)
    conservative = not gram.has_damping and gram.m == 0
    named = solver if isinstance(solver, str) else None
    if named == "lyapunov" and not conservative:
        raise InputError("solver='lyapunov' handles the conservative, unforced fit only "
                         "(damping=False, U=None); use 'auto', 'admm' or 'cvxpy'")
    if named == "cvxpy":
        ops = _solve_cvxpy(gram, eps)
    elif conservative and named in ("auto", "lyapunov"):
        ops = _solve_lyapunov(gram, eps)
        if named != "lyapunov" and ops.certificate["min_eig_K"] < eps:
            ops = _solve_constrained(gram, eps, lsq.Auto())
    else:
        ops = _solve_constrained(gram, eps, lsq.Auto(named) if named else solver)
    if strict and not ops.certificate.get("certified", False) and named != "lyapunov":
        c = ops.certificate
        raise SolverFailedError(f"the fit is not certified ({c['solver']}: duality gap "
                                f"{c.get('duality_gap', float('nan')):.2e}, status {c['status']}); "
                                "strict=True asks for an error instead of an uncertified model")
    return _unscaled(ops, c_state, c_input)


def _pow2_scale(*arrays) -> float:
    """The power of two nearest to max |entries| (1 for all-zero data): dividing by it is exact."""
    big = max((float(np.abs(a).max()) for a in arrays if a is not None and a.size), default=0.0)
    return 1.0 if big == 0 or not np.isfinite(big) else float(2.0 ** np.round(np.log2(big)))


def _unit_scaled(Qh, dQh, ddQh, U):
    """Take the state and input units out of the data, exactly (powers of two), so that data
    in any units - 1e160 or 1e-170 included - neither overflow nor underflow. K and C are
    invariant under a common scaling of Qh, dQh and ddQh; B scales by c_state / c_input."""
    arrays = [None if a is None else check_matrix(a, name)
              for a, name in ((Qh, "Qh"), (dQh, "dQh"), (ddQh, "ddQh"))]
    U = None if U is None else check_matrix(np.atleast_2d(U), "U")
    c_state = _pow2_scale(*arrays)
    c_input = _pow2_scale(U)
    arrays = [None if a is None else np.asarray(a) / c_state for a in arrays]
    return (*arrays, None if U is None else U / c_input), c_state, c_input


def _unscaled(ops: MechanicalOperators, c_state: float, c_input: float) -> MechanicalOperators:
    if c_state == 1.0 and c_input == 1.0:
        return ops
    cert = dict(ops.certificate)
    with np.errstate(over="ignore"):  # the squared misfit in user units may pass 1e308
        for key in ("objective", "data_misfit"):
            if key in cert:
                cert[key] = float(np.float64(cert[key]) * c_state * c_state)
    B = None if ops.B is None else ops.B * (c_state / c_input)
    return MechanicalOperators(ops.K, ops.C, B, cert, M=ops.M)


def _solve_lyapunov(gram: GramData, eps: float) -> MechanicalOperators:
    """Symmetric least-squares minimiser: G K + K G = -(X + X^T), via the SVD of L."""
    t0 = time.perf_counter()
    K = lsq.solve_symmetric(gram.L, gram.Z)
    seconds = time.perf_counter() - t0
    cert = _certificate(gram, K, None, None, "lyapunov", "optimal", seconds, eps)
    cert.update(lsq.kkt(gram.L, gram.Z, K, [], eps))  # unconstrained: stationarity only
    G = gram.L @ gram.L.T
    X = gram.Z @ gram.L.T
    grad = K @ G + G @ K + X + X.T
    cert["stationarity"] = float(np.linalg.norm(grad) / max(np.linalg.norm(2 * X), 1e-300))
    feasible = cert["min_eig_K"] >= eps
    if not feasible:
        cert["status"] = "infeasible: the symmetric minimiser has min eigenvalue < eps"
    # the unconstrained symmetric minimiser, exact: optimal (gap 0) when it is feasible
    cert.update(duality_gap=0.0 if feasible else float("inf"), certified=bool(feasible), iterations=0)
    return MechanicalOperators(K, None, None, cert)


def _floor(A: np.ndarray, eps: float) -> np.ndarray:
    """Symmetrise and make the computed eigenvalues >= eps despite rounding: eigenvalues are
    only known to ~1e-16 ||A||, so clip at eps + 64 u ||A||_2 when any falls below eps. ``A``:
    one matrix or a stack (each block floored on its own; one batched ``eigh``)."""
    A = sym(A)
    w, Q = np.linalg.eigh(A)
    floor = eps + 64 * np.finfo(float).eps * np.abs(w).max(axis=-1, keepdims=True)
    low = (w < floor).any(axis=-1)
    if not low.any():
        return A
    return np.where(low[..., None, None], sym(from_eig(np.maximum(w, floor), Q)), A)


def _solve_constrained(gram: GramData, eps: float, strategy) -> MechanicalOperators:
    """PSD-constrained fit by ``strategy`` (:mod:`dolfinx_lopinf.core.lsq`) on the compressed
    problem; K and C floored at eps against rounding, the certificate a dict: the solver's
    :class:`~dolfinx_lopinf.core.lsq.Certificate` fields, the fit's and the KKT residuals."""
    t0 = time.perf_counter()
    problem = lsq.Problem(gram.L, gram.Z, 2 if gram.has_damping else 1, eps, gram.m)
    theta, solved = strategy.solve(problem)
    K, C, B = _split_theta(theta, gram.r, gram.m, gram.has_damping)
    if C is None:
        K = _floor(K, eps)
    else:
        K, C = _floor(np.stack([K, C]), eps)
    cert = _certificate(gram, K, C, B, solved.solver, solved.status, time.perf_counter() - t0, eps)
    cert.update({k: v for k, v in solved.as_dict().items() if k != "seconds"})
    cert.update(problem.kkt(np.hstack([K] + ([C] if C is not None else [])
                                      + ([-B] if B is not None else []))))
    gap = solved.duality_gap
    cert["certified"] = bool(solved.converged and gap is not None
                             and gap <= getattr(strategy, "gap_tol", GAP_TOL))
    if not solved.converged:
        warnings.warn(f"{solved.solver} stopped after {solved.iterations} iterations without "
                      "meeting its tolerance; see the certificate's KKT residuals", SolverWarning,
                      stacklevel=3)
    return MechanicalOperators(K, C, B, cert)


def _solve_cvxpy(gram: GramData, eps: float) -> MechanicalOperators:
    try:
        import cvxpy as cp
    except ImportError as exc:  # pragma: no cover
        raise ImportError("solver='cvxpy' needs cvxpy: pip install cvxpy clarabel") from exc
    r, m = gram.r, gram.m
    # Scale unknowns so the conic solver sees O(1) numbers: Theta = s * Theta_s.
    s = np.linalg.norm(gram.Z) / max(np.linalg.norm(gram.L), 1e-300)
    K = cp.Variable((r, r), symmetric=True)
    blocks = [K]
    cons = [K >> (eps / s) * np.eye(r)]
    C = None
    if gram.has_damping:
        C = cp.Variable((r, r), symmetric=True)
        blocks.append(C)
        cons.append(C >> (eps / s) * np.eye(r))
    negB = cp.Variable((r, m)) if m else None
    if m:
        blocks.append(negB)
    theta = cp.hstack(blocks) if len(blocks) > 1 else K
    zn = np.linalg.norm(gram.Z)
    prob = cp.Problem(cp.Minimize(cp.sum_squares(theta @ (gram.L * s / zn) + gram.Z / zn)), cons)
    from .mass import clarabel

    t0 = time.perf_counter()
    try:
        raw = clarabel(cp, prob)
    except SolverFailedError as exc:
        raise SolverFailedError(f"cvxpy/Clarabel failed on the L-OpInf problem: {exc}") from exc
    seconds = time.perf_counter() - t0
    Kv = s * K.value
    Kv = 0.5 * (Kv + Kv.T)
    Cv = None if C is None else s * 0.5 * (C.value + C.value.T)
    Bv = None if negB is None else -s * negB.value
    cert = _certificate(gram, Kv, Cv, Bv, "cvxpy-clarabel", prob.status, seconds, eps)
    cert.update(duality_gap=raw["relative_gap"], iterations=raw["iterations"],
                certified=bool(prob.status == "optimal" and raw["relative_gap"] <= GAP_TOL))
    if prob.status != "optimal":
        warnings.warn(f"Clarabel returned {prob.status}; check the certificate", SolverWarning,
                      stacklevel=2)
    return MechanicalOperators(Kv, Cv, Bv, cert)


@_serial_blas
def infer_opinf(Qh, dQh, ddQh, U=None, *, damping: bool = True, ridge: float = RIDGE,
                strict: bool = False) -> MechanicalOperators:
    """Standard second-order OpInf: unconstrained least squares for [Kh, Ch, Bh].

    The baseline L-OpInf is compared against: it fits the training data, but Kh is
    neither symmetric nor definite, so the ROM carries no Lagrangian structure. The same
    ridge-regularised problem as L-OpInf (:func:`gram_data`), without constraints:
    Theta = -Z L^{-1}.
    """
    (Qh, dQh, ddQh, U), c_state, c_input = _unit_scaled(Qh, dQh, ddQh, U)
    gram = gram_data(Qh, dQh, ddQh, U, damping=damping, ridge=ridge, strict=strict)
    t0 = time.perf_counter()
    theta = -scipy.linalg.solve_triangular(gram.L, gram.Z.T, trans="T", lower=True).T
    seconds = time.perf_counter() - t0
    K, C, B = _split_theta(theta, gram.r, gram.m, damping)
    cert = _certificate(gram, K, C, B, "lstsq", "optimal", seconds, None)
    cert.update(duality_gap=0.0, certified=True, iterations=0)  # the exact least squares
    ops = MechanicalOperators(K, C, B, cert)
    return _unscaled(ops, c_state, c_input)


@_serial_blas
def infer_wave(Qh, ddQh, Fh, *, negative_semidefinite: bool = False, ridge: float = RIDGE,
               strict: bool = False) -> MechanicalOperators:
    """Symmetric Kh of the gray-box wave ROM qh_tt = Kh qh - Fh (METHOD.md section 4).

    Args:
        Qh, ddQh, Fh: (r, K) reduced states, their second derivatives and the reduced
            nonlinear term V^T f_nl(V qh) on the same grid.
        negative_semidefinite: also require Kh <= 0. The paper asks only for symmetry; but
            -Kh is a reduced discrete Laplacian, and a symmetric Kh with a positive
            eigenvalue makes the linear part of the ROM grow exponentially.
        ridge, strict: as in :func:`infer_mechanical`.

    Returns:
        :class:`MechanicalOperators` with ``K`` = Kh (symmetric, unique when Qh has full
        rank) and a certificate (stationarity of the Lyapunov equation).
    """
    Qh = check_matrix(Qh, "Qh")
    r, K = Qh.shape
    Fh = check_matrix(Fh, "Fh", rows=r, cols=K)
    # qh_tt = Kh qh - Fh  <=>  ddQh + Fh + (-Kh) Qh = 0: the mechanical form with K -> -Kh
    target = check_matrix(ddQh, "ddQh", rows=r, cols=K) + Fh
    if negative_semidefinite:  # -Kh >= 0: the conservative mechanical fit with eps = 0
        ops = infer_mechanical(Qh, None, target, damping=False, eps=0.0, ridge=ridge,
                               strict=strict)
        cert = dict(ops.certificate, max_eig_K=float(np.linalg.eigvalsh(-ops.K).max()))
        return MechanicalOperators(-ops.K, None, None, cert)
    (Qh, _, target, _), c_state, _ = _unit_scaled(Qh, None, target, None)
    gram = gram_data(Qh, None, target, damping=False, ridge=ridge, strict=strict)
    ops = _unscaled(_solve_lyapunov(gram, -np.inf), c_state, 1.0)
    Kh = -ops.K
    cert = dict(ops.certificate, min_eig_K=float(np.linalg.eigvalsh(Kh).min()), status="optimal",
                duality_gap=0.0, certified=True)  # unconstrained: the exact minimiser
    return MechanicalOperators(Kh, None, None, cert)


@_serial_blas
def infer_output(Qh, Y, *, ridge: float = RIDGE, strict: bool = False) -> np.ndarray:
    """Output operator Eh = argmin ||Y - Eh Qh||_F^2 (+ the ridge of :func:`gram_data`),
    (p, r) from Qh (r, K) and Y (p, K)."""
    Qh = check_matrix(Qh, "Qh")
    Y = check_matrix(np.atleast_2d(Y), "Y", cols=Qh.shape[1])
    c_state, c_out = _pow2_scale(Qh), _pow2_scale(Y)
    if not np.any(Y):
        return np.zeros((Y.shape[0], Qh.shape[0]))
    L, Z, *_ = _compress([Qh / c_state], -Y / c_out, [f"Qh[{i}]" for i in range(Qh.shape[0])],
                         ridge, strict, "Qh")
    E = -scipy.linalg.solve_triangular(L, Z.T, trans="T", lower=True).T
    return E * (c_out / c_state)
