"""Inference engine: structured solvers agree with the cvxpy reference, certify themselves,
and ROMs save/load and run with either scheme (numpy + cvxpy only)."""

import warnings

import numpy as np
import pytest

import dolfinx_lopinf as lo
from dolfinx_lopinf.core import lsq


def _forced_damped_data(r=5, m=2, n=6000, dt=2e-3, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((r, r))
    K = A @ A.T / r + 0.5 * np.eye(r)
    Cm = rng.standard_normal((r, r))
    C = 0.05 * Cm @ Cm.T / r + 0.01 * np.eye(r)
    B = rng.standard_normal((r, m))
    rom = lo.core.LagrangianROM(K=K, C=C, B=B)
    freqs = rng.uniform(0.5, 3.0, size=(m, 3))

    def u(t):
        return np.sin(freqs * t).sum(axis=1)

    tr = rom.simulate(rng.standard_normal(r), rng.standard_normal(r), dt, n, inputs=u)
    U = np.column_stack([u(t) for t in tr.times])
    Q = tr.Qh + noise * np.abs(tr.Qh).max() * rng.standard_normal(tr.Qh.shape)
    Qh, dQh, ddQh = lo.core.derivatives(Q, tr.times)
    return (Qh, dQh, ddQh, U[:, 4:-4]), (K, C, B)


def _solve(strategy, L, Z, n_blocks, eps):
    """(Theta, certificate dict) of ``strategy`` on ``lsq.Problem(L, Z, n_blocks, eps)``."""
    theta, cert = strategy.solve(lsq.Problem(L, Z, n_blocks, eps))
    return theta, cert.as_dict()


def _quiet(fn, *args, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*args, **kw)


def test_clean_forced_damped_data_recovers_the_operators():
    data, (K, C, B) = _forced_damped_data()
    ops = lo.core.infer_mechanical(*data)
    assert np.linalg.norm(ops.K - K) / np.linalg.norm(K) < 1e-4
    assert np.linalg.norm(ops.C - C) / np.linalg.norm(C) < 1e-2
    assert np.linalg.norm(ops.B - B) / np.linalg.norm(B) < 1e-4
    assert np.array_equal(ops.K, ops.K.T) and np.array_equal(ops.C, ops.C.T)


def test_active_constraints_match_clarabel():
    """Noisy data: the unconstrained fit is indefinite, so the PSD constraints are active;
    our interior point solution and Clarabel's reach the same objective."""
    data, _ = _forced_damped_data(noise=1e-3, seed=3)
    unconstrained = lo.core.infer_opinf(*data)
    assert min(np.linalg.eigvals(unconstrained.K).real.min(),
               np.linalg.eigvals(unconstrained.C).real.min()) < 0
    ours = lo.core.infer_mechanical(*data)
    ref = _quiet(lo.core.infer_mechanical, *data, solver="cvxpy")
    assert ours.certificate["solver"] == "ipm" and ours.certificate["duality_gap"] <= 1e-8
    gap = (ours.certificate["objective"] - ref.certificate["objective"]) / ref.certificate["objective"]
    assert gap < 1e-6, gap
    assert ours.certificate["min_eig_K"] >= 1e-8 * (1 - 1e-6)
    assert ours.certificate["min_eig_C"] >= 1e-8 * (1 - 1e-6)
    # KKT: multipliers (gradients on the constrained blocks) PSD, complementarity ~ 0
    assert ours.certificate["multiplier_min_eig"] > -1e-6
    assert ours.certificate["complementarity"] < 1e-6
    # the log-barrier method (the last resort) reaches the same point with a small gap
    from dolfinx_lopinf.core.inference import gram_data

    g = gram_data(*data)
    free = np.zeros(g.L.shape[0], dtype=bool)
    free[-data[3].shape[0]:] = True
    L_S, Z_S, _ = lsq.eliminate_free(g.L, g.Z, free)
    theta, info = _solve(lsq.Barrier(), L_S, Z_S, 2, 1e-8)
    assert info["converged"] and info["duality_gap"] < 1e-8
    r = data[0].shape[0]
    assert np.allclose(theta[:, :r], ours.K, rtol=1e-4, atol=1e-6 * np.abs(ours.K).max())


def test_conservative_admm_certificate_and_lyapunov_path():
    rng = np.random.default_rng(5)
    r = 6
    L = np.tril(rng.standard_normal((r, r))) + 3 * np.eye(r)
    # a target whose symmetric minimiser is indefinite: K* = -diag(...) mixes signs
    K_star = np.diag([5.0, 2.0, 1.0, -0.5, -2.0, 0.3])
    Z = -K_star @ L
    K, info = _solve(lsq.EigenbasisADMM(), L, Z, 1, 1e-8)
    assert info["converged"]
    kkt = lsq.kkt(L, Z, K, [slice(0, r)], 1e-8)
    assert kkt["multiplier_min_eig"] > -1e-7 and kkt["complementarity"] < 1e-6
    assert np.linalg.eigvalsh(K).min() >= 1e-8 * (1 - 1e-6)
    # feasible target: Lyapunov solution is exact
    K2 = lsq.solve_symmetric(L, -np.diag([1.0, 2, 3, 4, 5, 6]) @ L)
    assert np.allclose(K2, np.diag([1.0, 2, 3, 4, 5, 6]), atol=1e-10)


def test_conservative_fit_agrees_with_clarabel_when_constraint_active():
    rng = np.random.default_rng(2)
    r, n = 4, 800
    Qh = rng.standard_normal((r, n))
    K_true = np.diag([3.0, 1.0, -1.0, 2.0])  # indefinite: the constraint must act
    ddQh = -K_true @ Qh + 0.01 * rng.standard_normal((r, n))
    ours = lo.core.infer_mechanical(Qh, None, ddQh, damping=False)
    admm = lo.core.infer_mechanical(Qh, None, ddQh, damping=False, solver="admm")
    ref = _quiet(lo.core.infer_mechanical, Qh, None, ddQh, damping=False, solver="cvxpy")
    assert ours.certificate["solver"] == "ipm" and ours.certificate["duality_gap"] <= 1e-8
    assert admm.certificate["solver"] == "admm"
    for fit in (ours, admm):
        assert fit.certificate["objective"] <= ref.certificate["objective"] * (1 + 1e-6)


def test_infer_wave_recovers_a_symmetric_operator():
    rng = np.random.default_rng(4)
    r, n = 5, 500
    A = rng.standard_normal((r, r))
    K = -(A @ A.T) / r  # negative semidefinite (a discrete second derivative)
    Qh = rng.standard_normal((r, n))
    Fh = np.sin(Qh)
    ddQh = K @ Qh - Fh
    ops = lo.core.infer_wave(Qh, ddQh, Fh)
    assert np.allclose(ops.K, K, atol=1e-10)
    assert np.array_equal(ops.K, ops.K.T)


def test_rom_save_load_roundtrip_and_newmark(tmp_path):
    _, (K, C, B) = _forced_damped_data(r=3, m=1)
    rom = lo.core.LagrangianROM(K=K, C=C, B=B, E=np.ones((1, 3)), scheme="newmark",
                           meta={"method": "lopinf"})
    path = lo.core.rom.save_rom(tmp_path / "rom.npz", rom, basis_rows=np.eye(3)[:2], rows=[7, 9])
    loaded, extras = lo.core.rom.load_rom(path)
    assert loaded.scheme == "newmark" and loaded.meta == {"method": "lopinf"}
    assert np.array_equal(extras["rows"], [7, 9])
    u = lambda t: np.array([np.sin(t)])
    a = rom.simulate(np.ones(3), np.zeros(3), 1e-2, 300, inputs=u)
    b = loaded.simulate(np.ones(3), np.zeros(3), 1e-2, 300, inputs=u)
    assert np.array_equal(a.Y, b.Y)
    with pytest.raises(ValueError, match=r"inputs must have shape \(1, 301\)"):
        rom.simulate(np.ones(3), np.zeros(3), 1e-2, 300, inputs=np.zeros((2, 301)))


@pytest.mark.parametrize("scheme", ["midpoint", "newmark"])
def test_forced_rom_converges_at_second_order(scheme):
    from scipy.integrate import solve_ivp

    K, C, B = np.diag([1.0, 4.0]), 0.1 * np.eye(2), np.array([[1.0], [0.5]])
    rom = lo.core.LagrangianROM(K=K, C=C, B=B, scheme=scheme)
    u = lambda t: np.array([np.sin(2 * t)])
    rhs = lambda t, y: np.concatenate([y[2:], B @ u(t) - C @ y[2:] - K @ y[:2]])
    ref = solve_ivp(rhs, [0, 4], [1, 0, 0, 0], rtol=1e-12, atol=1e-13).y[:2, -1]
    errs = [np.abs(rom.simulate(np.array([1.0, 0]), np.zeros(2), dt, round(4 / dt),
                                inputs=u).Qh[:, -1] - ref).max() for dt in (0.02, 0.01)]
    assert 3.5 < errs[0] / errs[1] < 4.5


def test_bad_inputs_are_named():
    data, _ = _forced_damped_data(r=3, m=1)
    Qh, dQh, ddQh, U = data
    with pytest.raises(ValueError, match="ddQh must have"):
        lo.core.infer_mechanical(Qh, dQh, ddQh[:, :-1], U)
    bad = Qh.copy()
    bad[1, 5] = np.inf
    with pytest.raises(ValueError, match="non-finite"):
        lo.core.infer_mechanical(bad, dQh, ddQh, U)
    dup = (np.vstack([Qh, Qh[:1]]), np.vstack([dQh, dQh[:1]]), np.vstack([ddQh, ddQh[:1]]), U)
    with pytest.raises(lo.errors.RankDeficientDataError, match="rank 7 < 9"):
        lo.core.infer_mechanical(*dup, strict=True)
    with pytest.warns(lo.errors.IllConditionedDataWarning, match="rank 7 < 9"):
        lo.core.infer_mechanical(*dup)
    with pytest.raises(ValueError, match="unknown solver"):
        lo.core.infer_mechanical(Qh, dQh, ddQh, U, solver="sdpt3")
    rom = lo.core.LagrangianROM(K=np.eye(3), B=np.ones((3, 1)))
    with pytest.raises(ValueError, match="inputs must have shape"):
        rom.simulate(np.zeros(3), np.zeros(3), 0.1, 10, inputs=np.zeros((2, 10)))


def test_symmetric_normal_equations_match_the_residual():
    """x^T H x + 2 h^T x + ||Z||^2 is ||Theta(x) L + Z||_F^2 for the vech unknowns x."""
    rng = np.random.default_rng(1)
    r, nb = 5, 2
    L, Z = rng.standard_normal((nb * r, nb * r)), rng.standard_normal((r, nb * r))
    H, h = lsq.symmetric_normal_equations(L, Z, nb)
    for _ in range(3):
        blocks = [rng.standard_normal((r, r)) for _ in range(nb)]
        blocks = [b + b.T for b in blocks]
        x = np.concatenate([b[np.triu_indices(r)] for b in blocks])
        theta = np.hstack(blocks)
        assert x @ H @ x + 2 * h @ x + np.sum(Z**2) == pytest.approx(np.sum((theta @ L + Z) ** 2), rel=1e-12)


@pytest.mark.parametrize("method", ["auto", "admm"])
@pytest.mark.parametrize("r,seed", [(8, 0), (12, 2), (20, 1)])
def test_psd_block_solvers_are_certified_against_clarabel(r, seed, method):
    """Both PSD blocks active: the interior point method ("auto") and ADMM + face Newton
    ("admm") each return a feasible point whose certified duality gap is <= 1e-8, and that
    certified lower bound does not exceed Clarabel's value. (20, 1) is the case where ADMM
    needed 144 iterations to find the face."""
    from dolfinx_lopinf.core.synthetic import forced_data
    from dolfinx_lopinf.core.inference import _solve_cvxpy, gram_data

    Qh, dQh, ddQh, U = forced_data(r, 3000, seed=seed)
    g = gram_data(Qh, dQh, ddQh, U)
    free = np.zeros(g.L.shape[0], dtype=bool)
    free[-1] = True
    L_S, Z_S, _ = lsq.eliminate_free(g.L, g.Z, free)
    theta, info = _solve(lsq.PSDBlocks(method=method), L_S, Z_S, 2, 1e-8)
    assert info["converged"] and info["method"] == {"auto": "ipm", "admm": "admm+face"}[method]
    assert info["duality_gap"] <= 1e-8
    assert min(info["face_ranks"]) < r  # an active constraint: a proper face
    for b in (slice(0, r), slice(r, 2 * r)):
        assert np.array_equal(theta[:, b], theta[:, b].T)
        w = np.linalg.eigvalsh(theta[:, b])  # >= eps up to the rounding of eigvalsh
        assert w.min() >= 1e-8 - 64 * np.finfo(float).eps * np.abs(w).max()
    f_ours = float(np.sum((theta @ L_S + Z_S) ** 2))
    lower = f_ours * (1 - info["duality_gap"])
    ref = _quiet(_solve_cvxpy, g, 1e-8)
    # Clarabel's objective on the reduced problem (B minimised out exactly as in ours), at
    # its point made feasible (Clarabel meets K, C >= eps I only to its own tolerance, and
    # an infeasible point may undercut the bound by ~1e-8: a verdict rounding could flip)
    from dolfinx_lopinf.core.gram import psd_floor

    theta_ref = np.hstack([psd_floor(ref.K, 1e-8), psd_floor(ref.C, 1e-8)])
    f_ref_S = float(np.sum((theta_ref @ L_S + Z_S) ** 2))
    # Clarabel's point is feasible, so it cannot beat the certified lower bound
    assert lower <= f_ref_S * (1 + 1e-9), (lower, f_ref_S)
    assert f_ours <= f_ref_S * (1 + 1e-8)


def test_gram_data_is_the_compressed_problem():
    """L L^T = D D^T, Z L^T = ddQh D^T and ||ddQh||^2 - ||Z||^2 is the least-squares residual."""
    from dolfinx_lopinf.core.inference import gram_data

    rng = np.random.default_rng(4)
    Qh, dQh, ddQh = (rng.standard_normal((3, 500)) for _ in range(3))
    U = rng.standard_normal((2, 500))
    g = gram_data(Qh, dQh, ddQh, U)
    D = np.vstack([Qh, dQh, U])
    assert np.allclose(g.L @ g.L.T, D @ D.T, rtol=1e-12, atol=1e-10 * np.abs(D @ D.T).max())
    assert np.allclose(g.Z @ g.L.T, ddQh @ D.T, rtol=1e-12, atol=1e-10 * np.abs(ddQh @ D.T).max())
    theta = np.linalg.lstsq(D.T, ddQh.T, rcond=None)[0].T
    assert g.target_norm2 - np.sum(g.Z**2) == pytest.approx(np.sum((ddQh - theta @ D) ** 2), rel=1e-10)


def test_inference_runs_with_one_blas_thread_and_restores_the_callers_setting():
    """The entry points pin BLAS to one thread while they run (small kernels) and give the
    caller's thread count back, also when they raise."""
    from threadpoolctl import ThreadpoolController

    from dolfinx_lopinf.core._blas import blas_controller

    ctl = ThreadpoolController()
    data, _ = _forced_damped_data(r=3, m=1, n=800)
    with ctl.limit(limits=2, user_api="blas"):
        before = [p["num_threads"] for p in ctl.info() if p["user_api"] == "blas"]
        seen = []
        original = lo.core.inference.gram_data

        def spy(*a, **k):
            seen.append([p["num_threads"] for p in blas_controller().info() if p["user_api"] == "blas"])
            return original(*a, **k)

        lo.core.inference.gram_data = spy
        try:
            lo.core.infer_mechanical(*data)
            with pytest.raises(ValueError):
                lo.core.infer_mechanical(*data[:3], np.full_like(data[3], np.nan))
        finally:
            lo.core.inference.gram_data = original
        after = [p["num_threads"] for p in ctl.info() if p["user_api"] == "blas"]
    assert seen and all(n == 1 for n in seen[0])
    assert after == before


def test_interior_point_crossover_and_fallback_are_certified():
    """Stopped early, the interior point method hands its face to Newton on the fixed-rank
    face (crossover, certified in a few steps); stopped too early for the face to be right,
    ADMM + face Newton takes over - every path ends certified."""
    from dolfinx_lopinf.core.synthetic import forced_data
    from dolfinx_lopinf.core.inference import gram_data

    Qh, dQh, ddQh, U = forced_data(12, 3000, seed=2)
    g = gram_data(Qh, dQh, ddQh, U)
    free = np.zeros(g.L.shape[0], dtype=bool)
    free[-1] = True
    L_S, Z_S, _ = lsq.eliminate_free(g.L, g.Z, free)
    full, info_full = _solve(lsq.PSDBlocks(), L_S, Z_S, 2, 1e-8)
    assert info_full["method"] == "ipm" and not info_full["ipm"].get("crossover")
    f_full = np.sum((full @ L_S + Z_S) ** 2)
    for ipm_iters, method in [(5, "ipm"), (2, "admm+face")]:
        theta, info = _solve(lsq.PSDBlocks(ipm_max_iter=ipm_iters), L_S, Z_S, 2, 1e-8)
        assert info["converged"] and info["method"] == method and info["duality_gap"] <= 1e-8
        assert info["ipm"].get("crossover", False) == (method == "ipm")
        assert np.sum((theta @ L_S + Z_S) ** 2) == pytest.approx(f_full, rel=2e-8)
    with pytest.raises(ValueError, match="method"):
        _solve(lsq.PSDBlocks(method="clarabel"), L_S, Z_S, 2, 1e-8)


@pytest.mark.parametrize("seed,eliminated", [(2, True), (0, False)])
def test_interior_point_on_the_active_block_only_is_certified(seed, eliminated):
    """Only C's symmetric minimiser is indefinite: the interior point first runs on C with K
    minimised out exactly. Seed 2: K stays > eps I at the optimum, the reduced run is kept
    and equals the full interior point's answer; seed 0: K is active at the optimum, the
    reduced run is abandoned (early: K is below eps I from its first iterations) and the full
    one answers. Both certified <= 1e-8."""
    from dolfinx_lopinf.core.synthetic import forced_data
    from dolfinx_lopinf.core.inference import gram_data

    r = 12
    g = gram_data(*forced_data(r, 3000, seed=seed))
    free = np.zeros(g.L.shape[0], dtype=bool)
    free[-1] = True
    L_S, Z_S, _ = lsq.eliminate_free(g.L, g.Z, free)
    theta, info = _solve(lsq.PSDBlocks(), L_S, Z_S, 2, 1e-8)
    theta_full, info_full = _solve(lsq.PSDBlocks(eliminate=False), L_S, Z_S, 2, 1e-8)
    assert info["eliminated_blocks_tried"] == [0] and "eliminated_blocks_tried" not in info_full
    assert (info["ipm"].get("eliminated_blocks") == [0]) == eliminated
    assert info["face_ranks"][0] == r if eliminated else info["face_ranks"][0] < r
    if not eliminated:  # K below eps from the first iterations: abandoned at the second
        # watched one (measured 2; with the watch from rel 1e-3 only, 4)
        assert 1 <= info["eliminated_run_iterations"] <= 3
    for res in (info, info_full):
        assert res["converged"] and res["method"] == "ipm" and res["duality_gap"] <= 1e-8
    f, f_full = (float(np.sum((t @ L_S + Z_S) ** 2)) for t in (theta, theta_full))
    assert abs(f - f_full) <= 2e-8 * f_full
    assert np.linalg.eigvalsh(theta[:, :r]).min() >= 1e-8
    assert np.linalg.eigvalsh(theta[:, r:]).min() >= 1e-8 - 1e-14 * np.abs(theta[:, r:]).max()


def test_a_candidate_fit_keeps_a_nearly_certified_interior_point_without_its_crossover(monkeypatch):
    """An interior point stopped uncertified (here: asked for a gap of 1e-14, beyond what it
    resolves) crosses over to its face; with ``crossover_above`` (lo.fit's candidates:
    PSDBlocks(fallback=False), gap at most blocks.CANDIDATE_GAP) a gap at most that keeps the
    interior point's own point, and an unknown gap (inf) still crosses over."""
    from dolfinx_lopinf.core.inference import gram_data
    from dolfinx_lopinf.core.lsq import blocks, ipm
    from dolfinx_lopinf.core.lsq.face import FaceNewton
    from dolfinx_lopinf.core.lsq.problem import symmetric_start
    from dolfinx_lopinf.core.synthetic import forced_data

    g = gram_data(*forced_data(6, 3000, seed=0))
    free = np.zeros(g.L.shape[0], dtype=bool)
    free[-1] = True
    L_S, Z_S, _ = lsq.eliminate_free(g.L, g.Z, free)
    problem = lsq.Problem(L_S, Z_S, 2, 1e-8)
    x, feasible = symmetric_start(problem)
    crossed, real = [], ipm._crossover
    monkeypatch.setattr(ipm, "_crossover", lambda *a: crossed.append(a[2].duality_gap) or real(*a))
    runs = {}
    for above in (0.0, blocks.CANDIDATE_GAP):
        crossed.clear()
        x_ip, cert, _ = ipm.interior_point(problem, x, feasible, FaceNewton(problem, 1e-14), gap_tol=1e-14,
                                           eliminate=False, crossover_above=above)
        runs[above] = (x_ip, cert, list(crossed))
    (_, _, crossed0), (_, c1, crossed1) = runs[0.0], runs[blocks.CANDIDATE_GAP]
    assert not c1.converged and 1e-14 < c1.duality_gap <= blocks.CANDIDATE_GAP and crossed1 == []
    assert len(crossed0) == 1  # the same stop, crossed over
    crossed.clear()
    ipm.interior_point(problem, x, feasible, FaceNewton(problem, 1e-8), max_iter=3, eliminate=False,
                       crossover_above=blocks.CANDIDATE_GAP)  # stopped before any gap was computed
    assert crossed == [np.inf]
