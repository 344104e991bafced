"""Which integrator made the snapshots: the scheme family and its parameters, from the data.

Every scheme of :mod:`dolfinx_lopinf.core.schemes` gives a relation M Qm + C Qc + K Qk = B Uf
that the snapshots of that scheme obey exactly. With M = I and C, K, B free (no symmetry,
no definiteness), the relation of the true scheme still holds exactly on Galerkin-reduced
data (multiply by M^{-1}), so

    rho(theta) = min_{C, K, B} ||Qm + C Qc + K Qk - B Uf||_F / ||Qm||_F

(one linear least squares per parameter vector theta = (alpha_m, alpha_f, beta, gamma))
drops to the closure level (rounding for exact data, the POD truncation for FOM data) at the
scheme that made the data, and is larger elsewhere. :func:`identify` evaluates rho on the
standard members (Newmark's average / linear acceleration, Fox-Goodwin, central
differences, the midpoint rule, HHT-alpha and generalised-alpha over their usual
parameters), then refines the best member's family by Gauss-Newton on the residual vector
(``scipy.optimize.least_squares``, bounded to the stable range), with the Jacobian of
variable projection (the free operators eliminated; :meth:`Residual.projected`): one
evaluation of the relation gives the residual and its derivative in every parameter.

What the data can tell. A free response pins the family but not always every parameter:
Newmark's three-point relation spans every three-point recurrence, so beta and gamma are
seen only through the loads (the weights P(E) on f); generalised-alpha with
alpha_m = alpha_f is Newmark times a common factor. A refinement is therefore kept only when
it lowers rho by :data:`CLEAR_GAIN` or more; otherwise the standard member stays (it
predicts the same free response). The choice and the residuals are returned for the report.
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.linalg
import scipy.optimize

from . import schemes as S
from ..errors import InputError
from .holdout import prediction_error, split
from ._blas import serial_blas
from .gram import MechanicalOperators

#: a refinement (or a less standard member) must lower the relative residual this much
CLEAR_GAIN = 2.0
#: members within this factor of the best relation residual are also judged by prediction
SHORTLIST = 30.0
#: held-back prediction errors within this factor of the best are ties (the list's order
#: decides: two members the data cannot tell apart - the midpoint rule and average
#: acceleration on linearly varying loads - differ by up to 5x through the free fit's noise),
#: and errors below PREDICTION_FLOOR are ties at that floor
MARGIN = 3.0
PREDICTION_FLOOR = 1e-9
#: a held-back prediction whose relative error reaches this (predicting zero does as well) has
#: blown up: it counts as no prediction (inf), whatever its size (1e14 or 1e15 is rounding)
PREDICTION_USELESS = 1.0
#: ... but where the residual's choice blows up and another member's free fit predicts the
#: held-back samples to this, the predictions judge: in truncated coordinates the closure of
#: the dropped modes lowered the residual of 4-level generalised-alpha members below the
#: loop's own 3-level Newmark relation (1.8e-8 against 1.2e-7; exact recordings of the
#: package's NewmarkIntegrator), whose free fits blew up where Newmark's predicted to 6.5e-10
#: - the residual's choice then predicted an unseen load 15x worse at r = 8
PREDICTS_WELL = 1e-6
#: a refinement (parameters off the usual grid) replaces the standard member the prediction
#: keeps only when it predicts this much better. Loads that vary linearly between jumps do
#: not show where a scheme samples them (at t_n+1 or between steps): on such data a
#: generalised-alpha refinement near alpha_m = alpha_f = 1/2 predicted an average-acceleration
#: loop's held-back end 2.5x better, and an unseen smooth load 250x worse
REFINEMENT_GAIN = 10.0
#: relative residuals below this are ties: the relation holds to the data's rounding (or
#: to 8th-order differences on a fine grid), so the order of the members decides, not the
#: last bits (a different BLAS must give the same verdict)
RESIDUAL_FLOOR = 1e-10
#: Gauss-Newton iterations per refinement (it converges in a few where the data pin the
#: parameters; where they do not, more iterations buy nothing)
MAX_ITERATIONS = 20
#: a refined scheme whose residual's Jacobian (columns: the parameters) has a singular-value
#: ratio below this is reported as not determined by the data
UNDETERMINED = 1e-3


def standard_members() -> list:
    """The grid: the schemes users run, with their usual parameters."""
    members = [S.Newmark(), S.Midpoint(), S.Newmark(1 / 6, 0.5), S.Newmark(1 / 12, 0.5),
               S.CentralDifference()]
    members += [S.HHT(a) for a in (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 1 / 3)]
    members += [S.GeneralizedAlpha(rho_inf=rho) for rho in (0.0, 0.2, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)]
    members.append(S.GeneralizedAlpha(0.2, 0.4))  # the COMET elastodynamics tutorial
    return members


class _Compressed:
    """One trajectory's data, stacked as every shifted copy a relation can combine and
    compressed by one QR: S = [u_k; u_{k+1}; u_{k+2}; u_{k+3}; f_{k+s_lo} .. f_{k+s_hi}]
    (columns k), S^T = Q R. Every generalised-alpha / midpoint relation is A S for a small A
    that depends on the scheme, so its free least squares has the residual of
    R A_y^T - R A_d^T X: the same norm, at a cost independent of the number of samples.
    Inputs must lie on a uniform grid of the samples' spacing (any offset); else ValueError."""

    def __init__(self, Qh, times, U, ti):
        r, K = Qh.shape
        dt = float(np.mean(np.diff(times)))
        self.r, self.dt, self.m, self.c = r, dt, 0 if U is None else U.shape[0], 0.0
        self.R_bent = None
        blocks = [Qh[:, j:K - 3 + j] for j in range(4)]
        self.shifts = []
        cols = K - 3
        if U is not None:
            ti = times if ti is None else np.asarray(ti, dtype=float)
            a, b = _uniform_run(ti, dt)
            U, ti = U[:, a:b], ti[a:b]
            self.c = (ti[0] - times[0]) / dt  # offset of the load grid, in steps
            lo_s = int(np.floor(0.5 - self.c - 1e-9))
            hi_s = int(np.floor(3.0 - self.c + 1e-9)) + 1
            k0 = max(0, -lo_s)
            k1 = min(K - 3, U.shape[1] - hi_s)
            if k1 - k0 < 8:
                raise ValueError("too few columns")
            self.shifts = list(range(lo_s, hi_s + 1))
            blocks = [B[:, k0:k1] for B in blocks]
            blocks += [U[:, k0 + s_:k1 + s_] for s_ in self.shifts]
            # a scheme that interpolates its loads between samples cannot use the columns
            # next to a bend or jump of the load (the samples do not give the load the loop
            # applied there, S.kinks). Every scheme is judged on the same columns: a jump
            # excites the truncated modes most, and leaving its columns out for some
            # schemes only would favour them (an average-acceleration Newmark loop was
            # taken for the midpoint rule, 250x worse on an unseen smooth load)
            bent = S.kinks(U)
            keep = ~np.any([bent[k0 + s_:k1 + s_] for s_ in self.shifts], axis=0)
            if keep.sum() < 8:
                raise ValueError("too few columns")
            if not keep.all():
                self.R_bent = _qr_r(np.vstack(blocks)[:, keep])
            cols = k1 - k0
        stacked = np.vstack(blocks)
        self.R = _qr_r(stacked)
        self.cols = cols

    def weights(self, scheme) -> np.ndarray:
        """The relation's coefficients as one vector: cm, cc, ck on the four shifted copies,
        then the load weights on the shifted input copies (linear interpolation of the loads'
        positions on their grid). The compressed relation is linear in them (:meth:`combine`)."""
        if isinstance(scheme, S.Midpoint):
            # padded in front, like Newmark's (its four-point form leads with zeros): the
            # two relations are the same for linear data, and on the same columns their free
            # fits are the same too, so a tie is a tie (decided by the members' order)
            cm, cc, ck, cu, tau = scheme.coefficients(self.dt)
            cm, cc, ck = (np.insert(c, 0, 0.0) for c in (cm, cc, ck))
            tau += 1.0
        elif isinstance(scheme, S.GeneralizedAlpha):  # untrimmed: four points, loads at 1 - af
            cm, cc, ck, cu, tau = S.GeneralizedAlpha.coefficients(scheme, self.dt)
        else:
            raise ValueError("no compressed form")
        loads = np.zeros(len(self.shifts))
        if self.m:
            for j, w in enumerate(cu):
                p = j + tau - self.c
                i = int(np.floor(p + 1e-9))
                frac = p - i if p - i > 1e-9 else 0.0
                loads[i - self.shifts[0]] += w * (1 - frac)
                if frac:
                    loads[i + 1 - self.shifts[0]] += w * frac
        return np.concatenate([cm, cc, ck, loads])

    def combine(self, w):
        """(Yt, Ct, Kt, Ft) of the relation with coefficient vector ``w`` (:meth:`weights`;
        a stack (p, len) of them gives a stack of each)."""
        r = self.r
        R = self.R if self.R_bent is None else self.R_bent  # the common columns (above)
        w = np.asarray(w)
        # the three combinations of the four shifted copies at once: (..., 3, rows, r)
        YCK = np.einsum("ijk,...lj->...lik", R[:, :4 * r].reshape(len(R), 4, r),
                        w[..., :12].reshape(w.shape[:-1] + (3, 4)))
        Ft = None
        if self.m:
            nw, m = len(self.shifts), self.m
            Ft = np.einsum("iqk,...q->...ik", R[:, 4 * r:4 * r + nw * m].reshape(len(R), nw, m),
                           w[..., 12:])
        return YCK[..., 0, :, :], YCK[..., 1, :, :], YCK[..., 2, :, :], Ft

    def pieces(self, scheme):
        """(Yt, Ct, Kt, Ft) of ``scheme``'s relation, compressed."""
        return self.combine(self.weights(scheme))


