"""Structured least-squares solvers behind :mod:`dolfinx_lopinf.inference` (numpy only).

All solve, for an unknown Theta (r, p) whose column blocks are "symmetric PSD" (K, C) or
free (B), the compressed problem

    min_Theta  ||Theta L + Z||_F^2,     G = L L^T (p, p),  X = Z L^T (r, p)

(see :class:`~dolfinx_lopinf.inference.GramData`), so their cost never depends on the number
of snapshots K.

* :func:`solve_symmetric` - one symmetric block, no constraint: the Lyapunov equation
  G K + K G = -(X + X^T), exact through the SVD of L.
* :func:`solve_psd_single` - one symmetric block >= eps I: ADMM whose K-step is exact in
  the eigenbasis of G (robust to the 1e12 condition numbers of block-POD beam data).
* :func:`solve_symmetric_blocks` - several symmetric blocks, no definiteness: normal equations.
* :func:`solve_psd_blocks` - several symmetric blocks >= eps I: a primal-dual interior point
  method (HKM, Mehrotra) with a certified duality gap (closed-form dual bound); as fallback,
  ADMM with an exactly symmetric x-step until the optimal face shows, an exact solve on that
  face and Newton on the fixed-rank face.
* :func:`solve_ipm` - the same problem by a log-barrier interior point method with a
  duality-gap certificate (slow; the last resort).
* :func:`solve_admm` - any mix of symmetric-PSD (>= eps I) and free blocks, by ADMM on the
  splitting Theta_S = W (S = the constrained columns), W symmetric and >= eps I:

      Theta-step:  Theta (2 G + rho E) = -2 X + rho (W - Y) E      (E = 1 on constrained columns)
      W-step:      W = Pi(sym(Theta_S + Y)),  Pi = eigenvalue clipping at eps
      Y-step:      Y += Theta_S - W

  The Theta-step is r right-hand sides of one p x p system, solved by a QR of
  [sqrt(2) L^T; sqrt(rho E)] (never forming G, whose condition number is the square of the
  data's). rho is adapted by residual balancing. The certificate holds the KKT residuals:
  stationarity on free blocks, dual feasibility (the multiplier, i.e. the gradient on each
  constrained block, must be >= 0) and complementarity <multiplier, K - eps I> = 0.
"""

from __future__ import annotations

import functools
import time
import warnings

import numpy as np
import scipy.linalg


def _clip(A: np.ndarray, eps: float) -> np.ndarray:
    """Frobenius projection of sym(A) onto {S = S^T, S >= eps I}."""
    w, Q = np.linalg.eigh(0.5 * (A + A.T))
    return (Q * np.maximum(w, eps)) @ Q.T


def _lyapunov_rhs(L: np.ndarray, Z: np.ndarray):
    """SVD L = U diag(s) W^T and B = U^T (X + X^T) U with X = Z L^T, formed as
    Zt diag(s) + (Zt diag(s))^T from Zt = U^T Z W: the rounding of B in direction (i, j) is
    then ~ u ||Z|| max(s_i, s_j), not u ||Z|| s_1, so the solution in directions with small
    s (weakly determined by the data, fixed by the ridge) is not lost to rounding."""
    U, s, Wt = np.linalg.svd(L)
    Zs = (U.T @ Z @ Wt.T) * s[None, :]
    return U, s, Zs + Zs.T


