"""L-OpInf with a learned reduced mass, solved by our certified interior point.

With M = I fixed, L-OpInf is only right in a mass-orthonormal basis (V^T M V = I); a
black-box user has a Euclidean POD basis, where the reduced mass V^T M V is far from I, and
the fit inherits that model-form error. Here M is fitted too:

    M D2 + C D1 + K Qbar - B Ubar = R,        M, K (, C) symmetric, >= floors.

Misfit: the residual force in the norm dual to the kinetic energy, f = tr(R^T M^-1 R) (the
matrix-fractional function, jointly convex), normalised by tr(M W) = 1 with
W = Qbar Qbar^T / ||Qbar||_F^2. Both are invariant under q = T q~ (M -> T^T M T, data ->
T^-1 data): the learned model does not depend on the basis of the POD space, and in the
coordinates where M = I it is the M = I L-OpInf. Alone, this misfit determines the dynamics
(M^-1 K, M^-1 C) but hardly the scale of each mode, and its exact minimiser pushes modes onto
the floor (worse predictions); the fit minimises f - tau log det(M - F_M) instead, the
analytic centre of the fits within about ``rho`` of the least misfit (tau = rho f / r at the
answer; coordinate invariant too) - :mod:`dolfinx_lopinf.core.lsq.fractional`, whose
interior point solves it with a certified duality gap. Measured on the Newmark cantilever
(unseen load, r = 4 / 8): 6e-5 / 1.7e-5 against 7.9e-4 / 5.9e-5 with the earlier Clarabel
solve of the unregularised problem, stopped at its tolerance.

Coordinates. The solver works in balanced coordinates q~ = S q: the generalised eigenvectors
of the acceleration covariance A against W, scaled so that both become diag(lambda^-/+1/2)
(each direction's displacement and acceleration weights reciprocal). A POD basis is the
opposite: its last modes carry 1e-16 of the displacement variance and 1e-6 of the
acceleration, and the interior point's linear algebra loses its digits there (measured:
uncertified at r >= 12 in POD coordinates, certified in balanced ones). The answer is mapped
back exactly (M = S^T M~ S, K, C alike, B = S^T B~); the floors are kept in the user's
coordinates (F~ = eps S^-T S^-1).

Normalisation floor. The analytic centre of {M : tr(M W) = 1} is M = W^-1 / r: each direction's
mass inversely proportional to its state variance. A POD basis's last coordinates carry 1e-12 ..
1e-20 of the variance, so where the data hardly fix the modal scales (near-exact data: the
misfit is nearly flat along them) the regulariser gave those directions masses 1e7 .. 1e9 times
the leading one's and the fit weighted their residuals - truncation error, 10 % of their own
size - over the leading modes' equations (measured on recorded user loops at r = 8 / 12,
unseen load: 7e-6 / 1.0 relative error of the output against 2e-8 / 8e-12 for the free fit).
The normalisation is therefore tr(M W_f) = 1 with W_f = (W + W_FLOOR tr(W) I / r) / (1 + W_FLOOR):
directions with less than W_FLOOR of the mean variance get the weight of an isotropic mass in
the user's coordinates - the coefficients of an orthonormal basis (POD, Euclidean or
mass-orthonormal), where the physical reduced mass V^T M V is well conditioned. The fit is
invariant under orthogonal changes of coordinates and, where the data determine the modal
scales, under any other; in a scaled basis the floor is a prior on the scales of the weakly
excited directions only. Directions the data do not visit at all (Qh's singular values below
RANK_RTOL) are named in an IllConditionedDataWarning, or a RankDeficientDataError with
strict=True.

``solver="cvxpy"``: the same (regularised) problem through cvxpy/Clarabel, the reference.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from ._checks import check_matrix
from .conic import clarabel
from .gram import RANK_RTOL, MechanicalOperators, block_names, compress, psd_floor
from .lsq.fractional import RHO, FractionalProblem, MassInteriorPoint
from .lsq.linalg import sym
from .lsq.problem import eliminate_free
from ..errors import (IllConditionedDataWarning, InputError, RankDeficientDataError,
                      SolverFailedError, SolverWarning, warn)

#: Lower bound on the eigenvalues of the learned mass, relative to its normalisation
#: tr(M W) = 1 (W has unit trace, so M = I is feasible).
MASS_FLOOR = 1e-9
#: the normalisation's isotropic floor, relative to the mean state variance (module docstring)
W_FLOOR = 1e-2


def infer_with_mass(Qh, dQh, ddQh, U=None, *, damping: bool = True, eps: float = 1e-8,
                    ridge: float, strict: bool = False, solver: str = "auto", rho: float = RHO,
                    gap_tol: float = 1e-8, backend: str = "auto"):
    """Fit (M, K, C, B) of M qh_tt + C qh_t + K qh = B u (module docstring), normalised to
    tr(M W) = 1 in the user's coordinates.

    Args:
        Qh, dQh, ddQh, U: (r, K) states and derivative data of one relation (and (m, K)
            inputs), as for :func:`~dolfinx_lopinf.core.inference.infer_mechanical`.
        damping: fit C (needs dQh); eps: eigenvalue floor of K and C (user units);
        ridge, strict: as in :func:`~dolfinx_lopinf.core.gram.gram_data`; ``strict``
            also raises SolverFailedError when the fit is not certified.
        solver: ``"auto"`` (our interior point) or ``"cvxpy"`` (Clarabel, the reference).
        rho: the regularisation (module docstring); gap_tol: the certificate's tolerance;
        backend: the interior point's iteration, ``"numpy"``, ``"numba"`` or ``"auto"``.

    Returns:
        :class:`~dolfinx_lopinf.core.gram.MechanicalOperators` with ``M`` set and a
        certificate: ``solver``, ``certified``, ``duality_gap`` (relative, of the regularised
        problem), ``misfit_gap`` (f against the unregularised minimum), ``iterations``,
        ``seconds``, ...
    """
    if solver not in ("auto", "cvxpy"):
        raise InputError(f"mass='learned' is solved by 'auto' (our interior point) or 'cvxpy' "
                         f"(Clarabel), not {solver!r}")
    t0 = time.perf_counter()
    prep = prepare(Qh, dQh, ddQh, U, damping=damping, eps=eps, ridge=ridge, strict=strict, rho=rho)
    if solver == "cvxpy":
        theta_S, info = solve_cvxpy(prep.problem)
    else:
        xs, _, _, solved = MassInteriorPoint(gap_tol=gap_tol, backend=backend).solve(prep.problem)
        theta_S, info = prep.problem.theta(xs), _engine_info(solved)
    M, K, C, B = prep.operators(theta_S)
    cert = prep.certificate(M, K, C, B, info, gap_tol, time.perf_counter() - t0)
    if not cert["certified"]:
        msg = (f"learned-mass fit not certified: duality gap {cert['duality_gap']:.2e} > {gap_tol:g}"
               f" ({cert['solver']}, {cert.get('stopped', cert['status'])})")
        if strict:
            raise SolverFailedError(msg)
        warn(msg + "; check the model's held-back error", SolverWarning)
    c = float(np.sum(M * prep.W_user))  # normalise tr(M W) = 1 in the user's coordinates
    return MechanicalOperators(K / c, None if C is None else C / c, None if B is None else B / c, cert,
                               M=M / c)


def _engine_info(solved) -> dict:
    d = solved.details
    return {"solver": "mass-ipm", "status": solved.status, "iterations": solved.iterations,
            "solve_seconds": solved.seconds, "duality_gap": solved.duality_gap,
            "misfit_gap": d.get("misfit_gap"), "tau": d.get("tau"), "stopped": d.get("stopped"),
            "backend": d.get("backend"), "trace": d.get("trace"), "dual": d.get("dual")}


@dataclass
class Prepared:
    """One learned-mass fit's data in the solver's coordinates q~ = S q: the problem (free
    columns B minimised out), how to get B back, the block scaling and the user's W."""

    problem: FractionalProblem
    recover: object  # Theta_S -> the free columns (or None)
    S: np.ndarray
    blocks: list  # (name, scale): K = k K', C = k C', B = -k (-B)'
    W_user: np.ndarray
    eps: float
    data: dict  # user-coordinate arrays for the residual; rank, condition

    def operators(self, theta_S):
        """(M, K, C, B) in the user's coordinates from the solver's unknowns, floored."""
        r = self.S.shape[0]
        theta = theta_S if self.recover is None else np.hstack([theta_S, self.recover(theta_S)])
        ops, start = {}, 0
        for name, k in self.blocks:
            width = r if name != "B" else theta.shape[1] - start
            ops[name] = theta[:, start:start + width] * k
            start += width
        S = self.S
        back = lambda A: sym(S.T @ A @ S)  # noqa: E731
        M = psd_floor(back(ops["M"]), 0.0)
        K = psd_floor(back(ops["K"]), self.eps)
        C = psd_floor(back(ops["C"]), self.eps) if "C" in ops else None
        B = -(S.T @ ops["B"]) if "B" in ops else None
        return M, K, C, B

    def certificate(self, M, K, C, B, info, gap_tol, seconds) -> dict:
        d = self.data
        R = M @ d["ddQh"] + K @ d["Qh"] + (C @ d["dQh"] if C is not None else 0.0) \
            - (B @ d["U"] if B is not None else 0.0)
        wM = np.linalg.eigvalsh(M)
        feasible = bool(wM[0] > 0 and np.linalg.eigvalsh(K)[0] >= self.eps
                        and (C is None or np.linalg.eigvalsh(C)[0] >= self.eps))
        gap = info.get("duality_gap")
        gap = np.inf if gap is None else float(gap)
        certified = bool(gap <= gap_tol and feasible)
        c = float(np.sum(M * self.W_user))
        cert = {
            "solver": info["solver"], "certified": certified,
            "status": "optimal" if certified else "not certified",
            "duality_gap": gap, "misfit_gap": info.get("misfit_gap"),
            "iterations": info.get("iterations"), "seconds": seconds, "mass": "learned",
            "regularisation": self.problem.rho, "tau": info.get("tau"),
            "objective": float(np.sum(R * np.linalg.solve(M, R))) / c,
            "relative_residual": float(np.sqrt(np.sum(R * np.linalg.solve(M, R))
                                               / max(np.sum(d["ddQh"] * (M @ d["ddQh"])), 1e-300))),
            "normalisation": 1.0, "symmetry_error": 0.0, "eps": self.eps,
            "data_rank": d["rank"], "data_rows": d["rows"], "data_condition": d["cond"],
            "min_eig_M": float(wM[0] / c), "max_eig_M": float(wM[-1] / c),
            "min_eig_K": float(np.linalg.eigvalsh(K)[0] / c),
        }
        if C is not None:
            cert["min_eig_C"] = float(np.linalg.eigvalsh(C)[0] / c)
        for key in ("stopped", "backend", "solve_seconds", "clarabel_status", "dual"):
            if info.get(key) is not None:
                cert[key] = info[key]
        if info.get("trace") is not None:
            cert["ipm"] = {"trace": info["trace"]}
        return cert


