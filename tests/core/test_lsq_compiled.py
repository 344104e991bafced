"""The compiled (numba) interior point iteration against the numpy reference: the same
certified optimum (objectives to 1e-10, the same iteration counts, gaps <= 1e-8), the same
certificate fields, and the numpy fallback when the JIT is disabled."""

import numpy as np
import pytest

from dolfinx_lopinf.core import compiled, inference, lsq
from dolfinx_lopinf.core.lsq import _compiled, ipm
from dolfinx_lopinf.errors import InputError
from dolfinx_lopinf.core import synthetic

needs_numba = pytest.mark.skipif(not compiled.available(), reason="numba not installed or JIT disabled")
EPS = 1e-8


def _gram_problem(data):
    (Qs, dQs, ddQs, Us), _, _ = inference._unit_scaled(*data)
    g = inference.gram_data(Qs, dQs, ddQs, Us)
    return lsq.Problem(g.L, g.Z, 2, EPS, g.m)


def _solve(problem, backend, strategy=lsq.Auto):
    theta, cert = strategy(backend=backend).solve(problem)
    return theta, cert, problem.objective(theta)


# sets whose interior point path is stable under rounding (the numpy path itself moves by
# less than 1e-12 when the data are perturbed at 1e-15), both blocks active on all but forced
SETS = [("forced", 4, 600), ("forced", 6, 600), ("rigid", 6, 800), ("mixed", 6, 800),
        ("short", 6, 800), ("short", 4, 3000)]


@needs_numba
@pytest.mark.parametrize("kind, r, n", SETS)
def test_compiled_interior_point_reaches_the_numpy_optimum(kind, r, n):
    data = synthetic.mechanical_data(kind, r, n)
    problem = _gram_problem(data)
    th_np, c_np, f_np = _solve(problem, "numpy")
    th_nb, c_nb, f_nb = _solve(problem, "numba")
    assert c_np.details["ipm"]["backend"] == "numpy" and c_nb.details["ipm"]["backend"] == "numba"
    assert c_np.converged and c_nb.converged
    assert c_nb.iterations == c_np.iterations
    assert abs(f_nb - f_np) <= 1e-10 * f_np
    assert c_nb.duality_gap <= 1e-8 and c_np.duality_gap <= 1e-8
    assert c_nb.face_ranks == c_np.face_ranks
    trace_np, trace_nb = np.array(c_np.details["ipm"]["trace"]), np.array(c_nb.details["ipm"]["trace"])
    assert trace_nb.shape == trace_np.shape
    # the step lengths, to rounding while the Schur matrix is well conditioned (the last
    # iterations amplify rounding, both paths alike)
    half = len(trace_np) // 2
    np.testing.assert_allclose(trace_nb[:half, :2], trace_np[:half, :2], rtol=1e-7)
    for k in range(2):
        S = th_nb[:, k * r:(k + 1) * r]
        assert np.array_equal(S, S.T)
        assert np.linalg.eigvalsh(S).min() >= EPS - 64 * np.finfo(float).eps * np.abs(S).max()


