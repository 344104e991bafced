"""Polynomial Lagrangian operator inference: a reduced potential learned as one convex fit.

For St. Venant-Kirchhoff (SVK) elasticity the potential energy is a quartic polynomial of the
displacement (E = 1/2 (F^T F - I) is quadratic in grad u and W is quadratic in E), so on a
linear basis q -> V q the reduced potential is *exactly*

    U(q) = 1/2 q^T K q + U3(q) + U4(q),    U3 = sum_|a|=3 c_a q^a,   U4 = sum_|b|=4 d_b q^b,

and the reduced internal force is its gradient. This module learns U (and damping C, input B)
from reduced snapshots as the gradient of one potential, so the ROM is Lagrangian by
construction:

    qh_tt + C qh_t + grad U(qh) = B u.

Unknowns: the monomial coefficients of U (degree 2, 3, 4: C(r+1,2) + C(r+2,3) + C(r+3,4)),
C (symmetric, C(r+1,2)) and B (r m). The force is linear in them, so the fit is a least
squares. Its constraints (``constraint=``), all convex:

* ``"none"``: gradient structure only (plain least squares);
* ``"spd"``: K >= eps I and C >= eps I (the package's linear L-OpInf constraint);
* ``"quartic"``: also U4(q) = 1/2 z^T P z with z = vech(q q^T) (monomials q_i q_j, i <= j) and
  P >= 0, so the quartic part is a sum of squares (>= 0);
* ``"sos"`` (default): U(q) = m^T G m with m = [q; z] and G >= eps_g I (a Gram matrix: K = 2 G11,
  the cubic terms from G12, the quartic from G22). Then ``U(q) >= eps_g (|q|^2 + |z|^2)`` for every
  q: the potential is bounded below *and coercive*, so every unforced (damped or not) ROM
  trajectory stays in the bounded set {U <= E(0)}. The SVK reduced potential has exactly this
  form (W is a positive combination of squares of the entries of E, each linear + quadratic in
  q), so the constraint costs nothing on SVK data. P >= 0 alone does not bound U below: the
  cubic terms can win where the quartic part vanishes.

The data relation is the midpoint variational integrator's forced discrete Euler-Lagrange
equation (the FOM's scheme), which FOM snapshots obey exactly:

    D2_k + C D1_k + 1/2 (grad U(q_{k-1/2}) + grad U(q_{k+1/2})) = B Ubar_k,
    D2_k = (q_{k+1} - 2 q_k + q_{k-1}) / dt^2,   D1_k = (q_{k+1} - q_{k-1}) / (2 dt),
    q_{k+-1/2} = (q_k + q_{k+-1}) / 2,   Ubar_k = (u(t_{k-1/2}) + u(t_{k+1/2})) / 2

(:func:`midpoint_data`; the reduced mass is I - a mass-orthonormal basis). Constrained fits
are solved by cvxpy + Clarabel on the QR-compressed problem (its size does not depend on the
number of snapshots); the certificate holds Clarabel's primal and dual objectives and their gap
(optimality) and the minimum eigenvalue of the returned, exactly PSD-projected Gram matrix
(feasibility, checked in numpy after the solve).

:class:`PolynomialROM` integrates qh with the midpoint VI (``scheme="midpoint"``, the FOM's
scheme: symplectic, bounded energy error) or with the average-vector-field discrete gradient
(``scheme="avf"``: grad U replaced by the exact integral of grad U over the segment [q0, q1],
two-point Gauss-Legendre is exact for a quartic U; the energy ``1/2 |p|^2 + U(q)`` of the
conservative system is then conserved to the Newton tolerance). Each step is a reduced Newton
solve. :class:`PolynomialForce` is the unconstrained baseline (independent polynomial force
coefficients, no potential).

numpy (+ cvxpy/clarabel for constrained fits) only; no DOLFINx.
"""

from __future__ import annotations

import itertools
import time
import warnings
from dataclasses import dataclass, field
from math import comb

import numpy as np
import scipy.linalg

from ..errors import (InputError, NonLagrangianWarning, SolverFailedError, SolverWarning,
                      StepFailedError)
from ._checks import as_real_array, check_matrix, check_positive
from .compiled import NEWTON_STALL

CONSTRAINTS = ("none", "spd", "quartic", "sos")
SCHEMES = ("midpoint", "avf")


# -- monomials ------------------------------------------------------------------------------

def monomials(r: int, degree: int) -> np.ndarray:
    """Index tuples (i1 <= ... <= id) of the degree-``degree`` monomials in r variables,
    (C(r + d - 1, d), d), in lexicographic order."""
    return np.array(list(itertools.combinations_with_replacement(range(r), degree)),
                    dtype=np.intp).reshape(-1, degree)


def n_unknowns(r: int, m: int = 0, damping: bool = True) -> dict:
    """Unknowns of the potential fit per block at reduced dimension r (m inputs)."""
    out = {"K": comb(r + 1, 2), "cubic": comb(r + 2, 3), "quartic": comb(r + 3, 4),
           "C": comb(r + 1, 2) if damping else 0, "B": r * m}
    out["total"] = sum(out.values())
    out["gram_sos"] = comb(r + comb(r + 1, 2) + 1, 2)  # entries of the Gram matrix G
    out["unconstrained_force"] = r * (r + comb(r + 1, 2) + comb(r + 2, 3))
    return out


def monomial_values(X: np.ndarray, tuples: np.ndarray) -> np.ndarray:
    """(p, N) values of the monomials ``tuples`` (p, d) at points X (r, N)."""
    out = np.ones((len(tuples), X.shape[1]))
    for j in range(tuples.shape[1]):
        out *= X[tuples[:, j]]
    return out


def monomial_gradients(X: np.ndarray, tuples: np.ndarray) -> np.ndarray:
    """(r, p, N): d(monomial_j)/d x_l at points X (r, N)."""
    r, N = X.shape
    p, d = tuples.shape
    out = np.zeros((r, p, N))
    cols = np.arange(p)
    for pos in range(d):
        others = np.delete(tuples, pos, axis=1)
        val = monomial_values(X, others) if d > 1 else np.ones((p, N))
        np.add.at(out, (tuples[:, pos], cols), val)
    return out


def _symmetric_tensor(coef: np.ndarray, tuples: np.ndarray, r: int) -> np.ndarray:
    """The fully symmetric tensor T with T(q, ..., q) = sum_j coef_j q^tuples_j."""
    d = tuples.shape[1]
    T = np.zeros((r,) * d)
    for c, tup in zip(coef, tuples):
        perms = set(itertools.permutations(tup))
        for p in perms:
            T[p] = c / len(perms)
    return T


# -- the potential --------------------------------------------------------------------------