def solve_symmetric(L: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """argmin over symmetric K (r, r) of ||K L + Z||_F (L is r x r): the Lyapunov solution
    G K + K G = -(X + X^T), exact in the eigenbasis of G = L L^T."""
    U, s, B = _lyapunov_rhs(L, Z)
    K = U @ (-B / (s[:, None] ** 2 + s[None, :] ** 2)) @ U.T
    return 0.5 * (K + K.T)


def eliminate_free(L: np.ndarray, Z: np.ndarray, free: np.ndarray):
    """Minimise out the free columns of Theta.

    With the columns reordered as [free, constrained] and G re-factored as L' L'^T
    (L' = [[L_FF, 0], [L_SF, L_SS]] lower triangular, Z' = Z Q from a QR of (P L)^T),

        ||Theta L + Z||^2 = ||Theta_F L_FF + Theta_S L_SF + Z'_F||^2 + ||Theta_S L_SS + Z'_S||^2,

    and the first term vanishes for Theta_F = -(Theta_S L_SF + Z'_F) L_FF^{-1}.

    Returns:
        ``(L_SS, Z'_S, recover)`` where ``recover(Theta_S)`` gives Theta_F.
    """
    free = np.asarray(free, dtype=bool)
    order = np.concatenate([np.flatnonzero(free), np.flatnonzero(~free)])
    Q, R = np.linalg.qr(L[order].T)
    Lp, Zp = R.T, Z @ Q
    nf = int(free.sum())
    L_FF, L_SF, L_SS = Lp[:nf, :nf], Lp[nf:, :nf], Lp[nf:, nf:]

    def recover(theta_S):
        rhs = theta_S @ L_SF + Zp[:, :nf]
        return -scipy.linalg.solve_triangular(L_FF.T, rhs.T, lower=False).T

    return L_SS, Zp[:, nf:], recover


def solve_psd_single(L: np.ndarray, Z: np.ndarray, eps: float, *, start=None, tol: float = 1e-10,
                     max_iter: int = 20000) -> tuple[np.ndarray, dict]:
    """min ||K L + Z||_F^2 over K = K^T >= eps I (L is r x r) by ADMM on K = W.

    K-step: (G + rho/2) K + K (G + rho/2) = rho (W - Y) - (X + X^T), diagonal in the
    eigenbasis of G = U diag(lambda) U^T, so every direction is solved exactly whatever
    the conditioning of G; W-step: eigenvalue clipping of K + Y at eps.
    """
    t0 = time.perf_counter()
    U, s, B = _lyapunov_rhs(L, Z)
    lam = s**2
    start = U @ (-B / (lam[:, None] + lam[None, :])) @ U.T if start is None else start
    Wt = U.T @ _clip(start, eps) @ U
    Yt = np.zeros_like(Wt)
    rho = float(np.sqrt(lam.max() * max(lam.min(), lam.max() * 1e-16)))
    denom = lam[:, None] + lam[None, :]
    it, prim, dual = 0, np.inf, np.inf
    for it in range(1, max_iter + 1):
        Kt = (rho * (Wt - Yt) - B) / (denom + rho)
        W_old = Wt
        Wt = U.T @ _clip(U @ (Kt + Yt) @ U.T, eps) @ U
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
    K = 0.5 * (K + K.T)
    converged = prim < tol and dual < tol
    return K, {"iterations": it, "primal_residual": float(prim), "dual_residual": float(dual),
               "rho": rho, "converged": converged, "seconds": time.perf_counter() - t0}


def kkt(L: np.ndarray, Z: np.ndarray, theta: np.ndarray, blocks: list[slice], eps: float) -> dict:
    """KKT residuals of min ||Theta L + Z||^2 s.t. Theta[:, b] = sym >= eps I for b in blocks.

    Returns relative residuals: ``stationarity`` (gradient on free columns and the
    antisymmetric part on constrained ones), ``multiplier_min_eig`` (>= 0 at optimum) and
    ``complementarity`` (0 at optimum), all divided by ||2 X||.
    """
    X = Z @ L.T
    grad = 2.0 * ((theta @ L) @ L.T + X)
    scale = max(np.linalg.norm(2.0 * X), 1e-300)
    free = np.ones(theta.shape[1], dtype=bool)
    mult_min, comp = np.inf, 0.0
    for b in blocks:
        free[b] = False
        S = 0.5 * (grad[:, b] + grad[:, b].T)  # the multiplier of the PSD constraint
        mult_min = min(mult_min, float(np.linalg.eigvalsh(S).min()))
        Kb = theta[:, b]
        comp += abs(float(np.sum(S * (Kb - eps * np.eye(Kb.shape[0])))))
    stat = np.linalg.norm(grad[:, free]) if free.any() else 0.0
    return {"stationarity": float(stat / scale),
            "multiplier_min_eig": float(mult_min / scale) if blocks else 0.0,
            "complementarity": float(comp / scale)}


def solve_admm(L: np.ndarray, Z: np.ndarray, blocks: list[slice], eps: float, *,
               start: np.ndarray | None = None, tol: float = 1e-10, max_iter: int = 50000,
               ) -> tuple[np.ndarray, dict]:
    """min ||Theta L + Z||_F^2 with Theta[:, b] symmetric >= eps I for each slice b.

    Args:
        L: (p, p) factor of the Gram matrix, G = L L^T.
        Z: (r, p) data term.
        blocks: column slices of Theta that must be symmetric >= eps I (each r wide).
        eps: eigenvalue floor.
        start: optional (r, p) initial guess.
        tol: relative primal and dual residual at which to stop.

    Returns:
        ``(Theta, info)`` with iterations, residuals, seconds and the KKT residuals.
    """
    t0 = time.perf_counter()
    r, p = Z.shape
    mask = np.zeros(p, dtype=bool)
    for b in blocks:
        mask[b] = True
    X = Z @ L.T
    if start is None:
        # unconstrained least squares, then projected: a good warm start
        start = -scipy.linalg.lstsq(L.T, Z.T)[0].T
    theta = start.copy()
    W = np.zeros((r, p))
    for b in blocks:
        W[:, b] = _clip(theta[:, b], eps)
    Y = np.zeros((r, p))
    # rho of the size of the data curvature on the constrained columns
    gdiag = np.sum(L[mask] ** 2, axis=1) if mask.any() else np.ones(1)
    rho = float(2.0 * np.sqrt(gdiag.max() * gdiag.min())) if mask.any() else 1.0

    def factor(rho):
        A = np.vstack([np.sqrt(2.0) * L.T, np.diag(np.sqrt(rho) * mask.astype(float))])
        return np.linalg.qr(A, mode="r")  # R^T R = 2 G + rho E

    R = factor(rho)
    it, prim, dual = 0, np.inf, np.inf
    for it in range(1, max_iter + 1):
        rhs = -2.0 * X + rho * (W - Y) * mask
        # Theta R^T R = rhs  ->  solve R^T R Theta^T = rhs^T
        theta = scipy.linalg.cho_solve((R, False), rhs.T).T
        W_old = W.copy()
        for b in blocks:
            W[:, b] = _clip(theta[:, b] + Y[:, b], eps)
        Y[:, mask] += theta[:, mask] - W[:, mask]
        nt, nw = np.linalg.norm(theta[:, mask]), np.linalg.norm(W[:, mask])
        prim = np.linalg.norm(theta[:, mask] - W[:, mask]) / max(nt, nw, 1e-300)
        # dual residual rho ||W - W_old||, relative to the larger of rho ||Y|| and rho ||W||
        # (||Y|| alone -> 0 when the constraints are inactive and would never be met)
        dual = np.linalg.norm(W[:, mask] - W_old[:, mask]) / max(np.linalg.norm(Y[:, mask]), nw, 1e-300)
        if prim < tol and dual < tol:
            break
        if it % 20 == 0:  # residual balancing (Boyd et al. 2011, s. 3.4.1)
            if prim > 10 * dual:
                rho, Y = 2.0 * rho, Y / 2.0
                R = factor(rho)
            elif dual > 10 * prim:
                rho, Y = rho / 2.0, Y * 2.0
                R = factor(rho)
    # return the feasible iterate: constrained blocks from W, free blocks re-solved exactly
    result = theta.copy()
    result[:, mask] = W[:, mask]
    if (~mask).any() and mask.any():
        # free columns: min over Theta_F of ||Theta_F L_F + (Theta_S L_S + Z)||, L_F = rows of L
        rest = result[:, mask] @ L[mask] + Z
        result[:, ~mask] = -scipy.linalg.lstsq(L[~mask].T, rest.T)[0].T
    converged = prim < tol and dual < tol
    info = {"iterations": it, "primal_residual": float(prim), "dual_residual": float(dual),
            "rho": rho, "converged": converged, "seconds": time.perf_counter() - t0}
    info.update(kkt(L, Z, result, blocks, eps))
    if not converged:
        warnings.warn(f"ADMM stopped after {it} iterations (relative primal {prim:.2e}, dual "
                      f"{dual:.2e}); see the certificate's KKT residuals", RuntimeWarning,
                      stacklevel=3)
    return result, info


# -- interior point method for several symmetric PSD blocks ----------------------------------

@functools.lru_cache(maxsize=32)
def _vech_terms(r: int, n_blocks: int):
    """Index arrays of the symmetric basis of Theta = [S_1 .. S_b] (each S_k = S_k^T, r x r).

    Variable a = (block k, i <= j) has basis matrix e_i f_{kr+j}^T + e_j f_{kr+i}^T (one term
    when i = j). Returns rows[s], cols[s], local cols lcols[s] and masks[s] for the two terms.
    """
    i, j = np.triu_indices(r)
    k = np.repeat(np.arange(n_blocks), len(i))
    i, j = np.tile(i, n_blocks), np.tile(j, n_blocks)
    rows = [i, j]
    cols = [k * r + j, k * r + i]
    lcols = [j, i]
    masks = [np.ones(len(i)), (i != j).astype(float)]
    return rows, cols, lcols, masks, k


def _theta_from_x(x, r, n_blocks, terms):
    rows, cols, _, masks, _ = terms
    theta = np.zeros((r, n_blocks * r))
    theta[rows[0], cols[0]] = x
    theta[rows[1], cols[1]] = x  # same entries for i == j (mask 0 there): harmless overwrite
    return theta


def solve_symmetric_blocks(L: np.ndarray, Z: np.ndarray, n_blocks: int) -> np.ndarray:
    """argmin ||Theta L + Z||_F over Theta = [S_1 .. S_b] with symmetric S_k (no definiteness):
    the normal equations H x = -h in the b r (r+1)/2 upper-triangular unknowns."""
    r = Z.shape[0]
    terms = _vech_terms(r, n_blocks)
    H, h = symmetric_normal_equations(L, Z, n_blocks)
    # Jacobi equilibration: K and C entries multiply data of very different size (Qh, dQh)
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    Hs = H / np.outer(d, d)
    try:
        y = -scipy.linalg.cho_solve(scipy.linalg.cho_factor(Hs, check_finite=False), h / d,
                                    check_finite=False)
    except np.linalg.LinAlgError:
        y = -np.linalg.lstsq(Hs, h / d, rcond=None)[0]
    return _theta_from_x(y / d, r, n_blocks, terms)


def solve_ipm(L: np.ndarray, Z: np.ndarray, n_blocks: int, eps: float, *, gap_tol: float = 1e-10,
              max_newton: int = 200) -> tuple[np.ndarray, dict]:
    """min ||Theta L + Z||_F^2, Theta = [S_1 .. S_b], S_k = S_k^T >= eps I, by a log-barrier
    interior point method (Newton on t f(x) - sum_k logdet(S_k - eps I), t increased x20).

    Variables are the b r (r+1)/2 upper-triangular entries; Hessians are assembled from
    index arrays (no Kronecker products). The duality gap of the returned point is at most
    b r / t (reported relative to f); the dual certificate is Lambda_k = (S_k - eps I)^-1 / t.
    """
    t0 = time.perf_counter()
    r = Z.shape[0]
    terms = _vech_terms(r, n_blocks)
    rows, cols, lcols, masks, blk = terms
    const = float(np.sum(Z**2))
    H, h = symmetric_normal_equations(L, Z, n_blocks)

    def f(x):
        return float(x @ H @ x + 2 * h @ x + const)

    def blocks_of(x):
        theta = _theta_from_x(x, r, n_blocks, terms)
        return [theta[:, k * r:(k + 1) * r] - eps * np.eye(r) for k in range(n_blocks)]

    # feasible start: unconstrained symmetric minimiser with eigenvalues lifted above eps
    try:
        x = -scipy.linalg.solve(H, h, assume_a="sym")
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgWarning):
        x = -np.linalg.lstsq(H, h, rcond=None)[0]
    S = blocks_of(x)
    scale = max(max(np.abs(np.linalg.eigvalsh(Sk)).max() for Sk in S), 1e-12)
    lifted = [_clip(Sk + eps * np.eye(r), eps + 1e-3 * scale) for Sk in S]
    x = np.concatenate([Sk[np.triu_indices(r)] for Sk in lifted])
    m = n_blocks * r
    t = m / max(abs(f(x)), 1e-300) * 10.0
    newton = 0
    gap = np.inf
    while newton < max_newton:
        # centring: Newton on F(x) = t f(x) + phi(x)
        for _ in range(30):
            S = blocks_of(x)
            Sinv = [np.linalg.inv(Sk) for Sk in S]
            g_phi = np.zeros_like(x)
            H_phi = np.zeros_like(H)
            for k, Si in enumerate(Sinv):
                sel = blk == k
                idx = np.flatnonzero(sel)
                ri, cj = rows[0][sel], lcols[0][sel]
                g_phi[idx] = -Si[ri, cj] * (1.0 + masks[1][sel])
                block = np.zeros((len(idx), len(idx)))
                for s in range(2):
                    us, vs = (rows[s][sel], lcols[s][sel])
                    for tt in range(2):
                        ut, vt = (rows[tt][sel], lcols[tt][sel])
                        block += (masks[s][sel][:, None] * masks[tt][sel][None, :]
                                  * Si[np.ix_(vs, ut)] * Si[np.ix_(us, vt)])
                H_phi[np.ix_(idx, idx)] = block
            grad = t * 2.0 * (H @ x + h) + g_phi
            hess = t * 2.0 * H + H_phi
            try:
                dx = -scipy.linalg.cho_solve(scipy.linalg.cho_factor(hess), grad)
            except np.linalg.LinAlgError:
                dx = -np.linalg.lstsq(hess, grad, rcond=None)[0]
            decrement = float(-grad @ dx)
            newton += 1
            if decrement / 2.0 < 1e-9:
                break
            step, F0 = 1.0, t * f(x) - sum(np.linalg.slogdet(Sk)[1] for Sk in S)
            while step > 1e-12:
                xn = x + step * dx
                Sn = blocks_of(xn)
                if all(np.linalg.eigvalsh(Sk).min() > 0 for Sk in Sn):
                    Fn = t * f(xn) - sum(np.linalg.slogdet(Sk)[1] for Sk in Sn)
                    if Fn <= F0 - 0.25 * step * decrement:
                        break
                step *= 0.5
            x = xn
        gap = m / t
        if gap <= gap_tol * max(f(x), 1e-300):
            break
        t *= 20.0
    theta = _theta_from_x(x, r, n_blocks, terms)
    info = {"iterations": newton, "duality_gap": float(gap / max(f(x), 1e-300)),
            "converged": bool(gap <= gap_tol * max(f(x), 1e-300)),
            "seconds": time.perf_counter() - t0}
    return theta, info


