"""The reduced potential U(q) and force models of polynomial L-OpInf (numpy only).

For St. Venant-Kirchhoff (SVK) elasticity the potential energy is a quartic polynomial of the
displacement, so on a linear basis q -> V q the reduced potential is *exactly*

    U(q) = 1/2 q^T K q + U3(q) + U4(q),    U3 = sum_|a|=3 c_a q^a,   U4 = sum_|b|=4 d_b q^b,

and the reduced internal force is its gradient. :class:`PolynomialPotential` holds K and the
symmetric tensors of U3, U4 (unknowns: the monomial coefficients of degree 2, 3, 4,
C(r+1,2) + C(r+2,3) + C(r+3,4) of them, :func:`monomials`, :func:`n_unknowns`).
:func:`gram_maps` maps a Gram matrix G of U(q) = m^T G m (m = [q; z], z = vech(q q^T)) to those
coefficients - the sum-of-squares form of the fit's default constraint.
:class:`PolynomialForce` is the unconstrained baseline (independent polynomial force
coefficients, no potential); :func:`polynomial_tensors` gives either as the (K, F2, F3) the
compiled ROM loop takes.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from math import comb

import numpy as np

from ...errors import InputError


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