@dataclass
class PolynomialPotential:
    """U(q) = 1/2 q^T K q + T3(q, q, q) + T4(q, q, q, q) with symmetric tensors T3, T4.

    Attributes:
        K: (r, r) symmetric.  c3, c4: monomial coefficients (order of :func:`monomials`).
    """

    K: np.ndarray
    c3: np.ndarray
    c4: np.ndarray

    def __post_init__(self):
        self.K = 0.5 * (np.asarray(self.K, float) + np.asarray(self.K, float).T)
        r = self.r
        self.c3 = np.asarray(self.c3, float).reshape(-1)
        self.c4 = np.asarray(self.c4, float).reshape(-1)
        if len(self.c3) != comb(r + 2, 3) or len(self.c4) != comb(r + 3, 4):
            raise InputError(f"r = {r} needs {comb(r + 2, 3)} cubic and {comb(r + 3, 4)} quartic "
                             f"coefficients, got {len(self.c3)} and {len(self.c4)}")
        self.T3 = _symmetric_tensor(self.c3, monomials(r, 3), r)
        self.T4 = _symmetric_tensor(self.c4, monomials(r, 4), r)

    @property
    def r(self) -> int:
        return self.K.shape[0]

    @classmethod
    def from_coefficients(cls, theta: np.ndarray, r: int) -> "PolynomialPotential":
        """From the monomial coefficients [degree 2; degree 3; degree 4] (the fit's unknowns)."""
        p2, p3 = comb(r + 1, 2), comb(r + 2, 3)
        return cls(_k_from_quadratic(theta[:p2], r), theta[p2:p2 + p3], theta[p2 + p3:])

    def coefficients(self) -> np.ndarray:
        """[degree-2 monomial coefficients; c3; c4] (inverse of :meth:`from_coefficients`)."""
        t2 = monomials(self.r, 2)
        c2 = np.where(t2[:, 0] == t2[:, 1], 0.5, 1.0) * self.K[t2[:, 0], t2[:, 1]]
        return np.concatenate([c2, self.c3, self.c4])

    def value(self, Q: np.ndarray) -> np.ndarray:
        """U at the columns of Q (r, N) (or at one q (r,))."""
        Q = np.asarray(Q, float)
        one = Q.ndim == 1
        Q = Q.reshape(self.r, -1)
        K3 = np.tensordot(self.T3, Q, axes=([0], [0]))  # (r, r, N)
        K4 = np.tensordot(self.T4, Q, axes=([0], [0]))  # (r, r, r, N)
        u = 0.5 * np.einsum("in,ij,jn->n", Q, self.K, Q)
        u += np.einsum("ijn,in,jn->n", K3, Q, Q)
        u += np.einsum("ijkn,in,jn,kn->n", K4, Q, Q, Q)
        return u[0] if one else u

    def gradient(self, Q: np.ndarray) -> np.ndarray:
        """grad U at the columns of Q (r, N) (or at one q)."""
        Q = np.asarray(Q, float)
        if Q.ndim == 1:
            q = Q
            T3q = self.T3 @ q
            T4q = (self.T4 @ q) @ q
            return self.K @ q + 3.0 * (T3q @ q) + 4.0 * (T4q @ q)
        g = self.K @ Q
        g += 3.0 * np.einsum("ijk,jn,kn->in", self.T3, Q, Q)
        g += 4.0 * np.einsum("ijkl,jn,kn,ln->in", self.T4, Q, Q, Q)
        return g

    def hessian(self, q: np.ndarray) -> np.ndarray:
        """Hessian of U at one q (r,)."""
        return self.K + 6.0 * (self.T3 @ q) + 12.0 * ((self.T4 @ q) @ q)

    def force_and_jacobian(self, q):
        T3q = self.T3 @ q
        T4q = self.T4 @ q
        T4qq = T4q @ q
        g = self.K @ q + 3.0 * (T3q @ q) + 4.0 * (T4qq @ q)
        return g, self.K + 6.0 * T3q + 12.0 * T4qq


def _k_from_quadratic(c2: np.ndarray, r: int) -> np.ndarray:
    """K with 1/2 q^T K q = sum_{i <= j} c2_ij q_i q_j."""
    t2 = monomials(r, 2)
    K = np.zeros((r, r))
    K[t2[:, 0], t2[:, 1]] = c2
    K = K + K.T  # diagonal doubled: 1/2 K_ii = c_ii
    return K


@dataclass
class PolynomialForce:
    """The unconstrained baseline: f(q) = A1 q + A2 z2(q) + A3 z3(q) with independent rows
    (z2, z3 the degree-2 and degree-3 monomials): no potential, no symmetry.

    Attributes:
        A: (r, r + C(r+1,2) + C(r+2,3)) coefficients.
    """

    A: np.ndarray

    def __post_init__(self):
        self.A = np.asarray(self.A, float)
        r = self.A.shape[0]
        self.tuples = [monomials(r, 1), monomials(r, 2), monomials(r, 3)]
        if self.A.shape[1] != sum(len(t) for t in self.tuples):
            raise InputError(f"A must be ({r}, {sum(len(t) for t in self.tuples)}), got {self.A.shape}")

    @property
    def r(self) -> int:
        return self.A.shape[0]

    def features(self, Q):
        return np.vstack([monomial_values(Q, t) for t in self.tuples])

    def gradient(self, Q):
        Q = np.asarray(Q, float)
        one = Q.ndim == 1
        out = self.A @ self.features(Q.reshape(self.r, -1))
        return out[:, 0] if one else out

    def force_and_jacobian(self, q):
        X = q.reshape(-1, 1)
        J = np.concatenate([monomial_gradients(X, t)[:, :, 0] for t in self.tuples], axis=1)
        return self.A @ self.features(X)[:, 0], self.A @ J.T


# -- data -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class MidpointData:
    """Columns of the midpoint relation (see the module docstring), each (., k)."""

    minus: np.ndarray  # q_{k-1/2}
    plus: np.ndarray  # q_{k+1/2}
    D1: np.ndarray
    D2: np.ndarray
    Ubar: np.ndarray | None
    dt: float

    @property
    def Qbar(self):
        return 0.5 * (self.minus + self.plus)


def midpoint_data(Qh: np.ndarray, dt: float, inputs_mid: np.ndarray | None = None) -> MidpointData:
    """Data of the midpoint relation from reduced states Qh (r, K) at every step dt and the
    inputs at the half steps, (m, K-1): u(t_{k+1/2}) for k = 0 .. K-2 (or None)."""
    Qh = check_matrix(Qh, "Qh")
    if Qh.shape[1] < 3:
        raise InputError(f"Qh needs at least 3 time samples (columns), got {Qh.shape[1]}")
    dt = check_positive(dt, "dt")
    mid = 0.5 * (Qh[:, 1:] + Qh[:, :-1])
    D2 = (Qh[:, 2:] - 2 * Qh[:, 1:-1] + Qh[:, :-2]) / dt**2
    D1 = (Qh[:, 2:] - Qh[:, :-2]) / (2 * dt)
    Ubar = None
    if inputs_mid is not None:
        U = check_matrix(np.atleast_2d(as_real_array(inputs_mid, "inputs_mid")), "inputs_mid")
        if U.shape[1] != Qh.shape[1] - 1:
            raise InputError(f"inputs_mid must have K - 1 = {Qh.shape[1] - 1} columns (the half "
                             f"steps t_(k+1/2)), got shape {U.shape}")
        Ubar = 0.5 * (U[:, 1:] + U[:, :-1])
    return MidpointData(mid[:, :-1], mid[:, 1:], D1, D2, Ubar, dt)


def point_data(Q: np.ndarray, V: np.ndarray, A: np.ndarray, inputs: np.ndarray | None = None
               ) -> MidpointData:
    """Data of the continuous relation A + C V + grad U(Q) = B inputs at sample points (each
    (r, N); inputs (m, N) or None) - e.g. the probe accelerations of
    :func:`dolfinx_lopinf.fem.probes.probe` - in the form :func:`fit_polynomial` takes (both
    midpoints are the point itself)."""
    Q, V, A = (check_matrix(X, name) for X, name in ((Q, "Q"), (V, "V"), (A, "A")))
    if not (Q.shape == V.shape == A.shape):
        raise InputError(f"Q, V and A must have the same shape (r, N), got {Q.shape}, {V.shape}, "
                         f"{A.shape}")
    U = None
    if inputs is not None:
        U = check_matrix(np.atleast_2d(as_real_array(inputs, "inputs")), "inputs")
        if U.shape[1] != Q.shape[1]:
            raise InputError(f"inputs must have N = {Q.shape[1]} columns, got shape {U.shape}")
    return MidpointData(Q, Q, V, A, U, 0.0)