# -- several symmetric PSD blocks: ADMM to the face, then an exact solve on it ---------------

@functools.lru_cache(maxsize=32)
def _sym_index(r: int, n_blocks: int):
    """Index arrays of the vech unknowns x of Theta = [S_1 .. S_b] (S_k = S_k^T, r x r).

    Unknown a = (k, i <= j) sits at Theta[i, k r + j] and, when i != j, also at
    Theta[j, k r + i]. Returns ``(iu, full, rows0, cols0, rows1, cols1, offdiag, blk)``:
    ``full[i, j]`` is the vech position of (i, j) within a block, ``offdiag`` masks the
    second position, ``blk`` is the block of each unknown.
    """
    iu = np.triu_indices(r)
    nv = len(iu[0])
    full = np.zeros((r, r), dtype=np.intp)
    full[iu] = np.arange(nv)
    full = np.triu(full) + np.triu(full, 1).T
    blk = np.repeat(np.arange(n_blocks), nv)
    i, j = np.tile(iu[0], n_blocks), np.tile(iu[1], n_blocks)
    out = (iu, full, i, blk * r + j, j, blk * r + i, (i != j).astype(float), blk)
    for arr in (*iu, *out[1:]):
        arr.setflags(write=False)
    return out


def symmetric_normal_equations(L: np.ndarray, Z: np.ndarray, n_blocks: int):
    """H, h with ||Theta(x) L + Z||_F^2 = x^T H x + 2 h^T x + ||Z||_F^2 in the vech unknowns.

    Row i of Theta is E_i x, E_i selecting (S_1[i, :], .., S_b[i, :]) from x, so
    H = sum_i E_i^T G E_i and h = sum_i E_i^T X[i] with G = L L^T, X = Z L^T: r scatters of
    the p x p matrix G - O(r p^2) work.
    """
    r, p = Z.shape
    dest_H, dest_h = _normal_equation_index(r, n_blocks)
    G, X = L @ L.T, Z @ L.T
    n = n_blocks * r * (r + 1) // 2
    H = np.bincount(dest_H, weights=np.broadcast_to(G.ravel(), (r, p * p)).ravel(), minlength=n * n)
    h = np.bincount(dest_h, weights=X.ravel(), minlength=n)
    return H.reshape(n, n), h


