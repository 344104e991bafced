"""The interior point iteration of :class:`~dolfinx_lopinf.core.lsq.ipm.PrimalDualIPM` compiled
(numba, optional; ``pip install '.[fast]'``).

``_start`` forms the scaled problem and the starting point in one call (the numpy path's
``PrimalDualIPM.__init__`` and ``_start``: many small numpy calls); then one
call runs whole iterations - the Cholesky factors and inverses of the blocks X_k and
Lambda_k, the HKM terms written straight into the Schur matrix, its Cholesky (LAPACK
``dpotrf``; ``spotrf`` in the early iterations of large problems, each solve checked in
float64 with ``dsymv``: ipm.MIXED_FROM_N and after), the predictor and corrector directions
(two BLAS ``dtrsv`` each), the step lengths (``eigvalsh``) and the update - and returns to
Python only when the loop needs it: to certify (the same test as the numpy loop), to ask
``watch``, or to stop. The arithmetic is the numpy path's, step by step, so the iterates
agree to rounding (tests: objectives to 1e-10, the same iteration counts; with float32
factors a rounding flip can change a direction within the solve's accepted inexactness, so
there: both certified, objectives to 2e-8); the numpy path stays the reference and the
fallback (``backend="numpy"``, or ``DOLFINX_LOPINF_JIT=0``). M0 x is ``dsymv`` on M0's upper
triangle (half the memory traffic of a dgemv).

LAPACK and BLAS are scipy's (``scipy.linalg.cython_lapack``/``cython_blas``, the library
the numpy path calls): their addresses are registered with LLVM under fixed symbol names
when this module is imported, and the kernels call those names, so numba can cache the
compiled code (the addresses change from process to process, the names do not). The
kernels compile on first use with ``cache=True`` (:func:`warm_up` does it ahead of any
timer and returns the seconds it took) and run without the GIL (``nogil``); later processes
load them from numba's cache.
"""

from __future__ import annotations

import numpy as np

from .. import compiled as _jit

# status bits returned by the kernel
WATCH, CERTIFY, MAX_ITER, X_NOT_PD, SCHUR_NOT_PD, NOT_FINITE, NEAR = 1, 2, 4, 8, 16, 32, 64
STEP_FRACTION = 0.98  # the numpy path's (ipm.STEP_FRACTION)
STALL_STEP, STALL_GAP, STALL_RUN = 0.1, 1e3, 3  # ipm.STALL_STEP, ipm.STALL_GAP, ipm.STALL_RUN
NEAR_GAP, NEAR_FLAT = 10.0, 0.5  # ipm.NEAR_GAP, ipm.NEAR_FLAT

_dpotrf = _dtrsv = _spotrf = _strsv = _dsymv = _dsytrd = None  # bound to LAPACK/BLAS by kernels()


def available() -> bool:
    """Whether the compiled iteration can run (numba imports, ``DOLFINX_LOPINF_JIT`` not 0)."""
    return _jit.available()


def _externals():
    """LAPACK d/spotrf, dsytrd and BLAS d/strsv, dsymv of scipy as numba external functions (symbols
    registered with LLVM once per process)."""
    import llvmlite.binding as llb
    from numba import types
    from numba.extending import get_cython_function_address

    out = {}
    for lib, name, nargs in (("scipy.linalg.cython_lapack", "dpotrf", 5),
                             ("scipy.linalg.cython_blas", "dtrsv", 8),
                             ("scipy.linalg.cython_lapack", "spotrf", 5),
                             ("scipy.linalg.cython_blas", "strsv", 8),
                             ("scipy.linalg.cython_blas", "dsymv", 10),
                             ("scipy.linalg.cython_lapack", "dsytrd", 10)):
        symbol = f"dolfinx_lopinf_{name}"
        llb.add_symbol(symbol, get_cython_function_address(lib, name))
        out[name] = types.ExternalFunction(symbol, types.void(*(types.voidptr,) * nargs))
    return out


# --------------------------------------------------------------------------------------------
# Kernel source (plain Python; compiled by kernels(), which binds _dpotrf/_dtrsv first)
# --------------------------------------------------------------------------------------------

def _chol_inv(A, S, Lw):
    """S = R^-1 for the lower Cholesky factor R of the r x r block A (read: its lower
    triangle); False (S undefined) when A is not positive definite, as LAPACK decides it."""
    r = A.shape[0]
    if not _is_pd_shifted(A, 0.0, Lw):  # R in Lw
        return False
    for j in range(r):  # S = R^-1, lower, column by column
        for i in range(r):
            S[i, j] = 0.0
        S[j, j] = 1.0 / Lw[j, j]
        for i in range(j + 1, r):
            t = 0.0
            for k in range(j, i):
                t += Lw[i, k] * S[k, j]
            S[i, j] = -t / Lw[i, i]
    return True