def _concat(datas) -> MidpointData:
    if isinstance(datas, MidpointData):
        return datas
    if isinstance(datas, np.ndarray) or not isinstance(datas, (list, tuple)):
        raise InputError(f"data must be a MidpointData (from midpoint_data(...) or "
                         f"point_data(...)) or a list of them, got {type(datas).__name__}")
    datas = list(datas)
    for i, d in enumerate(datas):
        if not isinstance(d, MidpointData):
            raise InputError(f"data[{i}] is a {type(d).__name__}, not a MidpointData (from "
                             "midpoint_data(...) or point_data(...))")
    if not datas:
        raise InputError("no data: pass a MidpointData or a non-empty list of them")
    has_u = {d.Ubar is not None for d in datas}
    if len(has_u) > 1:
        raise InputError("either every trajectory has inputs or none has")
    if len({d.dt for d in datas}) > 1:
        raise InputError("the trajectories have different dt")
    cat = lambda name: np.hstack([getattr(d, name) for d in datas])  # noqa: E731
    return MidpointData(cat("minus"), cat("plus"), cat("D1"), cat("D2"),
                        cat("Ubar") if datas[0].Ubar is not None else None, datas[0].dt)


# -- the fit --------------------------------------------------------------------------------

@dataclass
class PolynomialOperators:
    """A fitted polynomial Lagrangian ROM: potential, damping C, input B and a certificate."""

    potential: PolynomialPotential
    C: np.ndarray | None
    B: np.ndarray | None
    certificate: dict = field(default_factory=dict)
    gram: np.ndarray | None = None  # the Gram matrix G of U = m^T G m ("sos")


def _sym_basis_matrix(X: np.ndarray) -> np.ndarray:
    """(r, p, N): d/dtheta of (C x) for C symmetric parametrised by its upper triangle."""
    r, N = X.shape
    t2 = monomials(r, 2)
    out = np.zeros((r, len(t2), N))
    cols = np.arange(len(t2))
    out[t2[:, 0], cols] += X[t2[:, 1]]
    off = t2[:, 0] != t2[:, 1]
    out[t2[off, 1], cols[off]] += X[t2[off, 0]]
    return out


def _sym_from_upper(c, r):
    t2 = monomials(r, 2)
    S = np.zeros((r, r))
    S[t2[:, 0], t2[:, 1]] = c
    S[t2[:, 1], t2[:, 0]] = c
    return S


def _design(data: MidpointData, damping: bool, sig: np.ndarray, force_features=None):
    """Design matrix A (r N, p) and target b (r N) of the relation in balanced coordinates
    q~ = S^-1 q, S = diag(sig) (each reduced coordinate scaled to unit RMS), row l multiplied
    by sig_l:  S D2 + C~ (S^-1 D1) + grad U~(q~) - B~ Ubar = 0, with U~(q~) = U(S q~),
    C~ = S C S, B~ = S B (f~ = S f(S q~) for the unconstrained force). Linear in the unknowns.
    The callers divide row l by sig_l again (:func:`_natural_rows`) before solving."""
    r, N = data.D2.shape
    mm, mp = data.minus / sig[:, None], data.plus / sig[:, None]
    blocks = []
    if force_features is None:  # potential: gradients of the degree-2, 3, 4 monomials
        for d in (2, 3, 4):
            t = monomials(r, d)
            blocks.append(0.5 * (monomial_gradients(mm, t) + monomial_gradients(mp, t)))
    else:  # unconstrained: f_l = sum_j A_lj phi_j, one block per row l
        phi = 0.5 * (force_features(mm) + force_features(mp))  # (P, N)
        P = phi.shape[0]
        blk = np.zeros((r, r * P, N))
        for l in range(r):
            blk[l, l * P:(l + 1) * P] = phi
        blocks.append(blk)
    if damping:
        blocks.append(_sym_basis_matrix(data.D1 / sig[:, None]))
    if data.Ubar is not None:
        m = data.Ubar.shape[0]
        blk = np.zeros((r, r * m, N))
        for l in range(r):
            blk[l, l * m:(l + 1) * m] = -data.Ubar
        blocks.append(blk)
    A = np.concatenate(blocks, axis=1)  # (r, p, N)
    A = A.transpose(0, 2, 1).reshape(r * N, -1)
    b = -(sig[:, None] * data.D2).reshape(-1)
    return A, b


def _natural_rows(A, b, sig, N):
    """Divide row l of the S-scaled relation by sig_l: the residual is then measured in the
    reduced coordinates themselves - for a mass-orthonormal basis the M^-1 norm of the
    full-order force residual (the norm dual to kinetic energy, invariant under rotations of
    q). Weighting row l by sig_l instead (the relation as written in q~) down-weights the
    small-amplitude, stiff coordinates by up to sig_max / sig_min (1e3-1e5 on elastic data):
    the fit then leaves their equations unfitted - 2e-4 data residual and a ROM that blows up
    from 3e-6 data error, measured on the SVK cantilever's probe data."""
    w = np.repeat(1.0 / sig, N)
    return A * w[:, None], b * w


def _monomial_scale(sig, tuples):
    """prod_i sig_i^alpha_i of each monomial (q = S q~: c_alpha = c~_alpha / this)."""
    return np.prod(sig[tuples], axis=1) if tuples.shape[1] else np.ones(len(tuples))


def _compress(A, b, ridge):
    """R, z with ||A x - b||^2 + ridge^2 sigma1^2 ||D x||^2 = ||R x - z||^2 + const, where
    D = diag(column norms) (columns normalised first; R upper triangular p x p)."""
    norms = np.linalg.norm(A, axis=0)
    norms[norms == 0] = 1.0
    An = A / norms
    p = An.shape[1]
    R = np.linalg.qr(np.hstack([An, b[:, None]]), mode="r")
    if R.shape[0] < p + 1:  # fewer equations than unknowns + 1: pad (the caller has checked)
        R = np.vstack([R, np.zeros((p + 1 - R.shape[0], p + 1))])
    s = np.linalg.svd(R[:p, :p], compute_uv=False)
    gamma = ridge * s[0]
    Rx, z = R[:p, :p], R[:p, p]
    if gamma > 0:
        R2 = np.linalg.qr(np.vstack([R[:p, :p + 1],
                                     np.hstack([gamma * np.eye(p), np.zeros((p, 1))])]), mode="r")
        Rx, z = R2[:p, :p], R2[:p, p]
    cond = float(s[0] / max(s[-1], 1e-300))
    rank = int(np.sum(s > 1e-10 * s[0]))
    _compress.residual2 = float(R[p, p] ** 2)  # |A x - b|^2 at the least-squares x (no ridge)
    return Rx, z, norms, cond, rank