def _qr_r(stacked):
    """R of the thin QR of stacked^T (the compressed data)."""
    return scipy.linalg.qr(stacked.T, mode="r", check_finite=False)[0][:min(stacked.shape)]


def _uniform_run(ti, dt):
    """[a, b): the longest run of input times spaced dt (to 1e-9 dt); ValueError unless it
    leaves out at most two samples at the ends (irregular inputs: the direct residual)."""
    ok = np.abs(np.diff(ti) - dt) <= 1e-9 * dt + 4 * np.finfo(float).eps * np.max(np.abs(ti))
    best, start = (0, 0), 0
    for i, good in enumerate(np.append(ok, False)):
        if not good:
            if i + 1 - start > best[1] - best[0]:
                best = (start, i + 1)
            start = i + 1
    if len(ti) - (best[1] - best[0]) > 2:
        raise ValueError("irregular input times")
    return best


class Residual:
    """rho(scheme) on one or several trajectories ``pieces`` = [(Qh, times, U, input_times,
    Vh, Ah), ...] (Vh, Ah None unless recorded: then the (u, v, a) relation is used).

    Generalised-alpha and midpoint relations on u alone use the compressed data
    (:class:`_Compressed`); the others (finite differences, the (u, v, a) relation, inputs
    on an irregular grid) form the relation's arrays."""

    def __init__(self, pieces):
        self.pieces = pieces
        self.forced = pieces[0][2] is not None
        self.states = all(p[4] is not None and p[5] is not None for p in pieces)
        self.evaluations = 0
        self._compressed = None
        if not self.states:
            try:
                self._compressed = [_Compressed(Qh, t, U, ti) for Qh, t, U, ti, _, _ in pieces]
            except ValueError:
                self._compressed = None

    def arrays(self, scheme):
        parts = []
        for Qh, times, U, ti, Vh, Ah in self.pieces:
            if self.states and isinstance(scheme, S.GeneralizedAlpha):
                parts.append(scheme.state_relation(Qh, Vh, Ah, times, U, ti, missing="zero"))
            else:
                parts.append(scheme.relation(Qh, times, U, ti, missing="zero"))
        Qk, Qc, Qm = (np.hstack([p[i] for p in parts]) for i in range(3))
        Uf = None if parts[0][3] is None else np.hstack([p[3] for p in parts])
        return Qk, Qc, Qm, Uf

    def vector(self, scheme) -> np.ndarray:
        """The least-squares residual of the free fit (a vector whose length depends only on
        the kind of relation), divided by ||Qm||_F."""
        self.evaluations += 1
        Y, D = self._system(scheme)
        return _relative(_project_off(Y, D)[3], Y)

    def compressed(self, scheme) -> bool:
        """Whether ``scheme``'s relation is evaluated on the compressed data."""
        return self._compressed is not None and isinstance(scheme, (S.GeneralizedAlpha, S.Midpoint))

    def _combined(self, weights):
        """(Y, D) of the compressed relation with coefficient vectors ``weights`` (one per
        trajectory, :meth:`_Compressed.weights`)."""
        parts = [c.combine(w) for c, w in zip(self._compressed, weights)]
        Y = np.concatenate([p[0] for p in parts], axis=-2)
        D = np.concatenate([np.concatenate([p[i] for p in parts], axis=-2) for i in (1, 2)]
                           + ([np.concatenate([p[3] for p in parts], axis=-2)] if self.forced else []),
                           axis=-1)
        return Y, D

    def _system(self, scheme):
        """(Y, D): the free least squares min ||Y - D Z||, Z = [-C^T; -K^T; B^T]."""
        if self.compressed(scheme):
            Y, D = self._combined([c.weights(scheme) for c in self._compressed])
        else:
            Qk, Qc, Qm, Uf = self.arrays(scheme)
            Y = Qm.T
            D = np.vstack([Qc, Qk] + ([] if Uf is None else [Uf])).T
        return Y, D

    def free_operators(self, scheme) -> MechanicalOperators:
        """The free fit (M = I; C, K, B unconstrained) of ``scheme``'s relation."""
        Y, D = self._system(scheme)
        scale = np.linalg.norm(D, axis=0)
        scale[scale == 0] = 1.0
        Z = scipy.linalg.lstsq(D / scale, -Y, check_finite=False)[0] / scale[:, None]
        r = Y.shape[1]
        B = Z[2 * r:].T if self.forced else None
        return MechanicalOperators(K=Z[r:2 * r].T, C=Z[:r].T, B=None if B is None else -B)

    def __call__(self, scheme) -> float:
        return float(np.linalg.norm(self.vector(scheme)))

    def projected(self, build, lo, hi):
        """(fun, jac) of x -> :meth:`vector` (build(x)) for ``scipy.optimize.least_squares``
        on compressed data, with the Jacobian of variable projection (Golub and Pereyra):
        for E = P_D^perp Y (Z = D^+ Y the free operators) and a parameter x_i,

            dE = P_D^perp (dY - dD Z) - (D^+)^T dD^T E,

        where dY, dD are the relation at the coefficients' derivative (the relation is
        linear in its coefficients; those are differentiated by a step of 1e-7 in x_i,
        inside [lo, hi]). One evaluation gives the residual and its Jacobian."""
        cache = {}

        def weights(x):
            return [c.weights(build(x)) for c in self._compressed]

        def evaluate(x):
            key = np.asarray(x, dtype=float).tobytes()
            if key not in cache:
                cache.clear()
                self.evaluations += 1
                w = weights(x)
                Y, D = self._combined(w)
                cache[key] = (x, w, Y) + _project_off(Y, D)
            return cache[key]

        def fun(x):
            _, _, Y, _, _, _, E = evaluate(x)
            return _relative(E, Y)

        def jac(x):
            x, w, Y, scale, Qd, Rd, E = evaluate(x)
            ny = max(np.linalg.norm(Y), np.finfo(float).tiny)
            Zs = scipy.linalg.solve_triangular(Rd, Qd.T @ Y, check_finite=False)
            dw = [[] for _ in w]  # per trajectory: the coefficients' derivative in each x_i
            for i in range(len(x)):
                h = 1e-7 * max(1.0, abs(x[i]))
                if x[i] + h > hi[i]:
                    h = -h
                xi = np.array(x, dtype=float)
                xi[i] += h
                for d, a, b in zip(dw, weights(xi), w):
                    d.append((a - b) / h)
            dY, dD = self._combined([np.array(d) for d in dw])  # (p, rows, r), (p, rows, nd)
            dDs = dD / scale
            G = dY - dDs @ Zs
            T = scipy.linalg.solve_triangular(Rd, (dDs.transpose(0, 2, 1) @ E).transpose(1, 0, 2)
                                              .reshape(Rd.shape[0], -1), trans="T",
                                              check_finite=False)
            dE = G - Qd @ (Qd.T @ G) - (Qd @ T).reshape(len(Qd), len(x), -1).transpose(1, 0, 2)
            J = dE.reshape(len(x), -1).T / ny
            J -= np.outer(E.ravel(), np.einsum("ij,pij->p", Y, dY) / ny**3)
            return J

        return fun, jac


