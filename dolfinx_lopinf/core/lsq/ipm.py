"""Several symmetric blocks >= eps I: a primal-dual interior point method (HKM direction,
Mehrotra predictor-corrector) with a certified duality gap, optionally on the active blocks
only, and a crossover to Newton on the face it shows when it stops short."""

from __future__ import annotations

import functools
import time

import numpy as np
import scipy.linalg

from .. import compiled as _jit
from . import _compiled
from .face import FaceNewton, polish
from .linalg import (
    SPDSolver,
    cholesky_solve,
    face_ranks,
    from_eig,
    lease,
    quadratic,
    release,
    sym,
    vech_index,
)
from .problem import Certificate, Problem, Strategy, symmetric_answer, symmetric_start
from ...errors import InputError

STEP_FRACTION = 0.98
#: STALL_RUN steps in a row shorter than STALL_STEP once m mu / f <= STALL_GAP x gap_tol are a
#: stall (the Schur matrix's rounding on weakly active constraints): the loop asks for the
#: certificate (the face multipliers of Problem.dual_gap may already give it) and, without one,
#: ends - the crossover (Newton on the face) takes over. A run of them, not one: a single
#: short step is often followed by long ones, and at small r an iteration costs far less than
#: the crossover
STALL_STEP, STALL_GAP, STALL_RUN = 0.1, 1e3, 3
#: near the tolerance, a step that does not halve m mu / f (rel <= NEAR_GAP gap_tol and
#: rel > NEAR_FLAT x the previous rel) asks for the certificate too: m mu / f overstates the
#: certified gap there (the face multipliers of Problem.dual_gap bound it more tightly, and
#: short steps can creep towards gap_tol for many iterations) - once per halving of m mu / f
#: (:class:`_NearAsks`); without one the loop goes on (only the tests above end it)
NEAR_GAP, NEAR_FLAT = 10.0, 0.5
#: mixed precision: from MIXED_FROM_N unknowns on (r >= 16 with two blocks), while
#: m mu / f > MIXED_ABOVE_GAP, the Schur matrix is factored in float32 (LAPACK spotrf: half the
#: memory traffic and twice the SIMD width of dpotrf, and that factorisation dominates an
#: iteration there). Each solve with that factor is checked in float64: r = b - M dx (one
#: dsymv), accepted if ||r|| <= MIXED_MAX_RESIDUAL ||b|| - an inexact Newton direction, which
#: the iteration absorbs: each one recomputes its residuals in float64 (seen: ||r|| / ||b|| ~
#: 1e-6 - 1e-4). If spotrf fails or a residual is larger, the iteration is redone in float64 and the run stays there (the Schur matrix's
#: condition has outgrown float32)
MIXED_FROM_N, MIXED_ABOVE_GAP, MIXED_MAX_RESIDUAL = 256, 1e-4, 1e-2


def _ask_certificate(trace, gap_tol) -> int:
    """Whether the loop asks for the certificate after the iterations ``trace`` ((step,
    sigma, m mu / f) each; the compiled kernel's _status is the same test): 2 - it asks and
    may end without one (tolerance met, a step below 1e-3, a stall), 1 - it asks only (a flat
    step near the tolerance, NEAR_GAP), 0 - not."""
    steps, rel = [t[0] for t in trace], trace[-1][2]
    stalled = (len(steps) >= STALL_RUN and max(steps[-STALL_RUN:]) < STALL_STEP
               and rel <= STALL_GAP * gap_tol)
    if rel <= gap_tol or steps[-1] < 1e-3 or stalled:
        return 2
    return int(len(trace) >= 2 and rel <= NEAR_GAP * gap_tol and rel > NEAR_FLAT * trace[-2][2])


class _NearAsks:
    """A flat step near the tolerance asks for the certificate once per halving of m mu / f:
    a certificate costs more than a small-r iteration, so asking at every flat step would
    cost more than it saves."""

    def __init__(self):
        self.last = np.inf

    def due(self, rel: float) -> int:
        if rel > NEAR_FLAT * self.last:
            return 0
        self.last = rel
        return 1


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


