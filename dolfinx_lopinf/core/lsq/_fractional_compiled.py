"""The learned-mass interior point's iteration (:mod:`.fractional`) compiled with numba.

One call of ``_step`` is one predictor-corrector iteration of ``fractional._State.step``, the
same arithmetic in the same order (numba's np.linalg is LAPACK, as numpy's): the Kronecker
kernels of the Schur matrix gathered from one matrix product per block pair, the
equilibrated Cholesky with the numpy path's diagonal shifts, the refined directions, the
exact pencil step lengths and the update; ``_estimate`` is ``_State.gap_estimate``. Python
keeps the loop, the certificate (``FractionalProblem.certify``, called a few times per fit)
and the stall test, so the iterates agree with the numpy path to rounding (tests). Kernels
compile with ``cache=True`` and run without the GIL (``nogil``: lo.fit fits its candidates on
threads); later processes load them from numba's cache.

Cold cache. Compiling them (with the Mh = I kernels of :mod:`._compiled` they call) takes
tens of seconds - LLVM optimising a 10 MB module - which a fresh machine (CI) would pay inside
its first learned-mass fit. So ``backend="auto"`` runs the compiled iteration only when it
is :func:`ready` (built in this process, or in numba's cache for this source and machine);
otherwise that fit takes the numpy iteration (the same iterates to rounding) and
:func:`compile_in_background` builds the kernels in a daemon thread (LLVM runs outside the
GIL), for the fits after it and, through the cache, for later processes. ``backend="numba"``
and :func:`warm_up` compile synchronously (a background build in progress is waited for).
"""

from __future__ import annotations

import atexit
import sys
import threading
import warnings

import numpy as np

from .. import compiled as _jit

STEP_FRACTION = 0.98  # fractional.STEP_FRACTION
SHIFTS = (0.0, 1e-12, 1e-10, 1e-8)  # fractional.SHIFTS
_potrf = _cs = _chol_inv = _pd = _min_eig = None  # lsq._compiled's kernels, bound by kernels()

# --------------------------------------------------------------------------------------------
# Kernel source (plain Python; compiled by kernels())
# --------------------------------------------------------------------------------------------


def _sym(A):
    return 0.5 * (A + A.T)


def _theta(x, full, r, b):
    """Theta (r, b r) from the vech unknowns x (b blocks)."""
    nv = x.shape[0] // b
    th = np.empty((r, b * r))
    for k in range(b):
        for i in range(r):
            for j in range(r):
                th[i, k * r + j] = x[k * nv + full[i, j]]
    return th


def _vech_blocks(G, iu0, iu1, Dw, r, b, out):
    """out = Dw * vech(sym(G_k)) for the b column blocks of G (r, b r)."""
    nv = iu0.shape[0]
    for k in range(b):
        for p in range(nv):
            i, j = iu0[p], iu1[p]
            out[k * nv + p] = Dw[p] * 0.5 * (G[i, k * r + j] + G[j, k * r + i])


def _blocks(x, full, r, b):
    nv = x.shape[0] // b
    X = np.empty((b, r, r))
    for k in range(b):
        for i in range(r):
            for j in range(r):
                X[k, i, j] = x[k * nv + full[i, j]]
    return X


