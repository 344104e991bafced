"""The sum-of-squares potential fit of :mod:`dolfinx_lopinf.core.polynomial.fit` by our certified
interior point (:mod:`dolfinx_lopinf.core.lsq.psd_qp`) instead of Clarabel.

Unknowns (balanced units, as the cvxpy formulation): g = vech(G) of the Gram matrix of
U = m^T G m (m = [q; z], n_g = r + r (r + 1) / 2), vech(C), and B. The potential's monomial
coefficients are M_v g (``gram_maps`` in vech coordinates), and the misfit is
||R (norms * [M_v g, c, b]) - z||^2 with the column-normalised, QR-compressed design R of
``fit_polynomial``. B (free) is minimised out exactly first. The Gram representation of a
polynomial is not unique (q_i^2 q_j^2 = (q_i q_j)^2 = (q_i^2)(q_j^2)): f is flat along the
null space N of M_v (:func:`gram_null`); the interior point's Schur matrix is positive
definite all the same (the Gram block's barrier), and the certificate keeps the bound finite
by making the Gram multiplier orthogonal to N - projecting it, then adding a multiple of the
data's moment matrix (:func:`moment_matrix`: positive definite, orthogonal to N) if the
projection cost positive definiteness.

Constraints: G >= eps_g I, K = 2 G_11 >= eps diag(sig^2), C >= eps diag(sig^2): three
blocks of n_g, r and r. The certificate is the interior point's (closed-form dual bound).
"""

from __future__ import annotations

import functools
import time
from math import comb

import numpy as np
import scipy.linalg

from .._blas import one_blas_thread
from ..lsq import psd_qp
from ..lsq.psd_qp import vech
from .potential import gram_maps

@functools.lru_cache(maxsize=8)
def gram_map_vech(r: int) -> np.ndarray:
    """(p_pot, n_g (n_g + 1) / 2): the monomial coefficients of m^T G m from vech(G)."""
    Mall = np.vstack(gram_maps(r))
    n = r + comb(r + 1, 2)
    i, j = np.triu_indices(n)
    out = Mall[:, i * n + j] + np.where(i != j, 1.0, 0.0) * Mall[:, j * n + i]
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=8)
def gram_null(r: int) -> np.ndarray:
    """An orthonormal basis of the null space of :func:`gram_map_vech` (the Gram matrices of
    the zero polynomial, in vech coordinates)."""
    Mv = gram_map_vech(r)
    Q, R, _ = scipy.linalg.qr(Mv.T, mode="full", pivoting=True, check_finite=False)
    rank = int(np.sum(np.abs(np.diag(R)) > 1e-12 * np.abs(R[0, 0])))
    out = np.ascontiguousarray(Q[:, rank:])  # orthonormal, orthogonal to Mv's rows
    out.setflags(write=False)
    return out


def moment_matrix(points, r):
    """mean over the points (r, N) of m m^T, m = [q; z] (z_ij = q_i q_j, i <= j): positive
    definite for rich data, and <it, N> = 0 for every Gram matrix N of the zero polynomial."""
    i, j = np.triu_indices(r)
    m = np.vstack([points, points[i] * points[j]])
    return m @ m.T / points.shape[1]


def solve_sos(R, z, norms, r, m, damping, eps, eps_gram, sig, p_pot, gap_tol=1e-8, points=None,
              f_const=0.0):
    """One BLAS thread (:func:`~dolfinx_lopinf.core._blas.serial_blas`: its matrices are
    a few hundred wide; threads cost more than they give there)."""
    with one_blas_thread():
        return _solve_sos(R, z, norms, r, m, damping, eps, eps_gram, sig, p_pot, gap_tol, points, f_const)