def _project_off(Y, D):
    """(scale, Qd, Rd, E): D's column norms (zero columns count 1), the thin QR of D with
    unit columns, and E = Y - Qd Qd^T Y, the part of Y the free fit cannot reach."""
    scale = np.linalg.norm(D, axis=0)
    scale[scale == 0] = 1.0
    Qd, Rd = scipy.linalg.qr(D / scale, mode="economic", check_finite=False)
    return scale, Qd, Rd, Y - Qd @ (Qd.T @ Y)


def _relative(E, Y):
    """The residual E as a vector, relative to ||Y||_F."""
    return E.ravel() / max(np.linalg.norm(Y), np.finfo(float).tiny)


def _fit(residual: Residual, build, x0, lo, hi):
    """Gauss-Newton (bounded least squares) on rho over the parameters x of ``build(x)``:
    the variable-projection Jacobian on compressed data, forward differences otherwise;
    (scheme, rho, sensitivity) or None."""
    x0 = np.clip(np.asarray(x0, dtype=float), np.add(lo, 1e-9), np.subtract(hi, 1e-9))
    try:
        if residual.compressed(build(x0)):
            fun, jac = residual.projected(build, lo, hi)
        else:
            fun, jac = (lambda x: residual.vector(build(x))), "2-point"
        sol = scipy.optimize.least_squares(fun, x0, bounds=(lo, hi), jac=jac, diff_step=1e-7,
                                           xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=MAX_ITERATIONS)
        best = build(sol.x)
        sv = np.linalg.svd(sol.jac, compute_uv=False) if sol.jac.size else np.ones(1)
        return best, residual(best), float(sv[-1] / sv[0]) if sv[0] > 0 else 0.0
    except (ValueError, np.linalg.LinAlgError):  # a parameter vector outside the family
        return None


