"""The peer of the parametric demos: ``opinf`` 0.6's parametric first-order models.

    pip install 'dolfinx_lopinf[peers]'

What an opinf user builds for a parametric second-order system (opinf's parametric tutorial
and :mod:`dolfinx_lopinf.studies.peers` for the conventions):

* the state x = [q; q_t] (q_t: opinf's ``UniformFiniteDifferencer(times, "ord6")`` of the
  recorded states), each variable scaled by its max |.| over all training trajectories
  (opinf's ``ShiftScaleTransformer(scaling="maxabs")``), in OUR basis for q and for q_t
  (the same reduced space as the L-OpInf rows: 2r first-order states);
* ``kind="affine"``: ``opinf.models.ParametricContinuousModel`` with an
  ``AffineLinearOperator`` whose coefficient functions are the monomials our UFL split found
  for K and C (plus 1: A(mu) = [[0, I], [-K(mu), -C(mu)]] needs it), each divided by its
  largest training value - the same affine information L-OpInf gets - and an ``InputOperator`` (``AffineInputOperator`` when B depends
  on mu); ``kind="interpolated"``: ``opinf.models.InterpContinuousModel`` (elementwise cubic
  spline in 1-D, opinf's default), the trajectories of one parameter stacked at its node;
* the reduced time derivatives: ``UniformFiniteDifferencer(times, "ord6")`` per trajectory;
* the regulariser: the search of ``ROM.fit_regselect_continuous`` (opinf's
  ``utils.gridsearch`` over ``np.logspace(-12, 2, 15)``: the mean relative L2 training error
  over the training trajectories, a candidate whose prediction leaves 5x the training range
  is unstable), written at the model level so that several trajectories of one parameter
  can share an interpolation node;
* prediction: the inferred linear ODE integrated exactly (matrix exponential, inputs linear
  between samples; :func:`dolfinx_lopinf.studies.peers._exact_model_class`).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np

from ..core.basis import Basis
from ..core.parametric import AffineStructure, projector
from ..errors import InputError
from ..core._blas import one_blas_thread
from .peers import DEFAULT_CANDIDATES, _exact_model_class, _opinf

KINDS = ("affine", "interpolated")


def _theta_fns(structure: AffineStructure, terms, mus):
    """The coefficient functions theta_t(mu) / max_train |theta_t|: nondimensional, as a
    careful user writes them (E ~ 1e5 beside 1 would make opinf's one L2 regulariser weigh
    the terms 1e10 apart)."""
    def raw(t, mu):
        return float(np.prod([np.atleast_1d(mu)[structure.parameters.index(k)] for k in t])) \
            if t else 1.0

    def make(t):
        scale = max(abs(raw(t, mu)) for mu in mus) or 1.0
        return lambda mu: raw(t, mu) / scale
    return [make(t) for t in terms]


@dataclass
class ParametricPeer:
    """A fitted opinf parametric model (module docstring)."""

    model: object
    kind: str
    r: int
    scales: tuple
    regularizer: float
    fit_seconds: float
    P: np.ndarray

    def predict(self, mu, times, inputs=None, q0=None, v0=None):
        """(Qh (r, K), Vh (r, K), finite): the peer's reduced positions and velocities at
        ``times`` (uniform) from (q0, v0) (full states; rest by default); ``inputs`` (m, K)
        at ``times``."""
        x0 = np.zeros(2 * self.r)
        if q0 is not None:
            x0[:self.r] = self.P @ q0 / self.scales[0]
        if v0 is not None:
            x0[self.r:] = self.P @ v0 / self.scales[1]
        X, finite = self.predict_scaled(mu, x0, times, inputs)
        return self.scales[0] * X[:self.r], self.scales[1] * X[self.r:], finite

    def predict_scaled(self, mu, x0, times, inputs=None):
        """(X (2r, K), finite) in opinf's scaled first-order coordinates."""
        opinf = _opinf()
        frozen = self.model.evaluate(np.atleast_1d(np.asarray(mu, dtype=float)))
        ops = [opinf.operators.LinearOperator(frozen.operators[0].entries)]
        if len(frozen.operators) > 1:
            ops.append(opinf.operators.InputOperator(frozen.operators[1].entries))
        exact = _exact_model_class(opinf)(ops)
        with warnings.catch_warnings(), one_blas_thread():
            warnings.simplefilter("ignore")
            X = np.asarray(exact.predict(x0, np.asarray(times, float), inputs))
        finite = X.shape[1] == len(times) and bool(np.all(np.isfinite(X)))
        if X.shape[1] < len(times):
            X = np.hstack([X, np.full((X.shape[0], len(times) - X.shape[1]), np.nan)])
        return X, finite