@functools.lru_cache(maxsize=32)
def _normal_equation_index(r: int, n_blocks: int):
    """Flat destinations in H (n x n) of G's entries for every row i of Theta (E_i^T G E_i),
    and in h of X[i]'s entries: the r scatters of :func:`symmetric_normal_equations` as one
    ``bincount``."""
    _, full, *_ = _sym_index(r, n_blocks)
    nv = r * (r + 1) // 2
    n = n_blocks * nv
    idx = (full[:, None, :] + nv * np.arange(n_blocks)[None, :, None]).reshape(r, -1)  # (r, p)
    dest_H = (idx[:, :, None] * n + idx[:, None, :]).ravel()
    dest_h = idx.ravel()
    for arr in (dest_H, dest_h):
        arr.setflags(write=False)
    return dest_H, dest_h


class _SPDSolver:
    """Jacobi-equilibrated Cholesky of an SPD matrix H (the K and C unknowns multiply data of
    very different size), reused for every solve; ``ok`` is False when H is singular."""

    def __init__(self, H: np.ndarray):
        self.d = np.sqrt(np.maximum(np.diag(H), 1e-300))
        self.Hs = H / np.outer(self.d, self.d)
        # lower Cholesky of the F-ordered view of the symmetric Hs (no copy, faster than upper)
        self.c, status = scipy.linalg.lapack.dpotrf(self.Hs.T, lower=1, clean=0)
        self.ok = status == 0

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        d = self.d if rhs.ndim == 1 else self.d[:, None]
        if self.ok:
            return scipy.linalg.lapack.dpotrs(self.c, rhs / d, lower=1)[0] / d
        return np.linalg.lstsq(self.Hs, rhs / d, rcond=None)[0] / d


