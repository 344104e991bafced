"""Several symmetric blocks >= eps I, the other way: ADMM (Anderson-accelerated) until the
optimal face shows, the exact minimiser on that face (polish), and Newton on the fixed-rank
face, certified by the closed-form dual bound."""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np
import scipy.linalg

from .linalg import SPDSolver, face_basis, from_eig, psd_project, sym, unvech
from .problem import Certificate, Problem, Strategy, symmetric_answer, symmetric_start


def _reduce_to_face(H, vec, J_cols, nv):
    """J^T H J and J^T vec for the block-diagonal J = diag(J_k) (J_k None: the identity)."""
    HJ = np.hstack([H[:, k * nv:(k + 1) * nv] if J is None else H[:, k * nv:(k + 1) * nv] @ J
                    for k, J in enumerate(J_cols)])

    def jt(k, M):  # J_k^T M
        return M if J_cols[k] is None else J_cols[k].T @ M
    M = np.vstack([jt(k, HJ[k * nv:(k + 1) * nv]) for k in range(len(J_cols))])
    return M, np.concatenate([jt(k, vec[k * nv:(k + 1) * nv]) for k in range(len(J_cols))])


def polish(problem: Problem, w, Q):
    """Exact minimiser of f on the face {S_k = eps I + P_k A_k P_k^T} (P_k: the eigenvectors
    of block k with eigenvalue w > eps), and the smallest relative eigenvalue of the A_k
    (> 0: the point lies on that face). Returns ``(x, a_min)``."""
    H, h = problem.normal_equations
    ix, eps = problem.index, problem.eps
    nv, x_eps = ix.nv, ix.x_eps(eps)
    T_cols = []
    for k in range(problem.n_blocks):
        P = Q[k][:, w[k] > eps]  # the whole cone when P is square: A_k = S_k - eps I directly
        T_cols.append(None if P.shape[1] == problem.r else face_basis(P, ix.iu))
    Hr, hr = _reduce_to_face(H, H @ x_eps + h, T_cols, nv)
    coef = -SPDSolver(sym(Hr)).solve(hr)
    xp, start, a_min = x_eps.copy(), 0, np.inf
    for k, Tk in enumerate(T_cols):
        m = nv if Tk is None else Tk.shape[1]
        ck = coef[start:start + m]
        if Tk is None:
            xp[k * nv:(k + 1) * nv] += ck
            A = ck[ix.full]
        else:
            xp[k * nv:(k + 1) * nv] += Tk @ ck
            A = unvech(ck, int((w[k] > eps).sum()))
        if A.size:
            a_min = min(a_min, float(np.linalg.eigvalsh(A).min() / max(np.abs(A).max(), 1e-300)))
        start += m
    return xp, a_min


class _Chart(NamedTuple):
    """S_k - eps I = P A P^T (rank m), N spans the complement; J: vech of the first-order dS
    per face coordinate (None in the interior, where S_k itself is the chart); nA: the
    number of A coordinates."""
    P: np.ndarray
    N: np.ndarray
    A: np.ndarray
    nA: int
    J: np.ndarray | None


