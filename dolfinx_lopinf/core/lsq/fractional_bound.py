"""The dual bound of the learned-mass certificate (:meth:`.fractional.FractionalProblem.certify`):
the repair of the dual point Y that makes the floor blocks' terms G_k = sym(Y L_k^T) >= 0
(compensated products, so that the check is exact where extended precision is not), the
projection of Y that zeroes them, and the scalar maximisation over the normalisation's
multiplier nu (Jacobi-scaled Cholesky log-determinants). The bound and its derivation are in
:mod:`.fractional`'s docstring.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from .linalg import from_eig


#: rounds of the floor blocks' repair (:func:`_repair`)
REPAIR_ROUNDS = 4


def _repair(Y, L, r, b):
    """(Y + dY, valid): a least-norm change of Y making G_k = sym(Y L_k^T) >= 0 for the floor
    blocks k >= 1, as the bound needs (an indefinite G_k leaves it -infinite). G_k is the small
    difference of terms |Y| |L_k| (Y nearly orthogonal to the rows of inactive floors), so it
    is formed by a compensated dot product and symmetrised before rounding (:func:`_dot2`,
    :func:`_sym2`: error u |G_k| + (2 p u)^2 |Y| |L|, where extended precision left p 1e-19
    |Y| |L|, above the G_k of near-exact data), and ``valid`` when every computed least
    eigenvalue exceeds that error plus the eigenvalues' r u |G_k|, less u |Y| |L_k|: the bound
    holds for Y up to its own rounding (a dual point that is stationary in the floor blocks,
    G_k = 0 as :func:`projected_dual` makes it, is only that to the rounding of Y; a step
    below that level cannot be represented in Y).
    The data rows L_k of near-exact data are ill-conditioned (singular values over 1e14): the
    least-norm dY is taken from L_S = L[r:] itself (its normal matrix squares the condition),
    G_k re-formed and the step repeated, each target a margin (twice the error) inside."""
    if b == 1:
        return Y, True
    u = np.finfo(float).eps
    LS = L[r:]
    for _ in range(REPAIR_ROUNDS + 1):
        hi, lo, bound = _dot2(Y, LS)
        ny = float(np.linalg.norm(Y))
        changes, ok = [], True
        for k in range(b - 1):
            cols = slice(k * r, (k + 1) * r)
            Gs, err = _sym2(hi[:, cols], lo[:, cols], bound[:, cols])
            w, Q = np.linalg.eigh(Gs)
            hide = float(np.linalg.norm(err)) + r * u * float(np.linalg.norm(Gs))
            if w[0] >= hide - u * ny * float(np.linalg.norm(LS[cols])):
                changes.append(np.zeros_like(Gs))
                continue
            ok = False
            changes.append(from_eig(np.maximum(w, 2.0 * hide) - w, Q))
        if ok:
            return Y, True
        dYt = scipy.linalg.lstsq(LS, np.hstack(changes).T, check_finite=False, lapack_driver="gelsd")[0]
        Y = Y + dYt.T
    return Y, False


def _dot2(A, B):
    """A @ B^T as an unevaluated sum hi + lo and a bound on its error, by the compensated dot
    product (Ogita, Rump and Oishi's Dot2: Dekker's exact products, Knuth's exact sums) - as
    if computed in twice the working precision: |hi + lo - A B^T| <= (p u)^2 |A| |B|^T.
    The compiled ``_fractional_compiled._dot2_loops`` when the learned-mass kernels are loaded (the same
    operations on each entry: bit for bit the same sums), else numpy over whole columns."""
    u = np.finfo(float).eps / 2
    kernels = _loaded_kernels()
    if kernels is not None:
        A, B = np.ascontiguousarray(A, dtype=float), np.ascontiguousarray(B, dtype=float)
        s, e = np.zeros((A.shape[0], B.shape[0])), np.zeros((A.shape[0], B.shape[0]))
        kernels["_dot2_loops"](A, B, s, e)
        return s, e, (2.0 * A.shape[1] * u) ** 2 * (np.abs(A) @ np.abs(B).T)
    split = 134217729.0  # 2^27 + 1

    def halves(x):
        c = split * x
        hi = c - (c - x)
        return hi, x - hi

    p = A.shape[1]
    s = np.zeros((A.shape[0], B.shape[0]))
    e = np.zeros_like(s)
    (Ah, Al), (Bh, Bl) = halves(A), halves(B)
    for j in range(p):
        a, bcol = A[:, j][:, None], B[:, j][None, :]
        prod = a * bcol
        ah, al, bh, bl = Ah[:, j][:, None], Al[:, j][:, None], Bh[:, j][None, :], Bl[:, j][None, :]
        perr = ((ah * bh - prod) + ah * bl + al * bh) + al * bl
        t = s + prod
        z = t - s
        e += ((s - (t - z)) + (prod - z)) + perr
        s = t
    return s, e, (2.0 * p * u) ** 2 * (np.abs(A) @ np.abs(B).T)


def _sym2(hi, lo, bound):
    """(sym(hi + lo) rounded once, its error bound) for a square block of :func:`_dot2`: the
    symmetric part is the small difference of large entries (Y L_k^T's antisymmetric part is
    free), so it is summed before rounding."""
    u = np.finfo(float).eps / 2
    t = hi + hi.T
    z = t - hi
    terr = (hi - (t - z)) + (hi.T - z)
    out = 0.5 * (t + (terr + lo + lo.T))
    return out, u * np.abs(out) + 4.0 * u * u * np.abs(hi) + 0.5 * (bound + bound.T)


def projected_dual(problem: "FractionalProblem", xs, Y) -> np.ndarray:  # noqa: F821 - no import cycle
    """Y with its floor-block part removed: the M-weighted orthogonal projection of Y onto
    {Y : sym(Y L_k^T) = 0, k >= 1}, i.e. G_k = 0 to rounding (the floors' multipliers set to
    zero - right where they are inactive).

    The interior point's Y carries its dual residual, and in the floor blocks that residual
    lies along the directions the data hardly see (near-exact data: the K, C data rows have
    singular values over 1e14): the least-norm repair of G_k >= 0 there moves Y by
    residual / sigma_min and ruins the bound. A projection never divides by sigma: with
    M = R R^T, sym(Y L_k^T) = 0 for all k >= 1 says R^T Y is orthogonal to the columns of
    D = [vec(R^-1 E L_k)] (E the symmetric units), so Y' = R^-T (I - Q Q^T) R^T Y with Q from
    a Householder QR of D (r p x (b - 1) r (r + 1) / 2, never its normal matrix): its G_k vanish
    to u |Y| |L| whatever the conditioning, and Y' - Y is at most Y's own floor-block part."""
    r, b, L = problem.r, problem.n_blocks, problem.L
    if b == 1:
        return Y
    M = problem.theta(xs)[:, :r]
    Rc = np.linalg.cholesky(M)
    Ri = scipy.linalg.solve_triangular(Rc, np.eye(r), lower=True, check_finite=False)
    i0, i1 = np.triu_indices(r)
    off = (i0 != i1)[None, None, :]
    cols = []
    for k in range(1, b):
        Lk = L[k * r:(k + 1) * r]
        D = Ri[:, None, i0] * Lk[i1].T[None, :, :] + off * Ri[:, None, i1] * Lk[i0].T[None, :, :]
        cols.append(D.reshape(-1, len(i0)))
    Q = scipy.linalg.qr(np.hstack(cols), mode="economic", check_finite=False)[0]
    e = (Rc.T @ Y).reshape(-1)
    e = e - Q @ (Q.T @ e)
    return scipy.linalg.solve_triangular(Rc, e.reshape(r, -1), lower=True, trans="T", check_finite=False)


def _dot_extended(A, B) -> np.ndarray:
    """A @ B accumulated in extended precision (numpy's longdouble: 64-bit mantissa on x86),
    rounded once. The certificate's A = sym(2 Y L_0^T - Y Y^T) is ~f while its terms are
    ~sqrt(f f_scale): in double the bound erred by ~u cond(W) sqrt(f f_scale) (measured:
    1e-16 f_scale on the Newmark cantilever at r = 20, f = 1e-10 f_scale - the size of the
    certified gap itself)."""
    return (A.astype(np.longdouble) @ B.astype(np.longdouble)).astype(float)


def _logdet(B):
    """(log det B, tr(B^-1 W), tr((B^-1 W)^2)) for SPD B by the Jacobi-scaled Cholesky - exact
    to rounding on the graded matrices of the certificate, where the generalised eigenvalues
    of (A, W) are not (measured: log det off by 4e-4 at eigenvalues spanning 1e15) - or None."""
    dg = np.diag(B)
    if not np.all(dg > 0):
        return None
    d = 1.0 / np.sqrt(dg)
    try:
        c = scipy.linalg.cho_factor(B * d[:, None] * d[None, :], lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    return 2.0 * float(np.sum(np.log(np.diag(c[0])))) - 2.0 * float(np.sum(np.log(d))), c, d


def _maximise_nu(A, W, tau, cc, nu0):
    """(nu, log det(A - nu W)): Newton on the concave nu cc + tau log det(A - nu W) from nu0
    (any nu with A - nu W > 0 gives a valid bound; this one is the best to rounding)."""
    def value(nu):
        out = _logdet(A - nu * W)
        return None if out is None else (nu * cc + tau * out[0], out)

    nu = nu0
    cur = value(nu)
    while cur is None:  # nu0 from the eigenvalues may sit just outside: move down
        nu -= max(abs(nu), tau) * 1e-6
        cur = value(nu)
    for _ in range(20):
        _, (ld, c, d) = cur
        X = scipy.linalg.cho_solve(c, W * d[:, None] * d[None, :], check_finite=False)  # (B^-1 W) scaled
        g1, g2 = cc - tau * float(np.trace(X)), -tau * float(np.sum(X * X.T))
        step = -g1 / g2
        for _ in range(60):
            nxt = value(nu + step)
            if nxt is not None and nxt[0] >= cur[0]:
                break
            step *= 0.5
        else:
            break
        nu, cur = nu + step, nxt
        if abs(step) <= 1e-15 * max(abs(nu), tau):
            break
    return nu, cur[1][0]


def _best_nu(lam, tau, c) -> float:
    """:func:`_best_nu_numpy`, by the compiled ``_best_nu_loops`` when the learned-mass kernels
    are loaded (the same arithmetic, bit for bit; r <= 128)."""
    kernels = _loaded_kernels()
    if kernels is None or len(lam) > 128:
        return _best_nu_numpy(lam, tau, c)
    return float(kernels["_best_nu_loops"](np.ascontiguousarray(lam, dtype=float), float(tau), float(c)))


def _best_nu_numpy(lam, tau, c) -> float:
    """argmax over nu < lam_min of c nu + tau sum log(lam_i - nu): c = tau sum 1/(lam_i - nu),
    by bisection on d = lam_min - nu in [tau / c, tau r / c] (the sum is monotone in nu)."""
    r = len(lam)
    lo, hi = tau / c, tau * r / c  # d: the root lies between (one term alone / all r equal)
    for _ in range(200):
        mid = np.sqrt(lo * hi) if lo > 0 else 0.5 * (lo + hi)
        if tau * np.sum(1.0 / (lam - lam[0] + mid)) > c:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-15 * hi:
            break
    return float(lam[0] - hi)


def _loaded_kernels():
    """The compiled learned-mass kernels if this process has them loaded, else None (never
    compiles: the certificate is not worth a build)."""
    from . import _fractional_compiled

    return _fractional_compiled.loaded()