@functools.lru_cache(maxsize=32)
def _kernel_index(r: int):
    """The compiled kernel's tables: vech pairs (i, j), their weights c (1/2 on the
    diagonal) and the vech position of every (i, j) of an r x r block."""
    i, j = np.triu_indices(r)
    full = np.zeros((r, r), dtype=np.int64)
    full[i, j] = full[j, i] = np.arange(len(i))
    return i.astype(np.int64), j.astype(np.int64), np.where(i == j, 0.5, 1.0), full  # private


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


def _max_step(S: np.ndarray, *dP: np.ndarray) -> float:
    """Largest a <= 1 with P_k + a dP_k >= 0 for all blocks, from the stacked inverse
    Cholesky factors S_k = R_k^-1 (P_k = R_k R_k^T): 1 / max(0, -min_k lambda_min(S_k dP_k
    S_k^T)) - one batched ``eigvalsh`` (it reads the lower triangle)."""
    ev = np.linalg.eigvalsh(S @ np.concatenate(dP) @ S.transpose(0, 2, 1)).min()
    return 1.0 if ev >= 0 else min(1.0, -1.0 / ev)


class _Stop(Exception):
    """The interior point cannot go on (the message says why)."""


class PrimalDualIPM:
    """min x^T H x + 2 h^T x + const  s.t.  X_k(x) = S_k(x) - eps I >= 0  by a primal-dual
    interior point method: HKM direction, Mehrotra predictor-corrector, one Cholesky per
    iteration.

    Optimality: grad f(x) = D vech(Lambda) (D: 2 off the diagonal), X_k Lambda_k = mu I.
    Newton on it with Lambda eliminated, dLambda = sym(X^-1 (R - dX Lambda)), gives
    (2 H + sum_k D (X_k^-1 (x)_s Lambda_k)) dx = -(grad f - D vech Lambda) + D vech sym(X^-1 R)
    - the Schur matrix; R = sigma mu I - X Lambda (- dX_aff dLambda_aff in the corrector).
    Each block is first scaled by a congruence X_k = D_k X'_k D_k (D_k^4 = diag of H on the
    block's diagonal entries), which keeps the cone and balances K against C. x stays
    strictly feasible and Lambda PSD, so ``certify(x, Lambda)`` (the closed-form dual bound,
    Lambda mapped back to the unscaled blocks) is a proof of the gap.
    """

    def __init__(self, H, h, const, r, n_blocks, eps, backend="auto", f_floor=0.0):
        self.ix = ix = vech_index(r, n_blocks)
        self.r, self.n_blocks, self.m = r, n_blocks, n_blocks * r
        self.backend = _jit.resolve_backend(backend)
        self.x_eps = ix.x_eps(eps)
        self.f_floor = max(float(f_floor), 1e-300)  # the gap's reference: max(f, f_floor)
        dg = np.diag(H).reshape(n_blocks, ix.nv)[:, ix.iu[0] == ix.iu[1]]
        self.dsc = np.maximum(dg, 1e-300) ** -0.25
        self.T = (self.dsc[:, ix.iu[0]] * self.dsc[:, ix.iu[1]]).reshape(-1)
        if self.backend == "numba":  # the scaled problem is formed by run(): compiled _start
            self.H = np.ascontiguousarray(H, dtype=float)
            self.h, self.const = np.ascontiguousarray(h, dtype=float), float(const)
            return
        self.c0 = quadratic(H, h, const, self.x_eps)
        self.Hs = self.T[:, None] * H * self.T[None, :]
        self.hs = self.T * (H @ self.x_eps + h)
        self.H2 = 2.0 * self.Hs
        self.Ms = self.H2.copy()  # Schur matrix: its diagonal blocks' upper triangles change
        _, _, _, _, _, tp, tq = _hkm_index(r)
        self.diag_pos = [(k * ix.nv + tp) * ix.n + k * ix.nv + tq for k in range(n_blocks)]
        self.H2_diag = np.stack([self.H2.reshape(-1)[pos] for pos in self.diag_pos])  # gathered once

    def f(self, v):
        """The objective in the scaled unknowns (const = ||Z||^2; a stopping guide only;
        the numpy iteration's)."""
        return quadratic(self.Hs, self.hs, self.c0, v)

    def run(self, x_start, *, certify, gap_tol, max_iter=40, watch=None, watch_below=np.inf):
        """Iterate from ``x_start`` until the certified relative gap is <= ``gap_tol``.
        ``watch(x, m mu / f)``, if given, is called after every iteration with
        m mu / f <= ``watch_below`` (it must answer True above it) and ends the loop when it
        returns False. Returns ``(x, Certificate)``; its ``face_ranks`` is the rank of each
        X_k and ``details`` holds ``trace`` ((step, sigma, m mu / f) per iteration), ``mu``
        and why it ``stopped`` short."""
        ix, m = self.ix, self.m
        cert = Certificate("ipm", False, 0, duality_gap=np.inf, face_multiplier_min=-np.inf,
                           details={"backend": self.backend, "float32_iterations": 0})
        if self.backend == "numba":
            x, X, Lam, mu = self._run_compiled(cert, x_start, certify, gap_tol, max_iter, watch,
                                               watch_below)
        else:  # m mu / f, and whether float32 may serve (MIXED_FROM_N)
            x, X, Lam = self._start(x_start)
            mu = float(np.sum(X * Lam)) / m
            rel, mixed = m * mu / max(abs(self.f(x)), self.f_floor), ix.n >= MIXED_FROM_N
        near = _NearAsks()
        for it in range(1, max_iter + 1) if self.backend == "numpy" else ():
            cert.iterations = it
            single = mixed and rel > MIXED_ABOVE_GAP
            try:
                dx, dL, a, sigma, used = self._step(x, X, Lam, it, single)
            except _Stop as stop:
                cert.details["stopped"] = str(stop)
                break
            cert.details["float32_iterations"] += used
            mixed = mixed and used == single  # float32 refused: float64 from now on
            x = x + a * dx
            X, Lam = ix.blocks(x), Lam + a * dL
            mu = float(np.sum(X * Lam)) / m
            rel = m * mu / max(abs(self.f(x)), self.f_floor)
            cert.details.setdefault("trace", []).append((a, sigma, rel))
            if (watch is not None and rel <= watch_below
                    and not watch(self.x_eps + self.T * x, rel)):
                cert.details["stopped"] = "stopped by watch"
                break
            ask = _ask_certificate(cert.details["trace"], gap_tol)
            if ask == 1:
                ask = near.due(rel)
            if ask and self._certified(cert, certify, x, Lam, gap_tol, a, may_stop=ask == 2):
                break
        cert.details["mu"] = mu
        cert.face_ranks = face_ranks(X, Lam)
        return self.x_eps + self.T * x, cert

    def _run_compiled(self, cert, x_start, certify, gap_tol, max_iter, watch, watch_below):
        """:meth:`run` by the compiled kernels (:mod:`._compiled`): the scaled problem and the
        start (``_start``, the numpy path's ``__init__`` and :meth:`_start`), then the loop,
        which iterates until it needs Python (certify, watch, stop): the same tests, in the
        same order. Returns the final (x, X, Lambda, mu)."""
        kernels, ix = _compiled.kernels(), self.ix
        M0, Mw = lease((ix.n, ix.n)), lease((ix.n, ix.n))  # 2 Hs, the Schur matrix
        mixed = ix.n >= MIXED_FROM_N
        Mf = lease((ix.n, ix.n) if mixed else (1, 1), np.float32)  # its float32 factor
        try:
            x, hs2 = np.empty(ix.n), np.empty(ix.n)
            X, Lam = np.empty((self.n_blocks, self.r, self.r)), np.empty((self.n_blocks, self.r, self.r))
            c0 = kernels["_start"](self.H, self.h, self.const, self.T, self.x_eps,
                                   np.ascontiguousarray(x_start, dtype=float),
                                   _kernel_index(self.r)[3], self.f_floor, M0, hs2, x, X, Lam)
            return self._loop(kernels["_iterate"], M0, Mw, Mf, hs2, c0,
                              np.array([MIXED_ABOVE_GAP if mixed else np.inf, MIXED_MAX_RESIDUAL]),
                              cert, x, Lam, certify, gap_tol, max_iter, watch, watch_below)
        finally:
            release(M0, Mw, Mf)

    def _loop(self, K, M0, Mw, Mf, hs2, c0, mixed, cert, x, Lam, certify, gap_tol, max_iter,
              watch, watch_below):
        st, ix, m = _compiled, self.ix, self.m
        iu0, iu1, cw, full = _kernel_index(self.r)
        trace, info = np.zeros((max_iter, 3)), np.zeros(7)
        near = _NearAsks()
        watch_below = watch_below if watch is not None else -np.inf
        it = 1
        while it <= max_iter:
            status = K(M0, hs2, c0, self.f_floor, ix.Dw[:ix.nv], iu0, iu1, cw, full, x,
                       Lam, Mw, Mf, mixed, it, max_iter, gap_tol, watch_below, trace, info)
            it = cert.iterations = int(info[0])
            cert.details["float32_iterations"] = int(info[6])
            if status & (st.X_NOT_PD | st.SCHUR_NOT_PD | st.NOT_FINITE):
                cert.details["stopped"] = (
                    f"iterate not positive definite at iteration {it}" if status & st.X_NOT_PD
                    else f"Schur matrix not positive definite at iteration {it}, mu "
                         f"{info[1]:.1e}, f {info[2]:.3e}" if status & st.SCHUR_NOT_PD
                    else f"direction not finite at iteration {it}")
                it -= 1  # the trace holds the iterations completed
                break
            mu, f_ref, a = info[1], info[2], info[3]
            if (status & st.WATCH and watch is not None
                    and not watch(self.x_eps + self.T * x, m * mu / f_ref)):
                cert.details["stopped"] = "stopped by watch"
                break
            ask = bool(status & st.CERTIFY) or (bool(status & st.NEAR)
                                                 and near.due(m * mu / f_ref))
            if ask and self._certified(cert, certify, x, Lam, gap_tol, a,
                                       may_stop=bool(status & st.CERTIFY)):
                break
            if status & st.MAX_ITER:
                break
            it += 1
        if it >= 1:
            cert.details["trace"] = list(map(tuple, trace[:min(it, max_iter)].tolist()))
        X = ix.blocks(x)
        return x, X, Lam, float(np.sum(X * Lam)) / m

    def _start(self, x_start):
        """Scaled x_start with its eigenvalues made positive, and Lambda = c X^-1."""
        ix = self.ix
        w, Q = np.linalg.eigh(ix.blocks((x_start - self.x_eps) / self.T))
        w = np.maximum(np.abs(w), 1e-3 * np.abs(w).max(axis=1, keepdims=True))
        X = from_eig(w, Q)
        x = ix.vech(X)
        f_ref = max(abs(self.f(x)), self.f_floor)
        return x, X, from_eig((0.1 * f_ref / self.m) / w, Q)  # c X^-1 in X's eigenbasis

    def _certified(self, cert, certify, x, Lam, gap_tol, a, may_stop=True) -> bool:
        """Ask ``certify`` for the gap (with the face the iterate shows); True when the loop
        should end (certified, no certificate for the point, or a short step where
        ``may_stop``)."""
        gap, lam_min = certify(self.x_eps + self.T * x,
                               Lam / (self.dsc[:, :, None] * self.dsc[:, None, :]),
                               functools.partial(face_ranks, self.ix.blocks(x), Lam.copy()))
        if not np.isfinite(gap):
            cert.details["stopped"] = "no certificate for this point"
            return True
        cert.duality_gap, cert.face_multiplier_min = gap, lam_min
        if gap <= gap_tol:
            cert.converged = True
            return True
        if may_stop and a < STALL_STEP:  # a < 1e-3, or a stall (_ask_certificate)
            cert.details["stopped"] = f"step length {a:.1e} below {STALL_STEP}"
            return True
        return False

    def _step(self, x, X, Lam, it, mixed=False):
        """Predictor-corrector direction and step: (dx, dLambda, step, sigma, whether float32
        served: asked by ``mixed``, spotrf succeeded and both solves passed their check)."""
        ix, m, b = self.ix, self.m, self.n_blocks
        try:  # X_k = R R^T and Lambda_k: one batched Cholesky, one batched triangular inverse
            S = np.linalg.inv(np.linalg.cholesky(np.concatenate([X, Lam])))
        except np.linalg.LinAlgError:  # X or Lambda lost definiteness to rounding
            raise _Stop(f"iterate not positive definite at iteration {it}") from None
        Xi = S[:b].transpose(0, 2, 1) @ S[:b]  # X^-1 = R^-T R^-1: PD however wide X's spread
        rd = 2.0 * (self.Hs @ x + self.hs) - ix.Dw * ix.vech(Lam)
        mu = float(np.sum(X * Lam)) / m
        XL = X @ Lam
        for single in (True, False) if mixed else (False,):
            c = self._schur_cholesky(Xi, Lam, single)
            if c is None:
                raise _Stop(f"Schur matrix not positive definite at iteration {it}, mu "
                            f"{mu:.1e}, f {self.f(x):.3e}")
            if single and c.dtype != np.float32:  # spotrf failed: c is the float64 factor
                single = False
            step = self._predictor_corrector(c, S, X, Xi, Lam, XL, rd, mu)
            if step is not None:
                return (*step, single)
        raise AssertionError("the float64 directions are always accepted")  # pragma: no cover

    def _predictor_corrector(self, c, S, X, Xi, Lam, XL, rd, mu):
        """(dx, dLambda, step, sigma) from the Schur factor ``c``, or None when a float32
        solve fails its residual check."""
        m = self.m
        pred = self._direction(c, Xi, Lam, rd, -XL)                             # mu -> 0
        if pred is None:
            return None
        _, dX, dL = pred
        a = _max_step(S, dX, dL)
        mu_aff = float(np.sum((X + a * dX) * (Lam + a * dL))) / m
        sigma = (mu_aff / mu) ** 3
        corr = self._direction(c, Xi, Lam, rd, sigma * mu * np.eye(self.r) - XL - dX @ dL)
        if corr is None:
            return None
        dx, dX, dL = corr
        return dx, dL, min(1.0, STEP_FRACTION * _max_step(S, dX, dL)), sigma

    def _schur_cholesky(self, Xi, Lam, single=False):
        """Lower Cholesky factor of the Schur matrix 2 H + HKM terms (float32 if ``single``
        and spotrf succeeds, else float64), or None."""
        hkm = _hkm_upper(Xi, Lam)
        hkm += self.H2_diag
        Ms_flat = self.Ms.reshape(-1)
        for k in range(self.n_blocks):  # the diagonal blocks' upper triangles; the rest stays 2 H
            Ms_flat[self.diag_pos[k]] = hkm[k]
        # lower Cholesky of the F-ordered view Ms^T (its lower triangle is Ms's upper one, the
        # part written above), faster than the upper one; no diagonal scaling is needed
        # (Cholesky's accuracy does not depend on one)
        if single:  # the F-ordered copy rounded to float32 (the compiled kernel's _potrf32)
            c, status = scipy.linalg.lapack.spotrf(self.Ms.T.astype(np.float32), lower=1, clean=0,
                                                   overwrite_a=1)
            if status == 0:
                return c
        c, status = scipy.linalg.lapack.dpotrf(self.Ms.T, lower=1, clean=0)
        for shift in (1e-12, 1e-10, 1e-8):  # rounding as mu -> 0: a small relative shift
            if status == 0:
                break
            Mshift = self.Ms.T.copy(order="F")
            Mshift[np.diag_indices(len(self.Ms))] *= 1.0 + shift
            c, status = scipy.linalg.lapack.dpotrf(Mshift, lower=1, clean=0, overwrite_a=1)
        return c if status == 0 else None

    def _direction(self, c, Xi, Lam, rd, R):
        """(dx, dX, dLambda) for the complementarity residual R, or None (a float32 ``c``
        whose solve fails the residual check)."""
        XiR = Xi @ R
        rhs = -rd + self.ix.Dw * self.ix.vech(sym(XiR))
        dx = cholesky_solve(c, rhs)
        if c.dtype == np.float32:  # its residual checked in float64 (MIXED_MAX_RESIDUAL)
            res = rhs - scipy.linalg.blas.dsymv(1.0, self.Ms.T, dx, lower=1)
            if not np.linalg.norm(res) <= MIXED_MAX_RESIDUAL * np.linalg.norm(rhs):
                return None
        dX = self.ix.blocks(dx)
        return dx, dX, sym(XiR - Xi @ dX @ Lam)


