"""Proper orthogonal decomposition bases, projection and (partial) reconstruction.

POD: V_r = the r leading left singular vectors of the snapshot matrix Q (n, K), so
V_r^T V_r = I and ||Q - V_r V_r^T Q||_F^2 = sum_{i>r} sigma_i^2 is minimal.
Weighted (e.g. mass-orthonormal) POD: with an SPD weight W = R^T R, V = R^{-1} U_r where U_r
are the leading left singular vectors of R Q, so V^T W V = I and projection is qh = V^T W q.
R is never formed (W may be a large sparse mass matrix): with the thin QR Q = Q_1 R_1 and the
Cholesky factor Q_1^T W Q_1 = L L^T, R Q = Z L^T R_1 with Z orthonormal, so the SVD of the small
L^T R_1 = U s X^T gives s and V = Q_1 L^-T U; :func:`leading_svd` does the same in a subspace.
With W = M (the FOM mass matrix, or the L2 Gram matrix of the space for a uniform density) the
reduced mass is exactly I and the projection is the Galerkin one, so the truncated modes leave
no mass term in the reduced dynamics - on user recordings 3-30x closer to the projection floor
than the Euclidean POD.
Block-diagonal POD: for a state made of blocks (beam deflection w and rotation theta),
V = diag(V_w, V_theta) with each block's own POD, so every reduced coordinate stays in one
physical block.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._checks import (as_real_array, check_blocks, check_finite, check_int, check_matrix,
                      check_weight, fro_norm)
from ..errors import InputError


@dataclass(frozen=True)
class Basis:
    """An orthonormal reduced basis.

    Attributes:
        V: (n, r) basis matrix with orthonormal columns.
        singular_values: name -> the singular values of that block's snapshots (for
            energy/decay plots): all of them from :func:`pod`, the leading ones from
            :func:`dolfinx_lopinf.fit` on large data (:func:`leading_svd`); a plain POD has
            the single block ``"all"``.
        blocks: name -> (row indices of the full state, column indices of V).
        weight: (n, n) SPD inner-product matrix W (V^T W V = I; dense or ``scipy.sparse``),
            or None for Euclidean.
        dual: (n, r) W V, what :meth:`project` applies where W itself is not kept (a model
            loaded from a file stores W V, not the n x n W); None otherwise.
    """

    V: np.ndarray
    singular_values: dict
    blocks: dict
    weight: np.ndarray | None = None
    dual: np.ndarray | None = None

    @property
    def n(self) -> int:
        return self.V.shape[0]

    @property
    def r(self) -> int:
        return self.V.shape[1]

    def projector(self) -> np.ndarray:
        """The (r, n) matrix P of :meth:`project` (Qh = P Q): V^T W, W V as stored for a
        loaded weighted basis, or V^T for a Euclidean one - formed once, for callers that
        project many arrays (the fits)."""
        if self.weight is not None:
            return np.asarray((self.weight @ self.V).T)
        if self.dual is not None:
            return self.dual.T
        return self.V.T

    def saved_dual(self) -> np.ndarray | None:
        """(n, r) W V for a model file (the projection of a weighted basis without the n x n
        W: :attr:`dual`), None for a Euclidean basis (V itself projects)."""
        if self.weight is None and self.dual is None:
            return None
        return np.ascontiguousarray(self.projector().T)

    def project(self, Q: np.ndarray) -> np.ndarray:
        """Reduced coordinates Qh = V^T W Q (W = I for Euclidean POD), (r, K) from (n, K)."""
        Q = as_real_array(Q, "Q")
        if Q.ndim not in (1, 2) or Q.shape[0] != self.n:
            raise InputError(f"Q must be (n,) or (n, K) with n = {self.n} (the basis' rows), got "
                             f"shape {Q.shape}")
        check_finite(Q, "Q")
        if self.weight is None and self.dual is not None:
            return self.dual.T @ Q
        return self.V.T @ (Q if self.weight is None else self.weight @ Q)

    def reconstruct(self, Qh: np.ndarray, rows=None) -> np.ndarray:
        """Full (or partial) states V[rows] Qh.

        Args:
            Qh: (r, K) or (r,) reduced coordinates.
            rows: optional row indices (e.g. the dofs of a point, a line or a surface);
                only those rows are formed, at cost O(len(rows) r K).
        """
        Qh = as_real_array(Qh, "Qh")
        if Qh.ndim not in (1, 2) or Qh.shape[0] != self.r:
            raise InputError(f"Qh must be (r,) or (r, K) with r = {self.r}, got shape {Qh.shape}")
        # non-finite Qh (a ROM that blew up) reconstruct to non-finite states: a result
        if rows is not None:
            rows = np.asarray(rows)
            if rows.dtype.kind not in "iu" or rows.ndim > 1:
                raise InputError(f"rows must be integer row indices, got {rows.dtype} of shape "
                                 f"{rows.shape}")
            if rows.size and (rows.min() < -self.n or rows.max() >= self.n):
                raise InputError(f"rows index outside 0..{self.n - 1}: min {rows.min()}, max "
                                 f"{rows.max()}")
        V = self.V if rows is None else self.V[rows]
        return V @ Qh

    def projection_error(self, Q: np.ndarray) -> float:
        """||Q - V project(Q)||_F / ||Q||_F, measured in the Euclidean norm of the state
        whatever the basis' weight: for a Euclidean basis the floor no ROM in it can go
        below; for a weighted one the error of its W-orthogonal projection, which a ROM can
        undercut slightly in this norm (it is the floor in the W norm). The norms are scaled
        first, so data of any finite magnitude (1e-170 .. 1e160) give the same ratio."""
        Qh = self.project(Q)
        Q = as_real_array(Q, "Q")
        denom = fro_norm(Q)
        if denom == 0:
            raise InputError("Q is identically zero; its relative projection error is undefined")
        return fro_norm(Q - self.V @ Qh) / denom

    def truncate(self, r: int) -> "Basis":
        """The same kind of basis with fewer columns (r split evenly over the blocks)."""
        r = check_int(r, "r", 1)
        sizes = _split(r, list(self.blocks))
        cols, new_blocks, start = [], {}, 0
        for (name, (rows, bcols)), size in zip(self.blocks.items(), sizes):
            if size > len(bcols):
                raise InputError(f"block {name!r} has only {len(bcols)} basis vectors, asked {size}")
            cols.extend(bcols[:size])
            new_blocks[name] = (rows, np.arange(start, start + size))
            start += size
        dual = None if self.dual is None else self.dual[:, cols]  # W V's columns, as V's
        return Basis(self.V[:, cols], self.singular_values, new_blocks, self.weight, dual)


def _split(r: int, names: list) -> list[int]:
    if r < len(names) or r % len(names):
        raise InputError(
            f"r = {r} must be a positive multiple of the number of blocks ({len(names)}: "
            f"{', '.join(map(str, names))}) so each block gets r / {len(names)} vectors"
        )
    return [r // len(names)] * len(names)


def pod(Q: np.ndarray, r: int, blocks: dict | None = None, rank_rtol: float = 1e-12,
        weight: np.ndarray | None = None) -> Basis:
    """POD basis of Q, block-diagonal when ``blocks`` is given.

    Args:
        Q: (n, K) snapshots (for the augmented sine-Gordon basis pass ``np.hstack([Q, F])``).
        r: total reduced dimension; with blocks, each of the b blocks gets r / b vectors.
        blocks: optional name -> row indices; rows not in any block get no basis vectors.
        rank_rtol: singular values below ``rank_rtol * sigma_max`` count as zero; asking for
            more vectors than the numerical rank is an error (they would be noise).
        weight: optional SPD (n, n) inner-product matrix (dense or ``scipy.sparse``), e.g.
            the mass matrix in state coordinates (``Snapshots.weight``): the basis is then
            W-orthonormal (not with ``blocks``).

    Returns:
        A :class:`Basis` with ``V`` (n, r).

    Example:
        >>> Q = np.random.default_rng(0).standard_normal((50, 30))
        >>> basis = pod(Q, 4, blocks={"a": np.arange(25), "b": np.arange(25, 50)})
        >>> basis.V.shape, bool(np.allclose(basis.V.T @ basis.V, np.eye(4)))
        ((50, 4), True)
    """
    Q = check_matrix(Q, "Q")
    if isinstance(r, (bool, np.bool_)) or not isinstance(r, (int, np.integer)) or r < 1:
        raise InputError(f"r must be a positive integer, got {r!r}")
    r = int(r)
    if not (isinstance(rank_rtol, (int, float, np.integer, np.floating)) and 0 <= rank_rtol < 1):
        raise InputError(f"rank_rtol must be a number in [0, 1), got {rank_rtol!r}")
    if weight is not None:
        if blocks:
            raise InputError("a weighted POD mixes blocks; pass either blocks or weight")
        return _weighted_pod(Q, r, check_weight(weight, Q.shape[0]), rank_rtol)
    blocks = check_blocks(blocks, Q.shape[0])
    if not blocks:
        U, s, _ = np.linalg.svd(Q, full_matrices=False)
        return from_svd(U, s, r, rank_rtol)
    sizes = _split(r, list(blocks))
    V = np.zeros((Q.shape[0], r))
    singular_values, out_blocks, start = {}, {}, 0
    for (name, rows), size in zip(blocks.items(), sizes):
        rows = np.asarray(rows)
        U, s, _ = np.linalg.svd(Q[rows], full_matrices=False)
        rank = int((s > rank_rtol * s[0]).sum()) if s.size and s[0] > 0 else 0
        if size > rank:
            raise InputError(
                f"block {name!r}: asked for {size} basis vectors but the snapshots have "
                f"numerical rank {rank} (singular values {_few(s[: rank + 2])}); lower r or record "
                "richer data"
            )
        V[rows, start : start + size] = U[:, :size]
        singular_values[name] = s
        out_blocks[name] = (rows, np.arange(start, start + size))
        start += size
    return Basis(V, singular_values, out_blocks)


def _few(s, k: int = 6) -> str:
    """At most k singular values around the rank, as text (not hundreds of them)."""
    s = np.asarray(s)
    if len(s) <= k:
        return np.array2string(s, precision=3)
    return (np.array2string(s[:2], precision=3)[:-1] + " ... "
            + np.array2string(s[-(k - 2):], precision=3)[1:])


def leading_svd(Q: np.ndarray, k: int, *, power: int = 3, seed: int = 0, weight=None):
    """(U, s): the k leading left singular vectors (n, k) and values of Q (n, K), by block
    subspace iteration from a seeded Gaussian start - Y = orth(Q Z), then ``power`` times
    Z = orth(Q^T Y), Y = orth(Q Z) - and a Rayleigh-Ritz step, the SVD of the k x K matrix
    Y^T Q. Each orthonormalisation keeps the small directions from drowning in the large
    ones, so s is exact to rounding (~1e-15 s_1) and the vectors are as accurate as the
    data's rounding determines them (the thin SVD of the same data perturbed by 2e-16
    moves them as much). Cost ~(4 power + 3) n K k flops against a full thin SVD's ~10 n K
    min(n, K): lo.fit needs only the leading modes. Deterministic: the same start every call.

    With an SPD ``weight`` W (checked by the caller) the same in the W inner product: orth
    makes Y W-orthonormal (a Euclidean QR, then the Cholesky factor of the well-conditioned
    Y^T W Y), Z = orth(Q^T W Y), and the Ritz step is the SVD of Y^T W Q; U is W-orthonormal
    and s are the singular values of R Q (W = R^T R)."""
    n, K = Q.shape
    k = max(1, min(int(k), n, K))
    Z = np.random.default_rng(seed).standard_normal((K, k))
    if weight is None:
        Y = np.linalg.qr(Q @ Z)[0]
        for _ in range(power):
            Z = np.linalg.qr(Q.T @ Y)[0]
            Y = np.linalg.qr(Q @ Z)[0]
        Ub, s, _ = np.linalg.svd(Y.T @ Q, full_matrices=False)
        return Y @ Ub, s
    Y = _w_orth(Q @ Z, weight)
    for _ in range(power):
        Z = np.linalg.qr(Q.T @ (weight @ Y))[0]
        Y = _w_orth(Q @ Z, weight)
    Ub, s, _ = np.linalg.svd((weight @ Y).T @ Q, full_matrices=False)
    return Y @ Ub, s


def _w_orth(Y, W):
    """A W-orthonormal basis of span(Y): Y = Q_1 R_1 (Euclidean QR), Q_1^T W Q_1 = L L^T,
    Q_1 L^-T (Q_1^T W Q_1 has the condition of W at most, so the Cholesky QR is stable)."""
    import scipy.linalg

    Y = np.linalg.qr(Y)[0]
    L = _span_cholesky(Y, W)
    return scipy.linalg.solve_triangular(L, Y.T, lower=True).T


def _span_cholesky(Y, W):
    """Lower Cholesky factor of Y^T W Y, or an InputError: W is not positive definite on the
    span of the snapshots."""
    import scipy.linalg

    S = Y.T @ (W @ Y)
    try:
        return scipy.linalg.cholesky(0.5 * (S + S.T), lower=True)
    except np.linalg.LinAlgError:
        raise InputError("weight is not positive definite on the snapshots' span (Y^T W Y has "
                         "no Cholesky factor); pass an SPD inner-product matrix such as the "
                         "mass matrix") from None


def from_svd(U, s, r: int, rank_rtol: float = 1e-12, weight=None) -> Basis:
    """The POD basis of r vectors from a thin SVD Q = U diag(s) X^T already computed (so a
    caller that needs more modes, e.g. to identify the time integrator, pays one SVD); with
    ``weight`` W, U is W-orthonormal (the SVD of R Q, W = R^T R: :func:`leading_svd`)."""
    rank = int((s > rank_rtol * s[0]).sum()) if s.size and s[0] > 0 else 0
    if r > rank:
        raise InputError(
            f"block 'all': asked for {r} basis vectors but the snapshots have numerical rank "
            f"{rank} (singular values {_few(s[: rank + 2])}); lower r or record richer data")
    return Basis(U[:, :r].copy(), {"all": s}, {"all": (np.arange(U.shape[0]), np.arange(r))},
                 weight)


def weighted_svd(Q: np.ndarray, W):
    """(U, s): the thin SVD of R Q in the W inner product (W = R^T R SPD, checked by the
    caller) - U (n, min(n, K)) W-orthonormal - without forming R (module docstring): the QR
    of Q, the Cholesky factor of Q_1^T W Q_1 and the SVD of L^T R_1, O(n K^2 + nnz(W) K)."""
    import scipy.linalg

    Q1, R1 = np.linalg.qr(Q)
    L = _span_cholesky(Q1, W)
    U, s, _ = np.linalg.svd(L.T @ R1, full_matrices=False)
    return Q1 @ scipy.linalg.solve_triangular(L.T, U, lower=False), s


def _weighted_pod(Q, r, W, rank_rtol):
    U, s = weighted_svd(Q, W)
    rank = int((s > rank_rtol * s[0]).sum()) if s.size and s[0] > 0 else 0
    if r > rank:
        raise InputError(f"asked for {r} basis vectors but the snapshots have numerical rank "
                         f"{rank} in the weighted inner product (singular values "
                         f"{_few(s[: rank + 2])}); lower r or record richer data")
    return Basis(U[:, :r].copy(), {"all": s}, {"all": (np.arange(Q.shape[0]), np.arange(r))}, W)