def _matmul(A, B, C):
    """C = A @ B (r x r)."""
    r = A.shape[0]
    for i in range(r):
        for j in range(r):
            C[i, j] = 0.0
        for k in range(r):
            a = A[i, k]
            for j in range(r):
                C[i, j] += a * B[k, j]


def _blocks(x, full, X):
    """X[k] = S_k(x)."""
    b, r = X.shape[0], X.shape[1]
    nv = x.shape[0] // b
    for k in range(b):
        for i in range(r):
            for j in range(r):
                X[k, i, j] = x[k * nv + full[i, j]]


def _assemble(M0, Xi, Lam, iu0, iu1, cw, Mw, shift):
    """The upper triangle (C order; the lower one of the F-ordered view) of the Schur matrix
    2 H + blockdiag(HKM_k) into Mw, the diagonal times 1 + shift. HKM_k's entry of the vech
    pairs p = (i, j), q = (k, l) (i <= j, k <= l) is c_p c_q (Xi_ik L_jl + Xi_il L_jk +
    L_ik Xi_jl + L_il Xi_jk); q runs over (k, l) row by row, so the inner loop over l is
    contiguous in every factor."""
    n = M0.shape[0]
    b, r = Xi.shape[0], Xi.shape[1]
    nv = n // b
    for p in range(n):
        Mw[p, p:] = M0[p, p:]
    for blk in range(b):
        X_, L_ = Xi[blk], Lam[blk]
        o = blk * nv
        for p in range(nv):
            i, j, cp = iu0[p], iu1[p], cw[p]
            row = Mw[o + p]
            q0 = o + p  # the flat position of (k, l) = (i, j) in the row: start of the triangle
            # first the rest of row k = i (l >= j), then full rows k > i (l >= k)
            for k in range(i, r):
                l0 = j if k == i else k
                xik, xjk, lik, ljk = X_[i, k], X_[j, k], L_[i, k], L_[j, k]
                ck = cp * (0.5 if k == l0 else 1.0)
                cc = cp  # off-diagonal pairs weigh c_p
                # the diagonal pair (k, k) first, if in range, with weight c_p / 2
                start = l0
                if l0 == k:
                    v = xik * L_[j, k] + X_[i, k] * ljk + lik * X_[j, k] + L_[i, k] * xjk
                    row[q0] += v * ck
                    q0 += 1
                    start = k + 1
                base = q0 - start  # affine in l: the loop vectorises
                Xi_i, Xj, Li, Lj = X_[i], X_[j], L_[i], L_[j]
                for l in range(start, r):
                    v = xik * Lj[l] + Xi_i[l] * ljk + lik * Xj[l] + Li[l] * xjk
                    row[base + l] += v * cc
                q0 = base + r
    if shift != 0.0:
        for p in range(n):
            Mw[p, p] *= 1.0 + shift


def _potrf(Mw, iw, ch):
    """In-place lower Cholesky of the F-ordered view of Mw; True on success."""
    iw[0] = Mw.shape[0]
    iw[1] = Mw.shape[0]
    iw[2] = 0
    _dpotrf(ch[0:].ctypes, iw[0:].ctypes, Mw.ctypes, iw[1:].ctypes, iw[2:].ctypes)
    return iw[2] == 0


def _potrf32(Mw, Mf, iw, ch):
    """Mw's upper triangle rounded into Mf and the in-place lower Cholesky of Mf's F-ordered
    view in float32 (LAPACK spotrf; numpy: spotrf of Ms.T.astype(float32)); True on success."""
    n = Mw.shape[0]
    for p in range(n):
        for q in range(p, n):
            Mf[p, q] = Mw[p, q]
    iw[0] = n
    iw[1] = n
    iw[2] = 0
    _spotrf(ch[0:].ctypes, iw[0:].ctypes, Mf.ctypes, iw[1:].ctypes, iw[2:].ctypes)
    return iw[2] == 0


def _chol_solve(Mw, v, iw, ch):
    """v <- (L L^T)^-1 v for the lower factor L of the F-ordered view of Mw (two dtrsv)."""
    iw[0] = Mw.shape[0]
    iw[1] = Mw.shape[0]
    iw[3] = 1
    # ch: 'L', 'N', 'T'
    _dtrsv(ch[0:].ctypes, ch[1:].ctypes, ch[1:].ctypes, iw[0:].ctypes, Mw.ctypes, iw[1:].ctypes,
           v.ctypes, iw[3:].ctypes)
    _dtrsv(ch[0:].ctypes, ch[2:].ctypes, ch[1:].ctypes, iw[0:].ctypes, Mw.ctypes, iw[1:].ctypes,
           v.ctypes, iw[3:].ctypes)


