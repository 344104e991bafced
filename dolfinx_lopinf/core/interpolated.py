"""Non-affine parameters: per-parameter L-OpInf fits interpolated on the SPD manifold (numpy).

When a parameter does not enter the operators affinely (a geometry factor, an inclusion's
radius: :mod:`dolfinx_lopinf.fem.affine` says which), each training parameter mu_j gets its
own L-OpInf fit (Kh_j, Ch_j >= eps I, Bh_j) in one common basis - the POD of all
trajectories - and the operators at a new mu are interpolated on the manifold of symmetric
positive definite matrices, where every interpolant and extrapolant is again SPD:

* ``"log-euclidean"``: K(mu) = expm( sum_j w_j(mu) logm(K_j) ) - any p; the weights w_j are
  those of piecewise-linear interpolation in 1-D (the end segments continued outside the
  range) and of a thin-plate-spline radial basis interpolant with a linear term for p > 1;
* ``"affine-invariant"`` (p = 1): the geodesic between the two neighbouring K_a, K_b,
  K(t) = K_a^{1/2} (K_a^{-1/2} K_b K_a^{-1/2})^t K_a^{1/2}, t in [0, 1] between them (outside
  the range the end geodesic continued, t < 0 or t > 1 - still SPD).

Inputs Bh are interpolated entry by entry with the same weights (1-D: the same t). Since
K(mu), C(mu) are SPD for every mu, the ROM (Newmark family, midpoint) is stable at every
parameter: there is no cone here; accuracy away from the training parameters is not
certified, and a :class:`~dolfinx_lopinf.errors.ParameterRangeWarning` says when a prediction
leaves the training range.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from . import schemes
from .basis import Basis
from .inference import RIDGE, infer_mechanical
from .parametric import _basis, _relations, _run, _scheme_of, _training, projector
from .rom import LagrangianROM, Trajectory
from ..errors import InputError, ParameterRangeWarning, warn

METHODS = ("log-euclidean", "affine-invariant")


def _eig_fn(A, fn):
    w, Q = np.linalg.eigh(0.5 * (A + A.T))
    return (Q * fn(w)) @ Q.T


def logm_spd(A):
    """The symmetric matrix logarithm of an SPD A (an InputError if A is not SPD)."""
    w = np.linalg.eigvalsh(0.5 * (A + A.T))
    if w[0] <= 0:
        raise InputError(f"the matrix is not positive definite (smallest eigenvalue {w[0]:.3g}): "
                         "no SPD logarithm")
    return _eig_fn(A, np.log)


def expm_sym(S):
    return _eig_fn(S, np.exp)


def geodesic(A, B, t):
    """The affine-invariant geodesic A #_t B = A^1/2 (A^-1/2 B A^-1/2)^t A^1/2 (SPD for any t)."""
    w, Q = np.linalg.eigh(0.5 * (A + A.T))
    if w[0] <= 0:
        raise InputError(f"geodesic: A is not positive definite ({w[0]:.3g})")
    h, hi = (Q * np.sqrt(w)) @ Q.T, (Q / np.sqrt(w)) @ Q.T
    return h @ _eig_fn(hi @ B @ hi, lambda x: np.power(np.maximum(x, np.finfo(float).tiny), t)) @ h


def _segment(grid, x):
    """(a, t): x = grid[a] + t (grid[a+1] - grid[a]), the end segments continued outside."""
    a = int(np.clip(np.searchsorted(grid, x, side="right") - 1, 0, len(grid) - 2))
    return a, (x - grid[a]) / (grid[a + 1] - grid[a])


class _Weights:
    """w_j(mu) of the interpolation (1-D piecewise linear; p-D thin-plate RBF, linear term)."""

    def __init__(self, params):
        self.params = params
        if params.shape[1] > 1:
            from scipy.interpolate import RBFInterpolator

            n = len(params)
            if n < params.shape[1] + 1:
                raise InputError(f"{n} training parameters cannot span {params.shape[1]} "
                                 "dimensions: train at >= p + 1 parameters")
            self._rbf = RBFInterpolator(params, np.eye(n), kernel="thin_plate_spline", degree=1)

    def __call__(self, mu):
        if self.params.shape[1] == 1:
            a, t = _segment(self.params[:, 0], mu[0])
            w = np.zeros(len(self.params))
            w[a], w[a + 1] = 1 - t, t
            return w
        return self._rbf(mu[None, :])[0]