def _covariances(Qh, ddQh, strict):
    """W (unit trace), the floored normalisation W_f = (W + W_FLOOR I / r) / (1 + W_FLOOR)
    (module docstring) and A (unit trace): warning or error (strict) for directions the states
    do not visit."""
    r = Qh.shape[0]
    W = sym(Qh @ Qh.T) / np.sum(Qh**2)
    A = sym(ddQh @ ddQh.T) / np.sum(ddQh**2)
    sv = np.linalg.svd(Qh, compute_uv=False)  # W's eigenvalues are these squared (and rounded)
    unseen = int(np.sum(sv < RANK_RTOL * sv[0]))
    W_f = (W + W_FLOOR * np.eye(r) / r) / (1.0 + W_FLOOR)
    if unseen:
        msg = (f"the states Qh span only {r - unseen} of the r = {r} reduced directions (singular "
               f"values below {RANK_RTOL:g} of the largest: fewer snapshots than r, or constant or "
               "dependent coordinates), so the data do not determine the learned mass there")
        if strict:
            raise RankDeficientDataError(msg + "; lower r or record a richer trajectory")
        warn(msg + f"; its scale there is set by the normalisation's isotropic floor ({W_FLOOR:g} "
             "of the mean state variance). Pass strict=True to raise instead.", IllConditionedDataWarning)
    return W, W_f, A