def _chol_solve32(Mf, v, v32, iw, ch):
    """_chol_solve with the float32 factor in Mf: v rounded to float32 (v32), two strsv,
    back to float64 (linalg.cholesky_solve of a float32 factor)."""
    n = Mf.shape[0]
    for i in range(n):
        v32[i] = v[i]
    iw[0] = n
    iw[1] = n
    iw[3] = 1
    _strsv(ch[0:].ctypes, ch[1:].ctypes, ch[1:].ctypes, iw[0:].ctypes, Mf.ctypes, iw[1:].ctypes,
           v32.ctypes, iw[3:].ctypes)
    _strsv(ch[0:].ctypes, ch[2:].ctypes, ch[1:].ctypes, iw[0:].ctypes, Mf.ctypes, iw[1:].ctypes,
           v32.ctypes, iw[3:].ctypes)
    for i in range(n):
        v[i] = v32[i]


def _symv(Mw, v, out, iw, ch):
    """out = M v for the symmetric M whose upper triangle (C order) Mw holds (BLAS dsymv)."""
    ab = np.array([1.0, 0.0])
    iw[0] = Mw.shape[0]
    iw[1] = Mw.shape[0]
    iw[3] = 1
    _dsymv(ch[0:].ctypes, iw[0:].ctypes, ab[0:].ctypes, Mw.ctypes, iw[1:].ctypes, v.ctypes,
           iw[3:].ctypes, ab[1:].ctypes, out.ctypes, iw[3:].ctypes)


def _direction(Mw, Mf, single, tol32, Xi, Lam, rd, R, Dw, iu0, iu1, full, dx, dX, dL, T1, T2,
               v32, wk, iw, ch):
    """The numpy path's _direction: XiR = Xi R, dx from the Schur factor, dX = S(dx),
    dL = sym(XiR - Xi dX Lambda); R is overwritten by XiR. With the float32 factor in Mf
    (``single``) the solve's residual is checked in float64 against Mw (wk: 2 x n scratch):
    False, and nothing else done, when it exceeds ``tol32`` (ipm.MIXED_MAX_RESIDUAL)."""
    b, r = Xi.shape[0], Xi.shape[1]
    nv = rd.shape[0] // b
    n = rd.shape[0]
    for k in range(b):
        _matmul(Xi[k], R[k], T1)
        for i in range(r):
            for j in range(r):
                R[k, i, j] = T1[i, j]
        for p in range(nv):
            i, j = iu0[p], iu1[p]
            dx[k * nv + p] = -rd[k * nv + p] + Dw[p] * (0.5 * (T1[i, j] + T1[j, i]))
    if single:
        rhs, res = wk[0], wk[1]
        for p in range(n):
            rhs[p] = dx[p]
        _chol_solve32(Mf, dx, v32, iw, ch)
        _symv(Mw, dx, res, iw, ch)
        rn, bn = 0.0, 0.0
        for p in range(n):
            res[p] = rhs[p] - res[p]
            rn += res[p] * res[p]
            bn += rhs[p] * rhs[p]
        if not np.sqrt(rn) <= tol32 * np.sqrt(bn):
            return False
    else:
        _chol_solve(Mw, dx, iw, ch)
    _blocks(dx, full, dX)
    for k in range(b):
        _matmul(Xi[k], dX[k], T1)
        _matmul(T1, Lam[k], T2)
        for i in range(r):
            for j in range(r):
                T1[i, j] = R[k, i, j] - T2[i, j]
        for i in range(r):
            for j in range(r):
                dL[k, i, j] = 0.5 * (T1[i, j] + T1[j, i])
    return True


def _is_pd_shifted(W, c, Lw):
    """Whether W + c I is positive definite (a Cholesky of its lower triangle succeeds; the
    factor is left in Lw's lower triangle)."""
    r = W.shape[0]
    for j in range(r):
        s = W[j, j] + c
        for k in range(j):
            s -= Lw[j, k] * Lw[j, k]
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        Lw[j, j] = d
        for i in range(j + 1, r):
            t = W[i, j]
            for k in range(j):
                t -= Lw[i, k] * Lw[j, k]
            Lw[i, j] = t / d
    return True