def _kernel_block(Ps, Qs, coefs, nt, iu0, iu1, H, ro, co):
    """H[ro + (ij), co + (ab)] = sum_t coef_t K(P_t, Q_t) (fractional.kernel), from one product
    G = sum_t coef_t vec(P_t) vec(Q_t^T)^T, G[(x, y), (u, v)] = sum_t coef_t P_t[x, y] Q_t[v, u]:
    then the four terms of K at (ij), (ab) are G[(j, a), (i, b)], G[(j, b), (i, a)],
    G[(i, a), (j, b)], G[(i, b), (j, a)] - two r x r blocks of G per row (ij), which stay in
    L1 cache while the row is written (fractional.kernel's Phi = sum P (x) Q spread each row's
    reads over r^2 cache lines: 3.0 -> 2.4 ms for the nine blocks at r = 20, the product
    included). The same products, summed in the same order."""
    r = Ps.shape[1]
    nv = iu0.shape[0]
    Pm = np.empty((r * r, nt))
    Qm = np.empty((nt, r * r))
    for t in range(nt):
        c = coefs[t]
        for i in range(r):
            for j in range(r):
                Pm[i * r + j, t] = c * Ps[t, i, j]
                Qm[t, i * r + j] = Qs[t, j, i]
    G = np.dot(Pm, Qm)
    for p in range(nv):
        i, j = iu0[p], iu1[p]
        cp = 0.5 if i == j else 1.0
        for q in range(nv):
            a, bb = iu0[q], iu1[q]
            cq = 0.5 if a == bb else 1.0
            H[ro + p, co + q] = cp * cq * (G[j * r + a, i * r + bb] + G[j * r + bb, i * r + a]
                                           + G[i * r + a, j * r + bb] + G[i * r + bb, j * r + a])


def _schur(Mi, Ym, Y, Om, s, L, Xi, Lam, iu0, iu1, r, b, H):
    """The Schur matrix (fractional.schur_terms + the floors' kernels) into H: its diagonal
    block pairs whole, the pairs k < l above them only - their mirrors below are the
    transposes, and :func:`_equilibrate` reads the upper block triangle alone."""
    nv = iu0.shape[0]
    D = Ym - Y
    JY = L.copy()
    Jm = L.copy()
    for i in range(r):
        for j in range(L.shape[1]):
            JY[i, j] -= Y[i, j]
            Jm[i, j] -= Ym[i, j]
    GY = np.dot(JY, JY.T)
    GmY = np.dot(Jm, JY.T)
    LJY = np.dot(L, JY.T)
    h = 0.5 / s
    DYm = np.dot(D, Ym.T)
    DYt = np.dot(D, Y.T)
    Ps = np.empty((9, r, r))
    Qs = np.empty((9, r, r))
    coefs = np.empty(9)
    for k in range(b):
        for l in range(k, b):  # the upper pairs, the lower ones mirrored: fractional.schur_terms
            ks, ls = slice(k * r, (k + 1) * r), slice(l * r, (l + 1) * r)
            Ps[0], Qs[0], coefs[0] = Mi, GY[ls, ks], 1.0
            Ps[1], Qs[1], coefs[1] = Om, GmY[ls, ks], 1.0 / s
            Ps[2], Qs[2], coefs[2] = DYm, GY[ls, ks], h
            Ps[3], Qs[3], coefs[3] = np.dot(D, L[ls].T), np.dot(Y, JY[ks].T), h
            Ps[4], Qs[4], coefs[4] = np.dot(D, JY[ls].T), np.dot(Ym, JY[ks].T), -h
            Ps[5], Qs[5], coefs[5] = DYt, LJY[ls, ks], -h
            nt = 6
            if k == 0 and l == 0:
                Ps[nt], Qs[nt], coefs[nt] = Mi, Om, 1.0
                nt += 1
            if k == 0:
                Ps[nt], Qs[nt], coefs[nt] = np.dot(D, Jm[ls].T), Om, -1.0 / s
                nt += 1
            if k == l:
                Ps[nt], Qs[nt], coefs[nt] = Xi[k], Lam[k], 1.0
                nt += 1
            _kernel_block(Ps, Qs, coefs, nt, iu0, iu1, H, k * nv, l * nv)


def _lin_parts(dx, full, r, b, L, JY, Jm, Ym, Y, Mi, Om, D, s):
    dth = _theta(dx, full, r, b)
    dM = np.ascontiguousarray(dth[:, :r])
    dV = np.dot(dth, L)
    dW = np.dot(dth, JY)
    dWm = np.dot(dth, Jm)
    kap = np.dot(Ym.T, dW) + np.dot(dV.T, Y)
    kap = 0.5 * (kap - kap.T)
    dY = 0.5 * np.dot(Mi, dW) + (np.dot(D, kap) + np.dot(Om, dWm)) / (2.0 * s)
    dOm = -_sym(np.dot(np.dot(Mi, dM), Om)) + _sym(np.dot(np.dot(D, dWm.T), Om)) / s
    return dM, dV, dW, dWm, dY, dOm


