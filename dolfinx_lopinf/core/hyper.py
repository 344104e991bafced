"""Structure-preserving hyper-reduction of a pointwise nonlinear potential (numpy only).

The reduced force of the wave ROM, V^T g(V qh), costs O(n r). Energy-conserving sampling and
weighting (ECSW, Farhat et al. 2015) replaces the sum over all n points by a weighted sum
over a few sampled points S,

    sum_i U(V_i qh)  ~  sum_{i in S} w_i U(V_i qh),    w_i >= 0,

so the ROM is *still* the Euler-Lagrange equation of a Lagrangian (a reduced potential),
keeps its symplectic midpoint integrator and bounded energy, and a step costs O(|S| r),
independent of n. The weights fit the reduced forces on training snapshots:

    min_w>=0 || C w - b ||,   C[(k, :), i] = V_i^T g(V_i qh_k),   b[(k, :)] = V^T g(V qh_k),

solved by a Lawson-Hanson active-set NNLS stopped as soon as ||C w - b|| <= tol ||b||,
which keeps S small.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from ._checks import check_matrix, check_positive, check_vector, pow2_scale
from ..errors import InputError


@dataclass(frozen=True)
class Sampling:
    """Sampled rows and weights: ``rows`` (s,), ``weights`` (s,), relative fit residual."""

    rows: np.ndarray
    weights: np.ndarray
    residual: float


def nnls_tolerance(C: np.ndarray, b: np.ndarray, tol: float, max_terms: int | None = None) -> tuple[np.ndarray, float]:
    """Lawson-Hanson non-negative least squares, stopped at ||C w - b|| <= tol ||b||."""
    C = check_matrix(C, "C")
    m, n = C.shape
    b = check_vector(b, "b", m)
    tol = check_positive(tol, "tol")
    # one power-of-two scale for C and b: exact, keeps the norms finite for data ~ 1e+-160,
    # and leaves w (the solution of C w = b) unchanged
    s = pow2_scale(C, b)
    C, b = C / s, b / s
    w = np.zeros(n)
    passive = np.zeros(n, dtype=bool)
    bnorm = np.linalg.norm(b)
    res = b.copy()
    max_terms = max_terms or min(m, n)
    while np.linalg.norm(res) > tol * bnorm and passive.sum() < max_terms:
        grad = C.T @ res
        grad[passive] = -np.inf
        j = int(np.argmax(grad))
        if grad[j] <= 0:
            break
        passive[j] = True
        while True:
            idx = np.flatnonzero(passive)
            z = np.zeros(n)
            z[idx] = scipy.linalg.lstsq(C[:, idx], b)[0]
            if np.all(z[idx] > 0):
                w = z
                break
            neg = idx[z[idx] <= 0]
            alpha = np.min(w[neg] / (w[neg] - z[neg] + 1e-300))
            w = w + alpha * (z - w)
            passive &= w > 1e-14
            w[~passive] = 0.0
        res = b - C @ w
    return w, float(np.linalg.norm(res) / max(bnorm, 1e-300))


def ecsw(V: np.ndarray, Qh: np.ndarray, g, *, tol: float = 1e-4, max_points: int | None = None) -> Sampling:
    """Sample points and weights for sum_i U(V_i qh) (see module docstring).

    Args:
        V: (n, r) basis.
        Qh: (r, K) reduced training states (a few hundred columns suffice).
        g: pointwise nonlinearity U'.
        tol: relative residual of the reduced-force fit at which to stop adding points.
    """
    V = check_matrix(V, "V")
    Qh = check_matrix(Qh, "Qh", rows=V.shape[1])
    if not callable(g):
        raise InputError(f"g must be a callable (the pointwise nonlinearity), got {type(g).__name__}")
    Z = V @ Qh  # (n, K)
    G = np.asarray(g(Z))
    if G.shape != Z.shape or not np.all(np.isfinite(G)):
        raise InputError(f"g(V Qh) must return finite values of shape {Z.shape}, got shape "
                         f"{G.shape}" + ("" if G.shape != Z.shape else " with non-finite values"))
    r, K = Qh.shape
    # C[(k, a), i] = V[i, a] g(Z[i, k])
    C = np.einsum("ia,ik->kai", V, G).reshape(K * r, V.shape[0])
    b = C.sum(axis=1)
    w, residual = nnls_tolerance(C, b, tol, max_points)
    rows = np.flatnonzero(w > 0)
    return Sampling(rows, w[rows], residual)