def _min_eig(W, dg, e):
    """Smallest eigenvalue of the symmetric W (overwritten): Householder reduction to a
    tridiagonal (dg, e) - backward stable, as LAPACK's eigvalsh - then bisection and Newton
    on the tridiagonal (cheaper than all eigenvalues by LAPACK's dsterf at these sizes)."""
    r = W.shape[0]
    v = np.empty(r)
    for k in range(r - 2):  # W stays symmetric: row k holds column k
        nrm = 0.0
        for i in range(k + 1, r):
            v[i] = W[k, i]
            nrm += v[i] * v[i]
        nrm = np.sqrt(nrm)
        if nrm == 0.0:
            e[k] = 0.0
            continue
        alpha = -nrm if v[k + 1] >= 0 else nrm
        vv = nrm * nrm - v[k + 1] * alpha  # |v|^2 / 2 for v = x - alpha e_1
        v[k + 1] -= alpha
        e[k] = alpha
        # p = A v / vv, w = p - (p.v / (2 vv)) v, A <- A - v w^T - w v^T on the trailing block
        pv = 0.0
        for i in range(k + 1, r):
            t = 0.0
            for j in range(k + 1, r):
                t += W[i, j] * v[j]
            dg[i] = t / vv  # p, in dg for now
            pv += dg[i] * v[i]
        c = pv / (2.0 * vv)
        for i in range(k + 1, r):
            dg[i] -= c * v[i]  # w
        for i in range(k + 1, r):
            vi, wi = v[i], dg[i]
            for j in range(k + 1, r):
                W[i, j] -= vi * dg[j] + wi * v[j]
    for k in range(r):
        dg[k] = W[k, k]
    if r >= 2:
        e[r - 2] = W[r - 2, r - 1]
    return _tridiag_min_eig(dg, e)


def _min_eig_lapack(W, dg, e, tau, work, iw, ch):
    """_min_eig with LAPACK's blocked Householder reduction (dsytrd on the lower triangle of
    W's F-ordered view - the same symmetric matrix; W overwritten; tau, work: n - 1 and
    work.size scratch) - 4x faster than _min_eig's loops at n = 80 (it updates only one
    triangle, in BLAS)."""
    n = W.shape[0]
    iw[0] = n
    iw[1] = n
    iw[2] = work.shape[0]
    iw[3] = 0
    _dsytrd(ch[0:].ctypes, iw[0:].ctypes, W.ctypes, iw[1:].ctypes, dg.ctypes, e.ctypes, tau.ctypes,
            work.ctypes, iw[2:].ctypes, iw[3:].ctypes)
    if iw[3] != 0:  # an argument refused (dsytrd returns before touching W): the loops' reduction
        return _min_eig(W, dg, e)
    return _tridiag_min_eig(dg, e)


def _tridiag_min_eig(dg, e):
    """The smallest eigenvalue of the symmetric tridiagonal (dg, e): bisection on the Sturm
    count to 1e-3 relative, then Newton on det(T - x I) from the left end (monotone for a
    polynomial with real roots), to rounding."""
    r = dg.shape[0]
    lo, hi, nrm = np.inf, -np.inf, 0.0
    for i in range(r):  # Gershgorin bounds
        rad = (abs(e[i - 1]) if i > 0 else 0.0) + (abs(e[i]) if i < r - 1 else 0.0)
        lo, hi = min(lo, dg[i] - rad), max(hi, dg[i] + rad)
        nrm = max(nrm, abs(dg[i]) + rad)
    if r == 1:
        return dg[0]
    tiny = 1e-300
    tol = 2.220446049250313e-16 * nrm + tiny
    while hi - lo > max(1e-3 * (abs(lo) + abs(hi)), tol):
        x = 0.5 * (lo + hi)
        if _sturm(dg, e, x) >= 1:
            hi = x
        else:
            lo = x
    x = lo
    for _ in range(60):  # Newton: det'/det = sum q_i' / q_i over the Sturm pivots q_i
        q, dq, s = dg[0] - x, -1.0, 0.0
        if q == 0.0:
            return x
        s = dq / q
        for i in range(1, r):
            e2 = e[i - 1] * e[i - 1]
            dq = -1.0 + e2 * dq / (q * q)
            q = dg[i] - x - e2 / q
            if q == 0.0:
                return x
            s += dq / q
        step = -1.0 / s
        if not (step > 0.0) or x + step >= hi:  # rounding at the root, or out of the bracket
            break
        x += step
        if step <= tol:
            break
    return x


def _sturm(dg, e, x):
    """Number of eigenvalues of the tridiagonal (dg, e) below x."""
    q, count = dg[0] - x, 0
    if q < 0.0:
        count += 1
    for i in range(1, dg.shape[0]):
        if q == 0.0:
            q = -1e-300
        q = dg[i] - x - e[i - 1] * e[i - 1] / q
        if q < 0.0:
            count += 1
    return count