def _chol_solve(c, dd, v):
    """dd * (C C^T)^-1 (dd * v) for the lower factor C of c's F-ordered view (LAPACK dpotrf in
    place: lsq._compiled._potrf), two BLAS dtrsv (_compiled._chol_solve)."""
    iw = np.zeros(4, dtype=np.int32)
    ch = np.array([76, 78, 84], dtype=np.uint8)
    y = dd * v
    _cs(c, y, iw, ch)
    return dd * y


def _inv_chol(A):
    """(S = R^-1, ok) for the lower Cholesky factor R of A (lsq._compiled._chol_inv)."""
    r = A.shape[0]
    S = np.zeros((r, r))
    Lw = np.zeros((r, r))
    ok = _chol_inv(A, S, Lw)
    return S, ok


def _spd_inv(A):
    S, ok = _inv_chol(A)
    return np.dot(S.T, S), ok


def _pencil(A):
    """1 / max(0, -lambda_min(A)) capped at 1 for the symmetric A = R^-1 E R^-T (A + I > 0:
    1 without an eigenvalue; otherwise LAPACK's Householder reduction (dsytrd) and
    lsq._compiled's bisection on the tridiagonal: 0.1 instead of 0.3 ms at the 80 x 80 pencils
    of r = 20, four per iteration)."""
    q = A.shape[0]
    Lw = np.zeros((q, q))
    if _pd(A, 1.0, Lw):
        return 1.0
    iw = np.zeros(4, dtype=np.int32)
    ch = np.array([76, 78, 84], dtype=np.uint8)
    ev = _min_eig(A.copy(), np.empty(q), np.empty(max(q - 1, 1)), np.empty(max(q - 1, 1)),
                  np.empty(64 * q), iw, ch)
    return 1.0 if ev >= 0 else min(1.0, -1.0 / ev)


def _direction(Xc, RX, D, Ym, Y, Om, JY, Jm, Mi, Xi, Lam, rD, rp, a, Ha, gam, c, dd, s, full, iu0,
               iu1, Dw, L, r, b):
    """fractional._State.step's direction (one refinement against the operator)."""
    n = rD.shape[0]
    Ip = np.eye(b * r)
    X11 = np.ascontiguousarray(Xc[:r, :r])
    X12 = np.ascontiguousarray(Xc[:r, r:])
    X22 = np.ascontiguousarray(Xc[r:, r:])
    dYc = 0.5 * D - X12 - 0.5 * np.dot(Ym + Y, X22)
    C11 = -Om + X11 + 2.0 * _sym(np.dot(X12, Y.T)) + np.dot(np.dot(Y, X22), Y.T)
    Gd = 2.0 * np.dot(dYc, JY.T)
    Gd[:, :r] -= C11
    for k in range(b):
        Gd[:, k * r:(k + 1) * r] -= np.dot(Xi[k], RX[k])
    rhs = np.empty(n)
    _vech_blocks(Gd, iu0, iu1, Dw, r, b, rhs)  # sym(Xi RX): the vech of the sym part
    rhs = -rD - rhs + gam * rp * a
    dx = _chol_solve(c, dd, rhs)
    dnu = (rp - np.dot(a, dx)) / np.dot(a, Ha)
    dx = dx + dnu * Ha
    # one refinement against the operator itself
    dM, dV, dW, dWm, dYl, dOml = _lin_parts(dx, full, r, b, L, JY, Jm, Ym, Y, Mi, Om, D, s)
    Gl = 2.0 * np.dot(dYl, JY.T)
    Gl[:, :r] -= dOml
    dXb = _blocks(dx, full, r, b)
    for k in range(b):
        Gl[:, k * r:(k + 1) * r] += np.dot(np.dot(Xi[k], dXb[k]), Lam[k])
    lin = np.empty(n)
    _vech_blocks(Gl, iu0, iu1, Dw, r, b, lin)
    lin += gam * a * np.dot(a, dx)
    res = rhs - (lin - dnu * a)
    e = _chol_solve(c, dd, res)
    de = -np.dot(a, e) / np.dot(a, Ha)
    dx = dx + e + de * Ha
    dnu = dnu + de
    dM, dV, dW, dWm, dYl, dOml = _lin_parts(dx, full, r, b, L, JY, Jm, Ym, Y, Mi, Om, D, s)
    dX = _blocks(dx, full, r, b)
    dL = np.empty((b, r, r))
    for k in range(b):
        dL[k] = _sym(np.dot(Xi[k], RX[k] - np.dot(dX[k], Lam[k])))
    rho_ = X22 - Ip
    dT22 = s * rho_ - _sym(np.dot(dWm.T, D))
    dT = s * rho_ + _sym(np.dot(Ym.T, dW) + np.dot(dV.T, Y))
    return dx, dnu, dM, dV, dWm, dYc + dYl, C11 + dOml, dT22, dT, dX, dL