class FaceNewton:
    """Newton's method on the fixed-rank faces {S_k = eps I + X_k, rank X_k = m_k, X_k >= 0}.

    Chart at X = P A P^T (N spans the complement): X(dA, dB) = W (A + dA) W^T with
    W = P + N dB (A + dA)^-1, which is PSD of rank m whenever A + dA > 0. To second order
    dS = P dA P^T + N dB P^T + P dB^T N^T + N dB A^-1 dB^T N^T, so the quadratic model is
    f + g^T d + d^T (J^T H J) d + sum_k tr([N^T Lambda_k N]_+ dB A^-1 dB^T) (J: d -> vech(dS)
    to first order, Lambda_k = grad_{S_k} f, []_+ the PSD part). Each step: one Cholesky of
    that model's Hessian, a backtracking line search on f; quadratic convergence once the
    ranks are right, so subspaces known only to ~1e-4 are corrected exactly. ``steps`` and
    ``trace`` ((step, gap) per step) count over every :meth:`refine` call.
    """

    def __init__(self, problem: Problem, gap_tol: float = 1e-8, max_steps: int = 10):
        self.problem, self.gap_tol, self.max_steps = problem, gap_tol, max_steps
        self.steps, self.trace = 0, []

    def details(self) -> dict:
        return {**({"newton_steps": self.steps} if self.steps else {}),
                **({"newton_trace": self.trace} if self.trace else {})}

    def refine(self, x, ranks):
        """``(x, certified relative gap)``, or None if a step fails or the face optimum is
        reached without a certificate (the ranks were wrong)."""
        p = self.problem
        H, h = p.normal_equations
        fx, gap = p.objective_x(x), np.inf
        for _ in range(self.max_steps):
            self.steps += 1
            grad_x = 2.0 * (H @ x + h)
            charts = self._charts(x, ranks)
            if charts is None:
                return None
            solver, g_d, starts = self._model(grad_x, charts)
            if not solver.ok:
                return None
            d = -0.5 * solver.solve(g_d)
            decrease = -0.5 * float(g_d @ d)  # predicted decrease of the model: -(g d + d M d)
            stepped = self._line_search(x, grad_x, d, decrease, charts, starts)
            if stepped is None:
                return None
            x, step, change = stepped
            fx += change
            gap, _ = p.dual_gap(x, ranks=ranks, enough=self.gap_tol)
            self.trace.append((step, gap))
            if gap <= self.gap_tol:
                break
            if decrease <= 1e-3 * self.gap_tol * fx:  # face optimum, not certified: wrong ranks
                return None
        return x, gap

    def _charts(self, x, ranks):
        p = self.problem
        ix, r = p.index, p.r
        S = ix.blocks(x) - p.eps * np.eye(r)
        charts = []
        for k in range(p.n_blocks):
            w, Q = np.linalg.eigh(S[k])
            m = ranks[k]
            P, N, A = Q[:, r - m:], Q[:, :r - m], np.diag(w[r - m:])
            if m and w[r - m] <= 0:
                return None
            if m == r:
                charts.append(_Chart(P, N, A, ix.nv, None))
                continue
            Pi, Pj, Ni, Nj = P[ix.iu[0]], P[ix.iu[1]], N[ix.iu[0]], N[ix.iu[1]]
            JA = face_basis(P, ix.iu)                                        # vech(P E_ab P^T)
            JB = (Ni[:, None, :] * Pj[:, :, None] + Pi[:, :, None] * Nj[:, None, :])
            charts.append(_Chart(P, N, A, JA.shape[1], np.hstack([JA, JB.reshape(ix.nv, -1)])))
        return charts

    def _model(self, grad_x, charts):
        """The model's Hessian (factored), gradient and the coordinate offsets per block."""
        p = self.problem
        ix = p.index
        M, g_d = _reduce_to_face(p.normal_equations[0], grad_x, [c.J for c in charts], ix.nv)
        Lam = ix.blocks(grad_x / ix.Dw)
        starts = np.concatenate([[0], np.cumsum([ix.nv if c.J is None else c.J.shape[1]
                                                 for c in charts])])
        for k, c in enumerate(charts):
            if c.N.shape[1] and c.P.shape[1]:
                # PSD part of N^T Lambda N: equal to it at the optimum (Lambda >= 0 there),
                # and keeps the model convex (a descent direction) far from it
                lw, lV = np.linalg.eigh(c.N.T @ Lam[k] @ c.N)
                sl = slice(starts[k] + c.nA, starts[k + 1])
                M[sl, sl] += np.kron(np.diag(1.0 / np.diag(c.A)), from_eig(np.maximum(lw, 0.0), lV))
        return SPDSolver(sym(M)), g_d, starts

    def _line_search(self, x, grad_x, d, decrease, charts, starts):
        """Backtracking on f: ``(x_new, step, f change)`` or None below a step of 0.1."""
        H = self.problem.normal_equations[0]
        step = 1.0
        while step > 0.1:  # a heavily damped step: far from the face optimum, back to ADMM
            x_new = self._chart_point(x, step * d, charts, starts)
            if x_new is not None:
                dx = x_new - x  # f(x + dx) - f(x) exactly, free of the cancellation in f
                change = float((grad_x + H @ dx) @ dx)
                if change <= -1e-4 * step * max(decrease, 0.0):
                    return x_new, step, change
            step *= 0.5
        return None

    def _chart_point(self, x, d, charts, starts):
        """The point of the charts at coordinates d, or None if it leaves them."""
        p = self.problem
        ix, eps, nv = p.index, p.eps, p.index.nv
        x_new = ix.x_eps(eps)
        for k, c in enumerate(charts):
            dk, m, sl = d[starts[k]:starts[k + 1]], c.P.shape[1], slice(k * nv, (k + 1) * nv)
            if m == 0:
                continue
            if c.J is None:  # interior chart: S_k + dS_k must stay > eps I
                x_new[sl] = x[sl] + dk
                if np.linalg.eigvalsh(ix.blocks(x_new)[k]).min() <= eps:
                    return None
                continue
            A_new = c.A + unvech(dk[:c.nA], m)
            try:
                cA = scipy.linalg.cho_factor(A_new, check_finite=False)
            except np.linalg.LinAlgError:
                return None
            dB = dk[c.nA:].reshape(m, -1).T                                   # (r - m, m)
            W = c.P + c.N @ scipy.linalg.cho_solve(cA, dB.T, check_finite=False).T
            x_new[sl] += (W @ A_new @ W.T)[ix.iu]
        return x_new


