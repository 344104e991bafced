"""One symmetric block: the Lyapunov minimiser (no constraint) and ADMM in the eigenbasis of
G (K >= eps I)."""

from __future__ import annotations

import time

import numpy as np

from .linalg import psd_project
from .problem import Certificate, Problem, Strategy


def _lyapunov_rhs(L: np.ndarray, Z: np.ndarray):
    """SVD L = U diag(s) W^T and B = U^T (X + X^T) U with X = Z L^T, formed as
    Zt diag(s) + (Zt diag(s))^T from Zt = U^T Z W: the rounding of B in direction (i, j) is
    then ~ u ||Z|| max(s_i, s_j), not u ||Z|| s_1, so the solution in directions with small
    s (weakly determined by the data, fixed by the ridge) is not lost to rounding."""
    U, s, Wt = np.linalg.svd(L)
    Zs = (U.T @ Z @ Wt.T) * s[None, :]
    return U, s, Zs + Zs.T


def _lyapunov_solution(U, lam, B):
    """K with G K + K G = -U B U^T, G = U diag(lam) U^T: diagonal in G's eigenbasis."""
    return U @ (-B / (lam[:, None] + lam[None, :])) @ U.T


def solve_symmetric(L: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """argmin over symmetric K (r, r) of ||K L + Z||_F (L is r x r): the Lyapunov solution
    G K + K G = -(X + X^T), exact in the eigenbasis of G = L L^T."""
    U, s, B = _lyapunov_rhs(L, Z)
    K = _lyapunov_solution(U, s**2, B)
    return 0.5 * (K + K.T)


class Lyapunov(Strategy):
    """One symmetric block, no definiteness: :func:`solve_symmetric` (closed form). When the
    minimiser is >= eps I it is also the constrained optimum (zero multiplier): duality gap 0;
    else it answers the unconstrained problem only (duality gap None: no certificate)."""

    def solve_blocks(self, problem: Problem):
        self._one_block(problem)
        t0 = time.perf_counter()
        K = solve_symmetric(problem.L, problem.Z)
        feasible = bool(np.linalg.eigvalsh(K)[0] >= problem.eps)
        return K, Certificate("lyapunov", True, 0, seconds=time.perf_counter() - t0,
                              duality_gap=0.0 if feasible else None)


class EigenbasisADMM(Strategy):
    """One symmetric block >= eps I by ADMM on K = W.

    K-step: (G + rho/2) K + K (G + rho/2) = rho (W - Y) - (X + X^T), diagonal in the
    eigenbasis of G = U diag(lambda) U^T, so every direction is solved exactly whatever the
    conditioning of G (robust to the 1e12 condition numbers of block-POD beam data); W-step:
    eigenvalue clipping of K + Y at eps; rho by residual balancing. Starts from ``start``
    or the Lyapunov minimiser.
    """

    def __init__(self, tol: float = 1e-10, max_iter: int = 20000, start=None):
        self.tol, self.max_iter, self.start = tol, max_iter, start

    def solve_blocks(self, problem: Problem):
        self._one_block(problem)
        t0 = time.perf_counter()
        eps, tol = problem.eps, self.tol
        U, s, B = _lyapunov_rhs(problem.L, problem.Z)
        lam = s**2
        start = _lyapunov_solution(U, lam, B) if self.start is None else self.start
        Wt = U.T @ psd_project(start, eps)[0] @ U
        Yt = np.zeros_like(Wt)
        rho = float(np.sqrt(lam.max() * max(lam.min(), lam.max() * 1e-16)))
        denom = lam[:, None] + lam[None, :]
        it, prim, dual = 0, np.inf, np.inf
        for it in range(1, self.max_iter + 1):
            Kt = (rho * (Wt - Yt) - B) / (denom + rho)
            W_old = Wt
            Wt = U.T @ psd_project(U @ (Kt + Yt) @ U.T, eps)[0] @ U
            Yt += Kt - Wt
            prim = np.linalg.norm(Kt - Wt) / max(np.linalg.norm(Kt), np.linalg.norm(Wt), 1e-300)
            dual = np.linalg.norm(Wt - W_old) / max(np.linalg.norm(Yt), np.linalg.norm(Wt), 1e-300)
            if prim < tol and dual < tol:
                break
            if it % 10 == 0:  # residual balancing
                if prim > 10 * dual:
                    rho, Yt = 2.0 * rho, Yt / 2.0
                elif dual > 10 * prim:
                    rho, Yt = rho / 2.0, Yt * 2.0
        K = U @ Wt @ U.T
        return 0.5 * (K + K.T), Certificate(
            "admm", bool(prim < tol and dual < tol), it, seconds=time.perf_counter() - t0,
            primal_residual=float(prim), dual_residual=float(dual), rho=rho)