def _refinements(residual: Residual, rho: dict):
    """Refined candidates, from the fewest parameters to the most: [(n_params, scheme, rho)].

    HHT's alpha and generalised-alpha's rho_inf (one parameter each) from their best grid
    member; then (alpha_m, alpha_f) with the optimal beta, gamma; with loads also Newmark's
    (beta, gamma) and all four generalised-alpha parameters (only the loads show them, and
    only through u: on recorded (u, v, a) the relation has no beta, gamma)."""
    def best(kind):
        pool = [m for m in rho if type(m) is kind]
        return min(pool, key=rho.get) if pool else None

    out = []
    floor = max(min(rho.values()), RESIDUAL_FLOOR)

    def promising(m):  # a family whose best member is far off cannot win: not refined
        return m is not None and rho[m] <= SHORTLIST * floor

    hht, ga = best(S.HHT), best(S.GeneralizedAlpha)
    hht = hht if promising(hht) else None
    if hht is not None:
        out.append((1, _fit(residual, lambda x: S.HHT(x[0]), [hht.alpha], [0.0], [1 / 3])))
    if ga is not None:
        rho0 = min(max((1 + ga.alpha_m) / (2 - ga.alpha_m), 0.0), 1.0)  # inverts alpha_m(rho)
        out.append((1, _fit(residual, lambda x: S.GeneralizedAlpha(rho_inf=x[0]), [rho0],
                            [0.0], [1.0])))
    start = min(rho, key=rho.get)
    am, af = (start.alpha_m, start.alpha_f) if isinstance(start, S.GeneralizedAlpha) else (0.1, 0.2)
    # (alpha_f, d = alpha_f - alpha_m >= 0): the optimal gamma = 1/2 + d stays >= 1/2
    two = _fit(residual, lambda x: S.GeneralizedAlpha(x[0] - x[1], x[0]), [af, af - am],
               [0.0, 0.0], [0.5, 1.0])
    out.append((2, two))
    if residual.forced and not residual.states and promising(best(S.Newmark)):
        nm = best(S.Newmark)
        out.append((2, _fit(residual, lambda x: S.Newmark(x[0], x[1]), [nm.beta, nm.gamma],
                            [0.0, 0.5], [1.0, 1.5])))
    if residual.forced and not residual.states:  # on recorded (u, v, a) the relation holds
        # alpha_m and alpha_f alone (GeneralizedAlpha.state_relation): beta, gamma would be
        # dead parameters, and the fit the two-parameter one at twice its evaluations
        g = two[0] if two is not None else (ga or S.GeneralizedAlpha(rho_inf=0.8))
        out.append((4, _fit(residual, lambda x: S.GeneralizedAlpha(*x),
                            [g.alpha_m, g.alpha_f, g.beta, g.gamma], [-1.0, 0.0, 0.0, 0.5],
                            [0.5, 0.5, 1.5, 1.5])))
    return [(n,) + c for n, c in out if c is not None]


