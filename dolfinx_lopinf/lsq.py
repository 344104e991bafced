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
* :func:`solve_admm_sym` - several symmetric blocks >= eps I: ADMM with an exactly symmetric
  x-step (vech normal equations, one Cholesky per penalty).
* :func:`solve_ipm` - the same problem by a log-barrier interior point method with a
  duality-gap certificate (slower; the fallback).
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

import time
import warnings

import numpy as np
import scipy.linalg


def _clip(A: np.ndarray, eps: float) -> np.ndarray:
    """Frobenius projection of sym(A) onto {S = S^T, S >= eps I}."""
    w, Q = np.linalg.eigh(0.5 * (A + A.T))
    return (Q * np.maximum(w, eps)) @ Q.T


def solve_symmetric(L: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """argmin over symmetric K (r, r) of ||K L + Z||_F (L is r x r): the Lyapunov solution."""
    U, s, _ = np.linalg.svd(L)
    X = Z @ L.T
    rhs = -U.T @ (X + X.T) @ U
    K = U @ (rhs / (s[:, None] ** 2 + s[None, :] ** 2)) @ U.T
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
    U, s, _ = np.linalg.svd(L)
    lam = s**2
    X = Z @ L.T
    B = U.T @ (X + X.T) @ U
    start = solve_symmetric(L, Z) if start is None else start
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


def _quadratic(G, X, terms):
    """f(x) = x^T H x + 2 h^T x + const for Theta(x) with ||Theta L + Z||^2, G = L L^T."""
    rows, cols, _, masks, _ = terms
    n = len(rows[0])
    H = np.zeros((n, n))
    h = np.zeros(n)
    for s in range(2):
        h += masks[s] * X[rows[s], cols[s]]
        for t in range(2):
            same_row = rows[s][:, None] == rows[t][None, :]
            H += (masks[s][:, None] * masks[t][None, :]) * same_row * G[np.ix_(cols[s], cols[t])]
    return H, h


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
    H, h = _quadratic(L @ L.T, Z @ L.T, terms)
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
    G = L @ L.T
    X = Z @ L.T
    const = float(np.sum(Z**2))
    H, h = _quadratic(G, X, terms)

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


def solve_admm_sym(L: np.ndarray, Z: np.ndarray, n_blocks: int, eps: float, *, tol: float = 1e-9,
                   max_iter: int = 20000, memory: int = 8) -> tuple[np.ndarray, dict]:
    """min ||Theta L + Z||_F^2 over Theta = [S_1 .. S_b], S_k = S_k^T >= eps I, by ADMM whose
    x-step is exactly symmetric, accelerated by Anderson mixing (type II, safeguarded).

    x-step: the b r (r+1)/2 upper-triangular unknowns solve
        (2 H + rho D) x = -2 h + rho D (w - y),   D = diag(1 on diagonals, 2 off)
    with one Cholesky factor per rho (H, h from :func:`_quadratic`); W-step: eigenvalue
    clipping of each block of S(x) + Y at eps; Y-step: y += x - w. The fixed-point map
    (w, y) -> (w', y') is Anderson-accelerated with ``memory`` past steps; a mixed step is
    kept only when it lowers the fixed-point residual. rho follows residual balancing.
    """
    t0 = time.perf_counter()
    r = Z.shape[0]
    terms = _vech_terms(r, n_blocks)
    _, _, _, masks, blk = terms
    H, h = _quadratic(L @ L.T, Z @ L.T, terms)
    Dw = 1.0 + masks[1]
    iu = np.triu_indices(r)
    nv = len(iu[0])
    full = np.zeros((r, r), dtype=int)  # vech position of every (i, j)
    full[iu] = np.arange(nv)
    full = np.triu(full) + np.triu(full, 1).T
    n = n_blocks * nv

    def project(v):
        out = np.empty_like(v)
        for k in range(n_blocks):
            blockv = v[k * nv:(k + 1) * nv]
            out[k * nv:(k + 1) * nv] = _clip(blockv[full], eps)[iu]
        return out

    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    try:  # warm start: the symmetric minimiser (Jacobi-equilibrated Cholesky solve)
        x = -scipy.linalg.cho_solve(scipy.linalg.cho_factor(H / np.outer(d, d), check_finite=False),
                                    h / d, check_finite=False) / d
    except np.linalg.LinAlgError:
        x = -np.linalg.lstsq(H / np.outer(d, d), h / d, rcond=None)[0] / d
    scale_k = np.array([np.mean(np.diag(H)[blk == k]) for k in range(n_blocks)])
    rho = 1.0

    def factor(rho):
        # explicit inverse (one Cholesky per rho): the x-step becomes one matrix-vector product
        P = rho * scale_k[blk] * Dw
        c = scipy.linalg.cho_factor(2.0 * H + np.diag(P), check_finite=False)
        return scipy.linalg.cho_solve(c, np.eye(len(P)), check_finite=False), P

    fac, P = factor(rho)
    h2 = -2.0 * h

    def step(z):
        w, y = z[:n], z[n:]
        x = fac @ (h2 + P * (w - y))
        w_new = project(x + y)
        return np.concatenate([w_new, y + x - w_new]), x

    z = np.concatenate([project(x), np.zeros(n)])
    z_next, x = step(z)
    g = z_next - z
    dZ, dG = [], []
    it, prim, dual = 0, np.inf, np.inf
    n_mixed, n_rho = 0, 0
    for it in range(1, max_iter + 1):
        w_prev = z[:n]
        candidate = None
        if dZ:
            Zm, Gm = np.array(dZ).T, np.array(dG).T
            GtG = Gm.T @ Gm
            gamma = np.linalg.solve(GtG + 1e-14 * np.trace(GtG) * np.eye(len(dZ)), Gm.T @ g)
            z_aa = z + g - (Zm + Gm) @ gamma
            z_aa_next, x_aa = step(z_aa)
            g_aa = z_aa_next - z_aa
            if np.linalg.norm(g_aa) < np.linalg.norm(g):
                candidate = (z_aa, z_aa_next, g_aa, x_aa)
                n_mixed += 1
        if candidate is None:
            z_new = z_next
            z_new_next, x_new = step(z_new)
            candidate = (z_new, z_new_next, z_new_next - z_new, x_new)
        z_c, z_c_next, g_c, x = candidate
        dZ.append(z_c - z)
        dG.append(g_c - g)
        dZ, dG = dZ[-memory:], dG[-memory:]
        z, z_next, g = z_c, z_c_next, g_c
        w, y = z_next[:n], z_next[n:]
        nw = np.linalg.norm(w)
        prim = np.linalg.norm(x - w) / max(np.linalg.norm(x), nw, 1e-300)
        dual = np.linalg.norm(w - w_prev) / max(np.linalg.norm(y), nw, 1e-300)
        if prim < tol and dual < tol:
            break
        if it % 25 == 0 and n_rho < 3 and (prim > 10 * dual or dual > 10 * prim):
            n_rho += 1  # each change costs a factorisation: allow a few
            f = 4.0 if prim > dual else 0.25
            rho *= f
            z = np.concatenate([z[:n], z[n:] / f])
            fac, P = factor(rho)
            z_next, x = step(z)
            g = z_next - z
            dZ, dG = [], []
    theta = _theta_from_x(z_next[:n], r, n_blocks, terms)
    converged = prim < tol and dual < tol
    return theta, {"iterations": it, "anderson_steps": n_mixed, "primal_residual": float(prim),
                   "dual_residual": float(dual), "converged": converged,
                   "seconds": time.perf_counter() - t0}