def _steps(SM, SO, SX, SL, s, dM, dWm, dT22, dY, dOm, dX, dL, r, b):
    """The largest step keeping Z, U (their pencils: diag(M, s I) and diag(Omega, I) factored)
    and the floors in their cones; S*: the inverse Cholesky factors."""
    pp = b * r
    q = r + pp
    isq = 1.0 / np.sqrt(s)
    Az = np.empty((q, q))
    Az[:r, :r] = np.dot(np.dot(SM, dM), SM.T)
    Az[:r, r:] = np.dot(SM, dWm) * isq
    Az[r:, :r] = Az[:r, r:].T
    Az[r:, r:] = dT22 * (isq * isq)
    As = np.zeros((q, q))
    As[:r, :r] = np.dot(np.dot(SO, dOm), SO.T)
    As[:r, r:] = -np.dot(SO, dY)
    As[r:, :r] = As[:r, r:].T
    out = min(_pencil(_sym(Az)), _pencil(_sym(As)))
    for k in range(b):
        out = min(out, _pencil(_sym(np.dot(np.dot(SX[k], dX[k]), SX[k].T))),
                  _pencil(_sym(np.dot(np.dot(SL[k], dL[k]), SL[k].T))))
    return out


def _equilibrate(H, a, c, nv):
    """gam = 1 / |a diag(H)^-1/2|^2 and dd = diag(H + gam a a^T)^-1/2 (fractional._State.step's
    arithmetic), and c = :func:`_scaled_upper` of H without a shift. Returns (gam, dd)."""
    n = H.shape[0]
    d0 = np.empty(n)
    for i in range(n):
        d0[i] = 1.0 / np.sqrt(H[i, i])  # sym leaves the diagonal exact
    ad = a * d0
    gam = 1.0 / np.dot(ad, ad)
    dd = np.empty(n)
    for i in range(n):
        dd[i] = 1.0 / np.sqrt(H[i, i] + gam * a[i] * a[i])
    _scaled_upper(H, a, gam, dd, nv, 0.0, c)
    return gam, dd