def opinf_parametric(data, basis: Basis, *, kind: str = "affine",
                     structure: AffineStructure | None = None,
                     candidates=DEFAULT_CANDIDATES, ddt_scheme: str = "ord6") -> ParametricPeer:
    """Fit opinf's parametric model (module docstring) to (mu, Snapshots) pairs in ``basis``."""
    if kind not in KINDS:
        raise InputError(f"kind must be one of {KINDS}, got {kind!r}")
    if kind == "affine" and structure is None:
        raise InputError("kind='affine' needs the affine structure (the coefficient functions)")
    opinf = _opinf()
    P = projector(basis)
    r = basis.r
    trajs = []
    for mu, s in data:
        if s.input_times is not None and not np.allclose(s.input_times, s.times):
            raise InputError("the opinf peer needs the inputs at the state times")
        Qh = P @ s.Q
        fd = opinf.ddt.UniformFiniteDifferencer(s.times, ddt_scheme)
        Vh = np.asarray(fd.estimate(Qh)[1])
        trajs.append((np.atleast_1d(np.asarray(mu, float)), s.times, Qh, Vh, s.U))
    sq = max(np.abs(t[2]).max() for t in trajs)
    sv = max(np.abs(t[3]).max() for t in trajs)
    X = [np.vstack([Qh / sq, Vh / sv]) for _, _, Qh, Vh, _ in trajs]
    ddts = []
    for (_, times, *_), x in zip(trajs, X):
        ddts.append(np.asarray(opinf.ddt.UniformFiniteDifferencer(times, ddt_scheme).estimate(x)[1]))
    forced = trajs[0][4] is not None
    if kind == "affine":
        a_terms = sorted({()} | set(structure.stiffness) | set(structure.damping),
                         key=lambda t: (len(t), t))
        mus = [t[0] for t in trajs]
        ops = [opinf.operators.AffineLinearOperator(_theta_fns(structure, a_terms, mus),
                                                    nterms=len(a_terms))]
        if forced:
            if structure.inputs == ((),):
                ops.append(opinf.operators.InputOperator())
            else:
                ops.append(opinf.operators.AffineInputOperator(
                    _theta_fns(structure, structure.inputs, mus), nterms=len(structure.inputs)))
        model = opinf.models.ParametricContinuousModel(ops, solver=opinf.lstsq.L2Solver(1.0))
        params = [t[0] for t in trajs]
        states, lhs = X, ddts
        inputs = [t[4] for t in trajs] if forced else None
    else:
        ops = [opinf.operators.InterpLinearOperator()]
        if forced:
            ops.append(opinf.operators.InterpInputOperator())
        model = opinf.models.InterpContinuousModel(ops, solver=opinf.lstsq.L2Solver(1.0))
        keys = sorted({tuple(t[0]) for t in trajs})
        params = [np.array(k) if len(k) > 1 else k[0] for k in keys]
        idx = [[i for i, t in enumerate(trajs) if tuple(t[0]) == k] for k in keys]
        states = [np.hstack([X[i] for i in ii]) for ii in idx]
        lhs = [np.hstack([ddts[i] for i in ii]) for ii in idx]
        inputs = [np.hstack([trajs[i][4] for i in ii]) for ii in idx] if forced else None
    peer = ParametricPeer(model, kind, r, (sq, sv), float("nan"), 0.0, P)
    t0 = time.perf_counter()
    with warnings.catch_warnings(), one_blas_thread():
        warnings.simplefilter("ignore")
        model.fit(params, states, lhs, inputs)
        shifts = [x.mean(axis=1, keepdims=True) for x in X]
        limits = [5.0 * np.abs(x - c).max() for x, c in zip(X, shifts)]

        def set_reg(reg):
            if kind == "affine":
                model.solver.regularizer = reg
            else:
                for solver in model.solvers:
                    solver.regularizer = reg
            model.refit()

        def training_error(reg):
            try:
                set_reg(reg)
            except Exception:  # noqa: BLE001 - opinf's search scores a failed refit as inf
                return np.inf
            err = 0.0
            for (mu, times, _, _, U), x, c, lim in zip(trajs, X, shifts, limits):
                pred, finite = peer.predict_scaled(mu, x[:, 0], times, U)
                if not finite or np.abs(pred - c).max() > lim:
                    return np.inf
                err += opinf.post.Lp_error(x, pred, times)[1]
            return err / len(trajs)

        best = opinf.utils.gridsearch(training_error, list(candidates), label="regularization")
        set_reg(best)
    peer.regularizer = float(best)
    peer.fit_seconds = time.perf_counter() - t0
    return peer
