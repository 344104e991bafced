"""Polynomial L-OpInf fits on data whose reduced coordinates differ in scale by orders of
magnitude (as elastic POD coordinates do): every equation is fitted, not only the
large-amplitude ones; point data (probe samples) in the fit's form; the sos fit reaches the
unconstrained optimum on exact data."""

import unittest.mock
import warnings

import numpy as np
import pytest

from dolfinx_lopinf.core import polynomial as pl
from dolfinx_lopinf.core.synthetic import potential_samples, stiff_potential
from dolfinx_lopinf.errors import InputError, SolverWarning


def test_every_equation_is_fitted_when_coordinates_differ_in_scale():
    """Noise of 1e-6 per entry: each row's residual stays at the noise level of that row. (With
    rows weighted by the coordinate scale, as before, the smallest coordinate's equation was
    left with a residual ~1e3 x its noise on such data.)"""
    pot, scales = stiff_potential()
    rng = np.random.default_rng(3)
    data, A, C, B = potential_samples(pot, scales, 600, rng, noise=1e-6)
    ops = pl.fit_polynomial(data, constraint="none")
    pred = -(ops.potential.gradient(data.plus) + ops.C @ data.D1) + ops.B @ data.Ubar
    row_err = np.linalg.norm(pred - A, axis=1) / np.linalg.norm(A, axis=1)
    assert row_err.max() < 1e-5, row_err


def test_point_data_checks_its_input():
    Q = np.zeros((2, 5))
    with pytest.raises(InputError, match="same shape"):
        pl.point_data(Q, Q, np.zeros((2, 4)))
    with pytest.raises(InputError, match="columns"):
        pl.point_data(Q, Q, Q, np.zeros((1, 4)))
    with pytest.raises(InputError, match="NaN"):
        pl.point_data(Q, Q, np.full((2, 5), np.nan))


def test_sos_fit_reaches_the_unconstrained_optimum_on_exact_stiff_data():
    """Exact data of an SOS potential: the constrained fit must not stop far above the optimum
    (the diagonally scaled formulation stopped at 5e-3 relative residual on SVK data)."""
    pot, scales = stiff_potential(r=3)
    data, A, C, B = potential_samples(pot, scales, 300, np.random.default_rng(4))
    ops = pl.fit_polynomial(data, constraint="sos")
    cert = ops.certificate
    assert cert["relative_residual"] < 1e-5, cert["relative_residual"]
    assert cert["min_eig_gram"] > 0 and cert["min_eig_C"] > 0 and cert["min_eig_K"] > 0
    theta = pot.coefficients()
    assert np.abs(ops.potential.coefficients() - theta).max() < 1e-4 * np.abs(theta).max()


@pytest.mark.parametrize("r, noise", [(3, 1e-4), (4, 1e-6), (6, 0.0)])
def test_sos_fit_by_our_interior_point_is_certified_and_matches_clarabel(r, noise):
    """solver='ipm': certified (gap <= 1e-8, no warning), the same residual as Clarabel, a
    Gram matrix >= 0. (Before the monomial congruence scaling it stalled at gaps ~1e-6 ..
    1e-5.) solver='ipm' is for the sos fit alone: another constraint is named."""
    pot, scales = stiff_potential(r=r)
    data, *_ = potential_samples(pot, scales, 300 if r < 5 else 900, np.random.default_rng(4),
                                 noise=noise)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # certified: nothing to warn about
        ours = pl.fit_polynomial(data, constraint="sos", solver="ipm")
    ref = pl.fit_polynomial(data, constraint="sos", solver="cvxpy")
    c, cr = ours.certificate, ref.certificate
    assert c["solver"] == "sos-ipm" and c["certified"] and c["duality_gap"] <= 1e-8, c["duality_gap"]
    assert c["min_eig_gram"] >= 0
    # the gap is relative to max(misfit, 1e-6 |z|^2): on exact data (r = 6) residuals ~1e-12
    assert abs(c["relative_residual"] - cr["relative_residual"]) <= 1e-3 * cr["relative_residual"] + 1e-10
    for key in ("duality_gap", "certified", "solver", "iterations", "seconds"):
        assert key in c and key in cr
    with pytest.raises(InputError, match="'sos' fit only"):
        pl.fit_polynomial(data, constraint="spd", solver="ipm")


