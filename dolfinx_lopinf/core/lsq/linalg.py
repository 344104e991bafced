"""The numerics every strategy shares, each written once: the residual and the quadratic
objective, eigen-reassembly and the PSD projection, the Jacobi-equilibrated SPD solve, the
vech index tables and the normal equations in the vech unknowns."""

from __future__ import annotations

import functools
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import scipy.linalg


def residual_norm2(theta: np.ndarray, L: np.ndarray, Z: np.ndarray) -> float:
    """The objective ||Theta L + Z||_F^2 of the compressed problem."""
    return float(np.sum((theta @ L + Z) ** 2))


def quadratic(H: np.ndarray, h: np.ndarray, c: float, x: np.ndarray) -> float:
    """The same objective in vech unknowns: x^T H x + 2 h^T x + c."""
    return float(x @ (H @ x) + 2.0 * h @ x + c)


def sym(A: np.ndarray) -> np.ndarray:
    """Symmetric part of a matrix or a stack of matrices."""
    return 0.5 * (A + np.swapaxes(A, -1, -2))


def from_eig(w: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Q diag(w) Q^T, for one matrix or a stack."""
    return (Q * w[..., None, :]) @ np.swapaxes(Q, -1, -2)


def psd_project(A: np.ndarray, floor: float):
    """Frobenius projection of sym(A) onto {S = S^T, S >= floor I} (batched): (S, w, Q) with
    sym(A) = Q diag(w) Q^T."""
    w, Q = np.linalg.eigh(sym(A))
    return from_eig(np.maximum(w, floor), Q), w, Q


def cholesky_solve(c: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x with L L^T x = b for the lower Cholesky factor L in ``c`` (its upper triangle is not
    read) and one right-hand side: two triangular solves (``dtrsv``). OpenBLAS's ``dpotrs``
    goes through the blocked ``trsm``, much slower for a single vector. A float32 factor (the interior point's mixed precision) solves
    with ``b`` rounded to float32 (``strsv``) and returns float64."""
    if c.dtype == np.float32:
        y = scipy.linalg.blas.strsv(c, b.astype(np.float32), lower=1)
        return scipy.linalg.blas.strsv(c, y, lower=1, trans=1, overwrite_x=1).astype(float)
    y = scipy.linalg.blas.dtrsv(c, b, lower=1)
    return scipy.linalg.blas.dtrsv(c, y, lower=1, trans=1, overwrite_x=1)


_SCRATCH: OrderedDict = OrderedDict()  # (shape, dtype) -> free arrays
_SCRATCH_LOCK = threading.Lock()


def lease(shape, dtype=np.float64) -> np.ndarray:
    """An uninitialised array (float64 unless ``dtype``) for a temporary that does not
    outlive its caller (give it back with :func:`release`). A fresh n x n array costs a page
    fault per 4 kB on first touch - for the 420 x 420 matrices of an r = 20 fit about as much
    as their Cholesky - so the large temporaries of the interior point are reused between fits."""
    key = (tuple(shape), np.dtype(dtype))
    with _SCRATCH_LOCK:
        free = _SCRATCH.get(key)
        if free:
            return free.pop()
    return np.empty(shape, dtype=dtype)


def release(*arrays: np.ndarray) -> None:
    """Give leased arrays back (a few per shape and dtype, for the four most recent ones)."""
    with _SCRATCH_LOCK:
        for a in arrays:
            key = (a.shape, a.dtype)
            free = _SCRATCH.setdefault(key, [])
            _SCRATCH.move_to_end(key)
            if len(free) < 4:
                free.append(a)
        while len(_SCRATCH) > 4:
            _SCRATCH.popitem(last=False)


class SPDSolver:
    """Jacobi-equilibrated Cholesky of an SPD matrix H (the K and C unknowns multiply data of
    very different size), reused for every solve; ``ok`` is False when H is singular (then
    ``solve`` is least squares)."""

    def __init__(self, H: np.ndarray):
        self.d = np.sqrt(np.maximum(np.diag(H), 1e-300))
        dd = np.outer(self.d, self.d, out=lease(H.shape))
        self._buf = Hs = np.divide(H, dd, out=lease(H.shape))  # given back by __del__
        release(dd)
        # lower Cholesky of the F-ordered view of the symmetric Hs, in place (no copy, faster
        # than upper): its lower triangle (the upper one of Hs) becomes the factor
        self.c, status = scipy.linalg.lapack.dpotrf(Hs.T, lower=1, clean=0, overwrite_a=1)
        self.ok = status == 0
        self._H = H

    def __del__(self):
        buf = getattr(self, "_buf", None)
        if buf is not None:
            self._buf = self.c = None
            try:
                release(buf)
            except Exception:  # noqa: BLE001 - module globals already gone at interpreter exit
                pass

    @functools.cached_property
    def condition(self) -> float:
        """The 1-norm condition number of the equilibrated H (LAPACK dpocon's estimate from
        the factor; inf when H is singular)."""
        if not self.ok:
            return np.inf
        # ||Hs||_1 = max_j sum_i |H_ij| / (d_i d_j): one pass over H, Hs not formed
        anorm = float(np.max((np.abs(self._H) @ (1.0 / self.d)) / self.d))
        rcond, _ = scipy.linalg.lapack.dpocon(self.c, anorm, uplo="L")
        return 1.0 / max(float(rcond), np.finfo(float).tiny)

    @functools.cached_property
    def Hs(self) -> np.ndarray:
        """The equilibrated matrix H / (d d^T) (formed again: the factor overwrote it)."""
        return self._H / np.outer(self.d, self.d)

    def whiten(self, B: np.ndarray) -> np.ndarray:
        """G = L^-1 B for the factor H = L L^T (L = D Ls, Ls the equilibrated factor), one
        triangular solve: G^T G = B^T H^-1 B (a Schur complement from one solve, where
        B^T (H^-1 B) needs two). Needs ``ok``."""
        if B.ndim == 1:
            return scipy.linalg.blas.dtrsv(self.c, B / self.d, lower=1)
        return scipy.linalg.blas.dtrsm(1.0, self.c, np.asfortranarray(B / self.d[:, None]), lower=1,
                                       overwrite_b=1)

    def unwhiten(self, g: np.ndarray) -> np.ndarray:
        """L^-T g for one vector: H^-1 b = unwhiten(whiten(b))."""
        return scipy.linalg.blas.dtrsv(self.c, g, lower=1, trans=1) / self.d

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        d = self.d if rhs.ndim == 1 else self.d[:, None]
        if self.ok and rhs.ndim == 1:
            return cholesky_solve(self.c, rhs / d) / d
        if self.ok:
            return scipy.linalg.lapack.dpotrs(self.c, rhs / d, lower=1)[0] / d
        return np.linalg.lstsq(self.Hs, rhs / d, rcond=None)[0] / d


@dataclass(frozen=True)
class VechIndex:
    """The vech unknowns x of Theta = [S_1 .. S_b] (S_k = S_k^T, r x r).

    Unknown a = (k, i <= j) sits at Theta[i, k r + j] and, when i != j, also at
    Theta[j, k r + i]. ``iu`` are the upper-triangle indices of one block, ``full[i, j]`` the
    vech position of (i, j) within a block, ``off`` is 1 for off-diagonal unknowns (0 on the
    diagonal), ``blk`` the block of each unknown, ``rows``/``lcols`` the row and in-block
    column of the first position of each unknown. Read-only; one per (r, b) (:func:`vech_index`).
    """

    r: int
    n_blocks: int
    iu: tuple
    full: np.ndarray
    rows: np.ndarray
    lcols: np.ndarray
    off: np.ndarray
    blk: np.ndarray

    @property
    def nv(self) -> int:
        """Unknowns per block, r (r + 1) / 2."""
        return len(self.iu[0])

    @property
    def n(self) -> int:
        return self.n_blocks * self.nv

    @property
    def Dw(self) -> np.ndarray:
        """<D vech(A), x> = <A, S(x)>: weight 2 off the diagonal."""
        return 1.0 + self.off

    def x_eps(self, eps: float) -> np.ndarray:
        """vech of [eps I .. eps I]."""
        return np.tile(eps * (1.0 - self.off[:self.nv]), self.n_blocks)

    def blocks(self, x: np.ndarray) -> np.ndarray:
        """(b, r, r) stack of the blocks S_k(x)."""
        return x.reshape(self.n_blocks, self.nv)[:, self.full]

    def vech(self, S: np.ndarray) -> np.ndarray:
        """x of a (b, r, r) stack of symmetric blocks."""
        return S[:, self.iu[0], self.iu[1]].reshape(-1)

    def theta(self, x: np.ndarray) -> np.ndarray:
        """Theta(x) = [S_1 .. S_b] (r, b r)."""
        return self.blocks(x).transpose(1, 0, 2).reshape(self.r, -1)


@functools.lru_cache(maxsize=32)
def vech_index(r: int, n_blocks: int) -> VechIndex:
    iu = np.triu_indices(r)
    nv = len(iu[0])
    full = np.zeros((r, r), dtype=np.intp)
    full[iu] = np.arange(nv)
    full = np.triu(full) + np.triu(full, 1).T
    blk = np.repeat(np.arange(n_blocks), nv)
    i, j = np.tile(iu[0], n_blocks), np.tile(iu[1], n_blocks)
    index = VechIndex(r, n_blocks, iu, full, i, j, (i != j).astype(float), blk)
    for arr in (*iu, full, i, j, index.off, blk):
        arr.setflags(write=False)
    return index


def face_ranks(X: np.ndarray, Lam: np.ndarray) -> list:
    """Rank of each X_k: the eigen-directions where X exceeds Lambda (their product is ~mu,
    strict complementarity sends one of them to 0; the interior point's scaling makes the two
    comparable: Lambda ~ grad f ~ H' x')."""
    wX, VX = np.linalg.eigh(X)
    wL = np.einsum("kia,kij,kja->ka", VX, Lam, VX)
    return [int(v) for v in (wX > wL).sum(axis=1)]


def face_basis(P: np.ndarray, iu) -> np.ndarray:
    """Columns vech(P E_ab P^T), a <= b, E_ab = e_a e_b^T + e_b e_a^T (one term if a = b): the
    vech coordinates of the symmetric matrices P A P^T."""
    a, b = vech_index(P.shape[1], 1).iu  # cached: built anew, they cost more than the work
    Pi, Pj = P[iu[0]], P[iu[1]]
    return Pi[:, a] * Pj[:, b] + (a != b) * Pi[:, b] * Pj[:, a]


def unvech(c: np.ndarray, m: int) -> np.ndarray:
    """The symmetric m x m matrix whose upper triangle (row-major) is c."""
    A = np.zeros((m, m))
    ia, ib = vech_index(m, 1).iu
    A[ia, ib] = A[ib, ia] = c
    return A


def symmetric_normal_equations(L: np.ndarray, Z: np.ndarray, n_blocks: int):
    """H, h with ||Theta(x) L + Z||_F^2 = x^T H x + 2 h^T x + ||Z||_F^2 in the vech unknowns.

    Row i of Theta is E_i x, E_i selecting (S_1[i, :], .., S_b[i, :]) from x, so
    H = sum_i E_i^T G E_i and h = sum_i E_i^T X[i] with G = L L^T, X = Z L^T: r scatters of
    the p x p matrix G - O(r p^2) work.
    """
    r, p = Z.shape
    dest_H, dest_h = _normal_equation_index(r, n_blocks)
    G, X = L @ L.T, Z @ L.T
    n = n_blocks * r * (r + 1) // 2
    H = np.bincount(dest_H, weights=np.broadcast_to(G.ravel(), (r, p * p)).ravel(), minlength=n * n)
    h = np.bincount(dest_h, weights=X.ravel(), minlength=n)
    return H.reshape(n, n), h


@functools.lru_cache(maxsize=32)
def _normal_equation_index(r: int, n_blocks: int):
    """Flat destinations in H (n x n) of G's entries for every row i of Theta (E_i^T G E_i),
    and in h of X[i]'s entries: the r scatters of :func:`symmetric_normal_equations` as one
    ``bincount``."""
    index = vech_index(r, n_blocks)
    nv, n = index.nv, index.n
    idx = (index.full[:, None, :] + nv * np.arange(n_blocks)[None, :, None]).reshape(r, -1)  # (r, p)
    dest_H = (idx[:, :, None] * n + idx[:, None, :]).ravel()
    dest_h = idx.ravel()
    for arr in (dest_H, dest_h):
        arr.setflags(write=False)
    return dest_H, dest_h