@serial_blas
def identify(pieces, *, members=None, refine: bool = True, holdout: float = 0.25,
             check_r: int | None = None):
    """The scheme whose relation the data obey, and whose recurrence predicts them, best
    (module docstring).

    Two looks at the data. The relation residual rho on all of it ranks the members and
    drives the refinement; where the data resolve the scheme (synthetic data, enough POD
    coordinates) it alone decides. Where the truncated modes' closure error is of the size
    of the differences between schemes, free operators can absorb it better for a wrong
    scheme; so the members within SHORTLIST of the best rho, and the refinements, are also
    fitted (free operators) on the first ``1 - holdout`` of each trajectory and predict the
    rest with their recurrence. The first member in order whose prediction error is within
    MARGIN of the best is the prediction's choice (a refinement replaces it when it predicts
    REFINEMENT_GAIN better); it overrides the residual's choice only where that predicts worse.

    Args:
        pieces: [(Qh (r, K), times (K,), U (m, K_u) or None, input_times or None,
            Vh or None, Ah or None), ...], one per trajectory.
        members: the schemes to compare first (default :func:`standard_members`).
        refine: refine the best members' parameters.
        holdout: the fraction held back for the prediction check (0: residuals only).
        check_r: the prediction check's free fits use the leading ``check_r`` coordinates
            (default all): fewer unknowns than the residual's fit, which sees every sample.

    Returns:
        ``(scheme, report)``; report: ``residuals`` (spec -> rho of every member),
        ``refined`` (spec -> rho), ``predictions`` (spec -> held-back error), ``chosen``,
        ``why``, ``evaluations``, ``loads`` (:func:`_load_kind`).
    """
    residual = Residual(pieces)
    members = standard_members() if members is None else list(members)
    rho = {}
    for m in members:
        try:
            rho[m] = residual(m)
        except (ValueError, np.linalg.LinAlgError):
            rho[m] = float("inf")
    best_rho = max(min(rho.values()), RESIDUAL_FLOOR)
    refined = _refinements(residual, rho) if refine else []
    report = {"residuals": {m.spec: v for m, v in rho.items()},
              "refined": {c.spec: v for _, c, v, _ in refined}}
    loads = _load_kind(pieces)
    chosen, why = _by_residual(members, rho, refined, report, loads)
    pieces_check = pieces if check_r is None else leading(pieces, check_r)
    predictions = _predictions(pieces_check, members, rho, best_rho, refined, holdout, loads)
    if predictions and not np.isfinite(predictions.get(chosen, np.inf)) \
            and not min(predictions.values()) <= PREDICTS_WELL:
        # the free fit of the residual's choice does not even predict, nor does any other
        # well: the data leave the free operators undetermined (e.g. repeated frequencies),
        # so prediction cannot judge
        report["predictions"] = {c.spec: e for c, e in predictions.items()}
        why += "; the free operators' predictions are not informative (the residual's choice blows up)"
        predictions = {}
    if predictions:
        report["predictions"] = {c.spec: e for c, e in predictions.items()}
        by_prediction = _by_prediction(members, refined, predictions, report, loads)
        e_res = predictions.get(chosen, np.inf)
        if by_prediction is not None and by_prediction[0] != chosen \
                and predictions[by_prediction[0]] < e_res:
            # the residual's choice predicts the held-back samples worse than the simplest
            # candidate the prediction check keeps: the truncated modes' closure error, not
            # the scheme, decided the residual (module docstring)
            chosen, why = by_prediction[0], by_prediction[1] + f"; over {why}"
        else:
            why += (f"; it also predicts the held-back samples best ({e_res:.3g} with free "
                    "operators)" if by_prediction is not None else "")
    report.update(chosen=chosen.spec, why=why, evaluations=residual.evaluations, loads=loads,
                  residual=residual(chosen))
    return chosen, report