def test_psd_qp_gives_no_bound_where_the_objective_is_flat_beyond_its_known_null_space():
    """A direction along which f is flat and that the problem does not declare (``null``) makes
    the dual function unbounded: the certificate is inf (uncertified), not a LinAlgError - the
    SVK cantilever's near-exact probe data at r = 6, 8 raised one from the sos fit."""
    from dolfinx_lopinf.core.lsq import psd_qp

    rng = np.random.default_rng(0)
    A = rng.standard_normal((5, 3))
    A = np.hstack([A, A[:, :1]])  # H = A^T A singular (columns 0 and 3 equal)
    b = rng.standard_normal(5)
    P0 = np.zeros((3, 4))  # one 2 x 2 block on unknowns 1, 2 and a diagonal entry 3
    P0[0, 1], P0[1, 3], P0[2, 2] = 1.0, 1.0, 1.0
    p = psd_qp.QuadraticPSD(A.T @ A, -A.T @ b, float(b @ b), [P0], [np.zeros((2, 2))], A=A, b=b)
    x = np.array([0.0, 1.0, 1.0, 0.2])  # strictly feasible: [[1, .2], [.2, 1]] > 0
    assert p.gap(x, [np.eye(2)]) == np.inf


def _svk_probes():
    """The SVK cantilever demo's probe data at r = 4 (quick mode: 78 samples of a one-step FOM
    acceleration; the data a sum of squares fits to ~5e-9 relative)."""
    from pathlib import Path

    from dolfinx_lopinf.core.polynomial.fit import point_data

    z = np.load(Path(__file__).with_name("data") / "svk_probes_r4.npz")
    return point_data(z["Q"], z["Vel"], z["A"], z["U"])


def test_the_default_sos_fit_is_ours_and_as_accurate_as_clarabel_on_near_exact_data(monkeypatch):
    """solver='auto' (the default) fits sos by our interior point: certified, and through the
    polish as close to the data as Clarabel (measured: relative residual 4.604e-9 against
    4.614e-9). The interior point alone stalls on its central path at 1.99e-8 (its gap is small
    only against its floor): without the polish this test fails."""
    from dolfinx_lopinf.core.lsq import psd_qp

    data = _svk_probes()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # certified: nothing to warn about
        ours = pl.fit_polynomial(data, constraint="sos")
    ref = pl.fit_polynomial(data, constraint="sos", solver="cvxpy")
    c, cr = ours.certificate, ref.certificate
    assert c["solver"] == "sos-ipm" and c["certified"] and "fallback_from" not in c
    assert c["polish"]["bound"] == "zero" and c["polish"]["misfit_after"] < 1e-3 * c["polish"]["misfit_before"]
    assert c["relative_residual"] <= 1.02 * cr["relative_residual"], (c["relative_residual"], cr["relative_residual"])
    assert c["min_eig_gram"] >= 0 and c["min_eig_K"] > 0 and c["min_eig_C"] > 0
    monkeypatch.setattr(psd_qp, "POLISH_FROM", np.inf)
    unpolished = pl.fit_polynomial(data, constraint="sos").certificate
    assert unpolished["polish"] is None
    assert unpolished["relative_residual"] > 2 * cr["relative_residual"]


def test_polish_keeps_every_block_feasible_and_never_raises_the_misfit():
    """The polish's steps stay inside the cones (x' strictly feasible), and f(x') <= f(x)."""
    from dolfinx_lopinf.core.lsq import psd_qp

    seen = []
    orig = psd_qp.polish

    def spy(p, x, Lam, gap):
        out = orig(p, x, Lam, gap)
        seen.append((p, x, out))
        return out

    with unittest.mock.patch.object(psd_qp, "polish", spy):
        pl.fit_polynomial(_svk_probes(), constraint="sos", solver="ipm")
    (p, x, (x1, gap1, record)), = seen
    assert p.objective(x1) <= p.objective(x) and gap1 <= record["gap_before"]
    for Xk in p.slacks(x1):
        assert np.linalg.eigvalsh(Xk)[0] > 0


