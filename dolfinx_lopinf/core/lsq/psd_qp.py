"""A convex quadratic objective under linear matrix inequalities of any sizes, by a certified
primal-dual interior point (HKM direction, Mehrotra predictor-corrector).

    min  f(x) = x^T H x + 2 h^T x + c      s.t.  X_k(x) = A_k(x) - F_k >= 0,   k = 1 .. K,

H > 0 (n x n), A_k: x -> vech of an n_k x n_k symmetric matrix, given by a dense
(n_k (n_k + 1) / 2, n) matrix P_k (vech: the upper triangle, row by row; the entry (i, j) of
vech stands for both (i, j) and (j, i)), F_k the floors. The polynomial (sum-of-squares)
potential fit is one (:mod:`dolfinx_lopinf.core.polynomial.sos`): a Gram matrix of
(r + r (r + 1) / 2)^2 / 2 unknowns and two small blocks.

Newton (multipliers Lambda_k eliminated, dLambda = sym(X^-1 (R - dX Lambda))):

    (2 H + sum_k P_k^T K(X_k^-1, Lambda_k) P_k) dx = -r_d + sum_k P_k^T D vech sym(X_k^-1 R_k),

r_d = 2 H x + 2 h - sum_k P_k^T D vech Lambda_k, K the Kronecker kernel of
:func:`.fractional.kernel`, D the weights 2 off the diagonal. x stays strictly feasible.

Certificate (as :meth:`.problem.Problem.dual_gap`): for any Lambda_k >= 0 the Lagrangian's
minimum g(Lambda) satisfies f(x) - g(Lambda) = 1/4 v^T H^-1 v + sum_k <Lambda_k, X_k(x)>,
v = r_d at x - two nonnegative terms, no cancellation; ``duality_gap`` = that over
max(f(x) + f_const, GAP_FLOOR f_scale) (f_const: what a compressed least squares dropped).
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from .. import compiled as _jit
from .fractional import kernel
from .linalg import SPDSolver, from_eig, sym
from .problem import Certificate
from ...errors import InputError

STEP_FRACTION = 0.98
#: the gap's reference is max(f + f_const, GAP_FLOOR f_scale): gap_tol 1e-8 of the floor is
#: 1e-14 f_scale, near what the interior point resolves on exact data (measured: stalls at
#: ~1e-14 f_scale of complementarity on the compressed polynomial fit); :func:`polish` goes on
#: from there where the data are fitted nearly exactly
GAP_FLOOR = 1e-6
SHIFTS = (0.0, 1e-12, 1e-10, 1e-8)
#: the interior point stops where two iterations did not halve a gap estimate below
#: FLAT_NEAR gap_tol (and the gap is not met): the polish goes on from there
FLAT_NEAR = 10.0
#: a step length below SLOW_STEP is a sign of a jam: the certified gap is computed there
SLOW_STEP = 0.5
#: QuadraticPSD._scaled_correction: a null-space part of its multiplier up to LEFT_ROUNDING u
#: |lin| is the rounding of computing it (measured up to 233 u |lin|)
LEFT_ROUNDING = 1e4


def _kernel_loop(P, Q, iu0, iu1, H):
    """H = K(P, Q) (:func:`.fractional.kernel` with one term) entry by entry: P and Q are
    n x n (in cache), where the numpy kernel gathers from their n^2 x n^2 Kronecker product."""
    nv = iu0.shape[0]
    for p in range(nv):
        i, j = iu0[p], iu1[p]
        cp = 0.5 if i == j else 1.0
        for q in range(nv):
            a, b = iu0[q], iu1[q]
            cq = 0.5 if a == b else 1.0
            H[p, q] = cp * cq * (P[j, a] * Q[b, i] + P[j, b] * Q[a, i] + P[i, a] * Q[b, j]
                                 + P[i, b] * Q[a, j])


def _sym_scaled_lower(S, d):
    """The lower triangle of S := sym(S) scaled by d on both sides, in place, in one pass:
    S_ij = ((S_ij + S_ji) (d_i / 2)) d_j for i >= j (the upper triangle is left as it was;
    the Cholesky factorisation reads the lower one). The operations of the numpy passes
    S += S^T, S *= d/2 (rows), S *= d (columns), in their order: the same bits."""
    n = S.shape[0]
    for i in range(n):
        hi = 0.5 * d[i]
        for j in range(i + 1):
            S[i, j] = ((S[i, j] + S[j, i]) * hi) * d[j]


_KERNEL_SIGNATURES = {"_kernel_loop": "void(float64[:, ::1], float64[:, ::1], int64[::1], int64[::1], "
                                      "float64[:, ::1])",
                      "_sym_scaled_lower": "void(float64[:, ::1], float64[::1])"}
_KERNELS = _jit.KernelSet(globals(), _KERNEL_SIGNATURES, unavailable="the compiled psd kernel is unavailable")


def _kernel(P, Q, n):
    """K(P, Q) for the Newton matrix: compiled when numba is there (the numpy kernel's
    Kronecker gathers are most of an iteration's time from n ~ 40 on), else numpy."""
    if _jit.resolve_backend("auto") == "numba":
        i, j, _, _ = _vech(n)
        H = np.empty((len(i), len(i)))
        _KERNELS.kernels()["_kernel_loop"](np.ascontiguousarray(P), np.ascontiguousarray(Q),
                                            i.astype(np.int64), j.astype(np.int64), H)  # writable
        return H
    return kernel([(1.0, P, Q)], n)



def sym_scaled_lower(S, d):
    """:func:`_sym_scaled_lower` (compiled where numba is there; else the three numpy passes,
    which also fill the upper triangle)."""
    if _jit.resolve_backend("auto") == "numba":
        _KERNELS.kernels()["_sym_scaled_lower"](S, np.ascontiguousarray(d, dtype=float))
        return S
    S += S.T
    S *= 0.5 * d[:, None]
    S *= d[None, :]
    return S


@functools.lru_cache(maxsize=32)
def _vech(n: int):
    i, j = np.triu_indices(n)
    full = np.zeros((n, n), dtype=np.intp)
    full[i, j] = full[j, i] = np.arange(len(i))
    w = np.where(i == j, 1.0, 2.0)
    for a in (i, j, full, w):
        a.setflags(write=False)
    return i, j, full, w


def unvech(v, n):
    return v[_vech(n)[2]]


def vech(S):
    i, j, _, _ = _vech(S.shape[0])
    return S[i, j]


@dataclass(frozen=True, eq=False)
class QuadraticPSD:
    """The problem of the module docstring; ``f_scale`` sets the gap floor."""

    H: np.ndarray
    h: np.ndarray
    c: float
    P: list
    F: list
    f_scale: float = 1.0
    null: np.ndarray | None = None    # (n, k) orthonormal: H's null space, inside block 0's
    moment: np.ndarray | None = None  # block 0: a PD matrix orthogonal to A_0(null)
    A: np.ndarray | None = None       # f = |A x - b|^2 (H = A^T A, h = -A^T b, c = |b|^2):
    b: np.ndarray | None = None       # f and its gradient from the residual, no cancellation
    f_const: float = 0.0              # a constant the objective stands for beside f (the gap's
                                      # reference is f + f_const: a compressed least squares)
    flat: object = None               # (n, k) scipy.sparse: any basis of A's null space (the
                                      # polish's steps in it; a sparse one makes them cheap)
    sizes: tuple = field(init=False)

    def __post_init__(self):
        sizes = []
        for Pk, Fk in zip(self.P, self.F):
            nk = Fk.shape[0]
            if Pk.shape != (nk * (nk + 1) // 2, len(self.h)):
                raise InputError(f"P_k {Pk.shape} does not map {len(self.h)} unknowns to {nk} x {nk}")
            sizes.append(nk)
        object.__setattr__(self, "sizes", tuple(sizes))

    @functools.cached_property
    def selections(self) -> list:
        """Per block (unknown indices, scale) when P_k is a scaled selection (one nonzero per
        row, all equal, in distinct columns), else None."""
        out = []
        for Pk in self.P:
            nz = Pk != 0
            cols = np.argmax(nz, axis=1)
            vals = Pk[np.arange(len(Pk)), cols]
            ok = (nz.sum(axis=1) == 1).all() and len(set(cols.tolist())) == len(cols) \
                and np.all(vals == vals[0])
            if ok and len(cols) and np.array_equal(cols, np.arange(cols[0], cols[0] + len(cols))):
                cols = slice(int(cols[0]), int(cols[0]) + len(cols))  # contiguous: a view, no gather
            out.append((cols, float(vals[0])) if ok else None)
        return out

    def block(self, k: int, x) -> np.ndarray:
        """P_k x (a gather where P_k is a scaled selection)."""
        sel = self.selections[k]
        if sel is None:
            return self.P[k] @ x
        idx, scale = sel
        return scale * x[idx]

    def block_T(self, k: int, v) -> np.ndarray:
        """P_k^T v (a scatter where P_k is a scaled selection)."""
        sel = self.selections[k]
        if sel is None:
            return self.P[k].T @ v
        idx, scale = sel
        out = np.zeros(len(self.h))
        out[idx] = scale * v
        return out

    def objective(self, x) -> float:
        if self.A is not None:
            res = self.A @ x - self.b
            return float(res @ res)
        return float(x @ (self.H @ x) + 2.0 * self.h @ x + self.c)

    def gradient(self, x) -> np.ndarray:
        if self.A is not None:
            return 2.0 * (self.A.T @ (self.A @ x - self.b))
        return 2.0 * (self.H @ x + self.h)

    def slacks(self, x) -> list:
        return [unvech(self.block(k, x), nk) - Fk for k, (Fk, nk) in enumerate(zip(self.F, self.sizes))]

    def lin(self, Lam) -> np.ndarray:
        """sum_k P_k^T D vech(Lambda_k): the gradient of sum_k <Lambda_k, A_k(x)>."""
        return sum(self.block_T(k, _vech(nk)[3] * vech(Lk)) for k, (Lk, nk) in enumerate(zip(Lam, self.sizes)))

    @functools.cached_property
    def _H_factor(self):
        H = self.H if self.null is None else self.H + self.null @ self.null.T  # H+ on range(H)
        d = 1.0 / np.sqrt(np.diag(H))
        try:
            return scipy.linalg.cho_factor(H * d[:, None] * d[None, :], lower=True, check_finite=False), d
        except np.linalg.LinAlgError:  # singular beyond the null space found: no bound
            return None

    def H_solve(self, v):
        """H^-1 v (H + N N^T with a null space N), or None where H is not positive definite
        numerically (a flat direction not in N: the dual function is unbounded there)."""
        if self._H_factor is None:
            return None
        c, d = self._H_factor
        return d * scipy.linalg.cho_solve(c, d * v, check_finite=False)

    def gap(self, x, Lam) -> float:
        """The certified relative gap of x with the multipliers Lambda (clipped >= 0). With a
        null space N of H (along which f is flat) the Lagrangian is bounded only if
        N^T sum_k P_k^T D vech Lambda_k = 0 (= c): any such multipliers >= 0 prove a bound.
        Block 0's multiplier is corrected so: first by the plain projection (Lambda_0 - L_0,
        L_0 the part along N); where that costs positive definiteness - Lambda_0's eigenvalues
        fall far below |L_0| near the optimum - by :meth:`_scaled_correction` (Lambda_0 +
        Lambda_0 Z Lambda_0) and by raising the projection t ``moment`` (PD, orthogonal to N);
        the smaller of their gaps."""
        Lam = [sym(Lk) for Lk in Lam]
        if self.null is None:
            return self._gap_at(x, Lam)
        n0 = self.sizes[0]
        c = self.null.T @ self.lin(Lam)  # the part to remove
        du = self.null @ c
        sel = self.selections[0]
        if sel is not None:  # P_0 = scale x selection: invert it directly
            idx, scale = sel
            L0 = unvech(du[idx] / (scale * _vech(n0)[3]), n0)
        else:
            L0 = unvech(np.linalg.lstsq(self.P[0].T * _vech(n0)[3][None, :], du, rcond=None)[0], n0)
        projected = Lam[0] - L0
        low = scipy.linalg.eigvalsh(projected, self.moment, subset_by_index=[0, 0])[0]
        if low >= 0:
            return self._gap_at(x, [projected] + Lam[1:])
        raised = projected - low * (1.0 + 1e-12) * self.moment
        gap = self._gap_at(x, [raised] + Lam[1:])
        scaled = self._scaled_correction(Lam, c)
        if scaled is not None:
            gap = min(gap, self._gap_at(x, [scaled] + Lam[1:]))
        return gap

    def _scaled_correction(self, Lam, c):
        """Lambda_0 + E with E = Lambda_0 Z Lambda_0, Z = unvech(P_0 N y) a Gram matrix of the
        zero polynomial, y solving (N^T P_0^T K(Lambda_0, Lambda_0) P_0 N) y = -c: the
        correction that removes the null part where Lambda_0 is large and leaves its small
        eigenvalues (those complementary to the large ones of X_0) nearly alone, so that it
        stays >= 0 and moves <Lambda_0, X_0> little. The moment raise instead adds t M with t
        ~ |L_0| / lambda_min(Lambda_0) (the SVK trajectory probes at r = 8, a jammed iterate:
        relative gap 0.34 -> 2.5e-7, the complementarity's). None where it does not apply."""
        sel = self.selections[0]
        if sel is None:
            return None
        idx, scale = sel
        n0 = self.sizes[0]
        N0 = self.null[idx]
        T = (scale * scale) * (N0.T @ (_kernel(Lam[0], Lam[0], n0) @ N0))
        try:
            y = scipy.linalg.solve(T, -c, assume_a="pos", check_finite=False)
        except (np.linalg.LinAlgError, ValueError):
            return None
        out = sym(Lam[0] + Lam[0] @ unvech(scale * (N0 @ y), n0) @ Lam[0])
        lin = self.lin([out] + Lam[1:])
        left = np.linalg.norm(self.null.T @ lin)
        # what is left along N must be no more than what remains of c or the rounding of lin
        # (measured on the SVK trajectory probes: up to 5.5e-7 |c| and 233 u |lin|; a failed
        # solve leaves ~|c|)
        if not np.all(np.isfinite(out)) or left > max(1e-6 * np.linalg.norm(c),
                                                       LEFT_ROUNDING * np.finfo(float).eps * np.linalg.norm(lin)):
            return None  # the solve lost the constraint: not a valid multiplier
        return out

    def _gap_at(self, x, Lam) -> float:
        """(1/4 v^T H^-1 v + sum_k <Lambda_k, X_k(x)>) / reference, Lambda clipped >= 0."""
        Lam = [from_eig(np.maximum(w, 0.0), Q) for w, Q in (np.linalg.eigh(Lk) for Lk in Lam)]
        v = self.gradient(x) - self.lin(Lam)
        comp = sum(float(np.sum(Lk * Xk)) for Lk, Xk in zip(Lam, self.slacks(x)))
        f = self.objective(x)
        Hv = self.H_solve(v)
        if Hv is None:
            return np.inf
        return max(0.25 * float(v @ Hv) + comp, 0.0) / self.reference(f)

    def reference(self, f) -> float:
        """The gap's reference: max(f + f_const, GAP_FLOOR f_scale)."""
        return max(f + self.f_const, GAP_FLOOR * self.f_scale, 1e-300)


def _add_kernels(p: QuadraticPSD, S, Xi, Lam):
    """S + sum_k P_k^T K(X_k^-1, Lambda_k) P_k, in place (unsymmetrised)."""
    for k, (Pk, Xik, Lk, nk) in enumerate(zip(p.P, Xi, Lam, p.sizes)):
        Kk = _kernel(Xik, Lk, nk)
        sel = p.selections[k]
        if sel is not None:  # P_k = scale x (a selection of unknowns): scatter, no products
            idx, scale = sel
            Kk *= scale * scale
            if isinstance(idx, slice):  # a contiguous range (the Gram block): in place
                S[idx, idx] += Kk
            else:
                S[np.ix_(idx, idx)] += Kk
        else:
            S += Pk.T @ Kk @ Pk
    return S


def _step_to_boundary(pairs) -> float:
    """The largest a with M + a dM >= 0 for every (M > 0, dM) of ``pairs`` (inf if none
    bounds it): 1 / the most negative eigenvalue of R^-1 dM R^-T, M = R R^T. LinAlgError
    where an M is not positive definite."""
    a = np.inf
    for Mk, dMk in pairs:
        Ri = np.linalg.inv(np.linalg.cholesky(Mk))
        ev = np.linalg.eigvalsh(Ri @ dMk @ Ri.T)[0]
        if ev < 0:
            a = min(a, -1.0 / ev)
    return a


def solve(problem: QuadraticPSD, x0, gap_tol=1e-8, max_iter=60):
    """The interior point from the strictly feasible x0: (x, Certificate)."""
    t0 = time.perf_counter()
    p = problem
    n = len(p.h)
    K = len(p.P)
    x = np.array(x0, dtype=float)
    X = p.slacks(x)
    m = sum(p.sizes)
    f = p.objective(x)
    mu0 = p.reference(f) / m
    Lam = [mu0 * np.linalg.inv(Xk) for Xk in X]
    trace, best, stopped = [], (np.inf, x, Lam), "max_iter"
    prev = (x, Lam)  # the last iterate inside the cones
    S_buf = np.empty((n, n))  # the Schur matrix's buffer, assembled and factorised in place
    gaps = []  # the certified gap where it was computed, else nan
    it = 0
    for it in range(1, max_iter + 1):
        X = p.slacks(x)
        mu = sum(float(np.sum(Xk * Lk)) for Xk, Lk in zip(X, Lam)) / m
        Xi = [np.linalg.inv(Xk) for Xk in X]

        def schur(S=S_buf, Xi=Xi, Lam=Lam):
            """The equilibrated sym(2 H + sum_k P_k^T K(X_k^-1, Lambda_k) P_k) (lower
            triangle) in the buffer, and the scaling dd."""
            np.multiply(p.H, 2.0, out=S)
            _add_kernels(p, S, Xi, Lam)
            dd = 1.0 / np.sqrt(np.diag(S))
            return sym_scaled_lower(S, dd), dd

        S, dd = schur()
        fac = None
        for shift in SHIFTS:
            if shift:  # the failed factorisation overwrote the buffer: assembled again
                S, dd = schur()
                S[np.diag_indices(n)] += shift
            try:
                fac = scipy.linalg.cho_factor(S, lower=True, overwrite_a=True, check_finite=False)
                break
            except np.linalg.LinAlgError:
                continue
        if fac is None:
            stopped = f"Schur matrix not positive definite at iteration {it}"
            break
        rd = p.gradient(x) - p.lin(Lam)

        def direction(R, rd=rd, Xi=Xi, dd=dd, fac=fac, Lam=Lam):
            rhs = -rd + sum(p.block_T(k, _vech(nk)[3] * vech(sym(Xik @ Rk)))
                            for k, (Xik, Rk, nk) in enumerate(zip(Xi, R, p.sizes)))
            dx = dd * scipy.linalg.cho_solve(fac, dd * rhs, check_finite=False)
            dX = [unvech(p.block(k, dx), nk) for k, nk in enumerate(p.sizes)]
            dL = [sym(Xik @ (Rk - dXk @ Lk)) for Xik, Rk, dXk, Lk in zip(Xi, R, dX, Lam)]
            return dx, dX, dL

        def step(dX, dL, X=X, Lam=Lam):
            return min(1.0, _step_to_boundary(list(zip(X, dX)) + list(zip(Lam, dL))))

        XL = [Xk @ Lk for Xk, Lk in zip(X, Lam)]
        try:
            dx, dX, dL = direction([-XLk for XLk in XL])
            a = step(dX, dL)
            mu_aff = sum(float(np.sum((Xk + a * dXk) * (Lk + a * dLk)))
                         for Xk, dXk, Lk, dLk in zip(X, dX, Lam, dL)) / m
            sigma = min(1.0, mu_aff / mu) ** 3
            dx, dX, dL = direction([sigma * mu * np.eye(nk) - XLk - dXk @ dLk
                                    for nk, XLk, dXk, dLk in zip(p.sizes, XL, dX, dL)])
            a = min(1.0, STEP_FRACTION * step(dX, dL))
        except np.linalg.LinAlgError:  # rounding took the iterate out of its cone: the one before
            stopped = f"an iterate left its cone by rounding at iteration {it}"
            x, Lam = prev
            break
        prev = (x, Lam)
        x = x + a * dx
        Lam = [Lk + a * dLk for Lk, dLk in zip(Lam, dL)]
        X = p.slacks(x)
        f = p.objective(x)
        est = sum(float(np.sum(Xk * Lk)) for Xk, Lk in zip(X, Lam)) / p.reference(f)
        trace.append((a, sigma, est))
        short = len(trace) >= 3 and max(t[0] for t in trace[-3:]) < 0.05
        near = est <= FLAT_NEAR * gap_tol
        # the gap also after a step below SLOW_STEP: where the iteration jams, its iterates'
        # dual residual (hence the gap) can grow 50x over a few steps that move nothing else
        # (SVK trajectory probes, r = 8: 4.2e-6 -> 2.0e-4), so the best is kept from the first
        gaps.append(p.gap(x, Lam) if est <= gap_tol or short or near or a < SLOW_STEP else np.nan)
        # flat at the tolerance: two iterations that halved neither an estimate already within
        # FLAT_NEAR gap_tol nor the certified gap (the complementarity's rounding floor on
        # exact data; the short steps that end it there came three iterations later, each a
        # Cholesky of the Schur matrix). Where the gap still falls - the dual residual's part,
        # on data no potential fits - the iterations go on.
        flat = near and len(trace) >= 3 and est > 0.5 * trace[-3][2] and gaps[-1] > 0.5 * gaps[-3]
        if not np.isnan(gaps[-1]):
            g = gaps[-1]
            if g < best[0]:
                best = (g, x, Lam)
            if g <= gap_tol:
                stopped = "certified"
                break
            if short or flat:
                stopped = f"stalled at iteration {it}" + (" (flat at the tolerance)" if flat and not short else "")
                break
    if not np.isfinite(best[0]):
        best = (p.gap(x, Lam), x, Lam)
    gap, x, Lam = best
    polished = None
    f = p.objective(x)
    if (p.A is not None and np.isfinite(gap) and f > POLISH_FROM * p.f_const
            and gap * p.reference(f) > gap_tol * (f + p.f_const)):
        # near-exact data: certified, if at all, only against the floor GAP_FLOOR f_scale, and
        # the interior point's own misfit is not small beside the data's (f_const)
        x, gap, polished = polish(p, x, Lam, gap)
        if gap <= gap_tol and stopped != "certified":
            stopped += "; certified after the polish"
    cert = Certificate("psd-qp-ipm", gap <= gap_tol, it, seconds=time.perf_counter() - t0, method="hkm",
                       duality_gap=gap, details={"trace": trace, "stopped": stopped, "blocks": list(p.sizes),
                                                 "unknowns": n, "constraints": K, "polish": polished})
    return x, cert


#: the polish: tried where the interior point's misfit f exceeds POLISH_FROM f_const (on the
#: benchmark's noisy stiff set f / f_const = 0.024, on the SVK demo's probes 18 and 57); at
#: most POLISH_STEPS steps, while each lowers f by 10 % at least (f / f_before <= POLISH_PROGRESS)
POLISH_FROM = 0.1
POLISH_STEPS = 8
POLISH_PROGRESS = 0.9


#: least_norm takes LAPACK gels's answer where the triangular factor's diagonal spans at most
#: 1 / GELS_RCOND; beyond, gelsd's (the two agree to ~cond u there, so the choice moves no
#: answer by more than the conditioning does)
GELS_RCOND = 1e-10


def least_norm(A, y):
    """The least-norm least-squares solution of A d = y: LAPACK gels (an LQ or QR factorisation,
    BLAS-3; a third of the SVD-based gelsd's time on the SVK polish's 522 x 1,026 systems)
    where its triangular factor is far from singular (:data:`GELS_RCOND`), else gelsd - gels
    has no rank test and answers a rank-deficient A with rounding-sized pivots (finite,
    1e11 where the answer is 1)."""
    m, n = A.shape
    gels, gels_lwork = scipy.linalg.lapack.get_lapack_funcs(("gels", "gels_lwork"), (A,))
    work, info = gels_lwork(m, n, 1)
    if info == 0:
        rhs = np.zeros((max(m, n), 1))
        rhs[:m, 0] = y
        lq, d, info = gels(A, rhs, lwork=int(work))
        pivots = np.abs(np.diag(lq[:min(m, n), :min(m, n)]))
        if info == 0 and pivots.min() > GELS_RCOND * pivots.max() and np.all(np.isfinite(d)):
            return d[:n, 0]
    # singular values below max(m, n) u of the largest are rounding (numpy's lstsq default;
    # scipy's, u alone, kept a zero row's ~1e-16 and answered 1e11)
    return scipy.linalg.lstsq(A, y, cond=max(m, n) * np.finfo(float).eps, check_finite=False,
                              lapack_driver="gelsd")[0]


def polish(p: QuadraticPSD, x, Lam, gap):
    """The interior point's answer moved towards the fits of the data, A x = b, keeping every
    X_k(x) > 0: steps d = argmin ||d||_W s.t. A (x + d) = b (W = sum_k P_k^T K(X_k^-1, X_k^-1)
    P_k, the log-det barrier's Hessian: its unit ball about x is feasible, and it measures d
    in the blocks' own scale), each taken as far as 0.99 of the feasible length allows, while
    the misfit falls by 10 % a step. f >= 0 bounds the optimum from below - tightly where
    A x = b is solvable, as in the polynomial fit - and the gap against it is f(x') plus the
    rounding of the residual, (||r|| + (n + 2) u (|| |A| |x'| || + ||b||))^2, over the
    reference; the multipliers' bound g(Lambda) holds as before. The smaller gap is kept, and
    x' only when it lowers the gap.

    Why: on near-exact data the optimum is an exact fit beside a nearly singular Gram matrix
    (the data's potential is a sum of few squares), the interior point's Newton systems
    (H = A^T A) stall on the central path at a misfit 10-60x the exact fit's (the SVK
    probes), and its gap is small only against the floor GAP_FLOOR f_scale. Where a cone
    blocks the way to A x = b the steps end where they stop lowering f.
    Returns (x', its gap, a record)."""
    x1, f0 = x, p.objective(x)
    f1, steps = f0, []
    n = len(x1)
    W, ones = np.empty((n, n)), np.ones(n)
    nullspace = _NullSpaceSteps.of(p)
    for _ in range(POLISH_STEPS):
        X = p.slacks(x1)
        try:
            Xi = [np.linalg.inv(Xk) for Xk in X]
            W.fill(0.0)
            _add_kernels(p, W, Xi, Xi)
            if nullspace is not None:
                d = nullspace.step(W, p.b - p.A @ x1)
            else:
                L = scipy.linalg.cho_factor(sym_scaled_lower(W, ones), lower=True, overwrite_a=True,
                                            check_finite=False)[0]  # the lower triangle is the factor
                Aw = scipy.linalg.solve_triangular(L, p.A.T, lower=True, check_finite=False).T  # A L^-T
                y = least_norm(Aw, p.b - p.A @ x1)
                d = scipy.linalg.solve_triangular(L, y, lower=True, trans="T", check_finite=False)
            t_max = _step_to_boundary([(Xk, Xk1 - Xk) for Xk, Xk1 in zip(X, p.slacks(x1 + d))])
        except np.linalg.LinAlgError:
            break
        t = 1.0 if t_max > 1.0 else 0.99 * t_max
        x_try = x1 + t * d
        f_try = p.objective(x_try)
        steps.append((float(t), f_try))
        if not f_try < f1:
            break
        progress = f_try / f1
        x1, f1 = x_try, f_try
        if progress > POLISH_PROGRESS:
            break
    e_r = (len(x1) + 2) * np.finfo(float).eps * (np.linalg.norm(np.abs(p.A) @ np.abs(x1))
                                                 + np.linalg.norm(p.b))
    gap_zero = (np.sqrt(f1) + e_r) ** 2 / p.reference(f1)
    gap_lam = p.gap(x1, Lam) if x1 is not x else gap
    gap1 = min(gap_lam, gap_zero)
    record = {"steps": steps, "misfit_before": f0, "misfit_after": f1, "gap_before": float(gap)}
    if not gap1 <= gap:  # nothing gained: the interior point's answer
        return x, gap, {**record, "misfit_after": f0, "kept": "interior point"}
    return x1, gap1, {**record, "bound": "zero" if gap_zero <= gap_lam else "multipliers"}


class _NullSpaceSteps:
    """The polish's step argmin ||d||_W s.t. A d = y through A's null space: d = d_0 + Z w with
    d_0 = A^+ y (one QR of A^T per polish) and (Z^T W Z) w = -Z^T W d_0, Z the problem's
    sparse basis ``flat`` (differences of two Gram entries of one monomial in the sos fit):
    a Cholesky factorisation of k x k per step, where the range-space step
    (A L^-T, W = L L^T) needs one of n x n, a triangular solve with m right-hand sides and an
    LQ factorisation (the SVK fit at r = 8: k = 504, n = 1,026, m = 522). A d = y holds
    through d_0 whatever the conditioning of Z^T W Z. Used where A has full row rank and
    m + k = n (Z spans the whole null space); else None."""

    def __init__(self, Z, Q, R):
        self.Z, self.Q, self.R = Z, Q, R

    @classmethod
    def of(cls, p: QuadraticPSD):
        if p.flat is None or p.A is None:
            return None
        m, n = p.A.shape
        if m + p.flat.shape[1] != n:
            return None
        AZ = np.asarray((p.flat.T @ p.A.T).T)  # A Z (sparse Z): ~0 where Z is in A's null space
        scale = np.abs(p.A).sum(axis=1)[:, None] * np.asarray(abs(p.flat).max(axis=0).todense())
        if not np.all(np.abs(AZ) <= 1e-10 * np.maximum(scale, np.finfo(float).tiny)):
            return None
        Q, R = scipy.linalg.qr(p.A.T, mode="economic", check_finite=False)  # A = R^T Q^T
        diag = np.abs(np.diag(R))
        if not diag.min() > GELS_RCOND * diag.max():  # rank-deficient rows: the range-space step
            return None
        return cls(p.flat, Q, R)

    def step(self, W, y):
        d0 = self.Q @ scipy.linalg.solve_triangular(self.R, y, trans="T", check_finite=False)
        WZ = (self.Z.T @ W).T  # W symmetric: W Z with the sparse Z on the left
        T = SPDSolver(np.asarray(self.Z.T @ WZ))  # Z^T W Z, equilibrated and factorised
        if not T.ok:
            raise np.linalg.LinAlgError("Z^T W Z is not positive definite")
        return d0 + self.Z @ T.solve(-(WZ.T @ d0))