#: loads whose second differences, away from their bends and jumps, stay below this fraction
#: of their size vary linearly between bends: they show two moments of a scheme's load weights
LINEAR_LOADS = 1e-8


def _load_kind(pieces) -> str:
    """"none" (free responses), "linear" (loads linear between bends and jumps) or "general"."""
    loads = [p[2] for p in pieces if p[2] is not None]
    if not loads:
        return "none"
    for U in loads:
        U = np.atleast_2d(np.asarray(U, dtype=float))
        if U.shape[1] < 3:
            return "general"
        d2 = np.abs(U[:, 2:] - 2 * U[:, 1:-1] + U[:, :-2])
        bent = S.kinks(U)
        smooth = ~(bent[:-2] | bent[1:-1] | bent[2:])
        if np.any(d2[:, smooth] > LINEAR_LOADS * max(np.abs(U).max(), np.finfo(float).tiny)):
            return "general"
    return "linear"


@functools.lru_cache(maxsize=4096)
def _signature(scheme, loads: str):
    """What of ``scheme``'s relation the data can see, or None (no closed form here).

    With M = I and C, K, B free, two relations hold on the same data when the row spaces of
    their coefficient vectors (cm; cc; ck), aligned on four points, coincide (one is an
    invertible matrix times the other: Newmark(beta, 1/2) for every beta, the midpoint rule
    and central differences on free responses) and their loads agree as far as the data
    show them: not at all (free responses), through the mean position of the load weights
    (loads linear between bends), or exactly."""
    if isinstance(scheme, S.Midpoint):
        cm, cc, ck, cu, tau = scheme.coefficients(1.0)
        cm, cc, ck = (np.insert(c, 0, 0.0) for c in (cm, cc, ck))
        tau += 1.0
    elif isinstance(scheme, S.GeneralizedAlpha):
        cm, cc, ck, cu, tau = S.GeneralizedAlpha.coefficients(scheme, 1.0)
    else:
        return None
    u, sv, _ = np.linalg.svd(np.vstack([cm, cc, ck]).T)
    rank = int(np.sum(sv > 1e-10 * sv[0]))
    span = u[:, :rank] @ u[:, :rank].T
    positions = tau + np.arange(len(cu))
    if loads == "none":
        load = np.zeros(0)
    elif loads == "linear":
        load = np.array([cu @ positions / cu.sum()])
    else:  # the weights on the load's grid (positions are multiples of 1/2 for the grid here)
        grid = np.zeros(16)
        for p_, w in zip(positions, cu):
            i, frac = int(np.floor(p_ + 1e-9)), p_ - np.floor(p_ + 1e-9)
            grid[i] += w * (1 - frac)
            grid[i + 1] += w * frac if frac > 1e-9 else 0.0
        load = grid / cu.sum()
    return span, load