def test_auto_falls_back_to_clarabel_when_ours_is_far_from_certified(monkeypatch):
    """Our interior point left with a gap above FALLBACK_GAP under solver='auto': Clarabel's
    certified answer is kept (its misfit is ours here), and the certificate names what was
    tried first; below FALLBACK_GAP ours stays, uncertified and warned."""
    from dolfinx_lopinf.core.polynomial import sos

    real = sos.solve_sos

    def uncertified(*args, **kwargs):
        theta, G, info = real(*args, **kwargs)
        return theta, G, {**info, "certified": False, "status": "stalled", "duality_gap": 1e-3}

    monkeypatch.setattr(sos, "solve_sos", uncertified)
    pot, scales = stiff_potential(r=3)
    data, *_ = potential_samples(pot, scales, 300, np.random.default_rng(4), noise=1e-4)
    c = pl.fit_polynomial(data, constraint="sos").certificate
    assert c["solver"].startswith("cvxpy") and c["certified"]
    assert c["fallback_from"]["solver"] == "sos-ipm" and c["fallback_from"]["duality_gap"] == 1e-3
    monkeypatch.setattr(pl.fit, "FALLBACK_GAP", 1e-2)
    with pytest.warns(SolverWarning, match="not certified"):
        c_near = pl.fit_polynomial(data, constraint="sos").certificate
    assert c_near["solver"] == "sos-ipm" and "fallback_tried" not in c_near
    with pytest.warns(SolverWarning, match="not certified"):
        c_ipm = pl.fit_polynomial(data, constraint="sos", solver="ipm").certificate
    assert c_ipm["solver"] == "sos-ipm" and not c_ipm["certified"]