def _balanced(W_reg, A):
    """S with S W_reg S^T = diag(lam^-1/2), S A_f S^T = diag(lam^1/2) (lam: the generalised
    eigenvalues of (A_f, W_reg), floored at 1e-12 of the largest; A_f: A with the floor of W_f,
    so that the directions the floor governs are balanced as well)."""
    r = len(A)
    lam, V = scipy.linalg.eigh((A + W_FLOOR * np.eye(r) / r) / (1.0 + W_FLOOR), W_reg)
    lam = np.maximum(lam, 1e-12 * lam.max())
    return lam[:, None] ** -0.25 * V.T


def prepare(Qh, dQh, ddQh, U, *, damping, eps, ridge, strict, rho) -> Prepared:
    """Check the data, pick the balanced coordinates, scale and compress the blocks, and set up
    the :class:`FractionalProblem` (B minimised out)."""
    Qh = check_matrix(Qh, "Qh")
    r, n_samples = Qh.shape
    ddQh = check_matrix(ddQh, "ddQh", rows=r, cols=n_samples)
    if damping:
        if dQh is None:
            raise InputError("damping=True needs the first derivatives dQh")
        dQh = check_matrix(dQh, "dQh", rows=r, cols=n_samples)
    if U is not None:
        U = check_matrix(np.atleast_2d(U), "U", cols=n_samples)
    m = 0 if U is None else U.shape[0]
    if not np.any(ddQh):
        raise InputError("the second-derivative data ddQh are identically zero: static snapshots "
                         "carry no dynamics to fit; record a trajectory that moves")
    if not (np.isfinite(rho) and 0 < rho < 1):
        raise InputError(f"rho must be a number in (0, 1), got {rho!r}")
    W, W_reg, A = _covariances(Qh, ddQh, strict)
    S = _balanced(W_reg, A)
    Qs, ddQs = S @ Qh, S @ ddQh
    dQs = S @ dQh if damping else None
    size = float(np.linalg.norm(ddQs))
    blocks = [("M", ddQs, 1.0), ("K", Qs, size / max(float(np.linalg.norm(Qs)), 1e-300))]
    if damping:
        blocks.append(("C", dQs, size / max(float(np.linalg.norm(dQs)), 1e-300)))
    if m:
        blocks.append(("B", U, size / max(float(np.linalg.norm(U)), 1e-300)))
    rows = [k * data for _, data, k in blocks]
    p = sum(x.shape[0] for x in rows)
    if n_samples < p:
        raise InputError(f"{n_samples} data columns (time samples; in lo.fit those its scheme's "
                         f"relation leaves, 2 to 8 fewer than recorded) cannot determine {p} "
                         "unknowns per row; record more time samples or lower r")
    names = [f"ddQh[{i}]" for i in range(r)] + block_names(r, m, damping)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedDataWarning)
        L, _, cond, rank, _ = compress(rows, np.zeros((0, n_samples)), names, ridge, False,
                                        "[ddQh; Qh; dQh; U]")
    if rank < p - r:  # r exact relations leave rank p - r: below it, entries are undetermined
        msg = (f"the data [ddQh; Qh; dQh; U] ({p} rows, row-normalised) have numerical rank "
               f"{rank} < {p - r} = rows - r (condition number {cond:.3g}): some operator "
               "directions are not determined by the data")
        if strict:
            raise RankDeficientDataError(msg + "; lower r or record a richer trajectory")
        warn(msg + f"; they were fixed by the ridge {ridge:g} * sigma_1. Pass strict=True to "
             "raise instead.", IllConditionedDataWarning)
    recover = None
    if m:
        free = np.zeros(p, dtype=bool)
        free[p - m:] = True
        L, _, recover = eliminate_free(L, np.zeros((r, p)), free)
    Si = np.linalg.inv(S)
    G = Si.T @ Si  # a floor c I in user coordinates is c S^-T S^-1 in the solver's
    floors = [MASS_FLOOR * G] + [eps / k * G for name, _, k in blocks if name in ("K", "C")]
    problem = FractionalProblem(np.ascontiguousarray(L), sym(S @ W_reg @ S.T), np.stack(floors), rho,
                                float(np.sum(L[:r] ** 2)))
    return Prepared(problem, recover, S, [(name, k) for name, _, k in blocks], W, eps,
                    {"Qh": Qh, "dQh": dQh, "ddQh": ddQh, "U": U, "rank": rank, "rows": p,
                     "cond": cond})