def _max_step(S, dX, dL, T1, W, Lw, dg, e):
    """Largest a <= 1 with P_k + a dP_k >= 0 (P: X and Lambda), from S_k = R_k^-1:
    1 / max(0, -min eig(S_k dP_k S_k^T)), as the numpy path. Only eigenvalues below -1/a
    matter, a the bound so far (first 1): a block with S dP S^T + I / a > 0 (a Cholesky)
    cannot lower it and needs no eigenvalue. NaN when a direction is not finite."""
    b, r = dX.shape[0], dX.shape[1]
    ev = -1.0
    for kk in range(2 * b):
        P = dX[kk] if kk < b else dL[kk - b]
        Sk = S[kk]
        _matmul(Sk, P, T1)
        for i in range(r):  # W = (S P) S^T, S^T in Lw for now (row-wise products vectorise)
            for j in range(r):
                Lw[j, i] = Sk[i, j]
        _matmul(T1, Lw, W)
        for i in range(r):
            for j in range(r):
                if not np.isfinite(W[i, j]):
                    return np.nan
        if _is_pd_shifted(W, -ev, Lw):
            continue
        ev = min(ev, _min_eig(W, dg, e))
    return min(1.0, -1.0 / ev)


def _inverses(X, Lam, S, Xi, Lw):
    """S[k] = R^-1 of X_k = R R^T, S[b + k] of Lambda_k, and Xi[k] = X_k^-1 = S^T S (rows of
    S, accumulated: PD however wide X's spread); False when a block is not positive definite."""
    b, r = X.shape[0], X.shape[1]
    for k in range(b):
        if not (_chol_inv(X[k], S[k], Lw) and _chol_inv(Lam[k], S[b + k], Lw)):
            return False
    for k in range(b):
        Sk = S[k]
        Xi[k] = 0.0
        for l in range(r):
            for i in range(l + 1):
                s = Sk[l, i]
                for j in range(l + 1):
                    Xi[k, i, j] += s * Sk[l, j]
    return True


def _status(trace, it, rel, a, gap_tol, watch_below):
    """The status bits after iteration ``it``: WATCH (m mu / f = rel <= watch_below), CERTIFY
    (ipm._ask_certificate: rel <= gap_tol, a step below 1e-3, or a stall - STALL_RUN steps
    below STALL_STEP with rel <= STALL_GAP gap_tol), else NEAR (a step that did not halve
    rel <= NEAR_GAP gap_tol)."""
    status = 0
    if rel <= watch_below:
        status |= WATCH
    stalled = it >= STALL_RUN and rel <= STALL_GAP * gap_tol
    for j in range(it - STALL_RUN, it):
        stalled = stalled and trace[j, 0] < STALL_STEP
    if rel <= gap_tol or a < 1e-3 or stalled:
        status |= CERTIFY
    elif it >= 2 and rel <= NEAR_GAP * gap_tol and rel > NEAR_FLAT * trace[it - 2, 2]:
        status |= NEAR
    return status


def _factor(M0, Xi, Lam, iu0, iu1, cw, Mw, Mf, single, iw, ch):
    """The Schur matrix assembled into Mw and factored: 2 in float32 (into Mf; tried when
    ``single``), 1 in float64 (in place, with the numpy path's relative diagonal shifts if
    rounding needs them), 0 when not positive definite."""
    if single:
        _assemble(M0, Xi, Lam, iu0, iu1, cw, Mw, 0.0)
        if _potrf32(Mw, Mf, iw, ch):
            return 2
    for shift in (0.0, 1e-12, 1e-10, 1e-8):
        _assemble(M0, Xi, Lam, iu0, iu1, cw, Mw, shift)
        if _potrf(Mw, iw, ch):
            return 1
    return 0