def _solve_sos(R, z, norms, r, m, damping, eps, eps_gram, sig, p_pot, gap_tol, points, f_const):
    """min ||R x - z||^2 over the sos-constrained potential, C and B (module docstring):
    (theta in balanced units [potential coefficients, vech C, B], G, certificate dict)."""
    t0 = time.perf_counter()
    n_g = r + comb(r + 1, 2)
    ng = n_g * (n_g + 1) // 2
    nC = comb(r + 1, 2) if damping else 0
    Mv = gram_map_vech(r)
    Rn = R * norms[None, :]  # acts on theta (balanced units)
    A_s = np.hstack([Rn[:, :p_pot] @ Mv, Rn[:, p_pot:p_pot + nC]])
    A_b = Rn[:, p_pot + nC:]
    if A_b.shape[1]:  # B minimised out: project onto the complement of A_b's columns
        Qb = scipy.linalg.qr(A_b, mode="economic", check_finite=False)[0]
        A_p, z_p = A_s - Qb @ (Qb.T @ A_s), z - Qb @ (Qb.T @ z)
    else:
        A_p, z_p = A_s, z
    H = A_p.T @ A_p
    h = -(A_p.T @ z_p)
    n = ng + nC
    if points is None:
        points = np.random.default_rng(0).standard_normal((r, 4 * n_g * n_g))
    moment = moment_matrix(points, r)
    # the constraints: G >= eps_g I; 2 G_11 >= eps diag(sig^2); C >= eps diag(sig^2)
    iG, jG = np.triu_indices(n_g)
    P_G = np.zeros((ng, n))
    P_G[np.arange(ng), np.arange(ng)] = 1.0
    i1, j1 = np.triu_indices(r)
    pos = {(a, b): k for k, (a, b) in enumerate(zip(iG, jG))}
    P_K = np.zeros((len(i1), n))
    P_K[np.arange(len(i1)), [pos[(a, b)] for a, b in zip(i1, j1)]] = 2.0
    P, F = [P_G, P_K], [eps_gram * np.eye(n_g), eps * np.diag(sig**2)]
    if damping:
        P_C = np.zeros((nC, n))
        P_C[np.arange(nC), ng + np.arange(nC)] = 1.0
        P.append(P_C)
        F.append(eps * np.diag(sig**2))
    N = np.zeros((n, gram_null(r).shape[1]))
    N[:ng] = gram_null(r)
    problem = psd_qp.QuadraticPSD(H, h, float(z_p @ z_p), P, F, f_scale=float(z @ z), null=N,
                                  moment=moment, A=A_p, b=z_p, f_const=f_const)
    x0 = _start(problem, Mv, A_p, z_p, r, n_g, ng, nC)
    x, cert = psd_qp.solve(problem, x0, gap_tol=gap_tol)
    g, c = x[:ng], x[ng:]
    G = psd_qp.unvech(g, n_g)
    pot = Mv @ g
    theta = [pot] + ([c] if damping else [])
    if A_b.shape[1]:
        b = scipy.linalg.lstsq(A_b, z - A_s @ x, check_finite=False)[0]
        theta.append(b)
    f = problem.objective(x)
    info = {"solver": "sos-ipm", "status": cert.status, "certified": bool(cert.converged),
            "iterations": cert.iterations, "duality_gap": float(cert.duality_gap),
            "solve_seconds": time.perf_counter() - t0, "objective": f,
            "stopped": cert.details["stopped"], "unknowns": n, "ipm_trace": cert.details["trace"],
            "min_eig_gram": float(np.linalg.eigvalsh(G).min()), "min_eig_gram_raw": float(np.linalg.eigvalsh(G).min())}
    return np.concatenate(theta), G, info


def _start(problem, Mv, A_p, z_p, r, n_g, ng, nC):
    """A strictly feasible start: the least-squares fit's potential as its smallest Gram
    matrix, then G, C shifted up until every block exceeds its floor by a margin."""
    y = scipy.linalg.lstsq(A_p, z_p, check_finite=False)[0]
    g = y[:ng]
    x = np.concatenate([g, y[ng:]])
    for _ in range(60):
        X = problem.slacks(x)
        low = [np.linalg.eigvalsh(Xk)[0] for Xk in X]
        if min(low) > 0:
            break
        scale = max(np.abs(psd_qp.unvech(x[:ng], n_g)).max(), 1e-300)
        shift = max(0.0, -min(low[:2])) + 0.1 * scale
        x[:ng] += shift * vech(np.eye(n_g))
        if nC and low[-1] <= 0:
            Cs = max(np.abs(x[ng:]).max(), 1e-300)
            x[ng:] += (max(0.0, -low[-1]) + 0.1 * Cs) * vech(np.eye(r))
    return x
