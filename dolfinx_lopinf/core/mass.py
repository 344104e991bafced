"""L-OpInf with a learned reduced mass (numpy + cvxpy/Clarabel).

With M = I fixed, L-OpInf is only right in a mass-orthonormal basis (V^T M V = I); a
black-box user has a Euclidean POD basis, where the reduced mass V^T M V is far from I (for
the Hermite beam its eigenvalues span five decades: theta dofs carry h^2 less mass), and the
fit inherits that model-form error (beam block basis r = 20: test error 8e-4 against a
projection error of 9.4e-6). Here M is fitted too:

    M D2 + C D1 + K Qbar - B Ubar = R,        M, K (, C) symmetric, >= eps I.

Which misfit. The plain ||R||_F^2 is not the right one: with any normalisation of the scale
(e.g. trace M = r) it can "switch off" equation rows - M, K, C small in a direction make R
small there - and its minimiser collapses onto the best-fitting mode (measured: M's
eigenvalues [4.8e-5, 5.6] at r = 20, test error 3.7e-3, worse than M = I). We measure the
residual force in the norm dual to the kinetic energy,

    f(M, K, C, B) = tr(R^T M^{-1} R)   (the matrix-fractional function: jointly convex),

normalised by tr(M W) = 1 with W = Qbar Qbar^T / ||Qbar||_F^2 (M = I is feasible). Both are
invariant under a change of reduced coordinates q = T q~ (M -> T^T M T, data -> T^-1 data):
the learned model does not depend on which basis of the POD space the user has, and in the
coordinates where the learned M is I it is exactly the M = I L-OpInf (so a mass-orthonormal
basis gives the usual fit). The problem is convex: an SDP, solved by Clarabel on the
compressed data (:func:`dolfinx_lopinf.core.inference.gram_data`'s QR, ridge included); then
K, C, B are re-solved exactly for that M (the inner problem is the M = I L-OpInf in the
coordinates q~ = M^{1/2} q, solved by our certified solver) and the point with the smaller
misfit kept.

Certificate (``certificate["gap"]``). Weak duality gives a lower bound on the optimum from
the SDP's dual (:func:`_dual_bound`); ``gap`` = (f - bound) / f0 with f0 = ||L_M||^2, the
misfit of Mh = I with no forces (the data's scale). K, C, B are also certified optimal for
the learned M by the inner solver (``inner_status``). Measured: the tutorial-style Newmark
loop at r = 2 and 4, gap 2e-8 to 5e-8 (certified); noisy synthetic data 2e-9 to 2e-8, exact
synthetic data 1e-6 to 1e-3; but at r = 8 (state covariance W's eigenvalues 2e-11 .. 1) the
bound is useless (gap ~4e6): where W barely weighs a direction, the primal is nearly free
along it and the bound needs the dual more accurately than the interior point's 1e-8.
``mass_stationarity`` (:func:`_mass_stationarity`) is the first-order check of M alone.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from ._checks import check_matrix
from .lsq.linalg import from_eig, psd_project
from ..errors import (IllConditionedDataWarning, InputError, RankDeficientDataError,
                     SolverFailedError, SolverWarning, warn)

#: Lower bound on the eigenvalues of the learned mass, relative to its normalisation
#: tr(M W) = 1 (W has unit trace, so M = I is feasible).
MASS_FLOOR = 1e-9


def _norm(A):
    return float(np.linalg.norm(A))


def infer_with_mass(Qh, dQh, ddQh, U=None, *, damping: bool = True, eps: float = 1e-8,
                    ridge: float, strict: bool = False):
    """Fit (M, K, C, B) of M qh_tt + C qh_t + K qh = B u (module docstring), normalised to
    tr(M W) = 1 in the user's coordinates.

    One solve. Solving again in q~ = M^{1/2} q of the answer (the problem is
    coordinate-invariant, Clarabel's accuracy is not) was measured: it lowers the misfit but
    gives worse models (cantilever r = 8: unseen-load error 1.7e-4 -> 3.8e-3; beam unseen-IC:
    a singular M) - the misfit's infimum switches modes off (M, K, C -> 0 in a direction),
    and the interior point's stopping short regularises. A nearly singular M warns and is
    floored at 1e-8 of its largest eigenvalue.

    Args:
        Qh, dQh, ddQh, U: (r, K) states and derivative data of one relation (and (m, K)
            inputs), as for :func:`~dolfinx_lopinf.core.inference.infer_mechanical`.
        damping: fit C (needs dQh); eps: eigenvalue floor of K and C (user units);
        ridge, strict: as in :func:`~dolfinx_lopinf.core.inference.gram_data`.

    Returns:
        :class:`~dolfinx_lopinf.core.inference.MechanicalOperators` with ``M`` set.
    """
    from .inference import MechanicalOperators

    t0 = time.perf_counter()
    ops = _fit_once(Qh, dQh, ddQh, U, damping=damping, eps=eps, ridge=ridge, strict=strict)
    w, Q = np.linalg.eigh(ops.M)
    if w[0] < 1e-8 * w[-1]:
        warn(f"the learned reduced mass is nearly singular (eigenvalues {w[0]:.3g} .. {w[-1]:.3g}):"
             " the fit switched a direction off; use mass='identity' or a smaller r",
             IllConditionedDataWarning)
        ops = MechanicalOperators(ops.K, ops.C, ops.B, ops.certificate,
                                  M=from_eig(np.maximum(w, 1e-8 * w[-1]), Q))
    W = Qh @ Qh.T / np.sum(Qh**2)
    c = np.sum(ops.M * W)  # normalise tr(M W) = 1 in the user's coordinates
    cert = dict(ops.certificate, seconds=time.perf_counter() - t0)
    cert.update(min_eig_M=float(np.linalg.eigvalsh(ops.M / c).min()),
                max_eig_M=float(np.linalg.eigvalsh(ops.M / c).max()),
                min_eig_K=float(np.linalg.eigvalsh(ops.K / c).min()))
    if ops.C is not None:
        cert["min_eig_C"] = float(np.linalg.eigvalsh(ops.C / c).min())
    sym = lambda A: None if A is None else 0.5 * (A + A.T)  # noqa: E731
    return MechanicalOperators(sym(ops.K) / c, sym(ops.C) / c if ops.C is not None else None,
                               None if ops.B is None else ops.B / c, cert, M=sym(ops.M) / c)


@dataclass
class _MassData:
    """The checked data of one learned-mass fit, its block scaling and compressed form."""

    Qh: np.ndarray
    dQh: np.ndarray | None
    ddQh: np.ndarray
    U: np.ndarray | None
    blocks: list  # (name, data rows, scalar): K = k K', C = k C', B = -k (-B)'
    L: np.ndarray  # the compressed, block-scaled data [ddQh; k Qh; k dQh; k U] (ridge included)
    W: np.ndarray  # the normalisation weight, tr(M W) = 1
    rank: int
    cond: float

    @property
    def r(self):
        return self.Qh.shape[0]

    @property
    def layout(self):
        return [(name, data.shape[0]) for name, data, _ in self.blocks]

    def floors(self, eps):
        return {name: eps / k for name, _, k in self.blocks if name in ("K", "C")}


def _mass_data(Qh, dQh, ddQh, U, damping, ridge, strict) -> _MassData:
    """Check the data, scale the blocks to the size of D2 (O(1) unknowns for Clarabel) and
    compress them; warn (or raise, strict) when the data leave operator entries undetermined."""
    from .inference import _block_names, _compress

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
    size = _norm(ddQh)
    blocks = [("M", ddQh, 1.0), ("K", Qh, size / max(_norm(Qh), 1e-300))]
    if damping:
        blocks.append(("C", dQh, size / max(_norm(dQh), 1e-300)))
    if m:
        blocks.append(("B", U, size / max(_norm(U), 1e-300)))
    rows = [k * data for _, data, k in blocks]
    names = ([f"ddQh[{i}]" for i in range(r)] + _block_names(r, m, damping))
    p = sum(x.shape[0] for x in rows)
    if n_samples < p:
        raise InputError(f"{n_samples} snapshots cannot determine {p} unknowns per row; record "
                         "more time samples or lower r")
    # Data that obey r exact relations have rank p - r (the relations are the null space the
    # fit looks for): only a rank below p - r means undetermined operator entries.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedDataWarning)
        L, _, cond, rank, _ = _compress(rows, np.zeros((0, n_samples)), names, ridge, False,
                                        "[ddQh; Qh; dQh; U]")
    if rank < p - r:
        msg = (f"the data [ddQh; Qh; dQh; U] ({p} rows, row-normalised) have numerical rank "
               f"{rank} < {p - r} = rows - r (condition number {cond:.3g}): some operator "
               "directions are not determined by the data")
        if strict:
            raise RankDeficientDataError(msg + "; lower r or record a richer trajectory")
        warn(msg + f"; they were fixed by the ridge {ridge:g} * sigma_1. Pass strict=True to "
             "raise instead.", IllConditionedDataWarning)
    W = Qh @ Qh.T
    W = 0.5 * (W + W.T) / np.trace(W)
    W += 1e-12 * np.eye(r)  # positive definite for the certificate's generalised eigenproblem
    return _MassData(Qh, dQh if damping else None, ddQh, U, blocks, L, W, rank, cond)


def _solve_sdp(data: _MassData, eps):
    """Clarabel on min tr(R^T M^-1 R), tr(M W) = 1, M >= floor, K, C >= eps (scaled units).
    Returns (Theta, status, Z12: the dual of the Schur-complement constraint, or None)."""
    try:
        import cvxpy as cp
    except ImportError as exc:  # pragma: no cover - the cvx extra
        raise ImportError("mass='learned' needs cvxpy and clarabel: pip install cvxpy clarabel") from exc
    r, floors = data.r, data.floors(eps)
    variables = {name: cp.Variable((r, r), symmetric=True) if name != "B"
                 else cp.Variable((r, d.shape[0])) for name, d, _ in data.blocks}
    cons = [variables["M"] >> MASS_FLOOR * np.eye(r), cp.trace(variables["M"] @ data.W) == 1]
    cons += [variables[name] >> floors[name] * np.eye(r) for name in floors]
    theta = cp.hstack([variables[name] for name, _, _ in data.blocks])
    # matrix_frac(Theta Ln, M) written out as cvxpy canonicalises it, to read the dual of the
    # Schur-complement constraint: -Z12 is the Y of the certificate (:func:`_dual_bound`)
    Ln = data.L / _norm(data.L)
    T = cp.Variable((Ln.shape[1], Ln.shape[1]), symmetric=True)
    schur = cp.bmat([[variables["M"], theta @ Ln], [(theta @ Ln).T, T]]) >> 0
    prob = cp.Problem(cp.Minimize(cp.trace(T)), cons + [schur])
    try:
        prob.solve(solver=cp.CLARABEL)
    except cp.error.SolverError as exc:
        raise SolverFailedError(f"Clarabel failed on the learned-mass L-OpInf problem: {exc}") from exc
    if prob.status not in ("optimal", "optimal_inaccurate"):
        raise SolverFailedError(f"Clarabel failed on the learned-mass L-OpInf problem: status {prob.status}")
    values = {name: (0.5 * (v.value + v.value.T) if name != "B" else v.value)
              for name, v in variables.items()}
    Z12 = None if schur.dual_value is None else np.asarray(schur.dual_value)[:r, r:]
    return np.hstack([values[name] for name, _, _ in data.blocks]), prob.status, Z12


def _misfit(theta, data: _MassData):
    """f in the scaled unknowns: ||M^-1/2 Theta L||^2."""
    R = theta @ data.L
    return float(np.sum(R * scipy.linalg.solve(theta[:, :data.r], R, assume_a="pos")))


def _best_candidate(theta_sdp, data: _MassData, eps, ridge):
    """Candidates, judged by f itself: Clarabel's point, K, C, B re-solved exactly for its M,
    and the M = I fit (feasible: tr(W) = 1) - exact when the data's own mass is I, where the
    interior point method stops at ~1e-6 relative. Returns (Theta, label, inner certificate)."""
    best, how, inner_cert = theta_sdp, "clarabel", None
    for candidate_M, label in ((theta_sdp[:, :data.r], "clarabel+exact-inner"),
                               (np.eye(data.r), "identity")):
        polished = _polish(candidate_M, data.Qh, data.dQh, data.ddQh, data.U, data.dQh is not None,
                           eps, ridge, data.blocks)
        if polished is not None and _misfit(polished[0], data) < _misfit(best, data):
            best, how, inner_cert = polished[0], label, polished[1]
    return best, how, inner_cert


def _certified_bound(Z12, data: _MassData, eps):
    """(lower bound, dual infeasibility) from the SDP's dual; (-inf, inf) without one."""
    bound, dual_infeasibility = -np.inf, np.inf
    if Z12 is not None:  # cvxpy's sign convention for the dual: take the better of +-Y
        for Y in (-Z12 * _norm(data.L), Z12 * _norm(data.L)):
            b, infeasible = _dual_bound(Y, data.L, data.W, data.r, data.layout, data.floors(eps))
            if infeasible < 1e-6 and b > bound:
                bound, dual_infeasibility = b, infeasible
    return bound, dual_infeasibility


def _operators(theta, data: _MassData, eps):
    """(M, K, C, B) in user units from the scaled unknowns, floored exactly."""
    from .inference import _floor

    ops, start = {}, 0
    for name, rows, k in data.blocks:
        ops[name] = theta[:, start:start + rows.shape[0]] * (k if name != "M" else 1.0)
        start += rows.shape[0]
    return (_floor(ops["M"], 0.0), _floor(ops["K"], eps),
            _floor(ops["C"], eps) if "C" in ops else None, -ops["B"] if "B" in ops else None)


def _fit_once(Qh, dQh, ddQh, U, *, damping, eps, ridge, strict):
    """One Clarabel solve of the learned-mass problem in the given coordinates, K, C, B
    re-solved exactly for its M, the M = I candidate, and the certificate of the best."""
    from .inference import MechanicalOperators

    t0 = time.perf_counter()
    data = _mass_data(Qh, dQh, ddQh, U, damping, ridge, strict)
    theta_sdp, status, Z12 = _solve_sdp(data, eps)
    sdp_seconds = time.perf_counter() - t0
    best, how, inner_cert = _best_candidate(theta_sdp, data, eps, ridge)
    f_best = _misfit(best, data)
    bound, dual_infeasibility = _certified_bound(Z12, data, eps)
    M, K, C, B = _operators(best, data, eps)
    R = M @ data.ddQh + K @ data.Qh + (C @ data.dQh if C is not None else 0.0) \
        - (B @ data.U if B is not None else 0.0)
    cert = {
        "solver": how, "status": "optimal" if status == "optimal" else "inaccurate",
        "clarabel_status": status, "mass": "learned", "objective": f_best,
        # certified: f - (a lower bound) relative to f0 = ||L_M||^2, the misfit of Mh = I with
        # no forces (the data's own scale; f itself -> 0 on exact data)
        "gap": (f_best - bound) / max(float(np.sum(data.L[:data.r] ** 2)), 1e-300),
        "dual_infeasibility": dual_infeasibility,
        "mass_stationarity": _mass_stationarity(best, data.L, data.W, data.r),
        "relative_residual": float(np.sqrt(np.sum(R * scipy.linalg.solve(M, R, assume_a="pos"))
                                           / max(np.sum(data.ddQh * (M @ data.ddQh)), 1e-300))),
        "normalisation": float(np.sum(M * data.W)), "symmetry_error": 0.0,
        "data_rank": data.rank, "data_rows": data.L.shape[0], "data_condition": data.cond,
        "seconds": time.perf_counter() - t0, "sdp_seconds": sdp_seconds, "eps": eps,
    }
    if inner_cert is not None:
        cert["inner_status"] = inner_cert.get("status")
    if status != "optimal":
        warnings.warn(f"learned-mass fit: Clarabel returned {status} ({how}); check the "
                      "model's held-back error", SolverWarning, stacklevel=3)
    return MechanicalOperators(K, C, B, cert, M=M)


def _polish(M, Qh, dQh, ddQh, U, damping, eps, ridge, blocks):
    """K, C, B re-solved exactly for fixed M: the M = I L-OpInf in q~ = S q, S = M^{1/2}
    (f = ||S D2 + C~ S D1 + K~ S Qbar - B~ Ubar||^2 with K = S K~ S, C = S C~ S, B = S B~).
    Returns (Theta in the scaled unknowns, the inner certificate), or None if it failed."""
    from .inference import infer_mechanical

    w, Q = np.linalg.eigh(M)
    if w.min() <= 0:
        return None
    S = from_eig(np.sqrt(w), Q)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            inner = infer_mechanical(S @ Qh, None if dQh is None else S @ dQh, S @ ddQh, U,
                                     damping=damping, eps=eps / w.min(), ridge=ridge)
        except Exception:  # the SDP answer stands; the certificate says it was not polished
            return None
    parts = {"M": M, "K": S @ inner.K @ S}
    if damping:
        parts["C"] = S @ inner.C @ S
    if inner.B is not None:
        parts["B"] = -(S @ inner.B)
    theta = np.hstack([parts[name] / k if name != "M" else parts[name] for name, _, k in blocks])
    return theta, inner.certificate


def _dual_bound(Y, L, W, r, layout, floors):
    """A lower bound on min f over the feasible set, from the point ``theta``: the certificate.

    For M > 0 and any Y, tr(R^T M^-1 R) >= 2 <Y, R> - <Y Y^T, M> (equality at Y = M^-1 R),
    and R = Theta L is linear, so with G = Y L^T = [G_M, G_K, G_C, G_B]

        f >= min over the feasible set of <2 G_M - Y Y^T, M> + 2 <G_K, K> + 2 <G_C, C> + 2 <G_B, B>
          = lambda_min(A, W) (1 - mu tr W) + mu tr A + 2 eps_K tr G_K + 2 eps_C tr G_C,

    A = sym(2 G_M - Y Y^T), provided G_B = 0 and sym G_K, sym G_C >= 0 (else the minimum is
    -inf). Y: the SDP's dual (-Z12 of its Schur-complement constraint; Y = M^-1 R at the
    optimum - from a primal point that is only near-optimal M^-1 amplifies the error where M
    is small, measured useless), its rows projected so that G_B = 0 exactly; the most
    negative eigenvalue of sym G_K, sym G_C left (relative to their norm) is returned as the
    dual infeasibility (the bound holds when it is at rounding level).
    Returns (bound, dual infeasibility)."""
    starts, start = {}, 0
    for name, width in layout:
        starts[name] = slice(start, start + width)
        start += width
    # Repair Y to dual feasibility: the least-norm change dY with (Y + dY) L_B^T = 0 and
    # sym((Y + dY) L_X^T) = its PSD part for X = K, C (the interior point method leaves
    # -1e-8-level eigenvalues where a floor is active). G_M moves too; the bound accounts for it.
    G = Y @ L.T
    rows, targets = [], []
    for name in ("K", "C", "B"):
        if name not in starts:
            continue
        Gs = G[:, starts[name]]
        if name == "B":
            targets.append(-Gs)
        else:
            Gsym = 0.5 * (Gs + Gs.T)
            targets.append(psd_project(Gsym, 0.0)[0] - Gsym)
        rows.append(L[starts[name]])
    if rows:
        LS = np.vstack(rows)
        Y = Y + scipy.linalg.lstsq(LS @ LS.T, np.hstack(targets).T)[0].T @ LS
    G = Y @ L.T
    bound, infeasible = 0.0, 0.0
    for name in ("K", "C"):
        if name in starts:
            Gs = G[:, starts[name]]
            Gs = 0.5 * (Gs + Gs.T)
            w_min = float(np.linalg.eigvalsh(Gs)[0])
            infeasible = max(infeasible, -w_min / max(np.linalg.norm(Gs), 1e-300))
            bound += 2 * floors[name] * float(np.trace(Gs))
    if "B" in starts:
        GB = G[:, starts["B"]]
        infeasible = max(infeasible, float(np.linalg.norm(GB)) / max(np.linalg.norm(G), 1e-300))
    A = 2 * G[:, :r] - Y @ Y.T
    A = 0.5 * (A + A.T)
    lam = float(scipy.linalg.eigvalsh(A, W, subset_by_index=[0, 0])[0])
    bound += lam * (1 - MASS_FLOOR * np.trace(W)) + MASS_FLOOR * float(np.trace(A))
    return float(bound), float(max(infeasible, 0.0))


def _mass_stationarity(theta, L, W, r):
    """First-order optimality of the learned mass, relative and scale-free: the largest
    decrease of f, to first order, over changes of M by at most 100 % in its own metric
    (||M^-1/2 dM M^-1/2||_F <= 1) that keep tr(M W) = 1, divided by f. With S = M^{1/2},
    G~ = S G S, W~ = S W S (dM = S X S keeps tr(M W) = 1 iff <X, W~> = 0) and nu = <G~, W~> / <W~, W~>: ||G~ - nu W~||_F / f. It is 0
    at an optimum with M above its floor; G = sym(2 M^-1 R L_2^T) - M^-1 R R^T M^-1 is the
    gradient of phi(M) = min_{K,C,B} f once K, C, B are optimal for M (Danskin)."""
    M = theta[:, :r]
    R = theta @ L
    MiR = scipy.linalg.solve(M, R, assume_a="pos")
    A = MiR @ L[:r].T
    G = A + A.T - MiR @ MiR.T
    w, Q = np.linalg.eigh(0.5 * (M + M.T))
    S = from_eig(np.sqrt(w), Q)
    Gt, Wt = S @ (0.5 * (G + G.T)) @ S, S @ W @ S
    nu = float(np.sum(Gt * Wt) / np.sum(Wt * Wt))
    f = float(np.sum(R * MiR))
    return float(np.linalg.norm(Gt - nu * Wt) / max(f, 1e-300))