class _AndersonADMM:
    """ADMM on x = w (w in the cone), Anderson-accelerated (type II, safeguarded), on the
    stacked z = (w, y): x-step (2 H + rho D) x = -2 h + rho D (w - y) (R^-1 of one Cholesky
    per rho, so a step is two matrix-vector products), w-step eigenvalue clipping of every
    block (one batched ``eigh``)."""

    def __init__(self, problem: Problem, x0, rho: float, memory: int):
        H, h = problem.normal_equations
        ix = problem.index
        self.problem, self.ix, self.n, self.memory, self.rho = problem, ix, ix.n, memory, rho
        self.H, self.h2 = H, -2.0 * h
        self.scale_k = np.array([np.mean(np.diag(H)[ix.blk == k]) for k in range(problem.n_blocks)])
        self._factor()
        self._restart(np.concatenate([self.project(x0)[0], np.zeros(self.n)]))

    def project(self, v):
        S, w, Q = psd_project(self.ix.blocks(v), self.problem.eps)
        return self.ix.vech(S), w, Q

    def _factor(self):
        self.P = self.rho * self.scale_k[self.ix.blk] * self.ix.Dw
        R, _ = scipy.linalg.cho_factor(2.0 * self.H + np.diag(self.P), lower=False, check_finite=False)
        Rinv, status = scipy.linalg.lapack.dtrtri(R, lower=0)
        if status != 0:
            raise np.linalg.LinAlgError("x-step matrix is not positive definite")
        self.fac = np.triu(Rinv)

    def step(self, z):
        """One ADMM step from z: (next z, the x-step, the w-step's eigenpairs)."""
        wv, yv = z[:self.n], z[self.n:]
        xv = self.fac @ (self.fac.T @ (self.h2 + self.P * (wv - yv)))
        w_new, ew, eQ = self.project(xv + yv)
        return np.concatenate([w_new, yv + xv - w_new]), xv, (ew, eQ)

    def _restart(self, z):
        self.z = z
        self.z_next, self.x, self.eig = self.step(z)
        self.g = self.z_next - z
        self.dZ, self.dG = [], []

    def rescale(self, fct: float):
        """rho *= fct (y scaled to match), a new factorisation, the Anderson memory cleared."""
        self.rho *= fct
        z = np.concatenate([self.z[:self.n], self.z[self.n:] / fct])
        self._factor()
        self._restart(z)

    def advance(self):
        """One (accelerated) step; returns the relative primal and dual residuals."""
        n, z, g = self.n, self.z, self.g
        w_prev = z[:n]
        candidate = self._anderson() if self.dZ else None
        if candidate is None:
            z_new_next, x_new, eig_new = self.step(self.z_next)
            candidate = (self.z_next, z_new_next, z_new_next - self.z_next, x_new, eig_new)
        z_c, z_c_next, g_c, self.x, self.eig = candidate
        self.dZ = (self.dZ + [z_c - z])[-self.memory:]
        self.dG = (self.dG + [g_c - g])[-self.memory:]
        self.z, self.z_next, self.g = z_c, z_c_next, g_c
        wv, yv = z_c_next[:n], z_c_next[n:]
        nw = np.linalg.norm(wv)
        prim = np.linalg.norm(self.x - wv) / max(np.linalg.norm(self.x), nw, 1e-300)
        dual = np.linalg.norm(wv - w_prev) / max(np.linalg.norm(yv), nw, 1e-300)
        return prim, dual

    def _anderson(self):
        Zm, Gm = np.array(self.dZ).T, np.array(self.dG).T
        GtG = Gm.T @ Gm
        gamma = np.linalg.solve(GtG + 1e-14 * np.trace(GtG) * np.eye(len(self.dZ)), Gm.T @ self.g)
        z_aa = self.z + self.g - (Zm + Gm) @ gamma
        z_aa_next, x_aa, eig_aa = self.step(z_aa)
        g_aa = z_aa_next - z_aa
        return (z_aa, z_aa_next, g_aa, x_aa, eig_aa) if np.linalg.norm(g_aa) < np.linalg.norm(self.g) else None