def _predictor_corrector(Mw, Mf, single, tol32, S, X, Xi, Lam, XL, rd, R, mu, Dw, iu0, iu1, full,
                         dx, dX, dL, T1, T2, Lw, dg, eo, v32, wk, iw, ch, step):
    """ipm.PrimalDualIPM._predictor_corrector: dx, dL and step = [length, sigma] (length NaN
    when a direction is not finite); False when a float32 solve fails its check."""
    b, r = X.shape[0], X.shape[1]
    m = b * r
    for k in range(b):  # predictor (mu -> 0)
        for i in range(r):
            for j in range(r):
                R[k, i, j] = -XL[k, i, j]
    if not _direction(Mw, Mf, single, tol32, Xi, Lam, rd, R, Dw, iu0, iu1, full, dx, dX, dL, T1,
                      T2, v32, wk, iw, ch):
        return False
    a = _max_step(S, dX, dL, T1, T2, Lw, dg, eo)
    step[0], step[1] = a, np.nan
    if not np.isfinite(a):
        return True
    mu_aff = 0.0
    for k in range(b):
        for i in range(r):
            for j in range(r):
                mu_aff += (X[k, i, j] + a * dX[k, i, j]) * (Lam[k, i, j] + a * dL[k, i, j])
    mu_aff /= m
    sigma = (mu_aff / mu) ** 3
    for k in range(b):  # corrector: R = sigma mu I - X Lambda - dX_aff dLambda_aff
        _matmul(dX[k], dL[k], T1)
        for i in range(r):
            for j in range(r):
                R[k, i, j] = -XL[k, i, j] - T1[i, j]
            R[k, i, i] += sigma * mu
    if not _direction(Mw, Mf, single, tol32, Xi, Lam, rd, R, Dw, iu0, iu1, full, dx, dX, dL, T1,
                      T2, v32, wk, iw, ch):
        return False
    a = _max_step(S, dX, dL, T1, T2, Lw, dg, eo)
    step[0], step[1] = min(1.0, STEP_FRACTION * a) if np.isfinite(a) else np.nan, sigma
    return True


def _iterate(M0, hs2, c0, f_floor, Dw, iu0, iu1, cw, full, x, Lam, Mw, Mf, mixed, it0, max_iter,
             gap_tol, watch_below, trace, info):
    """Iterations it0, it0 + 1, .. of PrimalDualIPM.run (x, Lam updated in place), until one
    of them asks for Python: returns status bits (WATCH: m mu / f <= watch_below, CERTIFY:
    the numpy loop's certify test, MAX_ITER, or a stop: X_NOT_PD, SCHUR_NOT_PD,
    NOT_FINITE); info = [last iteration, mu, f, step, sigma, float32 off (1.0: spotrf failed
    or a solve missed its check; the run's rule), float32 iterations]. The Schur matrix is
    factored in float32 (in Mf) while m mu / f > mixed[0] (ipm.MIXED_ABOVE_GAP; inf: never),
    its solves accepted up to the relative residual mixed[1] (ipm.MIXED_MAX_RESIDUAL)."""
    n = x.shape[0]
    b, r = Lam.shape[0], Lam.shape[1]
    nv = n // b
    m = b * r
    X = np.empty((b, r, r))
    S = np.empty((2 * b, r, r))
    Xi = np.empty((b, r, r))
    XL = np.empty((b, r, r))
    R = np.empty((b, r, r))
    dX = np.empty((b, r, r))
    dL = np.empty((b, r, r))
    T1 = np.empty((r, r))
    T2 = np.empty((r, r))
    Lw = np.empty((r, r))
    dg = np.empty(r)
    eo = np.empty(max(r - 1, 1))
    rd = np.empty(n)
    dx = np.empty(n)
    y = np.empty(n)
    v32 = np.empty(n, dtype=np.float32)
    wk = np.empty((2, n))
    step = np.empty(2)
    iw = np.zeros(4, dtype=np.int32)
    ch = np.array([76, 78, 84], dtype=np.uint8)  # 'L', 'N', 'T'
    _symv(M0, x, y, iw, ch)
    it = it0
    while it <= max_iter:
        info[0] = it
        _blocks(x, full, X)
        if not _inverses(X, Lam, S, Xi, Lw):
            return X_NOT_PD
        for k in range(b):
            for p in range(nv):
                rd[k * nv + p] = y[k * nv + p] + hs2[k * nv + p] - Dw[p] * Lam[k, iu0[p], iu1[p]]
        mu = np.sum(X * Lam) / m
        info[1] = mu
        single = False
        if info[5] == 0.0 and mixed[0] < np.inf:  # m mu / f now, as the numpy loop's rel
            f_now = max(abs(0.5 * (x @ y) + hs2 @ x + c0), f_floor)
            single = m * mu / f_now > mixed[0]
        for k in range(b):
            _matmul(X[k], Lam[k], XL[k])
        for _ in range(2):  # the second in float64, when float32 was refused
            kind = _factor(M0, Xi, Lam, iu0, iu1, cw, Mw, Mf, single, iw, ch)
            if kind == 0:
                info[2] = 0.5 * (x @ y) + hs2 @ x + c0
                return SCHUR_NOT_PD
            served = kind == 2 and _predictor_corrector(
                Mw, Mf, True, mixed[1], S, X, Xi, Lam, XL, rd, R, mu, Dw, iu0, iu1, full, dx, dX,
                dL, T1, T2, Lw, dg, eo, v32, wk, iw, ch, step)
            if served:
                info[6] += 1.0
                break
            if single:  # spotrf failed or a solve missed its check: float64 from now on
                info[5] = 1.0
                single = False
                if kind == 2:
                    continue
            _predictor_corrector(Mw, Mf, False, mixed[1], S, X, Xi, Lam, XL, rd, R, mu, Dw, iu0,
                                 iu1, full, dx, dX, dL, T1, T2, Lw, dg, eo, v32, wk, iw, ch, step)
            break
        a, sigma = step[0], step[1]
        if not np.isfinite(a):
            return NOT_FINITE
        for p in range(n):
            x[p] += a * dx[p]
        for k in range(b):
            for i in range(r):
                for j in range(r):
                    Lam[k, i, j] += a * dL[k, i, j]
        _symv(M0, x, y, iw, ch)
        _blocks(x, full, X)
        mu = np.sum(X * Lam) / m
        f_ref = max(abs(0.5 * (x @ y) + hs2 @ x + c0), f_floor)  # f_floor > 0 (PrimalDualIPM)
        rel = m * mu / f_ref
        trace[it - 1, 0] = a
        trace[it - 1, 1] = sigma
        trace[it - 1, 2] = rel
        info[1], info[2], info[3], info[4] = mu, f_ref, a, sigma
        status = _status(trace, it, rel, a, gap_tol, watch_below)
        if status:
            return status
        it += 1
    info[0] = max_iter
    return MAX_ITER


