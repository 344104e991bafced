"""The sum-of-squares potential fit of :mod:`dolfinx_lopinf.core.polynomial.fit` by our certified
interior point (:mod:`dolfinx_lopinf.core.lsq.psd_qp`) instead of Clarabel.

Unknowns (balanced units, as the cvxpy formulation): g = vech(G) of the Gram matrix of
U = m^T G m (m = [q; z], n_g = r + r (r + 1) / 2), vech(C), and B. The potential's monomial
coefficients are M_v g (``gram_maps`` in vech coordinates), and the misfit is
||R (norms * [M_v g, c, b]) - z||^2 with the column-normalised, QR-compressed design R of
``fit_polynomial``. B (free) is minimised out exactly first. The Gram representation of a
polynomial is not unique (q_i^2 q_j^2 = (q_i q_j)^2 = (q_i^2)(q_j^2)): f is flat along the
null space N of M_v (:func:`gram_null_sparse`); the interior point's Schur matrix is positive
definite all the same (the Gram block's barrier), and the certificate keeps the bound finite
by making the Gram multiplier orthogonal to N - projecting it, and where that costs positive
definiteness, the better of correcting it as Lambda + Lambda Z Lambda (Z in N) and adding a
multiple of the data's moment matrix (:func:`moment_matrix`: positive definite, orthogonal
to N; :meth:`~dolfinx_lopinf.core.lsq.psd_qp.QuadraticPSD.gap`). The polish steps through
N's sparse basis itself.

Constraints: G >= eps_g I, K = 2 G_11 >= eps diag(sig^2), C >= eps diag(sig^2): three
blocks of n_g, r and r. The certificate is the interior point's (closed-form dual bound).

Scaling. The monomials differ in size by orders of magnitude over the data (the design's
columns span 28 .. 2e6 at r = 8), and so did the interior point's Newton matrices: its dual
residual stopped at the rounding of its largest terms and the gap stalled at ~1e-5 after 30
iterations. The unknowns are therefore the congruence G' = D G D, C' = E C E, with D, E
diagonal (:func:`_monomial_scales`: the diagonal entries' columns of the design get unit
norm); congruence keeps the cones (G >= eps_g I  <=>  G' >= eps_g D^2), the null space and
the moment matrix transform with it, and the problem is the same one - its certificate is
the original's (r = 8: the design's condition on its range 3e5 -> 1.7e3; certified in 16
iterations).
"""

from __future__ import annotations

import functools
import time
from math import comb