class FaceADMM(Strategy):
    """Symmetric blocks >= eps I by ADMM to the optimal face, then an exact solve on it.

    Once ADMM's residuals are below ``admm_tol`` its clipping shows the face,
    S_k = eps I + P_k A_k P_k^T: :func:`polish` minimises f over the A_k exactly, then
    :class:`FaceNewton` also turns the P_k. Accepted when the certified relative gap is
    <= ``gap_tol`` - or, only when H is singular and the bound unavailable, when the
    multipliers are >= -``kkt_tol``; otherwise ADMM goes on with a 10x tighter target.
    """

    def __init__(self, gap_tol=1e-8, kkt_tol=1e-9, admm_tol=1e-4, max_iter=5000, memory=8, rho0=0.3):
        self.gap_tol, self.kkt_tol, self.admm_tol = gap_tol, kkt_tol, admm_tol
        self.max_iter, self.memory, self.rho0 = max_iter, memory, rho0

    def solve_blocks(self, problem: Problem):
        t0 = time.perf_counter()
        x, feasible = symmetric_start(problem)
        if feasible.all():
            return symmetric_answer(problem, x, t0)
        return self.run(problem, x, FaceNewton(problem, self.gap_tol), {}, t0)

    def run(self, problem: Problem, x, newton: FaceNewton, details: dict, t0: float):
        """ADMM from the symmetric minimiser x; ``details`` (of earlier stages) are kept."""
        admm = _AndersonADMM(problem, x, self.rho0, self.memory)
        target, n_rho, attempts = self.admm_tol, 0, []
        it, prim, dual, found = 0, np.inf, np.inf, None
        for it in range(1, self.max_iter + 1):
            prim, dual = admm.advance()
            if prim < target and dual < target:
                record, found = self._attempt(problem, admm.eig, it, newton)
                attempts.append(record)
                if found is not None:
                    break
                if target <= 1e-11:  # ADMM itself has converged: its feasible iterate
                    found = self._accept(problem, admm.z_next[:admm.n])
                    break
                target /= 10.0
            if it % 25 == 0 and n_rho < 3 and (prim > 10 * dual or dual > 10 * prim):
                n_rho += 1  # each change costs a factorisation: allow a few
                admm.rescale(4.0 if prim > dual else 0.25)
        if found is None:
            found = self._accept(problem, admm.z_next[:admm.n])[:3] + (False,)
        result, gap, lam_min, converged = found
        eps = problem.eps
        return problem.index.theta(result), Certificate(
            "admm", bool(converged), it, seconds=time.perf_counter() - t0, method="admm+face",
            duality_gap=float(gap), face_ranks=[int((admm.eig[0][k] > eps).sum()) for k in range(problem.n_blocks)],
            face_multiplier_min=lam_min, face_A_min=attempts[-1]["a_min"] if attempts else -np.inf,
            primal_residual=float(prim), dual_residual=float(dual), rho=admm.rho,
            polish_attempts=len(attempts),
            details={**details, **({"attempts": attempts} if attempts else {}), **newton.details()})

    def _accept(self, problem, x):
        """(x, gap, multiplier min, certified?) of ADMM's own iterate."""
        gap, lam_min = problem.dual_gap(x)
        return x, gap, lam_min, gap <= self.gap_tol or (not problem.spd.ok and lam_min >= -self.kkt_tol)

    def _attempt(self, problem: Problem, eig, it, newton: FaceNewton):
        """Polish on the face ADMM shows, then Newton on it: (record, (x, gap, lam_min, True)
        if certified, else None)."""
        ranks = [int((eig[0][k] > problem.eps).sum()) for k in range(problem.n_blocks)]
        xp, a_min = polish(problem, *eig)  # exact minimiser on the face (its subspaces fixed)
        record = {"iteration": it, "ranks": ranks, "a_min": a_min}
        if a_min <= 0:
            return record, None
        gap, lam_min = problem.dual_gap(xp, ranks=ranks, enough=self.gap_tol)
        record.update(polish_gap=gap, lam_min=lam_min)
        if gap <= self.gap_tol or (not problem.spd.ok and lam_min >= -self.kkt_tol):
            return record, (xp, gap, lam_min, True)
        if not problem.spd.ok:
            return record, None
        refined = newton.refine(xp, ranks)  # ... then Newton on the face, turning the subspaces
        record.update(newton=None if refined is None else refined[1])
        if refined is None or refined[1] > self.gap_tol:
            return record, None
        return record, (refined[0], *problem.dual_gap(refined[0], ranks=ranks, enough=self.gap_tol),
                        True)