def _start(H, h, const, T, x_eps, x_start, full, f_floor, M0, hs2, x, X, Lam):
    """PrimalDualIPM's scaled problem and start in one call (numpy: __init__ and _start):
    M0 = 2 T H T, hs2 = 2 T (H x_eps + h), and returned c0 = f(x_eps); then the start - per
    block the scaled S_k(x_start) - eps I = Q diag(w) Q^T, X_k = Q diag(w') Q^T with
    w' = max(|w|, 1e-3 max |w|), x = vech(X) - and Lambda_k = c X_k^-1 = Q diag(c / w') Q^T,
    c = 0.1 max(|f(x)|, f_floor) / m."""
    n = H.shape[0]
    b, r = X.shape[0], X.shape[1]
    nv = n // b
    for p in range(n):
        tp, s = 2.0 * T[p], 0.0
        for q in range(n):
            M0[p, q] = tp * H[p, q] * T[q]
            s += H[p, q] * x_eps[q]
        hs2[p] = s  # H x_eps for now
    c0 = x_eps @ hs2 + (2.0 * h) @ x_eps + const
    for p in range(n):
        hs2[p] = 2.0 * T[p] * (hs2[p] + h[p])
    W = np.empty((b, r))
    Q = np.empty((b, r, r))
    S = np.empty((r, r))
    for k in range(b):
        for i in range(r):
            for j in range(r):
                pos = k * nv + full[i, j]
                S[i, j] = (x_start[pos] - x_eps[pos]) / T[pos]
        w, V = np.linalg.eigh(S)
        top = np.abs(w).max()
        for i in range(r):
            W[k, i] = max(abs(w[i]), 1e-3 * top)
        Q[k] = V
        X[k] = (V * W[k]) @ V.T
        for i in range(r):
            for j in range(i, r):
                x[k * nv + full[i, j]] = X[k, i, j]
    y = M0 @ x
    c = 0.1 * max(abs(0.5 * (x @ y) + hs2 @ x + c0), f_floor) / (b * r)
    for k in range(b):
        Lam[k] = (Q[k] * (c / W[k])) @ Q[k].T
    return c0


