"""The compressed least-squares data every L-OpInf fit shares, and the fitted operators.

Write Theta = [Kh, Ch, -Bh] (r, p) for the unknown operators and D = [Qh; dQh; U] (p, K) for
the data rows (K snapshots). Then

    ||ddQh + Theta D||_F^2 = ||Theta L + Z||_F^2 + ||ddQh||_F^2 - ||Z||_F^2,
    G = D D^T = L L^T,  Z = ddQh D^T L^{-T}  (r, p)   (L from a thin QR of D^T),

so after one pass over the data (cost O(K p^2)) no solver depends on K. :func:`compress`
forms (L, Z) for any stack of data rows and target (row-normalised, with a relative ridge that
decides the directions double-precision data do not determine); :func:`gram_data` is the
mechanical form. The fits of :mod:`~dolfinx_lopinf.core.inference`,
:mod:`~dolfinx_lopinf.core.mass` and :mod:`~dolfinx_lopinf.core.parametric` all start here and
return :class:`MechanicalOperators`, their PSD blocks made safe against rounding by
:func:`psd_floor`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from ._checks import check_matrix
from ..errors import IllConditionedDataWarning, InputError, RankDeficientDataError, warn
from .lsq.linalg import from_eig, residual_norm2, sym


@dataclass(frozen=True)
class MechanicalOperators:
    """Inferred reduced operators of qh_tt + C qh_t + K qh = B u (None where not fitted).

    Attributes:
        K: (r, r) stiffness.  C: (r, r) damping or None.  B: (r, m) input or None.
        M: (r, r) learned reduced mass (``mass="learned"``), None when it is fixed to I.
        certificate: how the solve went, a dict: ``solver``, ``certified`` (the duality gap
            met its tolerance, 1e-8 by default, and the operators are feasible),
            ``duality_gap`` (relative), ``iterations``, ``seconds``, ``status``, ``objective`` (the
            squared residual norm ||ddQh + K Qh + C dQh - B U||_F^2), ``relative_residual``,
            ``min_eig_K``/``min_eig_C``, ``symmetry_error``, ``seconds``, and the fields of
            the solver's :class:`~dolfinx_lopinf.core.lsq.Certificate` (``iterations``,
            ``duality_gap``, KKT residuals, ...; :meth:`~dolfinx_lopinf.core.lsq.Certificate.as_dict`).
    """

    K: np.ndarray
    C: np.ndarray | None = None
    B: np.ndarray | None = None
    certificate: dict = field(default_factory=dict)
    M: np.ndarray | None = None


#: The relative duality gap below which a fit is ``certified`` (the engine's default).
GAP_TOL = 1e-8
#: Relative Tikhonov parameter of every fit (see :func:`gram_data`): directions of the
#: row-normalised data whose singular value is below ``RIDGE`` times the largest are not
#: determined by double-precision data; the ridge decides them (towards zero) instead of
#: rounding.
RIDGE = 1e-9
#: Singular values below ``RANK_RTOL`` times the largest count as "not determined by the
#: data" in the warning (and the error with ``strict=True``). Five decades above rounding
#: (~1e-16), so a different BLAS cannot move a well-determined problem across it.
RANK_RTOL = 1e-10


@dataclass(frozen=True)
class GramData:
    """The data of the least-squares problem after one pass over K snapshots.

    The problem is the ridge-regularised least squares

        min  ||Theta D + ddQh||_F^2 + gamma^2 ||Theta diag(s)||_F^2,    gamma = ridge * sigma_1,

    with s the row norms of D = [Qh; dQh; U] and sigma_1 the largest singular value of the
    row-normalised data diag(1/s) D. Its normal matrix is G = D D^T + gamma^2 diag(s)^2 = L L^T.

    Attributes:
        L: (p, p) lower-triangular factor of G.
        Z: (r, p) such that the objective is ||Theta L + Z||_F^2 + target_norm2 - ||Z||_F^2.
        target_norm2: ||ddQh||_F^2.
        r, m: reduced and input dimensions; ``has_damping`` tells whether dQh is in D.
        condition: condition number of the row-normalised data matrix (before the ridge).
        rank: number of its singular values above ``RANK_RTOL`` times the largest.
        ridge_weights: (p,) gamma * s, so the ridge term is ||Theta * ridge_weights||_F^2.
    """

    L: np.ndarray
    Z: np.ndarray
    target_norm2: float
    r: int
    m: int
    has_damping: bool
    condition: float = float("nan")
    rank: int = -1
    ridge_weights: np.ndarray | None = None

    def objective(self, theta: np.ndarray) -> float:
        """The objective the solvers minimise: ||Theta D + ddQh||_F^2 + the ridge term."""
        return float(residual_norm2(theta, self.L, self.Z) + self.target_norm2 - np.sum(self.Z**2))

    def data_objective(self, theta: np.ndarray) -> float:
        """||Theta D + ddQh||_F^2, the misfit without the ridge term."""
        ridge = 0.0 if self.ridge_weights is None else np.sum((theta * self.ridge_weights) ** 2)
        return self.objective(theta) - float(ridge)


def _data_matrix(Qh, dQh, ddQh, U, damping):
    Qh = check_matrix(Qh, "Qh")
    r, K = Qh.shape
    ddQh = check_matrix(ddQh, "ddQh", rows=r, cols=K)
    rows = [Qh]
    if damping:
        if dQh is None:
            raise InputError("damping=True needs the first derivatives dQh")
        rows.append(check_matrix(dQh, "dQh", rows=r, cols=K))
    m = 0
    if U is not None:
        U = check_matrix(np.atleast_2d(U), "U", cols=K)
        m = U.shape[0]
        rows.append(U)
    p = sum(block.shape[0] for block in rows)
    if K < p:
        raise InputError(
            f"{K} data columns (time samples; in lo.fit those its scheme's relation leaves, 2 "
            f"to 8 fewer than recorded) cannot determine {p} unknowns per row; record more "
            "time samples or lower r"
        )
    return rows, ddQh, r, m


def row_norms(A: np.ndarray) -> np.ndarray:
    """Euclidean row norms without overflow or underflow (data scaled by 1e+-160 included)."""
    big = np.abs(A).max(axis=1)
    safe = np.where(big > 0, big, 1.0)
    return big * np.linalg.norm(A / safe[:, None], axis=1)


def block_names(r, m, damping):
    names = [f"Qh[{i}]" for i in range(r)]
    names += [f"dQh[{i}]" for i in range(r)] if damping else []
    return names + [f"U[{i}]" for i in range(m)]


def gram_data(Qh, dQh, ddQh, U=None, *, damping=True, ridge: float = RIDGE,
              strict: bool = False) -> GramData:
    """Form the compressed, ridge-regularised least-squares data (one pass over the snapshots).

    Rank and conditioning. POD coordinates span many decades and the paper's block basis makes
    [Qh; dQh] nearly singular (theta ~ w'), so whether the smallest singular value of the data
    lies just above or just below a rank threshold is decided by rounding (the BLAS, the
    thread count, the MPI layout). No result may hinge on that. Hence:

    * the fit always carries the ridge gamma^2 ||Theta diag(s)||^2 with gamma = ``ridge`` *
      sigma_1 (row-normalised data): it changes directions with singular value
      sigma >> gamma by a relative (gamma / sigma)^2 (<= 1e-8 for sigma >= 1e-5 sigma_1 at the
      default 1e-9) and decides the directions the data do not see (sigma <~ gamma) towards
      zero - a unique, stable answer that depends continuously on the data;
    * directions with sigma < ``RANK_RTOL`` sigma_1 are reported: one
      :class:`~dolfinx_lopinf.errors.IllConditionedDataWarning` naming the rank, the condition
      number and what was done; ``strict=True`` raises
      :class:`~dolfinx_lopinf.errors.RankDeficientDataError` instead.

    ``ridge=0`` gives the plain least squares (it fails on singular data).
    """
    if not (np.isfinite(ridge) and 0 <= ridge < 1):
        raise InputError(f"ridge must be a number in [0, 1), got {ridge!r}")
    rows, ddQh, r, m = _data_matrix(Qh, dQh, ddQh, U, damping)
    if not np.any(ddQh):
        raise InputError(
            "the target (ddQh, the second derivatives, plus Fh for waves) is identically zero: "
            "static or empty snapshots carry no dynamics to fit; record a trajectory that moves")
    L, Z, cond, rank, weights = compress(rows, ddQh, block_names(r, m, damping), ridge, strict,
                                          "[Qh; dQh; U]")
    return GramData(L, Z, float(np.sum(ddQh**2)), r, m, damping, cond, rank, weights)


def compress(rows, target, names, ridge, strict, what):
    """(L, Z, condition, rank, ridge weights) of min ||Theta D + target||^2 + gamma^2
    ||Theta diag(s)||^2 with D = vstack(rows); see :func:`gram_data`."""
    scale = np.concatenate([row_norms(block) for block in rows])
    if np.any(scale == 0):
        zero = [names[i] for i in np.flatnonzero(scale == 0)]
        raise RankDeficientDataError(
            f"data rows {zero} of {what} are identically zero, so the operator entries "
            "that multiply them are not determined by the data; lower r to the rank of the "
            "snapshots (a zero POD coordinate means r exceeds it) or drop the zero input")
    # Row-normalised data Dn = diag(1/s) D (p x K). One Householder QR of the augmented tall
    # matrix [Dn^T, target^T] (K x (p + r)), Q never formed: its leading p x p block is R
    # (Dn^T = Qf R) and the block beside it is Qf^T target^T = Z^T. Then D D^T = L L^T with
    # L = diag(s) R^T - exact for any conditioning (the condition number is never squared;
    # POD coordinates span many decades), one LAPACK call on one Fortran-ordered copy of the
    # data, O(K (p + r)^2). The ridge appends rows gamma I to Dn^T (0 to target^T): one more
    # QR of a (2p) x (p + r) matrix.
    p, r, K = len(scale), target.shape[0], target.shape[1]
    A = np.empty((K, p + r), order="F")
    start = 0
    for block in rows:
        A[:, start:start + block.shape[0]] = block.T / scale[start:start + block.shape[0]]
        start += block.shape[0]
    A[:, p:] = target.T
    R_aug = scipy.linalg.qr(A, mode="r", overwrite_a=True, check_finite=False)[0][:p]
    sv = np.linalg.svd(R_aug[:, :p], compute_uv=False)
    cond = float(sv[0] / max(sv[-1], np.finfo(float).tiny))
    rank = int((sv > RANK_RTOL * sv[0]).sum())
    gamma = ridge * sv[0]
    if gamma > 0:
        R_aug = scipy.linalg.qr(np.vstack([R_aug, np.hstack([gamma * np.eye(p), np.zeros((p, r))])]),
                                mode="r", check_finite=False)[0][:p]
    if rank < p:
        msg = (f"the data matrix {what} ({p} rows, row-normalised) has numerical rank "
               f"{rank} < {p} at relative tolerance {RANK_RTOL:g} (condition number {cond:.3g}):"
               " some operator directions are not determined by the data")
        if strict:
            raise RankDeficientDataError(msg + "; lower r, record a richer trajectory or drop a "
                                         "block (or call without strict=True to regularise)")
        warn(msg + f"; they were fixed by the ridge {ridge:g} * sigma_1 (Tikhonov, towards zero)"
             " with the constraints kept. Pass strict=True to raise instead, or lower r for a fit "
             "the data determine alone.", IllConditionedDataWarning)
    L = scale[:, None] * R_aug[:, :p].T
    return L, R_aug[:, p:].T, cond, rank, (gamma * scale if gamma > 0 else None)


def psd_floor(A: np.ndarray, eps: float) -> np.ndarray:
    """Symmetrise and make the computed eigenvalues >= eps despite rounding: eigenvalues are
    only known to ~1e-16 ||A||, so clip at eps + 64 u ||A||_2 when any falls below eps. ``A``:
    one matrix or a stack (each block floored on its own; one batched ``eigh``)."""
    A = sym(A)
    w, Q = np.linalg.eigh(A)
    floor = eps + 64 * np.finfo(float).eps * np.abs(w).max(axis=-1, keepdims=True)
    low = (w < floor).any(axis=-1)
    if not low.any():
        return A
    return np.where(low[..., None, None], sym(from_eig(np.maximum(w, floor), Q)), A)