def fit_polynomial(data, *, constraint: str = "sos", damping: bool = True, eps: float = 1e-8,
                   eps_gram: float = 1e-13, ridge: float = 1e-10, solver: str = "cvxpy",
                   strict: bool = False) -> PolynomialOperators:
    """Fit U (degree 2-4), C and B to the midpoint relation of ``data`` (one BLAS thread: the
    compression's QR and the solver's matrices are a few hundred wide - threads cost more
    than they give there, and much more on a busy machine)."""
    from .inference import _blas_controller

    with _blas_controller().limit(limits=1, user_api="blas"):
        return _fit_polynomial(data, constraint=constraint, damping=damping, eps=eps,
                               eps_gram=eps_gram, ridge=ridge, solver=solver, strict=strict)


def _fit_polynomial(data, *, constraint, damping, eps, eps_gram, ridge, solver, strict):
    """:func:`fit_polynomial`.

    Args:
        data: a :class:`MidpointData` (from :func:`midpoint_data`) or a list of them (several
            trajectories; columns never straddle two).
        constraint: one of :data:`CONSTRAINTS` (module docstring).
        damping: fit C (symmetric; >= eps I unless ``constraint="none"``).
        eps: floor of K and C (relative to the largest |D2| / |q| scale, i.e. in the units of
            K: eps * max eigenvalue of the unconstrained K estimate is NOT used - eps is absolute).
        eps_gram: floor of the Gram matrix G ("sos"), in the scaled coordinates q / s with
            s = the RMS of the reduced states (so U >= eps_gram s^2 (|q/s|^2 + |z/s^2|^2)).
            Small by default: the SVK cantilever's Galerkin Gram matrix sits on the boundary
            of the PSD cone (the largest t with G - t I >= 0 is 0 to 3e-10 at r = 4..10), so a
            floor moves the potential - r = 8 tip error at the unseen a = 350: 1.0e-3 with a
            floor of 1e-10, 2.8e-4 with 1e-13, 2.6e-4 with 0 (Galerkin ROM 2.15e-4).
        ridge: relative Tikhonov parameter on the column-normalised data.
        solver: ``"cvxpy"`` (default): every constrained fit by Clarabel; ``"ipm"``: the
            "sos" fit by our interior point (:mod:`dolfinx_lopinf.core.polynomial_sos`: faster
            than Clarabel on the noisy test systems with the same residual, but its certificate
            stalls near 1e-6 relative, and on near-exact data - exact data's coefficients 2e-4
            off; the SVK cantilever's probes at r = 4 left at relative residual 3e-5 against
            Clarabel's 3e-9 - it is not certified: not yet the default).
        strict: raise SolverFailedError when a constrained fit is not certified.

    Returns:
        :class:`PolynomialOperators` with a certificate: ``solver``, ``status``, ``seconds``,
        ``n_unknowns``, ``relative_residual`` (||residual|| / ||D2||), ``data_condition``,
        ``data_rank``; for cvxpy fits ``primal_objective``, ``dual_objective``,
        ``duality_gap`` (absolute, in the solver's normalised objective), ``relative_gap``,
        ``iterations``, ``r_prim``, ``r_dual``; ``min_eig_K``, ``min_eig_C``, and
        ``min_eig_gram`` / ``min_eig_P`` (after an exact PSD projection in numpy).
    """
    if constraint not in CONSTRAINTS:
        raise InputError(f"constraint must be one of {CONSTRAINTS}, got {constraint!r}")
    for name, value in (("eps", eps), ("eps_gram", eps_gram), ("ridge", ridge)):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                or not (np.isfinite(value) and value >= 0):
            raise InputError(f"{name} must be a finite number >= 0, got {value!r} (a negative "
                             "floor would admit an indefinite, anti-physical K)")
    if not isinstance(damping, (bool, np.bool_)):
        raise InputError(f"damping must be True or False, got {damping!r}")
    if solver not in ("ipm", "cvxpy"):
        raise InputError(f"solver must be 'cvxpy' or 'ipm', got {solver!r}")
    data = _concat(data)
    r, N = data.D2.shape
    m = 0 if data.Ubar is None else data.Ubar.shape[0]
    nu = n_unknowns(r, m, damping)
    p_pot = nu["K"] + nu["cubic"] + nu["quartic"]
    if r * N < nu["total"]:
        raise InputError(f"{N} data columns x r = {r} rows = {r * N} equations cannot determine "
                         f"{nu['total']} unknowns; record more steps or lower r")
    t0 = time.perf_counter()
    sig = np.sqrt(np.mean(data.plus ** 2, axis=1))
    sig = np.where(sig > 0, sig, 1.0)
    A, b = _natural_rows(*_design(data, damping, sig), sig, N)
    R, z, norms, cond, rank = _compress(A, b, ridge)
    t_data = time.perf_counter() - t0
    cert = {"constraint": constraint, "n_unknowns": nu, "data_condition": cond, "data_rank": rank,
            "data_columns": N, "state_scales": sig}
    if constraint == "none":
        theta_n = scipy.linalg.solve_triangular(R, z)
        theta = theta_n / norms
        cert.update(solver="lstsq", status="optimal", duality_gap=0.0, certified=True, iterations=0)
        G = None
    elif constraint == "sos" and solver == "ipm":
        from .polynomial_sos import solve_sos

        theta, G, solver_info = solve_sos(R, z, norms, r, m, damping, eps, eps_gram, sig, p_pot,
                                          points=0.5 * (data.minus + data.plus) / sig[:, None],
                                          f_const=_compress.residual2)
        cert.update(solver_info)
    else:
        theta, G, solver_info = _solve_cvxpy(R, z, norms, r, m, damping, constraint, eps, eps_gram,
                                             sig, p_pot)
        cert.update(solver_info)
    if constraint != "none" and not cert["certified"]:
        msg = (f"the {constraint} polynomial fit is not certified ({cert['solver']}: duality gap "
               f"{cert['duality_gap']:.2e})")
        if strict:
            from ..errors import SolverFailedError
            raise SolverFailedError(msg)
        warnings.warn(msg + "; see the certificate", SolverWarning, stacklevel=2)
    # unscale: theta is in q~ = S^-1 q (see _design)
    pot_s = theta[:p_pot]
    div = np.concatenate([_monomial_scale(sig, monomials(r, d)) for d in (2, 3, 4)])
    potential = PolynomialPotential.from_coefficients(pot_s / div, r)
    k = p_pot
    C = None
    Si = np.diag(1.0 / sig)
    if damping:
        C = Si @ _sym_from_upper(theta[k:k + nu["C"]], r) @ Si
        k += nu["C"]
    B = Si @ theta[k:k + r * m].reshape(r, m) if m else None
    # residual of the unscaled relation
    res = data.D2 + 0.5 * (potential.gradient(data.minus) + potential.gradient(data.plus))
    if C is not None:
        res = res + C @ data.D1
    if B is not None:
        res = res - B @ data.Ubar
    cert.update(
        relative_residual=float(np.linalg.norm(res) / max(np.linalg.norm(data.D2), 1e-300)),
        min_eig_K=float(np.linalg.eigvalsh(potential.K).min()),
        min_eig_C=None if C is None else float(np.linalg.eigvalsh(C).min()),
        seconds=time.perf_counter() - t0, data_seconds=t_data)
    return PolynomialOperators(potential, C, B, cert, G)