_A1, _A2, _A3 = "float64[::1]", "float64[:, ::1]", "float64[:, :, ::1]"
_I1, _I2 = "int64[::1]", "int64[:, ::1]"
_SIGNATURES = {
    "_chol_inv": f"boolean({_A2}, {_A2}, {_A2})",
    "_matmul": f"void({_A2}, {_A2}, {_A2})",
    "_blocks": f"void({_A1}, {_I2}, {_A3})",
    "_assemble": f"void({_A2}, {_A3}, {_A3}, {_I1}, {_I1}, {_A1}, {_A2}, float64)",
    "_potrf": f"boolean({_A2}, int32[::1], uint8[::1])",
    "_potrf32": f"boolean({_A2}, float32[:, ::1], int32[::1], uint8[::1])",
    "_chol_solve32": f"void(float32[:, ::1], {_A1}, float32[::1], int32[::1], uint8[::1])",
    "_chol_solve": f"void({_A2}, {_A1}, int32[::1], uint8[::1])",
    "_symv": f"void({_A2}, {_A1}, {_A1}, int32[::1], uint8[::1])",
    "_direction": f"boolean({_A2}, float32[:, ::1], boolean, float64, {_A3}, {_A3}, {_A1}, {_A3}, {_A1}, "
                  f"{_I1}, {_I1}, {_I2}, {_A1}, {_A3}, {_A3}, {_A2}, {_A2}, float32[::1], {_A2}, "
                  f"int32[::1], uint8[::1])",
    "_inverses": f"boolean({_A3}, {_A3}, {_A3}, {_A3}, {_A2})",
    "_status": f"int64({_A2}, int64, float64, float64, float64, float64)",
    "_factor": f"int64({_A2}, {_A3}, {_A3}, {_I1}, {_I1}, {_A1}, {_A2}, float32[:, ::1], boolean, "
               f"int32[::1], uint8[::1])",
    "_predictor_corrector": f"boolean({_A2}, float32[:, ::1], boolean, float64, {_A3}, {_A3}, {_A3}, {_A3}, "
                            f"{_A3}, {_A1}, {_A3}, float64, {_A1}, {_I1}, {_I1}, {_I2}, {_A1}, "
                            f"{_A3}, {_A3}, {_A2}, {_A2}, {_A2}, {_A1}, {_A1}, float32[::1], "
                            f"{_A2}, int32[::1], uint8[::1], {_A1})",
    "_is_pd_shifted": f"boolean({_A2}, float64, {_A2})",
    "_sturm": f"int64({_A1}, {_A1}, float64)",
    "_tridiag_min_eig": f"float64({_A1}, {_A1})",
    "_min_eig": f"float64({_A2}, {_A1}, {_A1})",
    "_min_eig_lapack": f"float64({_A2}, {_A1}, {_A1}, {_A1}, {_A1}, int32[::1], uint8[::1])",
    "_max_step": f"float64({_A3}, {_A3}, {_A3}, {_A2}, {_A2}, {_A2}, {_A1}, {_A1})",
    "_iterate": f"int64({_A2}, {_A1}, float64, float64, {_A1}, {_I1}, {_I1}, {_A1}, {_I2}, {_A1}, {_A3}, "
                f"{_A2}, float32[:, ::1], {_A1}, int64, int64, float64, float64, {_A2}, {_A1})",
    "_start": f"float64({_A2}, {_A1}, float64, {_A1}, {_A1}, {_A1}, {_I2}, float64, {_A2}, {_A1}, "
              f"{_A1}, {_A3}, {_A3})",
}
# the Householder reduction's dot products summed in SIMD lanes (an equally exact order)
_FASTMATH = {"_min_eig": {"contract", "reassoc"}, "_tridiag_min_eig": {"contract", "reassoc"}}
# helpers first: a kernel is compiled against the compiled helpers it calls
_ORDER = ("_is_pd_shifted", "_chol_inv", "_matmul", "_blocks", "_assemble", "_potrf", "_potrf32",
          "_chol_solve", "_chol_solve32", "_symv", "_direction", "_inverses", "_status",
          "_factor", "_sturm", "_tridiag_min_eig", "_min_eig", "_min_eig_lapack", "_max_step", "_predictor_corrector", "_iterate",
          "_start")


def _bind_externals():
    g = globals()
    ext = _externals()
    g["_dpotrf"], g["_dtrsv"] = ext["dpotrf"], ext["dtrsv"]
    g["_spotrf"], g["_strsv"], g["_dsymv"] = ext["spotrf"], ext["strsv"], ext["dsymv"]
    g["_dsytrd"] = ext["dsytrd"]


# no fast-math: the same operations in the same order as written (FMA contraction aside), like
# the numpy path - except _FASTMATH's
_IPM_KERNELS = _jit.KernelSet(globals(), _SIGNATURES, fastmath=_FASTMATH, order=_ORDER,
                              before=_bind_externals,
                              unavailable="the compiled interior point is unavailable")


def kernels() -> dict:
    """The compiled kernels (compiled, or loaded from numba's cache, on the first call)."""
    return _IPM_KERNELS.kernels()


def warm_up() -> float | None:
    """Compile (or load from the cache) the kernels now; the seconds it took in this process
    (0.0 when already done), or None when the JIT is unavailable or disabled."""
    return _IPM_KERNELS.warm_up()


def compile_seconds() -> float | None:
    """Seconds the first :func:`kernels` call took in this process (None before it)."""
    return _IPM_KERNELS.compile_seconds