def _scaled_upper(H, a, gam, dd, nv, shift, c):
    """The upper triangle (C order: the lower one of the F-ordered view dpotrf reads) of
    c = diag(dd) (sym(H) + gam a a^T) diag(dd) + shift I, element by element as
    fractional._State.step rounds it (sym(H): the mean of H_ij and H_ji within a diagonal
    block pair of nv x nv; above it H_ij itself - its mirror, the numpy path's, is equal to
    the last bit, so the mean is H_ij exactly). One pass in 32 x 32 tiles; H is only read and
    c's lower triangle not written (whole-matrix expressions made four passes and four n x n
    temporaries: 3.6 ms against 0.8 ms at n = 630; writing both triangles of H and c, 1.1 ms)."""
    n = H.shape[0]
    T = 32
    for i0 in range(0, n, T):
        for j0 in range(i0, n, T):
            for i in range(i0, min(i0 + T, n)):
                end = (i // nv + 1) * nv  # j >= i is in i's diagonal block pair below this
                for j in range(max(j0, i), min(j0 + T, n)):
                    v = 0.5 * (H[i, j] + H[j, i]) if j < end else H[i, j]
                    c[i, j] = (v + gam * a[i] * a[j]) * (dd[i] * dd[j])
    for i in range(n):
        c[i, i] += shift


def _step(xs, Y, Om, Lam, state, L, a, x_floor, full, iu0, iu1, Dw, r, b, rho, f_floor, H, c):
    """fractional._State.step in place: state = [nu, tau, step, sigma, failure (1.0), misfit f];
    H, c: n x n workspaces for the Schur matrix and its factor, allocated once per solve (an
    n x n array allocated here costs its page faults on every call: at n = 630, 1.2 ms per
    3.2 MB array - more than the work done in it)."""
    nv = iu0.shape[0]
    n = b * nv
    pp = b * r
    q = r + pp
    nu, tau = state[0], state[1]
    th = _theta(xs + x_floor, full, r, b)
    M = np.ascontiguousarray(th[:, :r])
    V = np.dot(th, L)
    SM, okM = _inv_chol(M)
    SO, okO = _inv_chol(Om)
    if not (okM and okO):
        state[4] = 1.0
        return
    Mi = np.dot(SM.T, SM)
    Ym = np.dot(Mi, V)
    D = Ym - Y
    s = (np.sum(M * Om) + np.sum(np.dot(M, D) * D)) / r
    X = _blocks(xs, full, r, b)
    G = 2.0 * np.dot(Y, L.T)
    G[:, :r] -= Om + np.dot(Y, Y.T)
    for k in range(b):
        G[:, k * r:(k + 1) * r] -= Lam[k]
    rD = np.empty(n)
    _vech_blocks(G, iu0, iu1, Dw, r, b, rD)
    rD -= nu * a
    rp = (1.0 - np.dot(a, x_floor)) - np.dot(a, xs)
    fl = 0.0
    for k in range(1, b):
        fl += np.sum(X[k] * Lam[k])
    mu = (q * s + fl) / (q + (b - 1) * r)
    Xi = np.empty((b, r, r))
    SX = np.empty((b, r, r))
    SL = np.empty((b, r, r))
    for k in range(b):
        SX[k], okX = _inv_chol(X[k])
        SL[k], okL = _inv_chol(Lam[k])
        if not (okX and okL):
            state[4] = 1.0
            return
        Xi[k] = np.dot(SX[k].T, SX[k])
    _schur(Mi, Ym, Y, Om, s, L, Xi, Lam, iu0, iu1, r, b, H)
    gam, dd = _equilibrate(H, a, c, nv)
    ok = False
    iw = np.zeros(4, dtype=np.int32)
    ch = np.array([76, 78, 84], dtype=np.uint8)
    for shift in SHIFTS:
        if shift != 0.0:  # c was overwritten by the failed factorisation
            _scaled_upper(H, a, gam, dd, nv, shift, c)
        ok = _potrf(c, iw, ch)
        if ok:
            break
    if not ok:
        state[4] = 1.0
        return
    Ha = _chol_solve(c, dd, a)
    JY = L.copy()
    Jm = L.copy()
    JY[:r] -= Y
    Jm[:r] -= Ym
    Ip = np.eye(pp)
    Ir = np.eye(r)

    XL = np.empty((b, r, r))
    for k in range(b):
        XL[k] = np.dot(X[k], Lam[k])
    RX = -XL
    RX[0] += tau * Ir
    dx, dnu, dM, dV, dWm, dY, dOm, dT22, dT, dX, dL = _direction(np.zeros((q, q)), RX, D, Ym, Y, Om, JY, Jm, Mi, Xi, Lam, rD, rp, a, Ha, gam, c, dd, s, full, iu0, iu1, Dw, L, r, b)
    al = _steps(SM, SO, SX, SL, s, dM, dWm, dT22, dY, dOm, dX, dL, r, b)
    dS11 = dOm + 2.0 * _sym(np.dot(dY, Y.T))
    zs = (1.0 - al) * q * s + al * al * (np.sum(dM * dS11) - 2.0 * np.sum(dV * dY))
    fa = 0.0
    for k in range(1, b):
        fa += np.sum((X[k] + al * dX[k]) * (Lam[k] + al * dL[k]))
    sigma = min(1.0, max(zs + fa, 0.0) / (q + (b - 1) * r) / mu) ** 3
    dZa = np.empty((q, q))
    dZa[:r, :r] = dM
    dZa[:r, r:] = dV
    dZa[r:, :r] = dV.T
    dZa[r:, r:] = dT
    dSa = np.zeros((q, q))
    dSa[:r, :r] = dS11
    dSa[:r, r:] = -dY
    dSa[r:, :r] = -dY.T
    E = np.dot(dZa, dSa)
    w = np.empty((q, pp))
    w[:r] = Ym
    w[r:] = -Ip
    Zi = np.dot(w, w.T) / s
    Zi[:r, :r] += Mi
    ZiE = np.dot(w, np.dot(w.T, E)) / s
    ZiE[:r] += np.dot(Mi, E[:r])
    RX = sigma * mu * Ir - XL
    for k in range(b):
        RX[k] -= np.dot(dX[k], dL[k])
    RX[0] += (max(tau, sigma * mu) - sigma * mu) * Ir
    dx, dnu, dM, dV, dWm, dY, dOm, dT22, dT, dX, dL = _direction(_sym(sigma * mu * Zi - ZiE), RX,
        D, Ym, Y, Om, JY, Jm, Mi, Xi, Lam, rD, rp, a, Ha, gam, c, dd, s, full, iu0, iu1, Dw, L, r, b)
    al = min(1.0, STEP_FRACTION * _steps(SM, SO, SX, SL, s, dM, dWm, dT22, dY, dOm, dX, dL, r, b))
    xs += al * dx
    for k in range(b):
        Lam[k] += al * dL[k]
    Om += al * dOm - al * al * np.dot(dY, dY.T)
    for i in range(r):  # exactly symmetric (fractional._State.step)
        for j in range(i + 1, r):
            v = 0.5 * (Om[i, j] + Om[j, i])
            Om[i, j] = v
            Om[j, i] = v
    Y += al * dY
    th = _theta(xs + x_floor, full, r, b)
    M = np.ascontiguousarray(th[:, :r])
    V = np.dot(th, L)
    Mi, okM = _spd_inv(M)
    f = np.sum(V * np.dot(Mi, V)) if okM else np.inf
    state[0] = nu + al * dnu
    state[1] = min(tau, rho * max(f, f_floor, 1e-300) / r)  # tau never rises (fractional)
    state[2] = al
    state[3] = sigma
    state[5] = f


def _estimate(xs, Y, Om, Lam, tau, L, x_floor, full, r, b, f_floor):
    """fractional._State.gap_estimate."""
    th = _theta(xs + x_floor, full, r, b)
    M = np.ascontiguousarray(th[:, :r])
    V = np.dot(th, L)
    Mi, okM = _spd_inv(M)
    Ym = np.dot(Mi, V)
    f = np.sum(V * Ym)
    D = Ym - Y
    X = _blocks(xs, full, r, b)
    fl = 0.0
    for k in range(1, b):
        fl += np.sum(X[k] * Lam[k])
    return (np.sum(M * Om) + np.sum(np.dot(M, D) * D) + fl + abs(np.sum(X[0] * Lam[0]) - r * tau)) \
        / max(f, f_floor, 1e-300)


# the certificate's loops (:mod:`.fractional_bound`: _dot2, _best_nu; numpy / interpreted there
# when these are not loaded, the same arithmetic): no FMA contraction - Dekker's split products
# need each product rounded


def _dot2_loops(A, B, s, e):
    """s + e = A @ B^T by fractional_bound._dot2's arithmetic entry by entry, into zeroed s, e."""
    split = 134217729.0  # 2^27 + 1
    ra, rb, p = A.shape[0], B.shape[0], A.shape[1]
    for i in range(ra):
        for k in range(rb):
            si, ei = 0.0, 0.0
            for j in range(p):
                a, bj = A[i, j], B[k, j]
                ca, cb = split * a, split * bj
                ah = ca - (ca - a)
                bh = cb - (cb - bj)
                al, bl = a - ah, bj - bh
                prod = a * bj
                perr = ((ah * bh - prod) + ah * bl + al * bh) + al * bl
                t = si + prod
                z = t - si
                ei += ((si - (t - z)) + (prod - z)) + perr
                si = t
            s[i, k] = si
            e[i, k] = ei


def _pairwise_sum(x, n):
    """sum(x[:n]) in numpy's order for contiguous float64 up to n = 128 (its pairwise_sum: a
    plain loop below 8 entries, else eight interleaved accumulators combined as a tree, then
    the tail; longer arrays are split in halves there, not here - the caller keeps n <= 128)."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += x[i]
        return res
    a0, a1, a2, a3, a4, a5, a6, a7 = x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7]
    i = 8
    while i < n - n % 8:
        a0 += x[i]
        a1 += x[i + 1]
        a2 += x[i + 2]
        a3 += x[i + 3]
        a4 += x[i + 4]
        a5 += x[i + 5]
        a6 += x[i + 6]
        a7 += x[i + 7]
        i += 8
    res = ((a0 + a1) + (a2 + a3)) + ((a4 + a5) + (a6 + a7))
    while i < n:
        res += x[i]
        i += 1
    return res


def _best_nu_loops(lam, tau, c):
    """fractional_bound._best_nu_numpy in loops (r <= 128: the sums in numpy's order)."""
    r = lam.shape[0]
    lo, hi = tau / c, tau * r / c  # d: the root lies between (one term alone / all r equal)
    buf = np.empty(r)
    for _ in range(200):
        mid = np.sqrt(lo * hi) if lo > 0 else 0.5 * (lo + hi)
        for i in range(r):
            buf[i] = 1.0 / (lam[i] - lam[0] + mid)
        if tau * _pairwise_sum(buf, r) > c:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-15 * hi:
            break
    return lam[0] - hi


_A1, _A2, _A3 = "float64[::1]", "float64[:, ::1]", "float64[:, :, ::1]"
_I1, _I2 = "int64[::1]", "int64[:, ::1]"
_SIGNATURES = {
    "_step": f"void({_A1}, {_A2}, {_A2}, {_A3}, {_A1}, {_A2}, {_A1}, {_A1}, {_I2}, {_I1}, {_I1}, {_A1}, "
             f"int64, int64, float64, float64, {_A2}, {_A2})",
    "_estimate": f"float64({_A1}, {_A2}, {_A2}, {_A3}, float64, {_A2}, {_A1}, {_I2}, int64, int64, float64)",
    "_dot2_loops": f"void({_A2}, {_A2}, {_A2}, {_A2})",
    "_best_nu_loops": f"float64({_A1}, float64, float64)",
}
# helpers are plain functions numba compiles inline with their callers (njit on first use)
_HELPERS = ("_sym", "_theta", "_vech_blocks", "_blocks", "_kernel_block", "_schur", "_lin_parts",
            "_chol_solve", "_inv_chol", "_spd_inv", "_pencil", "_direction", "_steps", "_equilibrate",
            "_scaled_upper", "_pairwise_sum")


def _bind_helpers():
    """Before the kernels compile: the interior point's LAPACK / BLAS kernels bound and compiled
    (:mod:`._compiled`), the helpers jitted."""
    from numba import njit

    from . import _compiled

    g = globals()
    ipm = _compiled.kernels()  # LAPACK dpotrf / BLAS dtrsv bound and compiled there
    g["_potrf"], g["_cs"] = ipm["_potrf"], ipm["_chol_solve"]
    g["_chol_inv"], g["_pd"], g["_min_eig"] = ipm["_chol_inv"], ipm["_is_pd_shifted"], ipm["_min_eig_lapack"]
    for name in _HELPERS:
        g[name] = njit(cache=True, error_model="numpy")(getattr(g[name], "py_func", g[name]))


_KERNELS = _jit.KernelSet(globals(), _SIGNATURES, order=("_step", "_estimate", "_dot2_loops", "_best_nu_loops"),
                          fastmath={"_dot2_loops": set(), "_best_nu_loops": set()}, before=_bind_helpers,
                          unavailable="the compiled learned-mass interior point is unavailable")


_START_LOCK = threading.Lock()
_BACKGROUND: list = []  # the background build's thread, once started


def kernels() -> dict:
    """The compiled kernels (compiled, or loaded from numba's cache, on the first call; a
    background build under way is waited for)."""
    return _KERNELS.kernels()  # waits for a background build (compiled.BUILD_LOCK)


def loaded() -> dict | None:
    """The kernels if this process has built or loaded them, else None (never builds)."""
    return _KERNELS._kernels


def warm_up() -> float | None:
    """Compile (or load) the kernels now: the seconds it took in this process (0.0 when already
    done), or None when the JIT is unavailable or disabled."""
    return _KERNELS.warm_up()


def _cached(fn) -> bool:
    """Whether numba's cache holds ``fn`` compiled from this source on this machine (its index
    only - nothing is loaded or compiled; numba's own key: the machine and the bytecode)."""
    from numba.core.caching import FunctionCache
    from numba.core.registry import cpu_target

    cache = FunctionCache(getattr(fn, "py_func", fn))
    probe = cache._index_key("", cpu_target.target_context.codegen())
    return any(key[1:] == probe[1:] for key in cache._cache_file._load_index())


def ready() -> bool:
    """Whether the compiled iteration runs now without compiling: built in this process, or
    in numba's cache with the Mh = I kernels it calls (any doubt: False)."""
    if _KERNELS.compile_seconds is not None:
        return True
    if _BACKGROUND or not _jit.available():  # a build under way holds numba's compiler lock
        return False
    try:
        from . import _compiled

        return all(_cached(globals()[name]) for name in _SIGNATURES) and \
            all(_cached(getattr(_compiled, name)) for name in _compiled._SIGNATURES)
    except Exception:  # noqa: BLE001 - numba's cache internals moved: compile when asked
        return False


def compile_in_background() -> None:
    """Build the kernels in a daemon thread (once per process; module docstring)."""
    with _START_LOCK:  # not compiled.BUILD_LOCK: the build holds that throughout
        if _BACKGROUND or _KERNELS.compile_seconds is not None or not _jit.available():
            return
        thread = threading.Thread(target=_build_quietly, name="dolfinx_lopinf-mass-jit", daemon=True)
        _BACKGROUND.append(thread)
        thread.start()
        atexit.register(_finish_at_exit)


def _finish_at_exit() -> None:
    """Wait for a background build still running when the program ends. A daemon thread
    inside LLVM while the interpreter and LLVM's own globals are torn down can abort the
    process (seen once: an LLVM assertion and exit code 134 after a script had finished its
    work); the build is cached, so the wait is paid once per machine."""
    for thread in _BACKGROUND:
        if thread.is_alive():
            print("dolfinx_lopinf: finishing the one-time build of the compiled learned-mass fit "
                  "before exiting (cached for later runs; DOLFINX_LOPINF_JIT=0 turns the "
                  "compiled path off)", file=sys.stderr, flush=True)
            thread.join()


def _build_quietly() -> None:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            kernels()
    except Exception:  # noqa: BLE001 - a failed build leaves the numpy iteration in use
        pass