@functools.lru_cache(maxsize=65536)
def _equivalent(a, b, loads: str) -> bool:
    """True when the data cannot tell relations a and b apart (:func:`_signature`)."""
    if a == b:
        return True
    sa, sb = _signature(a, loads), _signature(b, loads)
    if sa is None or sb is None or sa[0].shape != sb[0].shape:
        return False
    return bool(np.abs(sa[0] - sb[0]).max() < 1e-8 and np.all(np.abs(sa[1] - sb[1]) < 1e-8))


def _class_best(scheme, values: dict, loads: str) -> float:
    """The lowest of ``values`` over the schemes equivalent to ``scheme`` on these data."""
    return min(v for m, v in values.items() if _equivalent(m, scheme, loads))


def _by_residual(members, rho, refined, report, loads="general"):
    """The first (most standard) member within CLEAR_GAIN of the best residual - a near tie
    is decided by the order of the list, never by the last bits - or a refinement that is
    CLEAR_GAIN better than it. Members the data cannot tell apart (:func:`_equivalent`)
    count as one, at the best residual of their class."""
    best_rho = max(min(rho.values()), RESIDUAL_FLOOR)
    level = {m: _class_best(m, rho, loads) for m in members}
    chosen = next(m for m in members if level[m] <= CLEAR_GAIN * best_rho)
    why = (f"relation residual {rho[chosen]:.3g} ({chosen.spec}); best of {len(members)} "
           f"standard members {best_rho:.3g}")
    if level[chosen] < rho[chosen]:
        why += " (the data cannot tell it from the best: the same relation up to its loads)"
    lowest = max(min([level[chosen]] + [v for _, _, v, _ in refined]), RESIDUAL_FLOOR)
    for _, cand, value, sensitivity in sorted(refined, key=lambda x: (x[0], x[2])):
        if max(value, RESIDUAL_FLOOR) * CLEAR_GAIN <= level[chosen] and value <= CLEAR_GAIN * lowest:
            why += f"; refined to {cand.spec}: {value:.3g}"
            if sensitivity < UNDETERMINED:
                report["undetermined"] = True
                why += (" - but the data barely determine these parameters (a free response "
                        "or a single-frequency load); they reproduce the data, name the "
                        "scheme if you know it")
            return cand, why
    if refined:
        why += f"; no refinement is {CLEAR_GAIN:g}x better ({lowest:.3g})"
    return chosen, why