def test_an_iterate_lost_to_rounding_ends_the_interior_point_and_auto_takes_clarabel(monkeypatch):
    """The SVK demo's projected-trajectory data at r = 4 (default size; closure-laden, fitted
    to 17 % at best): our interior point's iterate left its cone by rounding at iteration 38
    and the fit raised LinAlgError from a Cholesky factorisation. It now ends at the last
    iterate inside the cones, uncertified and saying why (where another rounding certifies it,
    fine), with the residual of Clarabel's certified answer."""
    from pathlib import Path

    from dolfinx_lopinf.core.lsq import psd_qp
    from dolfinx_lopinf.core.polynomial.fit import MidpointData

    z = np.load(Path(__file__).with_name("data") / "svk_trajectory_r4.npz")
    data = MidpointData(z["minus"], z["plus"], z["D1"], z["D2"], z["Ubar"], float(z["dt"]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ours = pl.fit_polynomial(data, constraint="sos", solver="ipm").certificate
        ref = pl.fit_polynomial(data, constraint="sos", solver="cvxpy").certificate
    assert ours["certified"] or "rounding" in ours["stopped"] or "flat" in ours["stopped"], ours["stopped"]
    assert ours["duality_gap"] <= 1e-6 and ours["min_eig_gram"] >= 0
    assert abs(ours["relative_residual"] - ref["relative_residual"]) <= 1e-3 * ref["relative_residual"]
    # (the gap still fell there while the complementarity was flat: stopping on the estimate
    # alone ended it at a gap of 2e-5.) Which iteration rounding takes out of its cone depends
    # on the BLAS: here a step to the boundary fails at the 30th (LinAlgError, as a Cholesky
    # factorisation of an indefinite matrix does) - the iterate before it is the answer
    real, calls = psd_qp._step_to_boundary, [0]

    def fails_late(pairs):
        calls[0] += 1
        if calls[0] == 30:
            raise np.linalg.LinAlgError("not positive definite")
        return real(pairs)

    monkeypatch.setattr(psd_qp, "_step_to_boundary", fails_late)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lost = pl.fit_polynomial(data, constraint="sos", solver="ipm").certificate
    assert "left its cone by rounding at iteration 15" in lost["stopped"], lost["stopped"]
    assert lost["iterations"] == 15 and lost["min_eig_gram"] >= 0 and np.isfinite(lost["duality_gap"])


def test_a_jammed_interior_point_still_certifies_its_complementarity_not_a_raised_multiplier():
    """The SVK demo's projected-trajectory data at r = 8 (every 2nd sample of the default run),
    as recorded and perturbed at 1e-15: the interior point jams at a complementarity of
    ~1e-7 .. 1e-6 (a fit no sum of squares makes exact). The Gram multiplier's part along the
    null space of the monomial map (rounding-sized, 1e-9) exceeds its smallest eigenvalues
    (1e-13) there, and raising the projection by the moment matrix made the certified gap
    1e-3 .. 1e-2 on 4 of these 6 copies (measured before the scaled correction) - above
    FALLBACK_GAP, so solver='auto' handed the fit to Clarabel (100 s at the full size). The
    gap must stay near the complementarity on every copy, with the same residual."""
    from pathlib import Path

    from dolfinx_lopinf.core.polynomial.fit import FALLBACK_GAP, MidpointData

    z = np.load(Path(__file__).with_name("data") / "svk_trajectory_r8.npz")
    rel = []
    for seed in range(4):
        rng = np.random.default_rng(seed)
        minus, plus, D1, D2 = (z[k] if seed == 0 else z[k] * (1.0 + 1e-15 * rng.standard_normal(z[k].shape))
                               for k in ("minus", "plus", "D1", "D2"))
        data = MidpointData(minus, plus, D1, D2, z["Ubar"], float(z["dt"]))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # uncertified (~1e-6): warned
            c = pl.fit_polynomial(data, constraint="sos", solver="ipm").certificate
        assert c["duality_gap"] <= 0.1 * FALLBACK_GAP, (seed, c["duality_gap"], c["stopped"])
        assert c["min_eig_gram"] >= 0
        rel.append(c["relative_residual"])
    assert max(rel) <= (1 + 1e-6) * min(rel), rel


def test_the_interior_point_hands_over_to_the_polish_where_it_is_flat_at_the_tolerance(monkeypatch):
    """The SVK demo's probes at r = 6 (near-exact data), as recorded and perturbed at 1e-15 (five
    copies): where the gap estimate reaches the complementarity's rounding floor near gap_tol
    and stays there, two iterations that halve neither it nor the certified gap end the
    interior point (flat at the tolerance) and the polish certifies - with the misfit of the
    run without the rule (FLAT_NEAR = 0), in at least two fewer iterations. Where the
    estimate falls below gap_tol instead (some roundings: measured, 2 of the 6 copies here),
    the interior point certifies by itself, with or without the rule. The rule must have
    fired on some copy (measured: 4 of 6)."""
    from pathlib import Path

    from dolfinx_lopinf.core.lsq import psd_qp
    from dolfinx_lopinf.core.polynomial.fit import MidpointData

    z = np.load(Path(__file__).with_name("data") / "svk_probes_r6.npz")
    fired = 0
    for seed in range(6):
        rng = np.random.default_rng(seed)
        minus, plus, D1, D2 = (z[k] if seed == 0 else z[k] * (1.0 + 1e-15 * rng.standard_normal(z[k].shape))
                               for k in ("minus", "plus", "D1", "D2"))
        data = MidpointData(minus, plus, D1, D2, z["Ubar"], float(z["dt"]))
        monkeypatch.setattr(psd_qp, "FLAT_NEAR", 10.0)
        early = pl.fit_polynomial(data, constraint="sos", solver="ipm").certificate
        monkeypatch.setattr(psd_qp, "FLAT_NEAR", 0.0)
        late = pl.fit_polynomial(data, constraint="sos", solver="ipm").certificate
        assert early["certified"] and late["certified"] and "flat" not in late["stopped"]
        if "flat at the tolerance" in early["stopped"]:
            fired += 1
            assert early["iterations"] + 2 <= late["iterations"], (seed, early["iterations"], late["iterations"])
            assert early["relative_residual"] <= 1.01 * late["relative_residual"]
        else:
            assert early["stopped"] == "certified" and early["iterations"] == late["iterations"], seed
    assert fired >= 1


def test_the_polish_step_through_the_null_space_is_the_range_space_step():
    """argmin ||d||_W s.t. A d = y two ways: through A's null space (d_0 + Z w, a k x k
    Cholesky factorisation, Z sparse) and through W's factor (A L^-T, least norm) - the same d,
    A d = y exactly; and the fit that uses it (the SVK probes at r = 4) polishes to the misfit
    of the range-space steps."""
    import scipy.linalg
    import scipy.sparse

    from dolfinx_lopinf.core.lsq import psd_qp

    rng = np.random.default_rng(5)
    n, k = 12, 5
    Z = scipy.sparse.random(n, k, density=0.3, random_state=6, format="csc") + scipy.sparse.eye(n, k, format="csc")
    A = scipy.linalg.null_space(Z.toarray().T).T  # rows spanning Z's orthogonal complement
    G = rng.standard_normal((n, n))
    W = G @ G.T + 1e-3 * np.eye(n)
    y = rng.standard_normal(A.shape[0])
    p = psd_qp.QuadraticPSD(A.T @ A, np.zeros(n), 0.0, [], [], A=A, b=y, flat=Z)
    d = psd_qp._NullSpaceSteps.of(p).step(W.copy(), y)
    L = np.linalg.cholesky(W)
    d_ref = scipy.linalg.solve_triangular(L, psd_qp.least_norm(scipy.linalg.solve_triangular(L, A.T, lower=True).T, y),
                                          lower=True, trans="T")
    assert np.allclose(d, d_ref, rtol=1e-9, atol=1e-11 * np.abs(d_ref).max())
    assert np.allclose(A @ d, y, atol=1e-12 * np.abs(y).max())
    assert psd_qp._NullSpaceSteps.of(psd_qp.QuadraticPSD(A.T @ A, np.zeros(n), 0.0, [], [], A=A, b=y,
                                                          flat=Z[:, :-1])) is None  # not the whole null space
    W_Z = Z.toarray()
    W_Z[0, 0] += 1.0  # a column outside A's null space: not used
    assert psd_qp._NullSpaceSteps.of(psd_qp.QuadraticPSD(A.T @ A, np.zeros(n), 0.0, [], [], A=A, b=y,
                                                          flat=scipy.sparse.csc_matrix(W_Z))) is None

    records = {}
    for name, of in (("null", psd_qp._NullSpaceSteps.of), ("range", lambda p: None)):
        with unittest.mock.patch.object(psd_qp._NullSpaceSteps, "of", of):
            c = pl.fit_polynomial(_svk_probes(), constraint="sos", solver="ipm").certificate
        assert c["certified"], name
        records[name] = c
    assert abs(records["null"]["relative_residual"] - records["range"]["relative_residual"]) \
        <= 1e-3 * records["range"]["relative_residual"]


def test_least_norm_is_the_minimum_norm_least_squares_solution():
    """LAPACK gels (LQ) where A has full row rank, gelsd (SVD) where it is (nearly) singular -
    gels itself answered an exactly zero row with 1e11-sized garbage, no error: both the
    minimum-norm solution, as numpy gives it."""
    from dolfinx_lopinf.core.lsq import psd_qp

    rng = np.random.default_rng(3)
    A, y = rng.standard_normal((30, 80)), rng.standard_normal(30)
    d = psd_qp.least_norm(A, y)
    assert np.allclose(d, np.linalg.lstsq(A, y, rcond=None)[0], rtol=1e-10, atol=1e-12)
    A[7] = 0.0  # an exactly zero row: gelsd answers
    d = psd_qp.least_norm(A, y)
    assert np.allclose(d, np.linalg.lstsq(A, y, rcond=None)[0], rtol=1e-10, atol=1e-12)
    A[7] = 1e-15 * rng.standard_normal(80)  # nearly: gels's pivot 1e-15, no error from gels
    d = psd_qp.least_norm(A, y)
    assert np.allclose(d, np.linalg.lstsq(A, y, rcond=None)[0], rtol=1e-10, atol=1e-12)
    tall, b = rng.standard_normal((80, 30)), rng.standard_normal(80)  # the least-squares solution
    assert np.allclose(psd_qp.least_norm(tall, b), np.linalg.lstsq(tall, b, rcond=None)[0], rtol=1e-10)


def test_the_scaled_correction_removes_the_null_part_or_is_refused(monkeypatch):
    """QuadraticPSD._scaled_correction on the r = 4 probes' last iterate: the corrected Gram
    multiplier has no part along the null space beyond rounding and stays >= 0 where Lambda_0
    is; a solve that does nothing (y = 0: the whole part left) is refused, not used."""
    import scipy.linalg

    from dolfinx_lopinf.core.lsq import psd_qp

    seen, orig = [], psd_qp.polish
    monkeypatch.setattr(psd_qp, "polish", lambda p, x, Lam, gap: seen.append((p, Lam)) or orig(p, x, Lam, gap))
    pl.fit_polynomial(_svk_probes(), constraint="sos", solver="ipm")
    (p, Lam), = seen
    Lam = [psd_qp.sym(Lk) for Lk in Lam]
    c = p.null.T @ p.lin(Lam)
    out = p._scaled_correction(Lam, c)
    assert out is not None
    lin = p.lin([out] + Lam[1:])
    assert np.linalg.norm(p.null.T @ lin) <= max(1e-6 * np.linalg.norm(c),
                                                 psd_qp.LEFT_ROUNDING * np.finfo(float).eps * np.linalg.norm(lin))
    monkeypatch.setattr(scipy.linalg, "solve", lambda T, b, **kw: np.zeros_like(b))
    assert p._scaled_correction(Lam, c) is None