@dataclass(frozen=True)
class InterpolatedModel:
    """Per-parameter L-OpInf operators in one basis, interpolated on the SPD manifold.

    Attributes:
        mu_train: (s, p) the distinct training parameters (sorted for p = 1).
        K, C, B: lists of s per-parameter operators (C, B None when not fitted).
        basis, scheme, dt, method, report: as for :class:`~dolfinx_lopinf.core.parametric.ParametricModel`.
    """

    mu_train: np.ndarray
    K: list
    C: list | None
    B: list | None
    basis: Basis
    scheme: schemes.Scheme
    dt: float
    method: str = "log-euclidean"
    report: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.method not in METHODS:
            raise InputError(f"method must be one of {METHODS}, got {self.method!r}")
        if self.method == "affine-invariant" and self.mu_train.shape[1] != 1:
            raise InputError("the affine-invariant geodesic interpolates one parameter; use "
                             "method='log-euclidean' for p > 1")
        object.__setattr__(self, "_w", _Weights(self.mu_train))
        logs = {name: [logm_spd(A) for A in mats] for name, mats in (("K", self.K), ("C", self.C))
                if mats is not None}
        object.__setattr__(self, "_logs", logs)

    @property
    def r(self) -> int:
        return self.basis.r

    @property
    def p(self) -> int:
        return self.mu_train.shape[1]

    def check_mu(self, mu) -> np.ndarray:
        a = np.asarray(mu, dtype=float).reshape(-1) if not isinstance(mu, dict) else None
        if a is None or a.shape != (self.p,) or not np.all(np.isfinite(a)):
            raise InputError(f"mu = {mu!r}: this model has {self.p} parameter(s); pass "
                             f"{self.p} finite number(s)")
        lo, hi = self.mu_train.min(axis=0), self.mu_train.max(axis=0)
        if np.any((a < lo) | (a > hi)):
            warn(f"mu = {a.tolist()} is outside the training range [{lo.tolist()}, {hi.tolist()}]: "
                 "the interpolated operators are SPD there (stable), their accuracy is not "
                 "known", ParameterRangeWarning)
        return a

    def operators(self, mu):
        """(M None, C, K, B) at mu (SPD interpolation of K and C, linear of B)."""
        mu = np.asarray(mu, dtype=float).reshape(-1)
        if self.method == "affine-invariant":
            a, t = _segment(self.mu_train[:, 0], mu[0])
            K = geodesic(self.K[a], self.K[a + 1], t)
            C = None if self.C is None else geodesic(self.C[a], self.C[a + 1], t)
            B = None if self.B is None else (1 - t) * self.B[a] + t * self.B[a + 1]
            return None, C, K, B
        w = self._w(mu)

        def blend(mats):
            return sum(wj * A for wj, A in zip(w, mats))

        K = expm_sym(blend(self._logs["K"]))
        C = None if self.C is None else expm_sym(blend(self._logs["C"]))
        B = None if self.B is None else blend(self.B)
        return None, C, K, B

    def rom(self, mu) -> LagrangianROM:
        mu = self.check_mu(mu)
        _, C, K, B = self.operators(mu)
        return LagrangianROM(K=K, C=C, B=B, scheme=schemes.rom_scheme(self.scheme),
                             meta={"method": f"interpolated-{self.method}", "mu": mu.tolist()})

    def predict(self, mu, n_steps: int | None = None, *, t_end: float | None = None, q0=None,
                v0=None, inputs=None, dt: float | None = None, every: int = 1,
                backend: str = "auto") -> Trajectory:
        """As :meth:`dolfinx_lopinf.core.parametric.ParametricModel.predict`."""
        return _run(self.rom(mu), self.basis, self.dt if dt is None else dt, n_steps, t_end, q0,
                    v0, inputs, every, backend)

    def reconstruct(self, Qh, rows=None):
        return self.basis.reconstruct(Qh, rows=rows)


def fit_interpolated(data, r: int | None = None, *, basis: Basis | None = None, weight=None,
                     scheme=None, damping: bool = True, method: str = "log-euclidean",
                     eps: float = 1e-8, ridge: float = RIDGE,
                     strict: bool = False) -> InterpolatedModel:
    """One L-OpInf fit per training parameter in a common basis, interpolated on the SPD
    manifold (module docstring).

    Args:
        data: (mu, Snapshots) pairs or a dict mu -> Snapshots / list (as
            :func:`~dolfinx_lopinf.core.parametric.fit_affine`); trajectories of one mu are
            fitted together.
        r, basis, weight, scheme, eps, ridge, strict: as for ``fit_affine``.
        damping: fit Ch (>= eps I) at every parameter.
        method: ``"log-euclidean"`` or ``"affine-invariant"`` (one parameter).
    """
    if method not in METHODS:
        raise InputError(f"method must be one of {METHODS}, got {method!r}")
    pairs = _training(data, None)
    scheme = _scheme_of(pairs, scheme)
    t0 = time.perf_counter()
    basis = _basis(pairs, r, basis, weight)
    t1 = time.perf_counter()
    rels = _relations(pairs, projector(basis), scheme)
    mus = np.unique(np.array([mu for mu, _ in pairs]), axis=0)
    if len(mus) < 2:
        raise InputError(f"interpolation needs >= 2 distinct training parameters, got {len(mus)}")
    K, C, B, certs = [], [], [], []
    for mu in mus:
        mine = [rel for rel in rels if np.array_equal(rel[0], mu)]
        Qk, Qc, Qm = (np.hstack([rel[i] for rel in mine]) for i in (1, 2, 3))
        Uf = None if mine[0][4] is None else np.hstack([rel[4] for rel in mine])
        ops = infer_mechanical(Qk, Qc if damping else None, Qm, Uf, damping=damping, eps=eps,
                               ridge=ridge, strict=strict)
        K.append(ops.K)
        C.append(ops.C)
        B.append(ops.B)
        certs.append({k: ops.certificate.get(k) for k in ("solver", "duality_gap",
                                                           "relative_residual", "min_eig_K")})
    report = {"method": f"interpolated-{method}", "parameters_trained": len(mus),
              "trajectories": len(pairs), "certificates": certs, "basis_seconds": t1 - t0,
              "fit_seconds": time.perf_counter() - t1, "scheme": scheme.spec,
              "stable_for": "every mu (SPD interpolation and extrapolation of Kh_j, Ch_j >= eps I)"}
    return InterpolatedModel(mus, K, C if damping else None, None if B[0] is None else B, basis,
                             scheme, pairs[0][1].dt, method, report)