def _predictions(pieces, members, rho, best_rho, refined, holdout, loads="general"):
    """{scheme: held-back prediction error} of the shortlisted members and the refinements
    (free operators fitted on the first part); {} when the data are too short to hold back.
    A member is shortlisted at the best residual of its class (:func:`_class_best`): the
    residuals of members the data cannot tell apart differ only by how the truncated modes'
    closure enters them (in a mass-orthonormal basis Newmark's beta = 1/4 came out 57x
    above central differences on loads linear between bends, and the loop was Newmark)."""
    shortlist = [m for m in members if _class_best(m, rho, loads) <= SHORTLIST * best_rho]
    return held_back_errors(pieces, shortlist + [c for _, c, _, _ in refined], holdout)


def leading(pieces, r):
    """The pieces in their leading ``r`` coordinates (states, velocities, accelerations)."""
    return [(p[0][:r],) + tuple(p[1:4]) + tuple(None if a is None else a[:r] for a in p[4:])
            for p in pieces]


def held_back_errors(pieces, candidates, holdout) -> dict:
    """{scheme: held-back prediction error} of each candidate's free operators (M = I; C, K, B
    unconstrained) fitted on the first 1 - ``holdout`` of every trajectory and run on the rest
    with its recurrence (inf where useless or failed); {} when the data are too short to hold
    back or no candidate predicts."""
    if not holdout or not pieces:
        return {}
    try:
        fit_part, held = split(pieces, holdout)
        fitted = Residual(fit_part)
    except (InputError, ValueError):
        return {}
    dt = float(np.mean(np.diff(pieces[0][1])))
    out = {}
    for cand in candidates:
        try:
            ops = fitted.free_operators(cand)
            with np.errstate(all="ignore"):
                e = max(prediction_error(ops, S.rom_scheme(cand), h, dt) for h in held)
            out[cand] = e if e < PREDICTION_USELESS else float("inf")
        except (ValueError, np.linalg.LinAlgError):
            out[cand] = float("inf")
    return out if any(np.isfinite(list(out.values()))) else {}


def _by_prediction(members, refined, e, report, loads="general"):
    """(scheme, why) from the held-back errors ``e``, or None (module docstring)."""
    best = max(min(e.values()), PREDICTION_FLOOR)
    level = {m: _class_best(m, e, loads) for m in members if m in e}
    standard = [m for m in members if m in e and level[m] <= MARGIN * best]
    chosen = standard[0] if standard else None
    for _, cand, _, sensitivity in sorted(refined, key=lambda x: x[0]):
        if cand in e and e[cand] <= MARGIN * best and (
                chosen is None or max(e[cand], PREDICTION_FLOOR) * REFINEMENT_GAIN <= level[chosen]):
            chosen = cand
            if sensitivity < UNDETERMINED:
                report["undetermined"] = True
            break
    if chosen is None:
        return None
    return chosen, (f"held-back prediction error {e[chosen]:.3g} ({chosen.spec}) with free "
                    f"operators, best {best:.3g} of {len(e)} candidates (those within "
                    f"{SHORTLIST:g}x of the best relation residual, and the refinements); the "
                    f"first standard member within {MARGIN:g}x is kept unless a refinement "
                    f"predicts {REFINEMENT_GAIN:g}x better")