import numpy as np
import scipy.linalg
import scipy.sparse

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
def gram_null_sparse(r: int):
    """A sparse basis of the null space of :func:`gram_map_vech` (CSC, two entries a column):
    each Gram entry reaches one monomial (with weight 1 or 2), so for each monomial reached by
    entries e_0 .. e_k the differences e_0 / w_0 - e_j / w_j, j = 1 .. k."""
    Mv = gram_map_vech(r)
    rows, cols = np.nonzero(Mv)
    if np.bincount(cols, minlength=Mv.shape[1]).max() != 1:
        raise AssertionError("a Gram entry reaches more than one monomial")
    ii, jj, vv = [], [], []
    k = 0
    for mono in range(Mv.shape[0]):
        entries = cols[rows == mono]
        for e in entries[1:]:
            ii += [entries[0], e]
            jj += [k, k]
            vv += [1.0 / Mv[mono, entries[0]], -1.0 / Mv[mono, e]]
            k += 1
    return scipy.sparse.csc_matrix((vv, (ii, jj)), shape=(Mv.shape[1], k))


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
    if A_b.shape[1]:  # B minimised out: the rows of the complement of A_b's columns
        # ||P (A_s x - z)|| = ||Q2^T (A_s x - z)|| with P = Q2 Q2^T: m - m_B rows of full rank
        # where the projection P A_s kept m rows of rank m - m_B (the polish's least-norm
        # steps need full row rank)
        Q2 = scipy.linalg.qr(A_b, mode="full", check_finite=False)[0][:, A_b.shape[1]:]
        A_p, z_p = Q2.T @ A_s, Q2.T @ z
    else:
        A_p, z_p = A_s, z
    n = ng + nC
    if points is None:
        points = np.random.default_rng(0).standard_normal((r, 4 * n_g * n_g))
    # the congruence scaling G = D^-1 G' D^-1, C = E^-1 C' E^-1 (module docstring): x = s * x'
    d = _monomial_scales(A_p[:, :ng], n_g)
    iG, jG = np.triu_indices(n_g)
    s = np.ones(n)
    s[:ng] = 1.0 / (d[iG] * d[jG])
    i1, j1 = np.triu_indices(r)
    e = np.ones(r)
    if nC:
        e = _monomial_scales(A_p[:, ng:], r)
        s[ng:] = 1.0 / (e[i1] * e[j1])
    A_x = A_p * s[None, :]
    H = A_x.T @ A_x
    h = -(A_x.T @ z_p)
    moment = moment_matrix(points, r) / np.outer(d, d)  # <D^-1 M D^-1, D N D> = <M, N> = 0
    # the constraints: G' >= eps_g D^2; 2 G'_11 >= eps D_1 diag(sig^2) D_1; C' >= eps E diag(sig^2) E
    P_G = np.zeros((ng, n))
    P_G[np.arange(ng), np.arange(ng)] = 1.0
    pos = {(a, b): k for k, (a, b) in enumerate(zip(iG, jG))}
    P_K = np.zeros((len(i1), n))
    P_K[np.arange(len(i1)), [pos[(a, b)] for a, b in zip(i1, j1)]] = 2.0
    P, F = [P_G, P_K], [eps_gram * np.diag(d**2), eps * np.diag((d[:r] * sig) ** 2)]
    if damping:
        P_C = np.zeros((nC, n))
        P_C[np.arange(nC), ng + np.arange(nC)] = 1.0
        P.append(P_C)
        F.append(eps * np.diag((e * sig) ** 2))
    # the null space in the scaled unknowns (x = s x': a direction n is n / s), sparse (the
    # polish's steps) and orthonormalised (the certificate's projections)
    Z = gram_null_sparse(r)
    flat = scipy.sparse.vstack([scipy.sparse.diags(1.0 / s[:ng]) @ Z,
                                scipy.sparse.csc_matrix((nC, Z.shape[1]))]).tocsc()
    N = scipy.linalg.qr(flat.toarray(), mode="economic", check_finite=False)[0]
    problem = psd_qp.QuadraticPSD(H, h, float(z_p @ z_p), P, F, f_scale=float(z @ z), null=N,
                                  moment=moment, A=A_x, b=z_p, f_const=f_const, flat=flat)
    x0 = _start(problem, Mv, A_x, z_p, r, n_g, ng, nC)
    x, cert = psd_qp.solve(problem, x0, gap_tol=gap_tol)
    f = problem.objective(x)  # in the scaled unknowns the problem is posed in
    x = s * x
    g, c = x[:ng], x[ng:]
    G = psd_qp.unvech(g, n_g)
    pot = Mv @ g
    theta = [pot] + ([c] if damping else [])
    if A_b.shape[1]:
        b = scipy.linalg.lstsq(A_b, z - A_s @ x, check_finite=False)[0]
        theta.append(b)
    min_eig_gram = float(np.linalg.eigvalsh(G).min())  # no projection here: raw = returned
    info = {"solver": "sos-ipm", "status": cert.status, "certified": bool(cert.converged),
            "iterations": cert.iterations, "duality_gap": float(cert.duality_gap),
            "solve_seconds": time.perf_counter() - t0, "objective": f,
            # ||R theta - z|| / ||z|| of the compressed problem (B at its optimum): the excess
            # over the unconstrained optimum's residual, as Clarabel's certificate reports it
            "excess_residual": float(np.sqrt(f / max(float(z @ z), 1e-300))),
            "stopped": cert.details["stopped"], "unknowns": n, "ipm_trace": cert.details["trace"],
            "polish": cert.details["polish"],
            "min_eig_gram": min_eig_gram, "min_eig_gram_raw": min_eig_gram}
    return np.concatenate(theta), G, info


def _monomial_scales(A, n) -> np.ndarray:
    """d_i = sqrt(|column (i, i)| of A) over the vech unknowns of an n x n block (1 where the
    data do not reach it): the congruence D G D that equalises the diagonal's columns."""
    i, j = np.triu_indices(n)
    norms = np.linalg.norm(A[:, i == j], axis=0)
    ok = norms > 1e-300
    d = np.ones(n)
    d[ok] = np.sqrt(norms[ok])
    return d


def _start(problem, Mv, A_p, z_p, r, n_g, ng, nC):
    """A strictly feasible start: the least-squares fit's potential as its smallest Gram
    matrix, then G, C shifted up until every block exceeds its floor by a margin."""
    y = psd_qp.least_norm(A_p, z_p)  # full row rank (B's columns removed): LAPACK gels
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