def _equilibrated_solve(H: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    return _SPDSolver(H).solve(rhs)


@functools.lru_cache(maxsize=32)
def _hkm_index(r: int):
    """Upper-triangle pairs (p <= q) of vech pairs p = (i, j), q = (k, l) (i <= j, k <= l): flat
    positions in an r x r matrix of (i, k), (j, l), (i, l), (j, k), the weights c_p c_q (c = 1/2
    on the diagonal) and the pair's flat position p nv + q in an nv x nv matrix."""
    i, j = np.triu_indices(r)
    nv = len(i)
    p, q = np.triu_indices(nv)
    c = np.where(i == j, 0.5, 1.0)
    out = (i[p] * r + i[q], j[p] * r + j[q], i[p] * r + j[q], j[p] * r + i[q], c[p] * c[q], p, q)
    for arr in out:
        arr.setflags(write=False)
    return out


def _hkm_upper(Xi: np.ndarray, Lam: np.ndarray) -> np.ndarray:
    """Upper triangle (in ``_hkm_index`` order) of M_k with M_k dx = D vech(sym(X_k^-1 dX Lambda_k))
    for every block k, in vech coordinates (D: 2 off the diagonal):
    M[(i,j),(k,l)] = c_ij c_kl (Xi_ik L_jl + Xi_il L_jk + L_ik Xi_jl + L_il Xi_jk), symmetric,
    so only the triangle Cholesky reads is formed: eight gathers from the r x r matrices."""
    ik, jl, il, jk, cc, _, _ = _hkm_index(Xi.shape[1])
    Xf, Lf = Xi.reshape(len(Xi), -1), Lam.reshape(len(Lam), -1)
    M = np.take(Xf, ik, axis=1) * np.take(Lf, jl, axis=1)
    M += np.take(Xf, il, axis=1) * np.take(Lf, jk, axis=1)
    M += np.take(Lf, ik, axis=1) * np.take(Xf, jl, axis=1)
    M += np.take(Lf, il, axis=1) * np.take(Xf, jk, axis=1)
    M *= cc
    return M


def _max_step(P_isqrt: np.ndarray, *dP: np.ndarray) -> float:
    """Largest a <= 1 with P_k + a dP_k >= 0 for all blocks, from the stacked P_k^-1/2:
    1 / max(0, -min_k lambda_min(P_k^-1/2 dP_k P_k^-1/2)) - one batched ``eigvalsh``."""
    ev = np.linalg.eigvalsh(P_isqrt @ np.concatenate(dP) @ P_isqrt).min()
    return 1.0 if ev >= 0 else min(1.0, -1.0 / ev)


STEP_FRACTION = 0.98


def _primal_dual_ipm(H, h, const, r, n_blocks, eps, x_start, *, certify, gap_tol, max_iter=40,
                     watch=None):
    """min x^T H x + 2 h^T x  s.t.  X_k(x) = S_k(x) - eps I >= 0  by a primal-dual interior point
    method: HKM direction, Mehrotra predictor-corrector, one Cholesky per iteration.

    Optimality: grad f(x) = D vech(Lambda) (D: 2 off the diagonal), X_k Lambda_k = mu I.
    Newton on it with Lambda eliminated, dLambda = sym(X^-1 (R - dX Lambda)), gives
    (2 H + sum_k D (X_k^-1 (x)_s Lambda_k)) dx = -(grad f - D vech Lambda) + D vech sym(X^-1 R)
    - the Schur matrix; R = sigma mu I - X Lambda (- dX_aff dLambda_aff in the corrector).
    Each block is first scaled by a congruence X_k = D_k X'_k D_k (D_k^4 = diag of H on the
    block's diagonal entries), which keeps the cone and balances K against C. x stays
    strictly feasible and Lambda PSD, so ``certify(x, Lambda)`` (the closed-form dual bound,
    Lambda mapped back to the unscaled blocks) is a proof of the gap;
    the loop ends when that certified relative gap is <= ``gap_tol``. ``watch(x, m mu / f)``,
    if given, is called after every iteration and ends the loop when it returns False.
    """
    iu, full, *_, off, _ = _sym_index(r, n_blocks)
    nv = len(iu[0])
    Dw = 1.0 + off
    eye = np.eye(r)
    x_eps = np.tile(eps * (1.0 - off[:nv]), n_blocks)
    dg = np.diag(H).reshape(n_blocks, nv)[:, iu[0] == iu[1]]
    dsc = np.maximum(dg, 1e-300) ** -0.25
    T = (dsc[:, iu[0]] * dsc[:, iu[1]]).reshape(-1)
    Hs = T[:, None] * H * T[None, :]
    hs = T * (H @ x_eps + h)
    H2 = 2.0 * Hs
    Ms = H2.copy()  # the Schur matrix: its diagonal blocks' upper triangles change every iteration
    Ms_flat, H2_flat = Ms.reshape(-1), H2.reshape(-1)
    _, _, _, _, _, tp, tq = _hkm_index(r)
    diag_pos = [(k * nv + tp) * (n_blocks * nv) + k * nv + tq for k in range(n_blocks)]

    def blocks(v):
        return v.reshape(n_blocks, nv)[:, full]

    def vech(S):
        return S[:, iu[0], iu[1]].reshape(-1)

    c0 = float(x_eps @ (H @ x_eps) + 2.0 * h @ x_eps + const)

    def f(v):  # the objective in the scaled unknowns (const = ||Z||^2; a stopping guide only)
        return float(v @ (Hs @ v) + 2.0 * hs @ v + c0)

    w, Q = np.linalg.eigh(blocks((x_start - x_eps) / T))
    floor = 1e-3 * np.abs(w).max(axis=1, keepdims=True)
    X = (Q * np.maximum(np.abs(w), floor)[:, None, :]) @ Q.transpose(0, 2, 1)
    x = vech(X)
    m = n_blocks * r
    f_ref = max(abs(f(x)), 1e-300)
    Lam = np.linalg.inv(X) * (0.1 * f_ref / m)
    info = {"iterations": 0, "converged": False, "duality_gap": np.inf, "face_multiplier_min": -np.inf}
    for it in range(1, max_iter + 1):
        info["iterations"] = it
        wX, VX = np.linalg.eigh(X)  # X^-1 through the eigenbasis: PD however wide X's spread
        if wX.min() <= 0:
            info["stopped"] = f"iterate not positive definite at iteration {it}"
            break
        Xi = (VX / wX[:, None, :]) @ VX.transpose(0, 2, 1)
        grad = 2.0 * (Hs @ x + hs)
        rd = grad - Dw * vech(Lam)
        mu = float(np.sum(X * Lam)) / m
        hkm = _hkm_upper(Xi, Lam)
        for k in range(n_blocks):  # the diagonal blocks' upper triangles; the rest stays 2 H
            Ms_flat[diag_pos[k]] = H2_flat[diag_pos[k]] + hkm[k]
        # lower Cholesky of the F-ordered view Ms^T (its lower triangle is Ms's upper one, the
        # part written above), 20 % faster than the upper one; no diagonal scaling is needed
        # (Cholesky's accuracy does not depend on one)
        c, status = scipy.linalg.lapack.dpotrf(Ms.T, lower=1, clean=0)
        for shift in (1e-12, 1e-10, 1e-8):  # rounding as mu -> 0: a small relative shift
            if status == 0:
                break
            Mshift = Ms.T.copy(order="F")
            Mshift[np.diag_indices(len(Ms))] *= 1.0 + shift
            c, status = scipy.linalg.lapack.dpotrf(Mshift, lower=1, clean=0, overwrite_a=1)
        if status != 0:
            info["stopped"] = f"Schur matrix not positive definite at iteration {it}, mu {mu:.1e}, f {f(x):.3e}"
            break

        def direction(R):
            XiR = Xi @ R
            rhs = -rd + Dw * vech(0.5 * (XiR + XiR.transpose(0, 2, 1)))
            dx = scipy.linalg.lapack.dpotrs(c, rhs, lower=1)[0]
            dX = blocks(dx)
            Tm = XiR - Xi @ dX @ Lam
            return dx, dX, 0.5 * (Tm + Tm.transpose(0, 2, 1))

        XL = X @ Lam
        try:
            wL, VL = np.linalg.eigh(Lam)
            if wL.min() <= 0:
                raise np.linalg.LinAlgError("multiplier not positive definite")
            V = np.concatenate([VX, VL])  # (X_k, Lambda_k)^-1/2 stacked for the step lengths
            P_is = (V / np.sqrt(np.concatenate([wX, wL]))[:, None, :]) @ V.transpose(0, 2, 1)
            dx, dX, dL = direction(-XL)                                   # predictor (mu -> 0)
            a = _max_step(P_is, dX, dL)
            mu_aff = float(np.sum((X + a * dX) * (Lam + a * dL))) / m
            sigma = (mu_aff / mu) ** 3
            dx, dX, dL = direction(sigma * mu * eye - XL - dX @ dL)        # corrector
            a = min(1.0, STEP_FRACTION * _max_step(P_is, dX, dL))
        except np.linalg.LinAlgError:  # X or Lambda lost definiteness to rounding
            info["stopped"] = f"iterate not positive definite at iteration {it}"
            break
        x = x + a * dx
        X, Lam = blocks(x), Lam + a * dL
        mu = float(np.sum(X * Lam)) / m
        f_ref = max(abs(f(x)), 1e-300)
        info.setdefault("trace", []).append((a, sigma, m * mu / f_ref))
        if watch is not None and not watch(x_eps + T * x, m * mu / f_ref):
            info["stopped"] = "stopped by watch"
            break
        if m * mu <= gap_tol * f_ref or a < 1e-3:
            gap, lam_min = certify(x_eps + T * x, Lam / (dsc[:, :, None] * dsc[:, None, :]))
            if not np.isfinite(gap):
                info["stopped"] = "no certificate for this point"
                break
            info.update(duality_gap=gap, face_multiplier_min=lam_min)
            if gap <= gap_tol:
                info["converged"] = True
                break
            if a < 1e-3:
                info["stopped"] = "step length below 1e-3"
                break
    # rank of each X_k at the solution: the eigen-directions where X exceeds Lambda (their
    # product is ~mu, strict complementarity sends one of them to 0; the scaling makes the
    # two comparable: Lambda ~ grad f ~ H' x')
    wX, VX = np.linalg.eigh(X)
    wL = np.einsum("kia,kij,kja->ka", VX, Lam, VX)
    info.update(mu=mu, ranks=[int(v) for v in (wX > wL).sum(axis=1)])
    return x_eps + T * x, info


def solve_psd_blocks(L: np.ndarray, Z: np.ndarray, n_blocks: int, eps: float, *,
                     gap_tol: float = 1e-8, kkt_tol: float = 1e-9, admm_tol: float = 1e-4,
                     max_iter: int = 5000, memory: int = 8, rho0: float = 0.3,
                     method: str = "auto", ipm_max_iter: int = 40,
                     eliminate: bool = True) -> tuple[np.ndarray, dict]:
    """min f(Theta) = ||Theta L + Z||_F^2 over Theta = [S_1 .. S_b], S_k = S_k^T >= eps I.

    In the vech unknowns x, f = x^T H x + 2 h^T x + ||Z||^2 (:func:`symmetric_normal_equations`).

    1. The symmetric minimiser H x = -h; if every block is >= eps I it is the answer.
    2. ``method="auto"``: a primal-dual interior point method (:func:`_primal_dual_ipm`,
       7-10 iterations of one Cholesky each) until the certificate of step 5 proves the
       gap. With ``eliminate`` it is first tried on the blocks whose symmetric minimiser is
       not >= eps I only, the others minimised out exactly (``ipm_on_active_blocks``; the
       common case of a well-determined stiffness and a weakly determined damping: a Schur
       matrix of half the size); kept only when the recovered blocks are >= eps I and the
       full problem's certificate holds. If no certificate (or ``method="admm"``), steps 3-5:
    3. ADMM on x = w (w in the cone), Anderson-accelerated (type II, safeguarded): x-step
       (2 H + rho D) x = -2 h + rho D (w - y) (R^-1 of one Cholesky per rho), w-step
       eigenvalue clipping of every block (one batched ``eigh``), rho by residual balancing.
    4. Once ADMM's residuals are below ``admm_tol`` its clipping shows the face,
       S_k = eps I + P_k A_k P_k^T (P_k: eigenvectors kept above eps, rank m_k). Polish: f
       minimised exactly over the A_k with the P_k fixed (normal equations T^T H T).
       Then Newton on the fixed-rank faces (see ``newton_on_face``), which also turns the
       P_k: quadratic convergence once the ranks are right, one Cholesky per step.
    5. Certificate: the point is feasible and the projected multipliers
       Lambda_k = [grad_{S_k} f]_+ >= 0 give the dual bound
       g(Lambda) = min_x f(x) - sum_k <Lambda_k, S_k(x) - eps I> <= f*, in closed form with
       the Cholesky of H. Accepted when (f - g) / f <= ``gap_tol`` (a proof of optimality to
       that relative accuracy) - or, only when H is singular and the bound unavailable, when
       the multipliers are >= -``kkt_tol``; otherwise ADMM goes on with a 10x tighter target.

    Returns ``(Theta, info)``: iterations, polish attempts, face ranks (rank of S_k - eps I),
    ``duality_gap`` (relative, certified), residuals and seconds; ``info["ipm"]["trace"]``
    lists (step, centring sigma, m mu / f) of every interior point iteration.
    """
    if method not in ("auto", "admm"):
        raise ValueError(f"method must be 'auto' (interior point, ADMM as fallback) or 'admm', "
                         f"not {method!r}")
    t0 = time.perf_counter()
    r = Z.shape[0]
    iu, full, _, _, _, _, off, blk = _sym_index(r, n_blocks)
    nv = len(iu[0])
    n = n_blocks * nv
    H, h = symmetric_normal_equations(L, Z, n_blocks)
    Dw = 1.0 + off
    scale_g = max(2.0 * float(np.linalg.norm(Z @ L.T)), 1e-300)
    x_eps = np.tile(eps * (1.0 - off[:nv]), n_blocks)
    terms = _vech_terms(r, n_blocks)

    def blocks(v):
        return v.reshape(n_blocks, nv)[:, full]

    def vech(S):
        return S[:, iu[0], iu[1]].reshape(-1)

    chol = _SPDSolver(H)
    x = -chol.solve(h)
    info = {"iterations": 0, "polish_attempts": 0}
    feasible = np.linalg.eigvalsh(blocks(x))[:, 0] >= eps  # per block: its minimiser is >= eps I
    if feasible.all():
        info.update(converged=True, method="symmetric-lsq", face_ranks=[r] * n_blocks,
                    duality_gap=0.0, seconds=time.perf_counter() - t0)
        return _theta_from_x(x, r, n_blocks, terms), info

    def dual_gap(x, lam=None):
        """Certified relative gap (f(x) - g(Lambda)) / f(x) of a feasible x, and the smallest
        eigenvalue of grad_S f(x) (relative to ||2 X||).

        For any Lambda >= 0, L(x') = f(x') - <Lambda, S(x') - eps I> has the minimiser x_s with
        f(x) - g(Lambda) = (x - x_s)^T H (x - x_s) + <Lambda, S(x) - eps I>,
        x - x_s = H^-1 v / 2, v = grad f(x) - D vech(Lambda): two nonnegative terms, no
        cancellation. Lambda is the PSD part of grad_S f(x) and, when given, also ``lam``
        (the interior point's multipliers); the smaller gap is a proof for both.
        """
        grad = 2.0 * (H @ x + h)
        lam_w, lam_Q = np.linalg.eigh(blocks(grad / Dw))
        slack = blocks(x) - eps * np.eye(r)
        gaps = []
        for lam_k in [(lam_Q * np.maximum(lam_w, 0.0)[:, None, :]) @ lam_Q.transpose(0, 2, 1)] + \
                ([] if lam is None else [lam]):
            v = grad - Dw * vech(lam_k)
            gaps.append(0.25 * float(v @ chol.solve(v)) + float(np.sum(lam_k * slack)))
        fx = float(np.sum((_theta_from_x(x, r, n_blocks, terms) @ L + Z) ** 2))
        return max(min(gaps), 0.0) / max(fx, 1e-300), float(lam_w.min()) / scale_g

    def polish(w, Q):
        """Exact minimiser of f on the face {S_k = eps I + P_k A_k P_k^T}."""
        T_cols, HT_cols = [], []
        for k in range(n_blocks):
            P = Q[k][:, w[k] > eps]
            if P.shape[1] == r:  # the whole cone: S_k = eps I + A_k, A_k in vech coordinates
                T_cols.append(None)
                HT_cols.append(H[:, k * nv:(k + 1) * nv])
                continue
            a, b = np.triu_indices(P.shape[1])
            Pi, Pj = P[iu[0]], P[iu[1]]
            Tk = Pi[:, a] * Pj[:, b] + (a != b) * Pi[:, b] * Pj[:, a]   # vech(P E_ab P^T)
            T_cols.append(Tk)
            HT_cols.append(H[:, k * nv:(k + 1) * nv] @ Tk)
        HT = np.hstack(HT_cols)
        g0 = H @ x_eps + h

        def tr(k, M):  # T_k^T M
            return M if T_cols[k] is None else T_cols[k].T @ M
        Hr = np.vstack([tr(k, HT[k * nv:(k + 1) * nv]) for k in range(n_blocks)])
        hr = np.concatenate([tr(k, g0[k * nv:(k + 1) * nv]) for k in range(n_blocks)])
        coef = -_equilibrated_solve(0.5 * (Hr + Hr.T), hr)
        xp, start, a_min = x_eps.copy(), 0, np.inf
        for k in range(n_blocks):
            if T_cols[k] is None:  # A_k = S_k - eps I directly
                m = nv
                xp[k * nv:(k + 1) * nv] += coef[start:start + m]
                A = blocks(np.tile(coef[start:start + m], n_blocks))[0]
            else:
                m = T_cols[k].shape[1]
                xp[k * nv:(k + 1) * nv] += T_cols[k] @ coef[start:start + m]
                rank = int((w[k] > eps).sum())
                A = np.zeros((rank, rank))
                ia, ib = np.triu_indices(rank)
                A[ia, ib] = A[ib, ia] = coef[start:start + m]
            if A.size:
                a_min = min(a_min, float(np.linalg.eigvalsh(A).min() / max(np.abs(A).max(), 1e-300)))
            start += m
        return xp, a_min

    def objective(x):
        return float(np.sum((_theta_from_x(x, r, n_blocks, terms) @ L + Z) ** 2))

    def newton_on_face(x, ranks, max_steps=10):
        """Newton's method on the fixed-rank faces {S_k = eps I + X_k, rank X_k = m_k, X_k >= 0}.

        Chart at X = P A P^T (N spans the complement): X(dA, dB) = W (A + dA) W^T with
        W = P + N dB (A + dA)^-1, which is PSD of rank m whenever A + dA > 0. To second order
        dS = P dA P^T + N dB P^T + P dB^T N^T + N dB A^-1 dB^T N^T, so the quadratic model is
        f + g^T d + d^T (J^T H J) d + sum_k tr([N^T Lambda_k N]_+ dB A^-1 dB^T) (J: d -> vech(dS)
        to first order, Lambda_k = grad_{S_k} f, []_+ the PSD part). Each step: one Cholesky of that model's
        Hessian, a backtracking line search on f; quadratic convergence once the ranks are
        right (they come from ADMM), so the subspaces ADMM only knows to ~admm_tol are
        corrected exactly. Returns (x, relative certified gap), or None if a step fails or the
        face optimum is reached without a certificate (the ranks were wrong).
        """
        fx = objective(x)
        gap = np.inf
        for _ in range(max_steps):
            info["newton_steps"] = info.get("newton_steps", 0) + 1
            S = blocks(x) - eps * np.eye(r)
            grad_x = 2.0 * (H @ x + h)
            Lam = blocks(grad_x / Dw)
            charts, J_cols = [], []
            for k in range(n_blocks):
                w, Q = np.linalg.eigh(S[k])
                m = ranks[k]
                P, N = Q[:, r - m:], Q[:, :r - m]
                A = np.diag(w[r - m:])
                if m and w[r - m] <= 0:
                    return None
                if m == r:  # interior of the cone: S_k itself is the chart (J_k = identity)
                    charts.append((P, N, A, nv))
                    J_cols.append(None)
                    continue
                a, b = np.triu_indices(m)
                Pi, Pj, Ni, Nj = P[iu[0]], P[iu[1]], N[iu[0]], N[iu[1]]
                JA = Pi[:, a] * Pj[:, b] + (a != b) * Pi[:, b] * Pj[:, a]      # vech(P E_ab P^T)
                JB = (Ni[:, None, :] * Pj[:, :, None] + Pi[:, :, None] * Nj[:, None, :])
                JB = JB.reshape(nv, -1)                                         # (a, c) a-major
                charts.append((P, N, A, len(a)))
                J_cols.append(np.hstack([JA, JB]))
            dims = [nv if Jk is None else Jk.shape[1] for Jk in J_cols]
            starts = np.concatenate([[0], np.cumsum(dims)])

            def jt(k, Mat):  # J_k^T Mat
                return Mat if J_cols[k] is None else J_cols[k].T @ Mat
            HJ = np.hstack([H[:, k * nv:(k + 1) * nv] if J_cols[k] is None
                            else H[:, k * nv:(k + 1) * nv] @ J_cols[k] for k in range(n_blocks)])
            M = np.vstack([jt(k, HJ[k * nv:(k + 1) * nv]) for k in range(n_blocks)])
            g_d = np.concatenate([jt(k, grad_x[k * nv:(k + 1) * nv]) for k in range(n_blocks)])
            for k, (P, N, A, nA) in enumerate(charts):
                if N.shape[1] and P.shape[1]:
                    # PSD part of N^T Lambda N: equal to it at the optimum (Lambda >= 0 there),
                    # and keeps the model convex (a descent direction) far from it
                    lw, lV = np.linalg.eigh(N.T @ Lam[k] @ N)
                    lam_nn = (lV * np.maximum(lw, 0.0)) @ lV.T
                    sl = slice(starts[k] + nA, starts[k + 1])
                    M[sl, sl] += np.kron(np.diag(1.0 / np.diag(A)), lam_nn)
            M = 0.5 * (M + M.T)
            solver = _SPDSolver(M)
            if not solver.ok:
                return None
            d = -0.5 * solver.solve(g_d)
            decrease = -0.5 * float(g_d @ d)  # predicted decrease of the model: -(g d + d M d)
            step = 1.0
            while step > 0.1:  # a heavily damped step: far from the face optimum, back to ADMM
                x_new = x_eps.copy()
                ok = True
                for k, (P, N, A, nA) in enumerate(charts):
                    dk = step * d[starts[k]:starts[k + 1]]
                    m = P.shape[1]
                    if m == 0:
                        continue
                    if J_cols[k] is None:  # interior chart: S_k + dS_k must stay > eps I
                        x_new[k * nv:(k + 1) * nv] = x[k * nv:(k + 1) * nv] + dk
                        if np.linalg.eigvalsh(blocks(x_new)[k]).min() <= eps:
                            ok = False
                            break
                        continue
                    dA = np.zeros((m, m))
                    ia, ib = np.triu_indices(m)
                    dA[ia, ib] = dA[ib, ia] = dk[:nA]
                    A_new = A + dA
                    try:
                        cA = scipy.linalg.cho_factor(A_new, check_finite=False)
                    except np.linalg.LinAlgError:
                        ok = False
                        break
                    dB = dk[nA:].reshape(m, -1).T                                # (r - m, m)
                    W = P + N @ scipy.linalg.cho_solve(cA, dB.T, check_finite=False).T
                    Xk = W @ A_new @ W.T
                    x_new[k * nv:(k + 1) * nv] += Xk[iu]
                if ok:
                    dx = x_new - x  # f(x + dx) - f(x) exactly, free of the cancellation in f
                    change = float((grad_x + H @ dx) @ dx)
                    if change <= -1e-4 * step * max(decrease, 0.0):
                        break
                step *= 0.5
            else:
                return None
            x, fx = x_new, fx + change
            gap, _ = dual_gap(x)
            info.setdefault("newton_trace", []).append((step, gap))
            if gap <= gap_tol:
                break
            if decrease <= 1e-3 * gap_tol * fx:  # face optimum, not certified: wrong ranks
                return None
        return x, gap

    def ipm_on_active_blocks(feasible):
        """The interior point on the blocks whose unconstrained minimiser is not >= eps I, the
        others (``feasible``, presumed inactive at the optimum) minimised out exactly:
        x_f = -H_ff^-1 (h_f + H_fa x_a), leaving x_a^T (H_aa - H_af H_ff^-1 H_fa) x_a + ... on the
        active blocks - a Schur matrix of half the size (one eighth of the Cholesky). With zero
        multipliers on the eliminated blocks the full problem's dual bound is the reduced one,
        so ``dual_gap`` of the full x proves the answer once the eliminated blocks are checked
        >= eps I; if they are not (the presumption was wrong), None."""
        pos = np.arange(n).reshape(n_blocks, nv)
        a_idx, f_idx = pos[~feasible].ravel(), pos[feasible].ravel()
        Hff = _SPDSolver(H[np.ix_(f_idx, f_idx)])
        if not Hff.ok:
            return None
        Hfa = H[np.ix_(f_idx, a_idx)]
        W = Hff.solve(np.column_stack([Hfa, h[f_idx]]))  # H_ff^-1 [H_fa, h_f]
        Hr = H[np.ix_(a_idx, a_idx)] - Hfa.T @ W[:, :-1]
        hr = h[a_idx] - Hfa.T @ W[:, -1]

        def full(xa):
            xf = np.empty(n)
            xf[a_idx], xf[f_idx] = xa, -(W[:, -1] + W[:, :-1] @ xa)
            return xf

        def eliminated_ok(xf):  # the eliminated blocks of a full x are >= eps I
            return np.linalg.eigvalsh(blocks(xf)[feasible]).min() >= eps

        def certify(xa, lam_a):
            xf = full(xa)
            if not eliminated_ok(xf):
                return np.nan, np.nan
            lam = np.zeros((n_blocks, r, r))
            lam[~feasible] = lam_a
            return dual_gap(xf, lam)

        def still_feasible(xa, rel_gap):  # once near the optimum, the eliminated blocks must be
            return rel_gap > 1e-3 or eliminated_ok(full(xa))

        xa, ip = _primal_dual_ipm(0.5 * (Hr + Hr.T), hr, float(np.sum(Z**2) - h[f_idx] @ W[:, -1]),
                                  r, int((~feasible).sum()), eps, x[a_idx], certify=certify,
                                  gap_tol=gap_tol, max_iter=ipm_max_iter, watch=still_feasible)
        if not ip["converged"]:
            return None
        ranks = np.full(n_blocks, r)
        ranks[~feasible] = ip["ranks"]
        ip.update(ranks=[int(k) for k in ranks], eliminated_blocks=[int(k) for k in np.flatnonzero(feasible)])
        return full(xa), ip

    reduced = None
    if method == "auto" and chol.ok and eliminate and feasible.any():
        reduced = ipm_on_active_blocks(feasible)
        info["eliminated_blocks_tried"] = [int(k) for k in np.flatnonzero(feasible)]
    if method == "auto" and chol.ok:  # the certificate needs H > 0
        if reduced is not None:
            x_ip, ip = reduced
        else:
            x_ip, ip = _primal_dual_ipm(H, h, float(np.sum(Z**2)), r, n_blocks, eps, x,
                                        certify=dual_gap, gap_tol=gap_tol, max_iter=ipm_max_iter)
        if not ip["converged"]:  # crossover: Newton on the face the interior point shows
            S = blocks(x_ip) - eps * np.eye(r)
            w, Q = np.linalg.eigh(S)
            w = np.where(np.arange(r)[None, :] >= r - np.array(ip["ranks"])[:, None], w, 0.0)
            x_face = x_eps + vech((Q * w[:, None, :]) @ Q.transpose(0, 2, 1))
            refined = newton_on_face(x_face, ip["ranks"]) if min(w.max(axis=1)) >= 0 else None
            if refined is not None and refined[1] <= gap_tol:
                x_ip = refined[0]
                ip.update(converged=True, duality_gap=refined[1], crossover=True,
                          face_multiplier_min=dual_gap(x_ip)[1])
        info["ipm"] = {k: v for k, v in ip.items() if k != "ranks"}
        if ip["converged"]:
            info.update(iterations=ip["iterations"], converged=True, method="ipm",
                        duality_gap=ip["duality_gap"], face_ranks=ip["ranks"],
                        face_multiplier_min=ip["face_multiplier_min"],
                        seconds=time.perf_counter() - t0)
            return _theta_from_x(x_ip, r, n_blocks, terms), info

    def project(v):
        w, Q = np.linalg.eigh(blocks(v))
        return vech((Q * np.maximum(w, eps)[:, None, :]) @ Q.transpose(0, 2, 1)), w, Q

    scale_k = np.array([np.mean(np.diag(H)[blk == k]) for k in range(n_blocks)])

    def factor(rho):
        # x-step matrix 2 H + rho D = R^T R: keep R^-1 (one Cholesky, one triangular inverse),
        # so that the x-step is two matrix-vector products
        P = rho * scale_k[blk] * Dw
        R, _ = scipy.linalg.cho_factor(2.0 * H + np.diag(P), lower=False, check_finite=False)
        Rinv, status = scipy.linalg.lapack.dtrtri(R, lower=0)
        if status != 0:
            raise np.linalg.LinAlgError("x-step matrix is not positive definite")
        return np.triu(Rinv), P

    rho = rho0
    fac, P = factor(rho)
    h2 = -2.0 * h

    def step(z):
        wv, yv = z[:n], z[n:]
        xv = fac @ (fac.T @ (h2 + P * (wv - yv)))
        w_new, ew, eQ = project(xv + yv)
        return np.concatenate([w_new, yv + xv - w_new]), xv, (ew, eQ)

    z = np.concatenate([project(x)[0], np.zeros(n)])
    z_next, x, eig = step(z)
    g = z_next - z
    dZ, dG = [], []
    it, prim, dual, n_rho = 0, np.inf, np.inf, 0
    target = admm_tol
    result, converged = None, False
    gap, lam_min, a_min = np.inf, -np.inf, -np.inf
    for it in range(1, max_iter + 1):
        w_prev = z[:n]
        candidate = None
        if dZ:
            Zm, Gm = np.array(dZ).T, np.array(dG).T
            GtG = Gm.T @ Gm
            gamma = np.linalg.solve(GtG + 1e-14 * np.trace(GtG) * np.eye(len(dZ)), Gm.T @ g)
            z_aa = z + g - (Zm + Gm) @ gamma
            z_aa_next, x_aa, eig_aa = step(z_aa)
            g_aa = z_aa_next - z_aa
            if np.linalg.norm(g_aa) < np.linalg.norm(g):
                candidate = (z_aa, z_aa_next, g_aa, x_aa, eig_aa)
        if candidate is None:
            z_new_next, x_new, eig_new = step(z_next)
            candidate = (z_next, z_new_next, z_new_next - z_next, x_new, eig_new)
        z_c, z_c_next, g_c, x, eig = candidate
        dZ.append(z_c - z)
        dG.append(g_c - g)
        dZ, dG = dZ[-memory:], dG[-memory:]
        z, z_next, g = z_c, z_c_next, g_c
        wv, yv = z_next[:n], z_next[n:]
        nw = np.linalg.norm(wv)
        prim = np.linalg.norm(x - wv) / max(np.linalg.norm(x), nw, 1e-300)
        dual = np.linalg.norm(wv - w_prev) / max(np.linalg.norm(yv), nw, 1e-300)
        if prim < target and dual < target:
            info["polish_attempts"] += 1
            ranks = [int((eig[0][k] > eps).sum()) for k in range(n_blocks)]
            # exact minimiser on the face ADMM found (its subspaces fixed) ...
            xp, a_min = polish(*eig)
            info.setdefault("attempts", []).append({"iteration": it, "ranks": ranks, "a_min": a_min})
            if a_min > 0:
                gap, lam_min = dual_gap(xp)
                info["attempts"][-1].update(polish_gap=gap, lam_min=lam_min)
                if gap <= gap_tol or (not chol.ok and lam_min >= -kkt_tol):
                    result, converged = xp, True
                    break
                if chol.ok:  # ... then Newton on the face, which also turns the subspaces
                    refined = newton_on_face(xp, ranks)
                    info["attempts"][-1].update(newton=None if refined is None else refined[1])
                    if refined is not None and refined[1] <= gap_tol:
                        result, converged = refined[0], True
                        gap, lam_min = dual_gap(result)
                        break
            if target <= 1e-11:  # ADMM itself has converged: its feasible iterate
                result = wv
                gap, lam_min = dual_gap(wv)
                converged = gap <= gap_tol or (not chol.ok and lam_min >= -kkt_tol)
                break
            target /= 10.0
        if it % 25 == 0 and n_rho < 3 and (prim > 10 * dual or dual > 10 * prim):
            n_rho += 1  # each change costs a factorisation: allow a few
            fct = 4.0 if prim > dual else 0.25
            rho *= fct
            z = np.concatenate([z[:n], z[n:] / fct])
            fac, P = factor(rho)
            z_next, x, eig = step(z)
            g = z_next - z
            dZ, dG = [], []
    if result is None:
        result = z_next[:n]
        gap, lam_min = dual_gap(result)
    info.update(iterations=it, converged=bool(converged), method="admm+face",
                primal_residual=float(prim), dual_residual=float(dual),
                face_ranks=[int((eig[0][k] > eps).sum()) for k in range(n_blocks)],
                duality_gap=float(gap), face_multiplier_min=lam_min, face_A_min=a_min,
                rho=rho, seconds=time.perf_counter() - t0)
    return _theta_from_x(result, r, n_blocks, terms), info