def gram_maps(r: int):
    """Linear maps from the Gram matrix G ((r + s) x (r + s), s = C(r+1, 2)) of
    U = m^T G m, m = [q; z], z_(ij) = q_i q_j (i <= j), to the monomial coefficients of
    degree 2, 3, 4: coefficient = sum over entries (a, b) of G of G_ab [m_a m_b == monomial].

    Returns a list of three (p_d, (r + s)^2) sparse-like dense matrices acting on vec(G)."""
    t2 = monomials(r, 2)
    s = len(t2)
    factors = [(i,) for i in range(r)] + [tuple(t) for t in t2]
    index = {d: {tuple(t): j for j, t in enumerate(monomials(r, d))} for d in (2, 3, 4)}
    n = r + s
    maps = {d: np.zeros((len(index[d]), n * n)) for d in (2, 3, 4)}
    for a in range(n):
        for b in range(n):
            mono = tuple(sorted(factors[a] + factors[b]))
            d = len(mono)
            maps[d][index[d][mono], a * n + b] += 1.0
    return maps[2], maps[3], maps[4]


# Clarabel asked for more than its defaults (1e-8): the polynomial fits' optimal residual is
# often 1e-7 of ||z|| (exact probe data), below what the default gap tolerance resolves. It then
# usually stops "optimal_inaccurate" close to the optimum; the certificate reports the gap.
CLARABEL_OPTIONS = {"tol_gap_abs": 1e-13, "tol_gap_rel": 1e-13, "tol_feas": 1e-13,
                    "tol_ktratio": 1e-10, "max_iter": 400}


def _gram_factor(c: np.ndarray, r: int, cp) -> np.ndarray:
    """L with L L^T a PSD Gram matrix of the polynomial with coefficients c (degree 2-4, in
    the fit's balanced coordinates), floored at 1e-8 of its largest eigenvalue: the least
    squares fit of the Gram map to c with relative weights (|c_j| floored at 1e-3 max |c|).
    Falls back to the identity when Clarabel fails (the diagonal scaling of the caller's
    variables still applies through the data)."""
    M2, M3, M4 = gram_maps(r)
    Mall = np.vstack([M2, M3, M4])
    n = r + comb(r + 1, 2)
    G = cp.Variable((n, n), symmetric=True)
    w = 1.0 / np.maximum(np.abs(c), 1e-3 * np.abs(c).max() + 1e-300)
    prob = cp.Problem(cp.Minimize(cp.norm(cp.multiply(w, Mall @ cp.vec(G, order="C") - c))), [G >> 0])
    try:
        prob.solve(solver=cp.CLARABEL)
    except cp.error.SolverError:
        return np.eye(n)
    if G.value is None:
        return np.eye(n)
    ev, Q = np.linalg.eigh(0.5 * (G.value + G.value.T))
    ev = np.maximum(ev, 1e-8 * ev.max())
    return Q * np.sqrt(ev)


def _scaled_psd(cp, n, d):
    """A symmetric variable X = D Xh D (D = diag(d)): (Xh, X); X >= 0 <=> Xh >= 0."""
    Xh = cp.Variable((n, n), symmetric=True)
    return Xh, cp.multiply(np.outer(d, d), Xh)


def _potential_block(cp, constraint, r, norms, x_ls, p_pot, eps, eps_gram, sig):
    """The potential's monomial coefficients as cvxpy expressions (balanced units), their
    constraints, and the Gram matrix G ("sos") or the quartic P ("quartic") expression.

    Every unknown enters in column-normalised units x = norms * theta (O(1) for Clarabel); a
    PSD variable is scaled by a congruence: a diagonal one, D_a = norms[column of its diagonal
    monomial]^(-1/2), or for G by L with L L^T a Gram matrix of the unconstrained potential."""
    nK, n3, n4 = comb(r + 1, 2), comb(r + 2, 3), comb(r + 3, 4)
    t2 = monomials(r, 2)
    diag2 = {int(i): j for j, (i, k) in enumerate(t2) if i == k}
    dK = norms[[diag2[i] for i in range(r)]] ** -0.5
    if constraint == "sos":
        # G = L Gh L^T: the optimum then sits near Gh = I, well inside the cone. The diagonal
        # congruence alone left Clarabel at "Solved" 4 orders above the optimum (5e-3 vs 1e-7
        # relative residual on exact Galerkin data of the SVK cantilever).
        L = _gram_factor(x_ls[:p_pot] / norms[:p_pot], r, cp)
        Li = np.linalg.inv(L)
        Gh = cp.Variable((len(L), len(L)), symmetric=True)
        G = L @ Gh @ L.T
        vecG = cp.vec(G, order="C")
        pot = cp.hstack([M @ vecG for M in gram_maps(r)])
        return pot, [Gh >> eps_gram * (Li @ Li.T), 2 * G[:r, :r] >> eps * np.diag(sig**2)], G, None
    Kh, Kv = _scaled_psd(cp, r, dK)
    c2 = cp.hstack([(0.5 if i == k else 1.0) * Kv[i, k] for i, k in t2])
    c3 = cp.multiply(1.0 / norms[nK:nK + n3], cp.Variable(n3))
    cons, P = [Kh >> eps * np.diag(sig**2 * dK ** -2.0)], None
    if constraint == "quartic":
        idx4 = {tuple(t): j for j, t in enumerate(monomials(r, 4))}
        pair_col = [p_pot - n4 + idx4[tuple(sorted((i, i, k, k)))] for i, k in t2]
        Ph, P = _scaled_psd(cp, nK, norms[pair_col] ** -0.5)
        _, _, M4 = gram_maps(r)
        n = r + nK  # z^T (P/2) z: G22 = P / 2, the quartic block of the Gram map
        idx = (np.arange(r, n)[:, None] * n + np.arange(r, n)[None, :]).reshape(-1)
        c4 = 0.5 * (M4[:, idx] @ cp.vec(P, order="C"))
        cons.append(Ph >> 0)
    else:
        c4 = cp.multiply(1.0 / norms[nK + n3:p_pot], cp.Variable(n4))
    return cp.hstack([c2, c3, c4]), cons, None, P


def _damping_block(cp, constraint, r, norms, x_ls, p_pot, eps, sig):
    """C as a cvxpy expression (>= eps I), its balanced-unit part of x and its constraint:
    congruence-scaled by the unconstrained C for "sos", diagonally otherwise."""
    nC = comb(r + 1, 2)
    t2 = monomials(r, 2)
    if constraint == "sos":  # C = LC Chh LC^T, LC LC^T = the unconstrained C (floored)
        w, Qc = np.linalg.eigh(_sym_from_upper(x_ls[p_pot:p_pot + nC] / norms[p_pot:p_pot + nC], r))
        LC = Qc * np.sqrt(np.maximum(np.abs(w), 1e-6 * np.abs(w).max() + 1e-300))
        Chh = cp.Variable((r, r), symmetric=True)
        Cv = LC @ Chh @ LC.T
        con = Cv >> eps * np.diag(sig**2)
    else:
        diag2 = {int(i): j for j, (i, k) in enumerate(t2) if i == k}
        dC = norms[[p_pot + diag2[i] for i in range(r)]] ** -0.5
        Ch, Cv = _scaled_psd(cp, r, dC)
        con = Ch >> eps * np.diag(sig**2 * dC ** -2.0)
    part = cp.multiply(norms[p_pot:p_pot + nC], cp.hstack([Cv[i, j] for i, j in t2]))
    return part, Cv, con