@needs_numba
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_interior_point_on_random_problems_and_one_active_block(seed):
    """The test problems of test_solvers (both blocks active), and one block active only:
    the other eliminated (the watch callback's path)."""
    rng = np.random.default_rng(seed)
    r, p = 5, 10
    L = np.tril(rng.standard_normal((p, p))) + 3 * np.eye(p)
    A = rng.standard_normal((r, r))
    K = A @ A.T / r + 0.1 * np.eye(r)
    w, Q = np.linalg.eigh(K)
    K_ind = (Q * (w - 0.6 * w.max() * (np.arange(r) < r // 2))) @ Q.T
    C = np.eye(r)
    for blocks, eliminated in (([K_ind, K_ind - 0.1 * np.eye(r)], False),
                               ([K_ind, C], True)):
        theta_star = np.hstack([0.5 * (B + B.T) for B in blocks])
        Z = -theta_star @ L + 1e-3 * rng.standard_normal((r, p))
        problem = lsq.Problem(L, Z, 2, EPS)
        _, c_np, f_np = _solve(problem, "numpy", lsq.PSDBlocks)  # eliminate=True at any r
        _, c_nb, f_nb = _solve(problem, "numba", lsq.PSDBlocks)
        assert c_nb.converged and c_nb.iterations == c_np.iterations
        assert abs(f_nb - f_np) <= 1e-10 * f_np
        assert ("eliminated_blocks" in c_nb.details["ipm"]) == eliminated


@needs_numba
def test_compiled_interior_point_with_the_full_run_interface():
    """PrimalDualIPM.run directly: the trace, mu, face ranks and a watch that stops it."""
    problem, _ = _gram_problem(synthetic.active_data("rigid", 4, 600)).without_free()
    H, h = problem.normal_equations
    x, _ = lsq.problem.symmetric_start(problem)
    out = {}
    for backend in ("numpy", "numba"):
        ipm_ = lsq.PrimalDualIPM(H, h, float(np.sum(problem.Z**2)), 4, 2, EPS, backend)
        out[backend] = ipm_.run(x, certify=problem.dual_gap, gap_tol=1e-8)
        calls = []
        stopped = ipm_.run(x, certify=problem.dual_gap, gap_tol=1e-8,
                           watch=lambda xx, rel, calls=calls: calls.append(rel) or len(calls) < 3)
        assert stopped[1].details["stopped"] == "stopped by watch" and stopped[1].iterations == 3
        assert len(stopped[1].details["trace"]) == 3
    (x_np, c_np), (x_nb, c_nb) = out["numpy"], out["numba"]
    assert c_nb.iterations == c_np.iterations and c_nb.face_ranks == c_np.face_ranks
    np.testing.assert_allclose(x_nb, x_np, rtol=0, atol=1e-7 * np.abs(x_np).max())
    assert abs(c_nb.details["mu"] - c_np.details["mu"]) <= 1e-3 * c_np.details["mu"]
    assert c_nb.duality_gap <= 1e-8


@needs_numba
def test_compiled_step_length_eigenvalue_matches_lapack():
    k = _compiled.kernels()
    rng = np.random.default_rng(3)
    iw, ch = np.zeros(4, dtype=np.int32), np.array([76, 78, 84], dtype=np.uint8)
    for r in (1, 2, 3, 5, 12, 20, 80):
        for t in range(30):
            A = rng.standard_normal((r, r))
            W = A + A.T
            if t % 3 == 0:  # graded
                g = np.geomspace(1.0, 1e-8, r)
                W = W * g[:, None] * g[None, :]
            ref = np.linalg.eigvalsh(W)
            e1 = max(r - 1, 1)
            got = k["_min_eig"](W.copy(), np.empty(r), np.empty(e1))
            # the learned-mass pencils' variant: LAPACK's reduction, the same bisection
            got_lapack = k["_min_eig_lapack"](W.copy(), np.empty(r), np.empty(e1), np.empty(e1),
                                              np.empty(64 * r), iw, ch)
            for g_ in (got, got_lapack):
                assert abs(g_ - ref[0]) <= 8 * np.finfo(float).eps * np.abs(ref).max() * r
    assert _compiled.warm_up() == 0.0 and _compiled.compile_seconds() > 0


@needs_numba
@pytest.mark.parametrize("kind, r", [("mixed", 4), ("rigid", 12), ("short", 20)])
def test_compiled_start_is_the_numpy_paths(kind, r):
    """The kernel _start: the scaled problem (2 Hs, 2 hs, c0) and the starting point
    (x, X, Lambda = c X^-1) of the numpy path's __init__ and _start, to rounding."""
    problem, _ = _gram_problem(synthetic.active_data(kind, r, 800)).without_free()
    H, h = problem.normal_equations
    x_start, feasible = lsq.problem.symmetric_start(problem)
    assert not feasible.all()  # a start with eigenvalues to flip
    ref = ipm.PrimalDualIPM(H, h, float(np.sum(problem.Z**2)), r, 2, EPS, "numpy")
    x_ref, X_ref, L_ref = ref._start(x_start)
    n = len(h)
    M0, hs2, x, X, Lam = np.empty((n, n)), np.empty(n), np.empty(n), np.empty((2, r, r)), np.empty((2, r, r))
    nb = ipm.PrimalDualIPM(H, h, float(np.sum(problem.Z**2)), r, 2, EPS, "numba")
    c0 = _compiled.kernels()["_start"](nb.H, nb.h, nb.const, nb.T, nb.x_eps, x_start,
                                       ipm._kernel_index(r)[3], nb.f_floor, M0, hs2, x, X, Lam)
    np.testing.assert_allclose(M0, ref.H2, rtol=1e-14, atol=0)
    np.testing.assert_allclose(hs2, 2 * ref.hs, rtol=1e-12, atol=1e-14 * np.abs(ref.hs).max())
    assert abs(c0 - ref.c0) <= 1e-12 * abs(ref.c0)
    for got, want in ((x, x_ref), (X, X_ref)):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())
    # Lambda's scale is 0.1 f(x) / m, f summed in another order (x^T M0 x / 2 + hs2^T x + c0,
    # the kernel's f): it cancels down from ||Z||^2, so to ~1e-12 relative, not to u
    np.testing.assert_allclose(Lam, L_ref, rtol=0, atol=1e-10 * np.abs(L_ref).max())


def test_compiled_kernel_constants_are_the_numpy_paths():
    for name in ("STEP_FRACTION", "STALL_STEP", "STALL_GAP", "STALL_RUN", "NEAR_GAP", "NEAR_FLAT"):
        assert getattr(_compiled, name) == getattr(ipm, name), name


def test_jit_disabled_falls_back_to_the_numpy_iteration(monkeypatch):
    monkeypatch.setenv(compiled.JIT_ENV, "0")
    assert not _compiled.available() and _compiled.warm_up() is None
    problem = _gram_problem(synthetic.active_data("mixed", 4, 600))
    theta, cert = lsq.Auto().solve(problem)
    assert cert.converged and cert.details["ipm"]["backend"] == "numpy"
    H, h = problem.without_free()[0].normal_equations
    assert ipm.PrimalDualIPM(H, h, 1.0, 4, 2, EPS).backend == "numpy"
    with pytest.raises(InputError, match="numba"):
        ipm.PrimalDualIPM(H, h, 1.0, 4, 2, EPS, backend="numba")


def test_leased_scratch_arrays_are_reused_and_bounded():
    a = lsq.linalg.lease((7, 7))
    lsq.linalg.release(a)
    single = lsq.linalg.lease((7, 7), np.float32)  # kept apart by dtype
    assert single.dtype == np.float32 and single is not a
    assert lsq.linalg.lease((7, 7)) is a
    for n in range(20, 30):
        lsq.linalg.release(np.empty((n, n)))
    assert len(lsq.linalg._SCRATCH) <= 4


@needs_numba
def test_compiled_interior_point_stopped_short_takes_the_same_crossover():
    """max_iter reached: both iterations stop at the same count, uncertified, and the
    crossover to Newton on the face (or its absence) is the same."""
    problem = _gram_problem(synthetic.forced_data(6, 600))
    for max_iter in (3, 6):
        out = {}
        for backend in ("numpy", "numba"):
            theta, cert = lsq.InteriorPoint(max_iter=max_iter, backend=backend).solve(problem)
            out[backend] = (cert.iterations, cert.converged, "crossover" in cert.details["ipm"]
                            or cert.details.get("crossover", False), problem.objective(theta))
        assert out["numba"][:3] == out["numpy"][:3]
        assert abs(out["numba"][3] - out["numpy"][3]) <= 1e-10 * out["numpy"][3]


def _float64_only(monkeypatch):
    monkeypatch.setattr(ipm, "MIXED_FROM_N", 10**9)


@pytest.mark.parametrize("kind, n", [("rigid", 800), ("short", 800), ("mixed", 3000)])
def test_mixed_precision_certifies_the_float64_optimum(kind, n, monkeypatch):
    """r = 20, both blocks active (n = 420 >= MIXED_FROM_N): the early Schur matrices are
    factored in float32, each solve checked in float64. Every run certified (gap <= 1e-8), so
    the objectives agree to 2e-8 (seen <= 2e-9 over 6 rounding variants each); iterations
    within 3 of the float64 run's (seen: 0-2; on mixed the check refuses float32 after 3-4
    iterations). The step lengths of the two backends are not compared: where a float32
    rounding flips, the directions differ by the solve's inexactness (seen: up to 0.6
    relative in one step)."""
    problem = _gram_problem(synthetic.mechanical_data(kind, 20, n))
    backends = ("numpy", "numba") if compiled.available() else ("numpy",)
    runs = {b: _solve(problem, b) for b in backends}
    _float64_only(monkeypatch)
    _, c64, f64 = _solve(problem, "numpy")
    assert c64.converged and c64.details["ipm"]["float32_iterations"] == 0
    for backend, (theta, cert, f) in runs.items():
        assert cert.converged and cert.duality_gap <= 1e-8, backend
        assert cert.details["ipm"]["float32_iterations"] >= 2, backend
        assert abs(f - f64) <= 2e-8 * f64, backend
        assert abs(cert.iterations - c64.iterations) <= 3, backend
        for k in range(2):
            S = theta[:, k * 20:(k + 1) * 20]
            assert np.array_equal(S, S.T)


def _ipm_traces(problem, backend, max_iter=6):
    """(trace, float32 iterations) of PrimalDualIPM.run on the blocks of ``problem``."""
    blocks, _ = problem.without_free()
    H, h = blocks.normal_equations
    x, _ = lsq.problem.symmetric_start(blocks)
    run = ipm.PrimalDualIPM(H, h, float(np.sum(blocks.Z**2)), blocks.r, 2, EPS, backend,
                            blocks.f_floor)
    _, cert = run.run(x, certify=blocks.dual_gap, gap_tol=1e-8, max_iter=max_iter)
    return cert.details["trace"], cert.details["float32_iterations"]


@pytest.mark.parametrize("backend", ["numpy", pytest.param("numba", marks=needs_numba)])
def test_mixed_precision_refused_is_the_float64_iteration(backend, monkeypatch):
    """A float32 factor refused - its solves miss the residual check (forced here by a bound
    of 0) or, numpy path, spotrf fails (forced) - redoes the iteration in float64 and stays
    there: the same iterates, bit for bit, as the float64 run."""
    problem = _gram_problem(synthetic.mechanical_data("rigid", 20, 800))
    assert _ipm_traces(problem, backend)[1] >= 3
    with monkeypatch.context() as m:
        m.setattr(ipm, "MIXED_MAX_RESIDUAL", 0.0)
        refused = _ipm_traces(problem, backend)
    if backend == "numpy":
        with monkeypatch.context() as m:
            m.setattr(ipm.scipy.linalg.lapack, "spotrf", lambda a, **kw: (a, 1))
            assert _ipm_traces(problem, backend) == refused
    _float64_only(monkeypatch)
    assert refused == (_ipm_traces(problem, backend)[0], 0)


@needs_numba
def test_compiled_factor_falls_back_when_float32_is_singular():
    """The kernel's _factor: float32 (2) when asked and spotrf succeeds, float64 (1) when the
    float32 rounding is singular ([[1, 1 - 1e-10], [1 - 1e-10, 1]]: 1 - 1e-10 rounds to 1.0f)
    or float32 is not asked."""
    k = _compiled.kernels()
    r, b = 2, 2
    n = b * r * (r + 1) // 2
    iu0, iu1, cw, _ = ipm._kernel_index(r)
    zeros = np.zeros((b, r, r))
    iw, ch = np.zeros(4, dtype=np.int32), np.array([76, 78, 84], dtype=np.uint8)
    near = np.eye(n)
    near[0, 1] = near[1, 0] = 1.0 - 1e-10
    for M0, single, kind in ((np.eye(n) + 0.1, True, 2), (near, True, 1), (np.eye(n), False, 1)):
        Mw, Mf = np.empty((n, n)), np.empty((n, n), dtype=np.float32)
        assert k["_factor"](M0, zeros, zeros, iu0, iu1, cw, Mw, Mf, single, iw, ch) == kind


def test_mixed_precision_only_from_mixed_from_n():
    """r = 12 with two blocks (n = 156 < MIXED_FROM_N): float64 throughout."""
    problem = _gram_problem(synthetic.mechanical_data("rigid", 12, 800))
    _, cert, _ = _solve(problem, "numpy")
    assert cert.converged and cert.details["ipm"]["float32_iterations"] == 0


@needs_numba
@pytest.mark.parametrize("n", [1, 3, 12])
def test_psd_qp_compiled_kernel_equals_the_numpy_kernel(n):
    """The sos interior point's Newton matrix kernel K(X^-1, Lambda), compiled, is the numpy
    Kronecker kernel's matrix to rounding (non-symmetric P and Q too: every index is used)."""
    from dolfinx_lopinf.core.lsq import psd_qp
    from dolfinx_lopinf.core.lsq.fractional import kernel

    rng = np.random.default_rng(n)
    P, Q = rng.standard_normal((n, n)), rng.standard_normal((n, n))
    H = psd_qp._kernel(P, Q, n)
    ref = kernel([(1.0, P, Q)], n)
    assert H.shape == ref.shape == (n * (n + 1) // 2,) * 2
    assert np.abs(H - ref).max() <= 1e-14 * np.abs(ref).max()


@needs_numba
@pytest.mark.parametrize("n", [1, 5, 40])
def test_psd_qp_compiled_symmetrisation_is_the_numpy_passes_bit_for_bit(n):
    """The sos interior point's one-pass sym + equilibration of the Schur matrix's lower
    triangle gives the bits of the numpy passes S += S^T, S *= d/2 (rows), S *= d (columns)."""
    from dolfinx_lopinf.core.lsq import psd_qp

    rng = np.random.default_rng(n)
    S, d = rng.standard_normal((n, n)) * 10.0 ** rng.uniform(-8, 8, (n, n)), rng.uniform(0.1, 10, n)
    ref = S.copy()
    ref += ref.T
    ref *= 0.5 * d[:, None]
    ref *= d[None, :]
    ours = psd_qp.sym_scaled_lower(S.copy(), d)
    low = np.tril_indices(n)
    assert np.array_equal(ours[low], ref[low])
