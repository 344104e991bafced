"""The compressed least-squares problem and the certificate every strategy returns."""

from __future__ import annotations

import dataclasses
import functools
import itertools
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from .linalg import (
    SPDSolver,
    face_basis,
    from_eig,
    residual_norm2,
    symmetric_normal_equations,
    unvech,
    vech_index,
)
from ...errors import InputError


#: the relative duality gap is measured against max(f, floor ||Z||^2) (Problem.f_floor), the
#: floor GAP_FLOOR, or RESOLUTION u^2 cond(H) when larger (Problem.resolved; u the unit
#: roundoff). Normal equations whose condition exceeds COND_MAX are solved with the ridge
#: raised to the first of RIDGE_STEPS that brings it there (Problem.resolved)
GAP_FLOOR, RESOLUTION = 1e-12, 1e10
COND_MAX, RIDGE_STEPS = 1e12, (1e-8, 1e-7, 1e-6, 1e-5, 1e-4)


@dataclass
class Certificate:
    """How a solve went.

    Attributes:
        solver: the strategy that produced the answer (``"lyapunov"``, ``"admm"``, ``"ipm"``,
            ``"symmetric-lsq"``, ``"barrier"``).
        converged: whether it met its tolerance (``status`` says it in words).
        iterations: its iteration count (0 for closed forms).
        seconds: wall time of the solve.
        method: the path of :class:`~dolfinx_lopinf.core.lsq.PSDBlocks` that answered
            (``"symmetric-lsq"``, ``"ipm"``, ``"admm+face"``).
        duality_gap: certified relative duality gap (f - g) / f.
        face_ranks: rank of S_k - eps I per block at the answer.
        face_multiplier_min: smallest eigenvalue of grad_S f at the answer (relative).
        face_A_min: smallest relative eigenvalue of the face coordinates at the last polish.
        primal_residual, dual_residual, rho: ADMM's relative residuals and penalty.
        polish_attempts: how often ADMM + face tried an exact solve on a face.
        stationarity, multiplier_min_eig, complementarity: KKT residuals (:func:`kkt`).
        details: traces and the records of sub-solvers (``"ipm"``, ``"attempts"``, ...).

    Fields left None are not part of :meth:`as_dict`.
    """

    solver: str
    converged: bool
    iterations: int = 0
    seconds: float | None = None
    method: str | None = None
    duality_gap: float | None = None
    face_ranks: list | None = None
    face_multiplier_min: float | None = None
    face_A_min: float | None = None
    primal_residual: float | None = None
    dual_residual: float | None = None
    rho: float | None = None
    polish_attempts: int | None = None
    stationarity: float | None = None
    multiplier_min_eig: float | None = None
    complementarity: float | None = None
    details: dict = field(default_factory=dict)

    @property
    def status(self) -> str:
        return "optimal" if self.converged else "not converged"

    def as_dict(self) -> dict:
        """The set fields and the details, flat (the certificate dict of earlier versions)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "details"}
        return {**{k: v for k, v in out.items() if v is not None}, **self.details}


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
    Q, R = scipy.linalg.qr(L[order].T, mode="economic", check_finite=False)
    Lp, Zp = R.T, Z @ Q
    nf = int(free.sum())
    L_FF, L_SF, L_SS = Lp[:nf, :nf], Lp[nf:, :nf], Lp[nf:, nf:]

    def recover(theta_S):
        rhs = theta_S @ L_SF + Zp[:, :nf]
        # Theta_F^T = -L_FF^-T rhs^T (LAPACK dtrtrs: no checks, the factor is ours)
        out, info = scipy.linalg.lapack.dtrtrs(L_FF, rhs.T, lower=1, trans=1)
        if info != 0:  # a zero pivot: L_FF singular (gram_data's ridge keeps it regular)
            raise np.linalg.LinAlgError(f"free columns not determined (dtrtrs info {info})")
        return -out.T

    return L_SS, Zp[:, nf:], recover


@dataclass(frozen=True, eq=False)
class Problem:
    """min f(Theta) = ||Theta L + Z||_F^2 over Theta = [S_1 .. S_b, F] (r, p): b symmetric
    blocks S_k >= eps I (r x r each), then ``n_free`` free columns F.

    ``L`` (p, p) is the factor of the Gram matrix G = L L^T and ``Z`` (r, p) the data term
    (:func:`dolfinx_lopinf.core.gram.gram_data`), so nothing here depends on the number of
    snapshots. In the vech unknowns x of the blocks (no free columns),
    f = x^T H x + 2 h^T x + ||Z||^2 with ``H, h = normal_equations``.
    """

    L: np.ndarray
    Z: np.ndarray
    n_blocks: int = 1
    eps: float = 0.0
    n_free: int = 0
    floor: float = GAP_FLOOR  # f_floor / ||Z||^2 (see resolved)

    def __post_init__(self):
        r, p = self.Z.shape
        if self.L.shape != (p, p) or p != self.n_blocks * r + self.n_free:
            raise InputError(f"L {self.L.shape} and Z {self.Z.shape} do not fit {self.n_blocks} "
                             f"symmetric blocks and {self.n_free} free columns")

    @property
    def r(self) -> int:
        return self.Z.shape[0]

    @property
    def block_slices(self) -> list[slice]:
        return [slice(k * self.r, (k + 1) * self.r) for k in range(self.n_blocks)]

    @property
    def index(self):
        return vech_index(self.r, self.n_blocks)

    @functools.cached_property
    def f_floor(self) -> float:
        """floor ||Z||^2: the smallest objective the relative gap is measured against. f itself
        is known only to ~u ||Z|| ||Theta L + Z||, so on data fitted almost exactly (f -> 0:
        exact derivatives of a linear model, say) a gap relative to f alone would ask for more
        digits than double precision has (:meth:`resolved` raises the floor further where
        the normal equations are ill-conditioned)."""
        return self.floor * float(np.sum(self.Z**2))

    def resolved(self):
        """``(problem, ridge)``: this problem as double precision can certify it - ``ridge``
        None when only the floor changed (or nothing: then the problem itself). Computed once
        per problem (cached).

        The certificate's 1/4 v^T H^-1 v knows the gradient only to ~u ||Z|| ||L||, which
        H^-1 amplifies to ~u^2 cond(H) ||Z||^2 (cond of the equilibrated H, LAPACK's
        estimate), so the floor becomes max(floor, RESOLUTION u^2 cond(H)): that noise 100x
        below a 1e-8 gap (below cond(H) ~ 2e9 nothing changes; the benchmark and held-out
        sets have 1e5 - 1e7). Where cond(H) > COND_MAX - rank-deficient data, whose condition
        the normal equations square, so gram_data's ridge 1e-9 sigma_1 is invisible in them -
        the interior point's directions carry errors ~u cond(H) and its dual residual stalls
        (r = 16 - 20: gaps 1e-4 - 1e-3, then ADMM and the barrier, long and uncertified):
        the ridge is raised (:meth:`with_ridge`) to the first of RIDGE_STEPS that brings the
        condition to COND_MAX. Computed only when asked (the estimate costs a factorisation
        of H): :class:`~dolfinx_lopinf.core.lsq.Auto` asks after the interior point fails."""
        return self._resolution

    @functools.cached_property
    def _resolution(self):
        unit = np.finfo(float).eps
        cond, ridge, problem = self.spd.condition, None, self
        if cond > COND_MAX:
            for step in RIDGE_STEPS:
                ridged = self.with_ridge(step)
                if ridged.spd.condition <= COND_MAX:
                    problem, ridge, cond = ridged, step, ridged.spd.condition
                    break
        floor = max(self.floor, RESOLUTION * unit**2 * cond) if np.isfinite(cond) else self.floor
        if problem is self and floor == self.floor:
            return self, None
        return dataclasses.replace(problem, floor=floor), ridge

    def with_ridge(self, ridge: float):
        """The problem plus gamma^2 ||Theta diag(s)||^2, s_j = ||L_j|| (the data rows' norms),
        gamma = ``ridge`` sigma_1(diag(1/s) L): the ridge of
        :func:`~dolfinx_lopinf.core.gram.gram_data`, once more. One QR of
        [[L^T, Z^T], [gamma diag(s), 0]], whose leading block row is [L'^T, Z'^T] (the
        constant ||R_22||^2 dropped, as ``gram_data`` drops the data's own)."""
        p, r = self.L.shape[0], self.r
        s = np.maximum(np.linalg.norm(self.L, axis=1), np.finfo(float).tiny)
        gamma = ridge * np.linalg.norm(self.L / s[:, None], 2)
        A = np.zeros((2 * p, p + r))
        A[:p, :p], A[:p, p:] = self.L.T, self.Z.T
        A[p:, :p] = gamma * np.diag(s)
        R = scipy.linalg.qr(A, mode="r", check_finite=False)[0][:p]
        return dataclasses.replace(self, L=R[:, :p].T.copy(), Z=R[:, p:].T.copy())

    def objective(self, theta: np.ndarray) -> float:
        """f(Theta) = ||Theta L + Z||_F^2."""
        return residual_norm2(theta, self.L, self.Z)

    def kkt(self, theta: np.ndarray) -> dict:
        """KKT residuals of ``theta`` (see :func:`kkt`)."""
        return kkt(self.L, self.Z, theta, self.block_slices, self.eps)

    def without_free(self):
        """``(problem on the blocks alone, recover)``: the free columns minimised out exactly
        (:func:`eliminate_free`); ``recover(Theta_S)`` gives them back."""
        free = np.zeros(self.L.shape[0], dtype=bool)
        free[self.L.shape[0] - self.n_free:] = True
        L_S, Z_S, recover = eliminate_free(self.L, self.Z, free)
        return Problem(L_S, Z_S, self.n_blocks, self.eps, floor=self.floor), recover

    @functools.cached_property
    def normal_equations(self):
        """(H, h) in the vech unknowns of the blocks (:func:`symmetric_normal_equations`)."""
        self._blocks_only()
        return symmetric_normal_equations(self.L, self.Z, self.n_blocks)

    @functools.cached_property
    def spd(self) -> SPDSolver:
        """The equilibrated Cholesky of H (``ok`` False when H is singular)."""
        return SPDSolver(self.normal_equations[0])

    @functools.cached_property
    def gradient_scale(self) -> float:
        """||2 X|| (X = Z L^T): the scale of the KKT residuals."""
        return max(2.0 * float(np.linalg.norm(self.Z @ self.L.T)), 1e-300)

    def objective_x(self, x: np.ndarray) -> float:
        """f at the vech unknowns x."""
        return self.objective(self.index.theta(x))

    def dual_gap(self, x: np.ndarray, lam: np.ndarray | None = None, ranks=None,
                 enough: float = 0.0):
        """Certified relative gap (f(x) - g(Lambda)) / max(f(x), f_floor) of a feasible x (the
        floor :attr:`f_floor` acts only on data fitted to ~1e-6 relative), and the smallest
        eigenvalue of grad_S f(x) (relative to ||2 X||).

        For any Lambda >= 0, L(x') = f(x') - <Lambda, S(x') - eps I> has the minimiser x_s with
        f(x) - g(Lambda) = (x - x_s)^T H (x - x_s) + <Lambda, S(x) - eps I>,
        x - x_s = H^-1 v / 2, v = grad f(x) - D vech(Lambda): two nonnegative terms, no
        cancellation. The candidates for Lambda, each tried only while the ones before give
        more than ``enough``: ``lam`` (the interior point's multipliers) when given, the PSD
        part of grad_S f(x) and, when the face ``ranks`` (rank of each S_k - eps I) are given
        (a sequence, or a function returning one: called only when needed), the multipliers
        on that face (:meth:`_face_multipliers`). The smallest gap is a proof for all: any
        Lambda >= 0 bounds, the choice only decides how tightly.
        """
        H, h = self.normal_equations
        ix = self.index
        grad = 2.0 * (H @ x + h)
        grad_S = ix.blocks(grad / ix.Dw)
        slack = ix.blocks(x) - self.eps * np.eye(self.r)
        fx = max(self.objective_x(x), self.f_floor, 1e-300)

        def gap(candidates):
            out = np.inf
            for lam_k in candidates:  # (a generator: the ones after a gap <= enough not formed)
                v = grad - ix.Dw * ix.vech(lam_k)
                out = min(out, 0.25 * float(v @ self.spd.solve(v)) + float(np.sum(lam_k * slack)))
                if max(out, 0.0) / fx <= enough:
                    break
            return max(out, 0.0) / fx

        rel = np.inf if lam is None else gap([lam])
        if rel > enough:
            lam_w, lam_Q = np.linalg.eigh(grad_S)
            rel = min(rel, gap([from_eig(np.maximum(lam_w, 0.0), lam_Q)]))
        else:  # certified by lam: the smallest eigenvalue alone, for the report
            lam_w = np.linalg.eigvalsh(grad_S)
        if ranks is not None and rel > enough:
            ranks = ranks() if callable(ranks) else ranks
            rel = min(rel, gap(self._face_multipliers(grad, slack, ranks)))
        return rel, float(lam_w.min()) / self.gradient_scale

    def _face_multipliers(self, grad, slack, ranks):
        """Multipliers supported on the face: Lambda_k = N_k M_k N_k^T, N_k the r - ranks[k]
        eigenvectors of S_k - eps I with the smallest eigenvalues, or one more (a direction
        the rank count may have missed: both it and its multiplier small), every combination
        over the blocks. M minimises the bound 0.25 v^T H^-1 v + <Lambda, S - eps I>
        (v = grad - D vech Lambda) - a least-squares problem in the m (m + 1) / 2 entries of
        each M_k - and is then clipped PSD. Near an optimum whose multipliers are small
        (weakly active constraints) this bound is tighter than the PSD part of the gradient,
        which pays <grad, S - eps I> on the inactive directions, where both are small but
        their product is not (the interior point stalls there at m mu / f ~ 1e-8)."""
        ix, r, nb = self.index, self.r, self.n_blocks  # (a generator of the candidates)
        widest = [min(r, max(r - int(k), 0) + 1) for k in ranks]
        cols, lin, owner, pairs, eigvecs = [], [], [], [], []
        for k in range(nb):
            N = np.linalg.eigh(slack[k])[1][:, :widest[k]]
            a, b = vech_index(widest[k], 1).iu
            J = np.zeros((ix.n, len(a)))
            J[k * ix.nv:(k + 1) * ix.nv] = ix.Dw[:ix.nv, None] * face_basis(N, ix.iu)
            S_N = N.T @ slack[k] @ N
            cols.append(J)
            lin.append(np.where(a == b, 1.0, 2.0) * S_N[a, b])   # <N E_ab N^T, S - eps I>
            owner.append(np.full(len(a), k))
            pairs.append(np.maximum(a, b))
            eigvecs.append(N)
        A, lin = np.hstack(cols), np.concatenate(lin)
        owner, top = np.concatenate(owner), np.concatenate(pairs)
        HiA = self.spd.solve(A)
        G, bA = A.T @ HiA, HiA.T @ grad                                # A^T H^-1 A, A^T H^-1 g
        for sizes in itertools.product(*[sorted({max(w - 1, 0), w}) for w in widest]):
            keep = top < np.asarray(sizes)[owner]                    # pairs (a, b) inside the face
            if not keep.any():
                continue
            # minimise 0.25 (g - A c)^T H^-1 (g - A c) + lin^T c: G c = bA - 2 lin
            c = np.zeros(len(lin))
            c[keep] = np.linalg.lstsq(G[np.ix_(keep, keep)], bA[keep] - 2.0 * lin[keep],
                                      rcond=None)[0]
            lam = np.zeros((nb, r, r))
            for k in range(nb):
                m = sizes[k]
                if m == 0:
                    continue
                # the kept pairs of block k, in triu_indices(m) order (row-major, a <= b)
                w, V = np.linalg.eigh(unvech(c[(owner == k) & keep], m))
                N = eigvecs[k][:, :m]
                lam[k] = from_eig(np.maximum(w, 0.0), N @ V)
            yield lam

    def _blocks_only(self):
        if self.n_free:
            raise InputError("minimise the free columns out first (Problem.without_free)")


def symmetric_start(problem: Problem):
    """The unconstrained symmetric minimiser x = -H^-1 h and, per block, whether it is >= eps I."""
    x = -problem.spd.solve(problem.normal_equations[1])
    return x, np.linalg.eigvalsh(problem.index.blocks(x))[:, 0] >= problem.eps


def symmetric_answer(problem: Problem, x, t0: float):
    """The symmetric minimiser is feasible, hence optimal (zero multipliers)."""
    return problem.index.theta(x), Certificate(
        "symmetric-lsq", True, 0, seconds=time.perf_counter() - t0, method="symmetric-lsq",
        duality_gap=0.0, face_ranks=[problem.r] * problem.n_blocks, polish_attempts=0)


class Strategy:
    """A way to solve a :class:`Problem`: ``solve(problem) -> (Theta, Certificate)``.

    The free columns are minimised out exactly first (:meth:`Problem.without_free`);
    subclasses implement ``solve_blocks`` for a problem of symmetric blocks alone. Any object
    with such a ``solve`` method can be passed as ``solver=`` to
    :func:`dolfinx_lopinf.core.infer_mechanical`.
    """

    def solve(self, problem: Problem):
        if not problem.n_free:
            return self.solve_blocks(problem)
        reduced, recover = problem.without_free()
        theta_S, cert = self.solve_blocks(reduced)
        return np.hstack([theta_S, recover(theta_S)]), cert

    def solve_blocks(self, problem: Problem):  # pragma: no cover - the interface
        raise NotImplementedError

    def _one_block(self, problem: Problem):
        if problem.n_blocks != 1:
            raise InputError(f"{type(self).__name__} solves one symmetric block, not "
                             f"{problem.n_blocks}")

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in vars(self).items() if not k.startswith("_"))
        return f"{type(self).__name__}({args})"