def _clarabel(cp, prob) -> dict:
    """Solve ``prob`` with Clarabel (:data:`CLARABEL_OPTIONS`); its certificate."""
    from cvxpy.reductions.solvers.solver_inverse_data import SolverInverseData

    t0 = time.perf_counter()
    data, chain, inverse = prob.get_problem_data(cp.CLARABEL)
    raw = chain.solver.solve_via_data(data, False, False, dict(CLARABEL_OPTIONS))
    inverse[-1] = SolverInverseData(inverse[-1], solver_options={})
    prob.unpack_results(raw, chain, inverse)
    seconds = time.perf_counter() - t0
    if prob.status not in ("optimal", "optimal_inaccurate"):
        raise SolverFailedError(f"Clarabel failed on the polynomial L-OpInf problem: status {prob.status}")
    gap = abs(raw.obj_val - raw.obj_val_dual)
    if prob.status != "optimal" and gap > 1e-6 * max(abs(raw.obj_val), 1e-300) + 1e-10:
        warnings.warn(f"Clarabel returned {prob.status} with duality gap {gap:.2e}; see the "
                      "certificate", SolverWarning, stacklevel=4)
    # ||R x - z|| of the compressed problem is the excess over the unconstrained optimum's
    # residual (the QR's constant part is dropped), relative to ||z||
    rel = float(gap / max(abs(prob.value), abs(raw.obj_val_dual), 1e-300))
    return {"solver": "cvxpy-clarabel", "status": prob.status, "clarabel_status": str(raw.status),
            "iterations": int(raw.iterations), "primal_objective": float(raw.obj_val),
            "dual_objective": float(raw.obj_val_dual), "r_prim": float(raw.r_prim),
            "r_dual": float(raw.r_dual), "solve_seconds": seconds,
            # the objective is |R x - z| / |z|: its gap is relative to the data's scale |z|
            "duality_gap": float(gap), "relative_gap": rel, "certified": bool(gap <= 1e-8),
            "objective": float(prob.value), "excess_residual": float(prob.value)}


def _solve_cvxpy(R, z, norms, r, m, damping, constraint, eps, eps_gram, sig, p_pot):
    """min ||R x - z|| / ||z|| over the constrained potential, C and B (balanced units):
    (theta, Gram matrix or None, certificate)."""
    try:
        import cvxpy as cp
    except ImportError as exc:  # pragma: no cover
        raise ImportError("constrained polynomial fits need cvxpy and clarabel: "
                          "pip install cvxpy clarabel") from exc
    x_ls = scipy.linalg.solve_triangular(R, z)  # the unconstrained answer (normalised units)
    nC = comb(r + 1, 2) if damping else 0
    pot, cons, G, P = _potential_block(cp, constraint, r, norms, x_ls, p_pot, eps, eps_gram, sig)
    parts, Cv, Bv = [cp.multiply(norms[:p_pot], pot)], None, None
    if damping:
        part, Cv, con = _damping_block(cp, constraint, r, norms, x_ls, p_pot, eps, sig)
        parts.append(part)
        cons.append(con)
    if m:
        Bx = cp.Variable(r * m)
        Bv = cp.multiply(1.0 / norms[p_pot + nC:], Bx)
        parts.append(Bx)
    # the residual norm, a second-order cone (conditioned like R, not like R^T R)
    prob = cp.Problem(cp.Minimize(cp.norm(R @ cp.hstack(parts) - z, 2) / max(np.linalg.norm(z), 1e-300)),
                      cons)
    info = _clarabel(cp, prob)
    Gv = None
    if constraint == "sos":
        w, Q = np.linalg.eigh(0.5 * (G.value + G.value.T))
        info["min_eig_gram_raw"] = float(w.min())
        Gv = (Q * np.maximum(w, 0.0)) @ Q.T  # exactly PSD (up to rounding of this product)
        info["min_eig_gram"] = float(np.linalg.eigvalsh(Gv).min())
        pot_v = np.concatenate([M @ Gv.reshape(-1) for M in gram_maps(r)])
    else:
        pot_v = np.asarray(pot.value, float)
        if constraint == "quartic":
            info["min_eig_P"] = float(np.linalg.eigvalsh(0.5 * (P.value + P.value.T)).min())
    theta = [pot_v]
    if damping:
        Cs = 0.5 * (Cv.value + Cv.value.T)
        t2 = monomials(r, 2)
        theta.append(Cs[t2[:, 0], t2[:, 1]])
    if m:
        theta.append(np.asarray(Bv.value, float))
    return np.concatenate(theta), Gv, info


def fit_force(data, *, damping: bool = True, ridge: float = 1e-10):
    """Unconstrained polynomial OpInf: f(q) = A [q; z2(q); z3(q)] with free A (r x ...), free
    C and B, least squares on the same midpoint relation. Returns (PolynomialForce, C, B, cert)."""
    data = _concat(data)
    r, N = data.D2.shape
    m = 0 if data.Ubar is None else data.Ubar.shape[0]
    proto = PolynomialForce(np.zeros((r, r + comb(r + 1, 2) + comb(r + 2, 3))))
    P = proto.A.shape[1]
    t0 = time.perf_counter()
    sig = np.sqrt(np.mean(data.plus ** 2, axis=1))
    sig = np.where(sig > 0, sig, 1.0)
    A, b = _design(data, False, sig, force_features=proto.features)
    if damping:  # free damping C~ (r x r, not symmetric), appended after [force, B]
        blk = np.zeros((r, r * r, N))
        for l in range(r):
            blk[l, l * r:(l + 1) * r] = data.D1 / sig[:, None]
        A = np.hstack([A, blk.transpose(0, 2, 1).reshape(r * N, -1)])
    A, b = _natural_rows(A, b, sig, N)
    Rx, z, norms, cond, rank = _compress(A, b, ridge)
    x = scipy.linalg.solve_triangular(Rx, z) / norms
    Af = x[:r * P].reshape(r, P)
    k = r * P
    Si = np.diag(1.0 / sig)
    B = None
    if m:
        B = Si @ x[k:k + r * m].reshape(r, m)
        k += r * m
    C = Si @ x[k:k + r * r].reshape(r, r) @ Si if damping else None
    # f~_l(q~) = sig_l f_l(S q~): A~_lj = sig_l A_lj prod sig^alpha_j
    mono = np.concatenate([_monomial_scale(sig, t) for t in proto.tuples])
    Af = Af / sig[:, None] / mono[None, :]
    force = PolynomialForce(Af)
    res = data.D2 + 0.5 * (force.gradient(data.minus) + force.gradient(data.plus))
    if C is not None:
        res = res + C @ data.D1
    if B is not None:
        res = res - B @ data.Ubar
    cert = {"solver": "lstsq", "n_unknowns": int(x.size), "data_condition": cond, "data_rank": rank,
            "relative_residual": float(np.linalg.norm(res) / np.linalg.norm(data.D2)),
            "seconds": time.perf_counter() - t0}
    return force, C, B, cert


# -- the reduced integrator -----------------------------------------------------------------

_GAUSS = (0.5 - 0.5 / np.sqrt(3.0), 0.5 + 0.5 / np.sqrt(3.0))

_LAZY_THETA = 0.1  # simplified Newton: refresh the Jacobian when |delta_k| > this |delta_(k-1)|


def polynomial_tensors(model):
    """(K, F2, F3) with f(q) = K q + F2(q, q) + F3(q, q, q), F2 and F3 symmetric in their
    trailing indices, for a :class:`PolynomialPotential` (F2 = 3 T3, F3 = 4 T4) or a
    :class:`PolynomialForce`; None for any other model (the compiled loop needs them)."""
    if isinstance(model, PolynomialPotential):
        return model.K.copy(), 3.0 * model.T3, 4.0 * model.T4
    if isinstance(model, PolynomialForce):
        r = model.r
        t1, t2, t3 = model.tuples
        n1, n2 = len(t1), len(t2)
        K = model.A[:, :n1]  # the degree-1 monomials are q_0 .. q_(r-1), in order
        F2 = np.stack([_symmetric_tensor(model.A[i, n1:n1 + n2], t2, r) for i in range(r)])
        F3 = np.stack([_symmetric_tensor(model.A[i, n1 + n2:], t3, r) for i in range(r)])
        return np.ascontiguousarray(K), F2, F3
    return None


