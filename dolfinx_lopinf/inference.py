"""Lagrangian operator inference (L-OpInf) and the standard OpInf baseline (METHOD.md s. 4).

Mechanical ROM with reduced mass fixed to I:

    qh_tt + Ch qh_t + Kh qh = Bh u,        y = Eh qh.

L-OpInf solves the constrained least-squares problem

    min  || ddQh + Kh Qh + Ch dQh - Bh U ||_F
    s.t. Kh = Kh^T, Ch = Ch^T, Kh >= eps I, Ch >= eps I   (matrix inequalities),

so the learned ROM is the Euler-Lagrange equation of L_h = 1/2 |qh_t|^2 - 1/2 qh^T Kh qh
(with Rayleigh-like dissipation Ch and input Bh u) by construction.

Compression: write Theta = [Kh, Ch, -Bh] (r, p) and D = [Qh; dQh; U] (p, K). Then

    ||ddQh + Theta D||_F^2 = ||Theta L + Z||_F^2 + ||ddQh||_F^2 - ||Z||_F^2,
    G = D D^T = L L^T,  Z = ddQh D^T L^{-T}  (r, p)   (L from a thin QR of D^T),

so after one pass over the data (cost O(K p^2)) the problem no longer depends on K.
Solvers. Without damping and inputs, the symmetric-only problem min ||K L + Z|| over
K = K^T has the closed-form solution of the Lyapunov equation

    G K + K G = -(X + X^T),   X = ddQh Qh^T = Z L^T,

solved through the SVD L = U S W^T (so G = U S^2 U^T):  U^T K U = -U^T (X + X^T) U / (s_i^2 + s_j^2).
If that minimiser already satisfies K >= eps I it *is* the L-OpInf solution (the constraint
is inactive, KKT holds with zero multiplier). Otherwise - and for damped/forced fits - the
compressed problem goes to cvxpy (Clarabel); the fast structured constrained solver is a
separate piece of work.

Standard (second-order) OpInf drops every constraint: Theta = -ddQh D^+ by least squares.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from ._checks import check_matrix


@dataclass(frozen=True)
class MechanicalOperators:
    """Inferred reduced operators of qh_tt + C qh_t + K qh = B u (None where not fitted).

    Attributes:
        K: (r, r) stiffness.  C: (r, r) damping or None.  B: (r, m) input or None.
        certificate: how the solve went: ``solver``, ``status``, ``objective`` (the squared
            residual norm ||ddQh + K Qh + C dQh - B U||_F^2), ``relative_residual``,
            ``min_eig_K``/``min_eig_C``, ``symmetry_error``, ``seconds``.
    """

    K: np.ndarray
    C: np.ndarray | None = None
    B: np.ndarray | None = None
    certificate: dict = field(default_factory=dict)


@dataclass(frozen=True)
class GramData:
    """The data of the least-squares problem after one pass over K snapshots.

    Attributes:
        L: (p, p) lower-triangular factor of G = D D^T (from a QR of D^T).
        Z: (r, p) = ddQh D^T L^{-T}.
        condition: condition number of the row-normalised data matrix.
        target_norm2: ||ddQh||_F^2.
        r, m: reduced and input dimensions; ``has_damping`` tells whether dQh is in D.
    """

    L: np.ndarray
    Z: np.ndarray
    target_norm2: float
    r: int
    m: int
    has_damping: bool
    condition: float = float("nan")


def _data_matrix(Qh, dQh, ddQh, U, damping):
    Qh = check_matrix(Qh, "Qh")
    r, K = Qh.shape
    ddQh = check_matrix(ddQh, "ddQh", rows=r, cols=K)
    rows = [Qh]
    if damping:
        if dQh is None:
            raise ValueError("damping=True needs the first derivatives dQh")
        rows.append(check_matrix(dQh, "dQh", rows=r, cols=K))
    m = 0
    if U is not None:
        U = check_matrix(np.atleast_2d(U), "U", cols=K)
        m = U.shape[0]
        rows.append(U)
    D = np.vstack(rows)
    if K < D.shape[0]:
        raise ValueError(
            f"{K} snapshots cannot determine {D.shape[0]} unknowns per row; record more "
            "time samples or lower r"
        )
    return D, ddQh, r, m


def gram_data(Qh, dQh, ddQh, U=None, *, damping=True) -> GramData:
    """Form the compressed least-squares data (one pass over the snapshots).

    Raises ``ValueError`` with the rank and condition number when D = [Qh; dQh; U] is
    rank deficient, because then the operators are not determined by the data.
    """
    D, ddQh, r, m = _data_matrix(Qh, dQh, ddQh, U, damping)
    # Thin QR of the row-normalised data, D^T = diag(s)^-1-free form: Dn^T = Qf R with
    # Dn = diag(1/s) D. Then G = D D^T = L L^T with L = diag(s) R^T and Z = ddQh Qf, without
    # ever squaring the condition number (POD coordinates span many decades).
    scale = np.linalg.norm(D, axis=1)
    if np.any(scale == 0):
        raise ValueError(f"data rows {np.flatnonzero(scale == 0).tolist()} of [Qh; dQh; U] are zero")
    Qf, R = np.linalg.qr((D / scale[:, None]).T)
    sv = np.linalg.svd(R, compute_uv=False)
    cond = sv[0] / max(sv[-1], np.finfo(float).tiny)
    # Rank deficient = singular at double precision. Block-diagonal POD makes the data badly
    # conditioned but not singular (theta = w' couples the blocks): 1e12 is normal there.
    tol = sv[0] * 50 * np.finfo(float).eps
    if sv[-1] <= tol:
        rank = int((sv > tol).sum())
        raise ValueError(
            f"the data matrix [Qh; dQh; U] has numerical rank {rank} < {D.shape[0]} "
            f"(condition number {cond:.3g}); the operators are not determined by the data - "
            "lower r, record a richer trajectory or drop a block"
        )
    if cond > 1e13:
        warnings.warn(
            f"the data matrix [Qh; dQh; U] is ill-conditioned (condition number {cond:.3g}); the "
            "fitted operators may be sensitive to noise - consider a smaller r", RuntimeWarning,
            stacklevel=3)
    L = scale[:, None] * R.T
    Z = ddQh @ Qf
    return GramData(L, Z, float(np.sum(ddQh**2)), r, m, damping, float(cond))


def _split_theta(theta, r, m, has_damping):
    K = theta[:, :r]
    C = theta[:, r : 2 * r] if has_damping else None
    B = -theta[:, theta.shape[1] - m :] if m else None
    return K, C, B


def _objective(gram: GramData, theta: np.ndarray) -> float:
    return float(np.sum((theta @ gram.L + gram.Z) ** 2) + gram.target_norm2 - np.sum(gram.Z**2))


def _certificate(gram, K, C, B, solver, status, seconds, eps):
    theta = np.hstack([K] + ([C] if C is not None else []) + ([-B] if B is not None else []))
    obj = max(_objective(gram, theta), 0.0)
    cert = {
        "solver": solver,
        "status": status,
        "objective": obj,
        "relative_residual": float(np.sqrt(obj / gram.target_norm2)),
        "symmetry_error": float(np.abs(K - K.T).max() / max(np.abs(K).max(), 1e-300)),
        "min_eig_K": float(np.linalg.eigvalsh(0.5 * (K + K.T)).min()),
        "seconds": seconds,
        "eps": eps,
        "data_condition": gram.condition,
    }
    if C is not None:
        cert["min_eig_C"] = float(np.linalg.eigvalsh(0.5 * (C + C.T)).min())
    return cert


def infer_mechanical(Qh, dQh, ddQh, U=None, *, eps: float = 1e-8, damping: bool = True,
                     solver: str = "auto") -> MechanicalOperators:
    """L-OpInf for qh_tt + Ch qh_t + Kh qh = Bh u with Kh, Ch symmetric, >= eps I.

    Args:
        Qh, dQh, ddQh: (r, K) reduced states and their first/second time derivatives on
            the same grid (see :func:`dolfinx_lopinf.ddt.derivatives`). ``dQh`` may be None
            when ``damping=False``.
        U: (m, K) inputs, or None for an unforced system.
        eps: lower bound on the eigenvalues of Kh (and Ch).
        damping: fit Ch too; ``False`` gives the conservative form (Kh, and Bh with inputs).
        solver: ``"auto"`` or ``"cvxpy"`` (Clarabel on the compressed problem).

    Returns:
        :class:`MechanicalOperators` with a certificate; warns if the solver did not reach
        optimality.

    Example:
        >>> t = np.linspace(0, 10, 2001); w = np.array([[1.0], [2.0]])
        >>> Q = np.vstack([np.cos(t), 0.5 * np.sin(2 * t)])
        >>> from dolfinx_lopinf.ddt import derivatives
        >>> ops = infer_mechanical(*derivatives(Q, t), damping=False)
        >>> bool(np.allclose(ops.K, np.diag([1.0, 4.0]), atol=1e-5))
        True
    """
    if solver not in ("auto", "cvxpy", "lyapunov", "admm"):
        raise ValueError(f"unknown solver {solver!r}; choose 'auto', 'lyapunov', 'admm' or 'cvxpy'")
    if not (np.isfinite(eps) and eps >= 0):
        raise ValueError(f"eps must be a finite number >= 0, got {eps}")
    gram = gram_data(Qh, dQh, ddQh, U, damping=damping)
    conservative = not gram.has_damping and gram.m == 0
    if solver in ("lyapunov", "admm") and not conservative:
        raise ValueError(f"solver={solver!r} handles the conservative, unforced fit only "
                         "(damping=False, U=None); use 'cvxpy'")
    if solver == "cvxpy" or not conservative:
        return _solve_cvxpy(gram, eps)
    ops = _solve_lyapunov(gram, eps)
    if solver == "lyapunov" or (solver == "auto" and ops.certificate["min_eig_K"] >= eps):
        return ops
    return _solve_admm(gram, eps, start=ops.K)


def _solve_lyapunov(gram: GramData, eps: float) -> MechanicalOperators:
    """Symmetric least-squares minimiser: G K + K G = -(X + X^T), via the SVD of L."""
    t0 = time.perf_counter()
    U, s, _ = np.linalg.svd(gram.L)
    X = gram.Z @ gram.L.T
    rhs = -U.T @ (X + X.T) @ U
    K = U @ (rhs / (s[:, None] ** 2 + s[None, :] ** 2)) @ U.T
    K = 0.5 * (K + K.T)
    seconds = time.perf_counter() - t0
    cert = _certificate(gram, K, None, None, "lyapunov", "optimal", seconds, eps)
    # stationarity of the symmetric problem, relative to the size of its terms
    G = gram.L @ gram.L.T
    grad = K @ G + G @ K + X + X.T
    cert["kkt_residual"] = float(np.linalg.norm(grad) / max(np.linalg.norm(X + X.T), 1e-300))
    if cert["min_eig_K"] < eps:
        cert["status"] = "infeasible: the symmetric minimiser has min eigenvalue < eps"
    return MechanicalOperators(K, None, None, cert)


def _solve_admm(gram: GramData, eps: float, start: np.ndarray, *, tol: float = 1e-10,
                max_iter: int = 20000) -> MechanicalOperators:
    """min ||K L + Z||_F^2 s.t. K = K^T >= eps I by ADMM on K = W, W in the PSD cone.

    K-step: (G + rho/2) K + K (G + rho/2) = rho (W - Y) - (X + X^T), diagonal in the
    eigenbasis of G = U diag(lambda) U^T; W-step: eigenvalue clipping of K + Y at eps;
    rho adapted by residual balancing. Returns a KKT certificate: with S = grad f(K) the
    optimality conditions are S >= 0 (dual feasibility) and <S, K - eps I> = 0.
    """
    t0 = time.perf_counter()
    U, s, _ = np.linalg.svd(gram.L)
    lam = s**2
    X = gram.Z @ gram.L.T
    B = U.T @ (X + X.T) @ U  # in the eigenbasis of G
    r = gram.r

    def project(A):
        w, Q = np.linalg.eigh(0.5 * (A + A.T))
        return (Q * np.maximum(w, eps)) @ Q.T

    Kt = U.T @ start @ U
    Wt = U.T @ project(start) @ U
    Yt = np.zeros_like(Kt)
    rho = float(np.sqrt(lam.max() * max(lam.min(), lam.max() * 1e-16)))
    denom = lam[:, None] + lam[None, :]
    it, prim, dual = 0, np.inf, np.inf
    for it in range(1, max_iter + 1):
        Kt = (rho * (Wt - Yt) - B) / (denom + rho)
        W_old = Wt
        Wt = U.T @ project(U @ (Kt + Yt) @ U.T) @ U
        Yt += Kt - Wt
        prim = np.linalg.norm(Kt - Wt) / max(np.linalg.norm(Kt), np.linalg.norm(Wt), 1e-300)
        dual = np.linalg.norm(Wt - W_old) / max(np.linalg.norm(Yt), 1e-300)
        if prim < tol and dual < tol:
            break
        if it % 10 == 0:  # residual balancing (Boyd et al. 2011, s. 3.4.1)
            if prim > 10 * dual:
                rho *= 2.0
                Yt /= 2.0
            elif dual > 10 * prim:
                rho /= 2.0
                Yt *= 2.0
    K = U @ Wt @ U.T
    K = 0.5 * (K + K.T)
    seconds = time.perf_counter() - t0
    converged = prim < tol and dual < tol
    cert = _certificate(gram, K, None, None, "admm", "optimal" if converged else
                        "not converged", seconds, eps)
    G = gram.L @ gram.L.T
    S = K @ G + G @ K + X + X.T  # gradient = the multiplier of K >= eps I at the optimum
    scale = max(np.linalg.norm(X + X.T), 1e-300)
    cert.update(iterations=it, primal_residual=float(prim), dual_residual=float(dual),
                multiplier_min_eig=float(np.linalg.eigvalsh(S).min() / scale),
                complementarity=float(abs(np.sum(S * (K - eps * np.eye(r)))) / (scale * max(np.linalg.norm(K), 1e-300))))
    if not converged:
        warnings.warn(f"ADMM stopped after {it} iterations (primal {prim:.2e}, dual {dual:.2e} "
                      f"relative residuals); the certificate says how far from optimal it is",
                      RuntimeWarning, stacklevel=3)
    return MechanicalOperators(K, None, None, cert)


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
    t0 = time.perf_counter()
    prob.solve(solver=cp.CLARABEL)
    seconds = time.perf_counter() - t0
    if prob.status not in ("optimal", "optimal_inaccurate"):
        raise RuntimeError(f"cvxpy/Clarabel failed on the L-OpInf problem: status {prob.status}")
    Kv = s * K.value
    Kv = 0.5 * (Kv + Kv.T)
    Cv = None if C is None else s * 0.5 * (C.value + C.value.T)
    Bv = None if negB is None else -s * negB.value
    cert = _certificate(gram, Kv, Cv, Bv, "cvxpy-clarabel", prob.status, seconds, eps)
    if prob.status != "optimal":
        warnings.warn(f"Clarabel returned {prob.status}; check the certificate", RuntimeWarning)
    return MechanicalOperators(Kv, Cv, Bv, cert)


def infer_opinf(Qh, dQh, ddQh, U=None, *, damping: bool = True) -> MechanicalOperators:
    """Standard second-order OpInf: unconstrained least squares for [Kh, Ch, Bh].

    The baseline L-OpInf is compared against: it fits the training data, but Kh is
    neither symmetric nor definite, so the ROM carries no Lagrangian structure.
    """
    D, ddQh, r, m = _data_matrix(Qh, dQh, ddQh, U, damping)
    t0 = time.perf_counter()
    theta = -np.linalg.lstsq(D.T, ddQh.T, rcond=None)[0].T
    seconds = time.perf_counter() - t0
    K, C, B = _split_theta(theta, r, m, damping)
    gram = gram_data(Qh, dQh, ddQh, U, damping=damping)
    return MechanicalOperators(K, C, B, _certificate(gram, K, C, B, "lstsq", "optimal", seconds, None))


def infer_output(Qh, Y) -> np.ndarray:
    """Output operator Eh = argmin ||Y - Eh Qh||_F, (p, r) from Qh (r, K) and Y (p, K)."""
    Qh = check_matrix(Qh, "Qh")
    Y = check_matrix(np.atleast_2d(Y), "Y", cols=Qh.shape[1])
    return np.linalg.lstsq(Qh.T, Y.T, rcond=None)[0].T