def _sub(H: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """H[np.ix_(rows, cols)] - a view when both are runs of consecutive indices (two blocks:
    always), no gather."""
    def run(idx):
        return len(idx) and idx[-1] - idx[0] == len(idx) - 1

    if run(rows) and run(cols):
        return H[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
    return H[np.ix_(rows, cols)]


#: the eliminated blocks are watched from this relative gap estimate on (:class:`_ActiveBlocks`)
WATCH_FROM = 0.3


class _ActiveBlocks:
    """The interior point on the blocks whose unconstrained minimiser is not >= eps I, the
    others (``feasible``, presumed inactive at the optimum) minimised out exactly:
    x_f = -H_ff^-1 (h_f + H_fa x_a), leaving x_a^T (H_aa - H_af H_ff^-1 H_fa) x_a + ... on the
    active blocks - a Schur matrix of half the size (one eighth of the Cholesky). With zero
    multipliers on the eliminated blocks the full problem's dual bound is the reduced one,
    so ``Problem.dual_gap`` of the full x proves the answer once the eliminated blocks are
    checked >= eps I; if they are not (the presumption was wrong), no answer."""

    def __init__(self, problem: Problem, feasible: np.ndarray):
        H, h = problem.normal_equations
        self.problem, self.feasible = problem, feasible
        pos = np.arange(problem.index.n).reshape(problem.n_blocks, problem.index.nv)
        self.a_idx, self.f_idx = pos[~feasible].ravel(), pos[feasible].ravel()
        a, f = self.a_idx, self.f_idx
        self.Hff = Hff = SPDSolver(np.ascontiguousarray(_sub(H, f, f)))
        self.ok = Hff.ok
        self.below, self.iterations = 0, 0  # the watch's run of checks below eps; the run's length
        if self.ok:  # H_ff = L L^T: H_af H_ff^-1 H_fa = G^T G with G = L^-1 H_fa (one trsm)
            self.G, self.g = Hff.whiten(_sub(H, f, a)), Hff.whiten(h[f])
            self.Hr = sym(_sub(H, a, a) - self.G.T @ self.G)
            self.hr = h[self.a_idx] - self.G.T @ self.g
            self.const = float(np.sum(problem.Z**2) - self.g @ self.g)

    def full(self, xa):
        xf = np.empty(self.problem.index.n)
        xf[self.a_idx], xf[self.f_idx] = xa, -self.Hff.unwhiten(self.g + self.G @ xa)
        return xf

    def eliminated_ok(self, xf) -> bool:
        """The eliminated blocks of a full x are >= eps I."""
        return np.linalg.eigvalsh(self.problem.index.blocks(xf)[self.feasible]).min() >= self.problem.eps

    def certify(self, xa, lam_a, ranks_a, enough):
        xf = self.full(xa)
        if not self.eliminated_ok(xf):
            return np.nan, np.nan
        p = self.problem
        lam = np.zeros((p.n_blocks, p.r, p.r))
        lam[~self.feasible] = lam_a
        def ranks():
            out = np.full(p.n_blocks, p.r)
            out[~self.feasible] = ranks_a()
            return out

        return p.dual_gap(xf, lam, ranks, enough=enough)

    def watch(self, xa, rel_gap) -> bool:
        """Once near the optimum (rel_gap <= 1e-3), the eliminated blocks must be >= eps I;
        from rel_gap <= WATCH_FROM, they may fall below it at one iteration, not at two in
        a row. A wrong presumption shows from the first iterations: on the benchmark's chain
        (r = 20, K = 3,000) the eliminated stiffness block's smallest eigenvalue sat at
        -3.7e-5 .. -2.4e-5 from the first iteration on (the reduced run stopped at the fifth,
        2.8 ms of a 16 ms fit), where on a right one (forced, r = 20, K = 10,000) it stayed
        at 0.29 .. 0.82."""
        ok = self.eliminated_ok(self.full(xa))
        self.below = 0 if ok else self.below + 1
        return ok or (rel_gap > 1e-3 and self.below < 2)

    def run(self, x, gap_tol, max_iter, backend="auto"):
        """``(full x, Certificate)`` of a converged reduced run, or None."""
        if not self.ok:
            return None
        p, active = self.problem, int((~self.feasible).sum())
        ipm = PrimalDualIPM(self.Hr, self.hr, self.const, p.r, active, p.eps, backend, p.f_floor)
        xa, cert = ipm.run(x[self.a_idx], certify=functools.partial(self.certify, enough=gap_tol),
                           gap_tol=gap_tol, max_iter=max_iter, watch=self.watch, watch_below=WATCH_FROM)
        self.iterations = cert.iterations
        if not cert.converged:
            return None
        ranks = np.full(p.n_blocks, p.r)
        ranks[~self.feasible] = cert.face_ranks
        cert.face_ranks = [int(k) for k in ranks]
        cert.details["eliminated_blocks"] = [int(k) for k in np.flatnonzero(self.feasible)]
        return self.full(xa), cert


def interior_point(problem: Problem, x, feasible, newton, *, gap_tol=1e-8, max_iter=40,
                   eliminate=True, backend="auto", crossover_above=0.0):
    """The interior point from the symmetric minimiser ``x`` (``feasible``: its blocks that
    are >= eps I): first on the active blocks only (``eliminate``, if some block is
    feasible), else on all; if it stops uncertified, Newton on the face it shows
    (``newton``: a :class:`FaceNewton`). Needs H > 0. ``backend``: the iteration in numpy or
    compiled (:class:`PrimalDualIPM`; ``"auto"``: compiled when numba is there).
    ``crossover_above``: an uncertified run with a gap at most this keeps its own point (no
    crossover). Returns ``(x, Certificate, details)``."""
    H, h = problem.normal_equations
    details, result = {}, None
    if eliminate and feasible.any():
        reduced = _ActiveBlocks(problem, feasible)
        result = reduced.run(x, gap_tol, max_iter, backend)
        details["eliminated_blocks_tried"] = [int(k) for k in np.flatnonzero(feasible)]
        details["eliminated_run_iterations"] = reduced.iterations
    if result is None:
        ipm = PrimalDualIPM(H, h, float(np.sum(problem.Z**2)), problem.r, problem.n_blocks,
                            problem.eps, backend, problem.f_floor)
        result = ipm.run(x, certify=functools.partial(problem.dual_gap, enough=gap_tol),
                         gap_tol=gap_tol, max_iter=max_iter)
    x_ip, cert = result
    if not cert.converged and not cert.duality_gap <= crossover_above:
        x_ip = _crossover(problem, x_ip, cert, newton, gap_tol)
    details["ipm"] = {k: v for k, v in cert.as_dict().items() if k not in ("solver", "face_ranks")}
    return x_ip, cert, details


def _crossover(problem: Problem, x_ip, cert, newton, gap_tol):
    """The exact minimiser on the face the stopped interior point shows, its eigenvectors
    fixed (:func:`polish`, one solve), then Newton on that face (eigenvectors free) - or, if
    both fail, on a face with one more active direction in one block (the rank count decides
    on X_k against Lambda_k, and a weakly active direction has both small); updates ``cert``
    if certified."""
    ix, r, eps = problem.index, problem.r, problem.eps
    w0, Q = np.linalg.eigh(ix.blocks(x_ip) - eps * np.eye(r))
    shown = list(cert.face_ranks)
    for ranks in [shown] + [[m - (j == k) for j, m in enumerate(shown)]
                            for k in range(problem.n_blocks) if shown[k] > 0]:
        w = np.where(np.arange(r)[None, :] >= r - np.array(ranks)[:, None], w0, 0.0)
        if min(w.max(axis=1)) < 0:
            continue
        polished, a_min = polish(problem, eps + w, Q)  # keeps the directions with w > 0
        face = [int(k) for k in (w > 0).sum(axis=1)]
        gap, lam_min = (problem.dual_gap(polished, ranks=face, enough=gap_tol) if a_min > 0
                        else (np.inf, None))
        x_face = polished
        if gap > gap_tol:
            refined = newton.refine(ix.x_eps(eps) + ix.vech(from_eig(w, Q)), ranks)
            if refined is None or refined[1] > gap_tol:
                continue
            (x_face, gap), face = refined, ranks
            lam_min = problem.dual_gap(x_face)[1]
        cert.converged, cert.duality_gap, cert.face_ranks = True, gap, face
        cert.details["crossover"] = True
        cert.face_multiplier_min = lam_min
        return x_face
    return x_ip


class InteriorPoint(Strategy):
    """Symmetric blocks >= eps I by the primal-dual interior point (:func:`interior_point`,
    crossover included) alone, without the ADMM fallback of :class:`PSDBlocks`."""

    def __init__(self, gap_tol: float = 1e-8, max_iter: int = 40, eliminate: bool = True,
                 backend: str = "auto"):
        self.gap_tol, self.max_iter, self.eliminate = gap_tol, max_iter, eliminate
        self.backend = backend

    def solve_blocks(self, problem: Problem):
        t0 = time.perf_counter()
        x, feasible = symmetric_start(problem)
        if feasible.all():
            return symmetric_answer(problem, x, t0)
        if not problem.spd.ok:
            raise InputError("the interior point's certificate needs a nonsingular H")
        newton = FaceNewton(problem, self.gap_tol)
        x_ip, ip, details = interior_point(problem, x, feasible, newton, gap_tol=self.gap_tol,
                                           max_iter=self.max_iter, eliminate=self.eliminate,
                                           backend=self.backend)
        return problem.index.theta(x_ip), ip_answer(ip, details, newton, t0)


def ip_answer(ip: Certificate, details: dict, newton, t0: float) -> Certificate:
    """The certificate of an interior point answer."""
    return Certificate("ipm", ip.converged, ip.iterations, seconds=time.perf_counter() - t0,
                       method="ipm", duality_gap=ip.duality_gap, face_ranks=ip.face_ranks,
                       face_multiplier_min=ip.face_multiplier_min, polish_attempts=0,
                       details={**details, **newton.details()})