class PolynomialROM:
    """qh_tt + C qh_t + f(qh) = B u, integrated by the midpoint VI or the AVF discrete gradient.

    Args:
        model: a :class:`PolynomialPotential` (f = grad U) or :class:`PolynomialForce`, or any
            object with ``r`` and ``force_and_jacobian(q) -> (f, J)`` (e.g. the FOM-assembled
            Galerkin force of :mod:`dolfinx_lopinf.fem.galerkin_nonlinear`; numpy loop only).
        C: (r, r) damping or None.  B: (r, m) input matrix or None.
    """

    def __init__(self, model, C=None, B=None):
        if not hasattr(model, "force_and_jacobian"):
            raise InputError("model must be a PolynomialPotential, a PolynomialForce or have "
                             f"force_and_jacobian(q); got {type(model).__name__}")
        self.model = model
        self.r = model.r
        self.C = None if C is None else as_real_array(C, "C")
        self.B = None if B is None else as_real_array(B, "B")
        for name, A, shape in (("C", self.C, (self.r, self.r)),):
            if A is not None and A.shape != shape:
                raise InputError(f"{name} must be {shape}, got {A.shape}")
        if self.B is not None and (self.B.ndim != 2 or self.B.shape[0] != self.r):
            raise InputError(f"B must be (r = {self.r}, m), got {self.B.shape}")
        for name, A in (("C", self.C), ("B", self.B)):
            if A is not None and not np.all(np.isfinite(A)):
                raise InputError(f"{name} contains NaN or inf; an operator must be finite (did "
                                 "its fit fail?)")
        if self.C is not None:
            from .rom import _structure_problems

            problems = _structure_problems("C", self.C)
            if problems:
                warnings.warn("; ".join(problems) + ": this damping is not dissipative - the "
                              "model's energy can grow", NonLagrangianWarning, stacklevel=2)
        self._tensors = None

    def energy(self, Q, P):
        if not hasattr(self.model, "value"):
            return None
        return 0.5 * np.sum(P * P, axis=0) + self.model.value(Q)

    def simulate(self, q0, v0, dt: float, n_steps: int, *, inputs=None, every: int = 1,
                 backend: str = "auto", on_failure: str = "raise", scheme="midpoint",
                 tol: float = 1e-13, max_iter: int = 50, blowup: float = 1e8,
                 atol: float = 0.0, jacobian: str = "fresh", inputs_mid=None):
        """Integrate n_steps from (q0, v0) - the contract of every ROM's ``simulate``
        (:class:`~dolfinx_lopinf.core.rom.Trajectory`).

        Each step solves, for d = q1 - q0 (reduced Newton until the residual is below ``tol``
        times the size of its terms)::

            d/dt + C d/2 + dt/2 g(q0, q1) = p0 + dt/2 B u_{k+1/2},
            p1 = d/dt - C d/2 - dt/2 g(q0, q1) + dt/2 B u_{k+1/2},

        with g = f((q0+q1)/2) (midpoint) or the two-point Gauss average of f on [q0, q1] (AVF).
        A Newton correction below NEWTON_STALL (16 eps) times the state also ends the
        iteration (full Newton, both loops): the residual test alone, at tol = 1e-13, let the
        force's rounding decide whether a step converged. ``atol`` (default 0) is added to the
        stopping test, ``|R| <= tol size + atol``: the rounding floor of a force that is not
        evaluated to machine precision relative to its own size (a DOLFINx-assembled force
        near rest sums cell terms that cancel).

        Args:
            inputs: for a forced model, u(t) -> (m,) (evaluated at the step midpoints), an
                (m, n_steps) array at the midpoints or an (m, n_steps + 1) array at
                t_0 .. t_n (averaged to the midpoints); None: the free response.
                (``inputs_mid``: the former name of the midpoint array.)
            every: keep every ``every``-th step.
            on_failure: a step whose Newton iteration fails, or a state beyond ``blowup``
                times the initial scale: ``"raise"`` (default) a
                :class:`~dolfinx_lopinf.errors.StepFailedError` naming the step; ``"stop"``:
                the trajectory up to it, NaN after (``trajectory.stable`` False).
            jacobian: ``"fresh"`` (Newton) or ``"lazy"`` (simplified Newton, numpy loop only:
                the last factorised Newton matrix is kept, across steps too, and formed afresh
                when convergence slows, ``|delta_k| > 0.1 |delta_(k-1)|``; it pays when the
                Jacobian costs far more than the force, e.g. the FOM-assembled Galerkin force).
            backend: ``"numpy"`` (the reference loop, any model), ``"numba"`` (the compiled
                loop for a :class:`PolynomialPotential` or :class:`PolynomialForce`, equal to
                rounding) or ``"auto"``. Compilation happens before the timer.

        Returns:
            :class:`~dolfinx_lopinf.core.rom.Trajectory` (Vh: the momenta p = qh_t, the
            reduced mass being I); ``info``: ``newton_iterations``, ``jacobians``,
            ``energy`` (``1/2 |p|^2 + U(q)`` per stored column, when the model has a potential).
        """
        from .rom import Trajectory, _check_on_failure, _initial_state

        _check_on_failure(on_failure)
        if scheme not in SCHEMES:
            raise InputError(f"scheme must be one of {SCHEMES}, got {scheme!r}")
        dt = check_positive(dt, "dt")
        if isinstance(n_steps, bool) or int(n_steps) != n_steps or n_steps < 0:
            raise InputError(f"n_steps must be a non-negative integer, got {n_steps!r}")
        if isinstance(every, bool) or int(every) != every or every < 1:
            raise InputError(f"every must be a positive integer, got {every!r}")
        try:
            atol = float(atol)
        except (TypeError, ValueError):
            atol = float("nan")
        if not (np.isfinite(atol) and atol >= 0):
            raise InputError(f"atol must be a finite number >= 0, got {atol!r}")
        if inputs_mid is not None:
            if inputs is not None:
                raise InputError("give inputs or inputs_mid (its former name), not both")
            inputs = inputs_mid
        r = self.r
        q, p = (np.array(a) for a in _initial_state(q0, v0, r))
        n_steps = int(n_steps)
        BU = self._midpoint_forcing(inputs, dt, n_steps)
        if jacobian not in ("fresh", "lazy"):
            raise InputError(f"jacobian must be 'fresh' or 'lazy', got {jacobian!r}")
        lazy = jacobian == "lazy"
        backend = self._backend(backend, lazy)
        Qs = np.full((r, n_steps + 1), np.nan)
        Ps = np.full((r, n_steps + 1), np.nan)
        Qs[:, 0], Ps[:, 0] = q, p
        Cm = np.zeros((r, r)) if self.C is None else self.C
        A0 = np.eye(r) / dt + 0.5 * Cm
        limit = blowup * max(np.abs(q).max(), np.abs(p).max() * dt, 1e-300) + blowup
        run = self._run_numba if backend == "numba" else self._run_numpy
        t0 = time.perf_counter()
        iters, n_jac, stable = run(q, p, dt, n_steps, BU, A0, Cm, scheme,
                                   float(tol), atol, int(max_iter), float(limit), Qs, Ps, lazy)
        seconds = time.perf_counter() - t0
        info = {"newton_iterations": iters, "jacobians": n_jac}
        if not stable:
            k = int(np.argmax(~np.all(np.isfinite(Qs), axis=0)))
            message = (f"the reduced step {k} (t = {k * dt:.6g}) failed: Newton did not "
                       f"converge in {max_iter} iterations or the state grew beyond {blowup:g} "
                       "times its initial scale; try a smaller dt")
            if on_failure == "raise":
                raise StepFailedError(message, step=k)
            info["failure"] = message
        Qs, Ps = Qs[:, ::every], Ps[:, ::every]
        info["energy"] = self.energy(Qs, Ps)
        return Trajectory(dt * every * np.arange(Qs.shape[1]), Qs, Ps, None, seconds, backend,
                          info)

    def _midpoint_forcing(self, inputs, dt, n_steps):
        """B u at the step midpoints (r, n_steps), or None (unforced / the free response)."""
        if self.B is None:
            if inputs is not None:
                raise InputError("this ROM has no input operator B (it is unforced); do not "
                                 "pass inputs")
            return None
        if inputs is None:
            return None
        m = self.B.shape[1]
        if callable(inputs):
            U = np.column_stack([np.atleast_1d(np.asarray(inputs(dt * (k + 0.5)), dtype=float))
                                 for k in range(n_steps)]) if n_steps else np.zeros((m, 0))
        else:
            U = as_real_array(inputs, "inputs")
            U = U.reshape(1, -1) if U.ndim == 1 else U
            if U.shape == (m, n_steps + 1):
                U = 0.5 * (U[:, 1:] + U[:, :-1])
        if U.shape != (m, n_steps):
            raise InputError(f"inputs must be (m = {m}, n_steps = {n_steps}) at the step midpoints "
                             f"or (m, n_steps + 1) at t_0 .. t_n, or a callable, got {U.shape}")
        if not np.all(np.isfinite(U)):
            raise InputError("inputs contain NaN or inf; the forcing must be finite")
        return self.B @ U

    def _backend(self, requested, lazy) -> str:
        """The loop that runs: numba when asked for (or "auto" and available) and the model is
        polynomial and the Jacobian fresh; numpy otherwise (a named error when "numba" was
        asked for explicitly and cannot run). Compiles the kernels outside any timer."""
        from . import compiled

        backend = compiled.resolve_backend(requested)
        if backend == "numba" and lazy:
            if requested == "numba":
                raise InputError("jacobian='lazy' runs in the numpy loop only (the compiled loop's "
                                 "polynomial Jacobian is cheap); pass backend='auto' or 'numpy'")
            return "numpy"
        if backend == "numba":
            if self._tensors is None:
                self._tensors = polynomial_tensors(self.model)
            if self._tensors is None:
                if requested == "numba":
                    raise InputError("backend='numba' compiles the polynomial ROM for a "
                                     "PolynomialPotential or PolynomialForce; this model is a "
                                     f"{type(self.model).__name__} - pass backend='auto' or 'numpy'")
                return "numpy"
            compiled.polynomial_kernels()  # compile / load from the cache outside the timer
        return backend

    def _run_numba(self, q, p, dt, n_steps, BU, A0, Cm, scheme, tol, atol, max_iter, limit, Qs,
                   Ps, lazy):
        """The compiled loop (same residual, update and stopping tests as :meth:`_run_numpy`)."""
        from . import compiled

        K, F2, F3 = self._tensors
        BUT = np.ascontiguousarray(BU.T) if BU is not None else np.empty((0, self.r))
        stats = np.zeros(3, dtype=np.int64)
        c = np.ascontiguousarray
        compiled.polynomial_kernels()["_poly_run"](
            c(K), c(F2), c(F3), c(A0), c(Cm, dtype=float), BUT, q, p, dt, n_steps,
            scheme == "avf", tol, atol, max_iter, limit, Qs, Ps, stats)
        if stats[2] < 0:
            raise np.linalg.LinAlgError(f"Singular matrix (the reduced Newton matrix at step "
                                        f"{int(stats[0]) + 1})")
        return int(stats[1]), int(stats[1]), bool(stats[2] == 1)

    def _scheme_force(self, q, d, scheme, fresh):
        """g(q0, q1 = q0 + d) of the scheme and (when ``fresh``) its Jacobian in d."""
        fj = self.model.force_and_jacobian
        if scheme == "midpoint":
            if fresh:
                g, J = fj(q + 0.5 * d)
                return g, 0.5 * J
            return self._force_only(q + 0.5 * d), None
        if fresh:
            g1, J1 = fj(q + _GAUSS[0] * d)
            g2, J2 = fj(q + _GAUSS[1] * d)
            return 0.5 * (g1 + g2), 0.5 * (_GAUSS[0] * J1 + _GAUSS[1] * J2)
        return 0.5 * (self._force_only(q + _GAUSS[0] * d) + self._force_only(q + _GAUSS[1] * d)), None

    def _force_only(self, x):
        f_only = getattr(self.model, "force", None) or getattr(self.model, "gradient", None)
        return f_only(x) if f_only is not None else self.model.force_and_jacobian(x)[0]

    def _run_numpy(self, q, p, dt, n_steps, BU, A0, Cm, scheme, tol, atol, max_iter, limit, Qs,
                   Ps, lazy):
        """The reference loop; returns (Newton iterations, Jacobians formed, stable)."""
        iters, n_jac = 0, 0
        lu, need_j = None, True
        d = dt * p
        for k in range(n_steps):
            half_input = 0.5 * dt * BU[:, k] if BU is not None else 0.0
            rhs = p + half_input
            ok, prev = False, np.inf
            for _ in range(max_iter):
                fresh = not lazy or need_j or lu is None
                g, J = self._scheme_force(q, d, scheme, fresh)
                Ad = A0 @ d
                R = Ad + 0.5 * dt * g - rhs
                size = np.abs(Ad).max() + 0.5 * dt * np.abs(g).max() + np.abs(rhs).max()
                if not np.all(np.isfinite(R)):
                    break
                if np.abs(R).max() <= tol * max(size, 1e-300) + atol:
                    ok = True
                    break
                iters += 1
                if not lazy:
                    n_jac += 1
                    delta = np.linalg.solve(A0 + 0.5 * dt * J, R)
                    d = d - delta
                    if np.abs(delta).max() <= NEWTON_STALL * max(np.abs(q).max(), np.abs(d).max()):
                        ok = True  # the correction is below the state's rounding: converged
                        break
                    continue
                if fresh:
                    n_jac += 1
                    lu = scipy.linalg.lu_factor(A0 + 0.5 * dt * J)
                    need_j = False
                delta = scipy.linalg.lu_solve(lu, R)
                d = d - delta
                step = np.abs(delta).max()
                if step > _LAZY_THETA * prev:
                    need_j = True  # convergence slowed: a fresh Jacobian at the next iterate
                prev = step
            q1 = q + d
            if not ok or not np.all(np.isfinite(q1)) or np.abs(q1).max() > limit:
                return iters, n_jac, False
            p = d / dt - 0.5 * Cm @ d - 0.5 * dt * g + half_input
            q = q1
            Qs[:, k + 1], Ps[:, k + 1] = q, p
        return iters, n_jac, True