#: Clarabel's tolerances for comparisons of accuracy (its defaults are 1e-8 absolute and
#: relative: the benchmark's timings use them)
TIGHT = {"tol_gap_abs": 1e-14, "tol_gap_rel": 1e-12, "tol_feas": 1e-12, "tol_ktratio": 1e-10,
         "max_iter": 400}


def solve_cvxpy(problem: FractionalProblem, tau: float | None = None, rounds: int = 3, options=None):
    """The reference: Clarabel (through cvxpy) on min f - tau log det(M - F_0), <W, M> = 1,
    S_k >= F_k, the objective divided by f at our start (O(1) for Clarabel). ``tau`` None: the
    fixed point tau = rho f / r by ``rounds`` solves; ``options``: Clarabel's (e.g. TIGHT).
    Returns (Theta, info: Clarabel's status, iterations, relative gap, seconds, tau)."""
    try:
        import cvxpy as cp
    except ImportError as exc:  # pragma: no cover - the cvx extra
        raise ImportError("solver='cvxpy' needs cvxpy and clarabel: pip install cvxpy clarabel") from exc
    from .lsq.fractional import start

    r, b = problem.r, problem.n_blocks
    f_ref = problem.gap_reference(problem.misfit(start(problem)))
    scale = np.sqrt(f_ref)
    Ln = problem.L / scale  # f / f_ref: O(1) numbers for Clarabel
    t0 = time.perf_counter()
    fixed = tau is not None
    tau = tau if fixed else problem.tau_of(f_ref)
    out, its = None, 0
    for _ in range(1 if fixed else rounds):
        S = [cp.Variable((r, r), symmetric=True) for _ in range(b)]
        theta = cp.hstack(S)
        obj = cp.matrix_frac(theta @ Ln, S[0]) - (tau / scale**2) * cp.log_det(S[0] - problem.floors[0])
        cons = [cp.trace(S[0] @ problem.W) == 1] + [S[k] - problem.floors[k] >> 0 for k in range(1, b)]
        prob = cp.Problem(cp.Minimize(obj), cons)
        raw = clarabel(cp, prob, options)
        its += raw["iterations"]
        out = np.hstack([sym(v.value) for v in S])
        f = float(np.sum((out @ problem.L) * np.linalg.solve(out[:, :r], out @ problem.L)))
        if not fixed:
            tau = problem.tau_of(f)
    info = {"solver": "cvxpy-clarabel", "status": prob.status, "clarabel_status": raw["status"],
            "iterations": its, "solve_seconds": time.perf_counter() - t0, "tau": tau,
            "duality_gap": raw["relative_gap"]}
    if prob.status != "optimal":
        warn(f"learned-mass fit: Clarabel returned {prob.status}", SolverWarning)
    return out, info

