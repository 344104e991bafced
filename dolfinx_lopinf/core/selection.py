"""Choosing the reduced dimension from what the scene needs (numpy only).

``choose_r`` fits L-OpInf on the first part of the training window and scores it on the
held-back rest, for increasing r, and returns the smallest r whose held-back relative state
error (or output error) meets the target. Nothing outside the training window is used, so
the choice is honest cross-validation in time.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ._checks import check_matrix, check_positive, check_uniform_times, check_vector
from ..errors import InputError
from .basis import pod
from .ddt import derivatives
from .inference import infer_mechanical, infer_output
from .metrics import relative_error
from .rom import LagrangianROM


@dataclass(frozen=True)
class Choice:
    """The chosen r (None if no candidate met the target) and the score of every candidate."""

    r: int | None
    target: float
    scores: list = field(default_factory=list)  # [{"r", "holdout_error", "met"}]


def choose_r(Q: np.ndarray, times: np.ndarray, r_values, target: float, *, blocks=None,
             holdout: float = 0.25, Y: np.ndarray | None = None, V0: np.ndarray | None = None,
             weight: np.ndarray | None = None) -> Choice:
    """Smallest r in ``r_values`` whose conservative L-OpInf ROM meets ``target`` on the
    held-back last ``holdout`` fraction of the training window.

    Args:
        Q: (n, K) training states at uniform ``times`` (K,).
        r_values: candidate reduced dimensions, tried in increasing order.
        target: relative error to reach: on the states, or on ``Y`` (p, K) when given.
        blocks, weight: passed to :func:`dolfinx_lopinf.pod`.
        holdout: fraction of the window held back for scoring.
        V0: (n,) initial velocity (zero when None).

    Returns:
        :class:`Choice`.
    """
    Q = check_matrix(Q, "Q")
    dt = check_uniform_times(times)
    times = np.asarray(times, dtype=float)
    if len(times) != Q.shape[1]:
        raise InputError(f"times has {len(times)} entries but Q has {Q.shape[1]} columns; pass "
                         "one time per column")
    if not (isinstance(holdout, (int, float, np.integer, np.floating)) and 0 < holdout < 1):
        raise InputError(f"holdout must be in (0, 1), got {holdout!r}")
    target = check_positive(target, "target")
    r_values = list(r_values)
    if not r_values or any(isinstance(r, (bool, np.bool_)) or not isinstance(r, (int, np.integer))
                           or r < 1 for r in r_values):
        raise InputError(f"r_values must be a non-empty list of positive integers, got {r_values!r}")
    if Y is not None:
        Y = check_matrix(np.atleast_2d(Y), "Y", cols=Q.shape[1])
    K = Q.shape[1]
    k_fit = int(round((1 - holdout) * (K - 1))) + 1
    if k_fit < 9 + max(r_values) or K - k_fit < 2:
        raise InputError(f"the window ({K} samples) is too short to hold back {holdout:.0%} "
                         f"and still fit r = {max(r_values)}")
    v0 = np.zeros(Q.shape[0]) if V0 is None else check_vector(V0, "V0", Q.shape[0])
    scores = []
    for r in sorted(r_values):
        basis = pod(Q[:, :k_fit], r, blocks=blocks, weight=weight)
        Qh_all = basis.project(Q[:, :k_fit])
        Qh, _, ddQh = derivatives(Qh_all, times[:k_fit])
        ops = infer_mechanical(Qh, None, ddQh, damping=False)
        E = None if Y is None else infer_output(Qh_all, Y[:, :k_fit])
        rom = LagrangianROM(K=ops.K, E=E)
        tr = rom.simulate(basis.project(Q[:, 0]), basis.project(v0), dt, K - 1)
        if Y is None:
            err = relative_error(Q[:, k_fit:], basis.reconstruct(tr.Qh[:, k_fit:]))
        else:
            err = relative_error(Y[:, k_fit:], tr.Y[:, k_fit:])
        scores.append({"r": r, "holdout_error": err, "met": bool(err <= target)})
        if err <= target:
            return Choice(r, target, scores)
    return Choice(None, target, scores)
