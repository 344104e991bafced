"""Fits on rank-deficient and ill-conditioned data (numpy only): a warning and a sound,
unique answer by default, an error with strict=True, and no dependence on which side of a
rank threshold rounding puts the data (issue: the beam demo failed on another machine's BLAS).
"""

import warnings

import numpy as np
import pytest

import dolfinx_lopinf as lo
from dolfinx_lopinf.core.gram import RANK_RTOL


def _near_dependent_data(delta, seed=0):
    """A 6-mode oscillator q_tt = -K q (K SPD, coordinates mixed by a random rotation) whose
    last two modes are excited with amplitude ``delta``: for delta = 0 the data have rank 4 in
    6 coordinates (as when r exceeds what a trajectory excites), for tiny delta they are
    singular to rounding. Exact second derivatives."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 20.0, 4001)
    w = np.array([1.0, 1.7, 2.9, 4.1, 5.3, 6.7])
    a = np.array([1.0, 0.5, 0.3, 0.2, delta, delta])
    modal = a[:, None] * np.cos(w[:, None] * t + rng.uniform(0, np.pi, 6)[:, None])
    R = np.linalg.qr(rng.standard_normal((6, 6)))[0]
    return R @ modal, R @ (-(w**2)[:, None] * modal)


def _fit(Q, ddQ, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", lo.errors.IllConditionedDataWarning)
        return lo.core.infer_mechanical(Q, None, ddQ, damping=False, **kw)


def test_exact_rank_deficiency_warns_and_strict_raises():
    Q, ddQ = _near_dependent_data(0.0)
    with pytest.raises(lo.errors.RankDeficientDataError, match=r"rank 4 < 6.*lower r"):
        lo.core.infer_mechanical(Q, None, ddQ, damping=False, strict=True)
    with pytest.warns(lo.errors.IllConditionedDataWarning, match=r"rank 4 < 6.*ridge"):
        ops = lo.core.infer_mechanical(Q, None, ddQ, damping=False)
    # sound: symmetric, >= eps I, and it fits the dynamics the data do determine
    assert np.array_equal(ops.K, ops.K.T) and ops.certificate["min_eig_K"] >= 1e-8
    assert ops.certificate["relative_residual"] < 1e-3
    assert ops.certificate["data_rank"] == 4


def test_zero_row_names_the_row_and_the_remedy():
    Q, ddQ = _near_dependent_data(1e-3)
    Q[5] = 0.0
    with pytest.raises(lo.errors.RankDeficientDataError, match=r"Qh\[5\].*lower r"):
        lo.core.infer_mechanical(Q, None, ddQ, damping=False)


@pytest.mark.parametrize("delta", [1e-16, 1e-14, 1e-12])
def test_fit_does_not_depend_on_rounding_at_the_rank_edge(delta):
    """Data whose smallest singular value sits at the level of rounding: perturbing them at
    1e-14 relative (what another BLAS or MPI layout does) moves the operators by a bounded
    amount - the ridge makes the problem's condition number <= 1 / RIDGE."""
    Q, ddQ = _near_dependent_data(delta)
    rng = np.random.default_rng(1)
    Ks, Ko = [], []
    for _ in range(3):
        noise = 1 + 1e-14 * rng.standard_normal(Q.shape)
        Ks.append(_fit(Q * noise, ddQ * noise).K)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", lo.errors.IllConditionedDataWarning)
            Ko.append(lo.core.infer_opinf(Q * noise, None, ddQ * noise, damping=False).K)
    for K in (Ks, Ko):
        spread = max(np.abs(k - K[0]).max() for k in K[1:]) / np.abs(K[0]).max()
        assert spread < 1e-6, spread


def test_well_conditioned_fit_is_unchanged_by_the_ridge():
    Q, ddQ = _near_dependent_data(1e-1)
    assert _fit(Q, ddQ).certificate["data_rank"] == 6
    K0, K1 = _fit(Q, ddQ, ridge=0.0).K, _fit(Q, ddQ).K
    cond = _fit(Q, ddQ).certificate["data_condition"]
    # relative change (ridge * cond)^2 in the worst direction, here ~1e-15: far below 1e-10
    assert np.abs(K1 - K0).max() <= max((1e-9 * cond) ** 2, 1e-12) * 10 * np.abs(K0).max()


def test_rank_tolerance_has_margin_over_rounding():
    """The rank verdict sits five decades above double-precision rounding."""
    assert RANK_RTOL >= 1e4 * np.finfo(float).eps


def test_data_in_extreme_units_are_fitted():
    """K does not depend on the units of the state; data scaled by 1e160 or 1e-170 neither
    overflow nor underflow (a power-of-two scaling is taken out exactly)."""
    Q, ddQ = _near_dependent_data(1e-1)
    K = _fit(Q, ddQ).K
    for c in (1e160, 1e-170):
        assert np.allclose(_fit(Q * c, ddQ * c).K, K, rtol=1e-9, atol=1e-9 * np.abs(K).max())


def test_static_data_are_refused_with_a_reason():
    Q, _ = _near_dependent_data(1e-1)
    with pytest.raises(lo.errors.InputError, match="identically zero"):
        lo.core.infer_mechanical(Q, None, np.zeros_like(Q), damping=False)
    with pytest.raises(lo.errors.InputError, match="identically zero"):
        lo.core.infer_wave(Q, np.zeros_like(Q), np.zeros_like(Q))
