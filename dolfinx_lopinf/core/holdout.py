"""Judging a model by what it predicts: the held-back end of every trajectory.

:func:`split` keeps the first ``1 - holdout`` of every trajectory for fitting and hands back
the rest with the samples before it; :func:`prediction_error` runs a scheme's multistep
recurrence (:meth:`dolfinx_lopinf.core.schemes.Scheme.recurrence`) of fitted operators from
those samples over the held-back end - no velocities or accelerations needed - and returns
the relative error ||predicted - recorded||_F / ||recorded||_F (inf for a run that blew up).
The recurrence runs as the ROM loops do (compiled when numba is installed).
"""

from __future__ import annotations

import numpy as np

from . import schemes
from ..errors import InputError
from .rom import _affine_loop


def prediction_error(ops, scheme, held, dt, backend="numpy") -> float:
    """Relative error of the scheme's multistep recurrence of ``ops`` over the held-back
    samples, started from the samples before them (``held`` = (Qh, times, U, ti))."""
    Qh, times, U, ti = held
    r = Qh.shape[0]
    M = np.eye(r) if ops.M is None else ops.M
    Gc, Hc, cu, tau_rel = scheme.recurrence(M, ops.C, ops.K, ops.B, dt)
    lead = Gc.shape[0] // r  # samples that start the recurrence
    n = Qh.shape[1] - lead
    forcing = None
    if U is not None and Hc is not None:
        t_load = times[0] + (np.arange(n + len(cu) - 1) + tau_rel) * dt
        F = schemes.sample_inputs(U, times if ti is None else ti, t_load, outside="nan",
                                  bends="keep")
        W = sum(c * F[:, j:j + n] for j, c in enumerate(cu))
        known = np.all(np.isfinite(W), axis=0)
        n = int(np.argmin(known)) if not known.all() else n  # up to the last recorded load
        if n < 1:
            return float("inf")
        forcing = [(0, n, Hc @ W[:, :n])]
    X = np.empty((Gc.shape[0], n + 1))
    x = np.ascontiguousarray(Qh[:, :lead].T.ravel())
    X[:, 0] = x
    with np.errstate(all="ignore"):
        _affine_loop(Gc, x, forcing, n, 1, X, backend)
    pred = X[-r:, 1:]
    ref = Qh[:, lead:lead + n]
    err = np.linalg.norm(pred - ref) / max(np.linalg.norm(ref), np.finfo(float).tiny)
    return float(err) if np.isfinite(err) else float("inf")


def split(pieces, holdout):
    """(fit parts, held-back parts): the first 1 - holdout of every trajectory, and the rest
    with the samples before it that start a four-point recurrence."""
    fit_part, held = [], []
    for i, (Qh, times, U, ti, Vh, Ah) in enumerate(pieces):
        K = Qh.shape[1]
        k_cut = int(round((1 - holdout) * K))
        if k_cut < 17 or K - k_cut < 4:
            which = f"snapshots[{i}]" if len(pieces) > 1 else "the trajectory"
            raise InputError(f"{which} has {K} samples: too short to compare models on a "
                             f"held-back {holdout:.0%} (it needs >= 17 samples before and 4 after "
                             "the cut); record longer, or pass scheme=, mass= and damping= to "
                             "skip the comparison")
        def cut(a, k=k_cut):
            return None if a is None else a[:, :k]

        U_fit = U[:, :k_cut] if U is not None and ti is None else U
        fit_part.append((Qh[:, :k_cut], times[:k_cut], U_fit, ti, cut(Vh), cut(Ah)))
        start = k_cut - 3
        held.append((Qh[:, start:], times[start:], U[:, start:] if U is not None and ti is None
                     else U, ti))
    return fit_part, held

