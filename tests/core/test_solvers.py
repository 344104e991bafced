"""The least-squares solvers as objects (dolfinx_lopinf.core.lsq): the shared numerics, the
Problem and its Certificate, and each strategy on its own - every strategy reaches the same
certified optimum, and infer_mechanical takes a name or a strategy object (numpy only)."""

import warnings

import numpy as np
import pytest

import dolfinx_lopinf as lo
from dolfinx_lopinf.core import lsq
from dolfinx_lopinf.errors import InputError
from dolfinx_lopinf.core.lsq import linalg

EPS = 1e-8


def _problem(r=5, n_blocks=2, n_free=0, seed=0, active=True):
    """A compressed problem whose unconstrained optimum has indefinite blocks (``active``)."""
    rng = np.random.default_rng(seed)
    p = n_blocks * r + n_free
    L = np.tril(rng.standard_normal((p, p))) + 3 * np.eye(p)
    blocks = []
    for _ in range(n_blocks):
        A = rng.standard_normal((r, r))
        S = A @ A.T / r + 0.1 * np.eye(r)
        if active:
            w, Q = np.linalg.eigh(S)
            S = (Q * (w - 0.6 * w.max() * (np.arange(r) < r // 2))) @ Q.T
        blocks.append(0.5 * (S + S.T))
    theta_star = np.hstack(blocks + [rng.standard_normal((r, n_free))])
    Z = -theta_star @ L + 1e-3 * rng.standard_normal((r, p))
    return lsq.Problem(L, Z, n_blocks, EPS, n_free)


def _assert_feasible(theta, problem):
    for b in problem.block_slices:
        assert np.array_equal(theta[:, b], theta[:, b].T)
        w = np.linalg.eigvalsh(theta[:, b])
        assert w.min() >= EPS - 64 * np.finfo(float).eps * np.abs(w).max()


# -- the shared numerics ------------------------------------------------------------------

def test_psd_project_is_the_frobenius_projection_and_batches():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((3, 4, 4))
    S, w, Q = linalg.psd_project(A, 0.1)
    assert np.allclose(w, np.linalg.eigvalsh(linalg.sym(A)))
    for k in range(3):
        one = linalg.psd_project(A[k], 0.1)[0]
        assert np.array_equal(one, S[k])  # the batched projection is the single one
        assert np.linalg.eigvalsh(one).min() >= 0.1 - 1e-12
        # idempotent, and the residual is orthogonal to the cone's tangent at S (NSD part)
        assert np.allclose(linalg.psd_project(one, 0.1)[0], one, atol=1e-12)
        assert np.linalg.eigvalsh(linalg.sym(A[k]) - one).max() <= 1e-12
    assert np.allclose(linalg.from_eig(w, Q), linalg.sym(A))


def test_spd_solver_equilibrates_and_falls_back_on_singular_matrices():
    rng = np.random.default_rng(1)
    B = rng.standard_normal((6, 6))
    d = np.logspace(-6, 6, 6)
    H = d[:, None] * (B @ B.T + np.eye(6)) * d[None, :]  # SPD, condition ~1e24 by its scaling
    y = rng.standard_normal((6, 2))
    rhs = d[:, None] * ((B @ B.T + np.eye(6)) @ y)  # H x = rhs for x = y / d, every entry accurate
    solver = linalg.SPDSolver(H)
    assert solver.ok
    assert np.allclose(solver.solve(rhs) * d[:, None], y, rtol=1e-10)
    assert np.allclose(solver.solve(rhs[:, 0]) * d, y[:, 0], rtol=1e-10)
    singular = linalg.SPDSolver(np.diag([1.0, 0.0]))
    assert not singular.ok and np.allclose(singular.solve(np.array([2.0, 0.0])), [2.0, 0.0])



def test_whitened_solves_give_the_schur_complement_of_a_badly_scaled_matrix():
    """G = L^-1 B (H = L L^T, L the equilibrated factor with its scaling): G^T G = B^T H^-1 B
    and unwhiten(whiten(b)) = H^-1 b, on the scaling of test_spd_solver_equilibrates..."""
    rng = np.random.default_rng(4)
    A = rng.standard_normal((8, 8))
    d = np.logspace(-5, 5, 8)
    H = d[:, None] * (A @ A.T + np.eye(8)) * d[None, :]
    B = d[:, None] * rng.standard_normal((8, 3))  # rows scaled with H: B^T H^-1 B is O(1)
    solver = linalg.SPDSolver(H)
    G = solver.whiten(B)
    exact = (B / d[:, None]).T @ np.linalg.solve(A @ A.T + np.eye(8), B / d[:, None])
    assert np.allclose(G.T @ G, exact, rtol=1e-12, atol=1e-12 * np.abs(exact).max())
    b = B[:, 0]
    assert np.allclose(solver.unwhiten(solver.whiten(b)) * d,
                       np.linalg.solve(A @ A.T + np.eye(8), b / d), rtol=1e-10)
    assert np.allclose(solver.whiten(b), G[:, 0], rtol=1e-14, atol=0)


def test_the_reduced_problem_of_the_active_blocks_is_the_exact_schur_complement():
    """_ActiveBlocks minimises the presumed-inactive blocks out: for every x_a, the full
    objective at full(x_a) equals the reduced one, and full(x_a) minimises over x_f."""
    from dolfinx_lopinf.core.lsq import ipm

    rng = np.random.default_rng(5)
    r, p = 3, 6
    L = rng.standard_normal((p, p)) * np.logspace(0, -3, p)[:, None]
    Z = rng.standard_normal((r, p))
    problem = lsq.Problem(L, Z, 2, 1e-8)
    reduced = ipm._ActiveBlocks(problem, np.array([False, True]))
    assert reduced.ok
    H, h = problem.normal_equations
    for _ in range(3):
        xa = rng.standard_normal(len(reduced.a_idx))
        x = reduced.full(xa)
        f_full = x @ H @ x + 2 * h @ x + np.sum(Z**2)
        f_red = xa @ reduced.Hr @ xa + 2 * reduced.hr @ xa + reduced.const
        assert np.isclose(f_full, f_red, rtol=1e-10)
        grad_f = (H @ x + h)[reduced.f_idx]  # stationary in the eliminated unknowns
        assert np.linalg.norm(grad_f) <= 1e-10 * np.linalg.norm(H[reduced.f_idx]) * np.linalg.norm(x)
    assert np.array_equal(reduced.Hr, reduced.Hr.T)


def test_cholesky_solve_is_the_two_triangular_solves_of_potrs():
    rng = np.random.default_rng(3)
    A = rng.standard_normal((30, 30))
    H = A @ A.T + 30 * np.eye(30)
    c = np.asfortranarray(np.linalg.cholesky(H) + np.triu(rng.standard_normal((30, 30)), 1))
    b = rng.standard_normal(30)  # the upper triangle of c is garbage and must not be read
    assert np.allclose(linalg.cholesky_solve(c, b), np.linalg.solve(H, b), rtol=1e-12, atol=0)

def test_vech_index_round_trips_and_lays_out_theta():
    r, nb = 4, 2
    ix = linalg.vech_index(r, nb)
    assert ix.nv == 10 and ix.n == 20 and linalg.vech_index(r, nb) is ix  # cached, read-only
    with pytest.raises(ValueError):
        ix.full[0, 0] = 1
    x = np.arange(ix.n, dtype=float)
    S = ix.blocks(x)
    assert np.array_equal(S, S.transpose(0, 2, 1)) and np.array_equal(ix.vech(S), x)
    assert np.array_equal(ix.theta(x), np.hstack(list(S)))
    assert np.array_equal(ix.blocks(ix.x_eps(0.5)), np.stack([0.5 * np.eye(r)] * nb))
    # <D vech(A), x> = <A, S(x)> for symmetric A
    A = linalg.sym(np.random.default_rng(0).standard_normal((nb, r, r)))
    assert np.isclose(ix.Dw * ix.vech(A) @ x, np.sum(A * S))


def test_face_basis_and_unvech_span_the_face():
    rng = np.random.default_rng(2)
    r, m = 5, 2
    P = np.linalg.qr(rng.standard_normal((r, m)))[0]
    A = linalg.unvech(rng.standard_normal(m * (m + 1) // 2), m)
    iu = np.triu_indices(r)
    c = A[np.triu_indices(m)]
    assert np.allclose(linalg.face_basis(P, iu) @ c, (P @ A @ P.T)[iu])


def test_objective_is_written_once_and_agrees_everywhere():
    """||Theta L + Z||^2 three ways: the residual, the quadratic in vech unknowns, GramData."""
    problem = _problem(seed=3)
    H, h = problem.normal_equations
    x = np.random.default_rng(3).standard_normal(problem.index.n)
    theta = problem.index.theta(x)
    f = problem.objective(theta)
    assert linalg.quadratic(H, h, float(np.sum(problem.Z**2)), x) == pytest.approx(f, rel=1e-12)
    assert problem.objective_x(x) == f == linalg.residual_norm2(theta, problem.L, problem.Z)


# -- the problem and the certificate ------------------------------------------------------

def test_problem_checks_its_layout_and_minimises_free_columns_out():
    with pytest.raises(ValueError, match="do not fit"):
        lsq.Problem(np.eye(7), np.zeros((3, 7)), 2, EPS)
    problem = _problem(r=3, n_free=2, seed=4)
    with pytest.raises(ValueError, match="free columns"):
        problem.normal_equations  # noqa: B018
    reduced, recover = problem.without_free()
    assert reduced.n_free == 0 and reduced.L.shape == (6, 6)
    theta_S = np.hstack([np.eye(3), 2 * np.eye(3)])
    theta = np.hstack([theta_S, recover(theta_S)])
    # the free columns are optimal for the given blocks, and the objectives agree
    assert problem.objective(theta) == pytest.approx(reduced.objective(theta_S), rel=1e-10)
    grad = 2 * (theta @ problem.L + problem.Z) @ problem.L.T
    assert np.abs(grad[:, 6:]).max() < 1e-9 * np.abs(grad).max()


def test_certificate_as_dict_is_the_flat_dict_of_set_fields():
    cert = lsq.Certificate("ipm", True, 7, seconds=0.5, duality_gap=1e-9,
                           details={"ipm": {"iterations": 7}, "crossover": True})
    d = cert.as_dict()
    assert d == {"solver": "ipm", "converged": True, "iterations": 7, "seconds": 0.5,
                 "duality_gap": 1e-9, "ipm": {"iterations": 7}, "crossover": True}
    assert cert.status == "optimal"
    assert lsq.Certificate("admm", False).status == "not converged"


# -- the strategies, each on its own ------------------------------------------------------

def test_lyapunov_is_exact_and_wants_one_block():
    rng = np.random.default_rng(5)
    L = np.tril(rng.standard_normal((4, 4))) + 3 * np.eye(4)
    K = np.diag([1.0, 2.0, 3.0, 4.0])
    theta, cert = lsq.Lyapunov().solve(lsq.Problem(L, -K @ L, 1, EPS))
    assert np.allclose(theta, K, atol=1e-12) and cert.converged and cert.solver == "lyapunov"
    assert cert.duality_gap == 0.0  # >= eps I: the constrained optimum, certified
    indefinite = np.diag([-1.0, 2.0, 3.0, 4.0])
    _, cert = lsq.Lyapunov().solve(lsq.Problem(L, -indefinite @ L, 1, EPS))
    assert cert.duality_gap is None  # the unconstrained minimiser: no certificate
    with pytest.raises(ValueError, match="one symmetric block"):
        lsq.Lyapunov().solve(_problem())


def test_eigenbasis_admm_agrees_with_the_interior_point_on_one_block():
    problem = _problem(r=6, n_blocks=1, seed=6)
    theta, cert = lsq.EigenbasisADMM().solve(problem)
    assert cert.converged and cert.solver == "admm" and cert.iterations > 0
    _assert_feasible(theta, problem)
    kkt = problem.kkt(theta)
    assert kkt["multiplier_min_eig"] > -1e-7 and kkt["complementarity"] < 1e-6
    theta_ip, cert_ip = lsq.InteriorPoint().solve(problem)
    assert cert_ip.converged and cert_ip.duality_gap <= 1e-8
    assert problem.objective(theta) == pytest.approx(problem.objective(theta_ip), rel=1e-7)


@pytest.mark.parametrize("seed", [0, 1])
def test_every_block_strategy_reaches_the_same_certified_optimum(seed):
    problem = _problem(r=5, n_blocks=2, seed=seed)
    results = {}
    for strategy in (lsq.InteriorPoint(), lsq.InteriorPoint(eliminate=False), lsq.FaceADMM(),
                     lsq.PSDBlocks(), lsq.PSDBlocks(method="admm"), lsq.Barrier(), lsq.Auto()):
        theta, cert = strategy.solve(problem)
        assert cert.converged, strategy
        assert cert.duality_gap <= 1e-8, (strategy, cert.duality_gap)
        _assert_feasible(theta, problem)
        results[repr(strategy)] = problem.objective(theta)
    f = np.array(list(results.values()))
    assert f.max() - f.min() <= 2e-8 * f.min(), results
    assert lsq.FaceADMM().solve(problem)[1].method == "admm+face"
    assert lsq.PSDBlocks().solve(problem)[1].method == "ipm"


def test_free_columns_are_handled_by_every_strategy():
    problem = _problem(r=4, n_blocks=2, n_free=2, seed=7)
    theta, cert = lsq.PSDBlocks().solve(problem)
    assert theta.shape == (4, 10) and cert.converged
    grad = 2 * (theta @ problem.L + problem.Z) @ problem.L.T
    assert np.abs(grad[:, 8:]).max() < 1e-8 * np.abs(grad).max()  # free columns stationary


def test_the_symmetric_minimiser_answers_when_it_is_feasible():
    problem = _problem(r=4, seed=8, active=False)
    theta, cert = lsq.PSDBlocks().solve(problem)
    assert cert.method == "symmetric-lsq" and cert.iterations == 0 and cert.duality_gap == 0.0
    H, h = problem.normal_equations
    assert np.allclose(problem.index.vech(np.stack(np.split(theta, 2, axis=1))),
                       -np.linalg.solve(H, h))


def test_primal_dual_ipm_certifies_its_gap_and_reports_its_face():
    problem = _problem(r=5, seed=9)
    H, h = problem.normal_equations
    x0 = -np.linalg.solve(H, h)
    ipm = lsq.PrimalDualIPM(H, h, float(np.sum(problem.Z**2)), 5, 2, EPS)
    x, cert = ipm.run(x0, certify=problem.dual_gap, gap_tol=1e-8)
    assert cert.converged and cert.duality_gap <= 1e-8 and 0 < cert.iterations < 40
    assert len(cert.details["trace"]) == cert.iterations
    assert all(k < 5 for k in cert.face_ranks)  # both constraints active
    gap, _ = problem.dual_gap(x)
    assert gap <= 1e-8


def test_face_newton_turns_a_rough_face_into_a_certified_optimum():
    """Stopped after three interior point iterations, the point shows the face; polish and
    Newton on it reach the certified optimum in a few steps."""
    problem = _problem(r=5, seed=10)
    H, h = problem.normal_equations
    ipm = lsq.PrimalDualIPM(H, h, float(np.sum(problem.Z**2)), 5, 2, EPS)
    x, rough = ipm.run(-np.linalg.solve(H, h), certify=problem.dual_gap, gap_tol=1e-8, max_iter=3)
    assert not rough.converged
    newton = lsq.FaceNewton(problem, 1e-8)
    ranks = lsq.InteriorPoint().solve(problem)[1].face_ranks
    S = problem.index.blocks(x) - EPS * np.eye(5)
    w, Q = np.linalg.eigh(S)
    w = np.where(np.arange(5)[None, :] >= 5 - np.array(ranks)[:, None], w, 0.0)
    x_face = problem.index.x_eps(EPS) + problem.index.vech(linalg.from_eig(w, Q))
    xp, a_min = lsq.polish(problem, w + EPS * (w > 0), Q)
    assert a_min > 0
    refined = newton.refine(xp, ranks) or newton.refine(x_face, ranks)
    assert refined is not None and refined[1] <= 1e-8
    assert newton.steps >= 1 and newton.details()["newton_steps"] == newton.steps


# -- infer_mechanical takes a name or an object, and rejects what it does not know --------

def _forced_data(r=4):
    from dolfinx_lopinf.core.synthetic import forced_data

    return forced_data(r, 3000, seed=3)


def test_infer_mechanical_rejects_unknown_solvers_naming_the_valid_ones():
    data = _forced_data()
    with pytest.raises(InputError, match="unknown solver 'sdpt3'.*'auto', 'lyapunov', 'admm', 'cvxpy'"):
        lo.core.infer_mechanical(*data, solver="sdpt3")
    with pytest.raises(InputError, match="solve\\(problem\\) method, not a int"):
        lo.core.infer_mechanical(*data, solver=3)
    with pytest.raises(InputError, match="conservative, unforced"):
        lo.core.infer_mechanical(*data, solver="lyapunov")


def test_infer_mechanical_takes_a_strategy_object_and_admm_is_a_real_path():
    data = _forced_data()
    auto = lo.core.infer_mechanical(*data)
    # Auto is PSDBlocks, which tries the active blocks alone only from r = ELIMINATE_FROM_R on
    assert data[0].shape[0] < lsq.blocks.ELIMINATE_FROM_R
    obj = lo.core.infer_mechanical(*data, solver=lsq.PSDBlocks(eliminate=False))
    assert np.array_equal(obj.K, auto.K) and np.array_equal(obj.B, auto.B)
    assert {k for k in auto.certificate if k != "seconds"} == {k for k in obj.certificate if k != "seconds"}
    admm = lo.core.infer_mechanical(*data, solver="admm")
    assert admm.certificate["method"] == "admm+face" and admm.certificate["solver"] == "admm"
    assert admm.certificate["status"] == "optimal" and admm.certificate["duality_gap"] <= 1e-8
    assert admm.certificate["objective"] == pytest.approx(auto.certificate["objective"], rel=1e-7)

    class Clip(lsq.Strategy):  # a user's strategy: the unconstrained fit, projected
        def solve_blocks(self, problem):
            theta = lsq.PSDBlocks(method="admm", max_iter=1).solve_blocks(problem)[0]
            return theta, lsq.Certificate("clip", False, 1)

    with pytest.warns(lo.errors.SolverWarning, match="clip stopped after 1 iterations"):
        ops = lo.core.infer_mechanical(*data, solver=Clip())
    assert ops.certificate["solver"] == "clip" and ops.certificate["status"] == "not converged"


def test_conservative_admm_skips_the_lyapunov_shortcut():
    rng = np.random.default_rng(2)
    Qh = rng.standard_normal((3, 600))
    ddQh = -np.diag([3.0, 1.0, 2.0]) @ Qh + 0.01 * rng.standard_normal((3, 600))
    auto = lo.core.infer_mechanical(Qh, None, ddQh, damping=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        admm = lo.core.infer_mechanical(Qh, None, ddQh, damping=False, solver="admm")
    assert auto.certificate["solver"] == "lyapunov" and admm.certificate["solver"] == "admm"
    assert np.allclose(admm.K, auto.K, rtol=1e-6)


@pytest.mark.parametrize("kind", ["rigid", "mixed", "short"])
def test_both_active_benchmark_data_is_certified_with_both_blocks_on_the_constraint(kind):
    from dolfinx_lopinf.core import synthetic

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ops = lo.core.infer_mechanical(*synthetic.active_data(kind, 6, 3000), eps=1e-8)
    cert = ops.certificate
    assert cert["solver"] == "ipm" and cert["status"] == "optimal"
    assert cert["duality_gap"] <= 1e-8
    assert all(rank < 6 for rank in cert["face_ranks"])  # Kh and Ch both have eigenvalues at eps
    for S in (ops.K, ops.C):
        assert np.array_equal(S, S.T) and np.linalg.eigvalsh(S).min() >= 1e-8


# -- the face multipliers of the certificate -----------------------------------------------

def test_face_multipliers_give_a_sound_bound_at_any_feasible_point():
    """dual_gap with face ranks is a bound: at feasible points around the certified optimum
    (on the face, off it into the interior, with the right and the wrong ranks) the gap it
    certifies is never below the true one, (f(x) - f*) / f(x)."""
    problem, _ = _problem(r=5, seed=3).without_free()
    theta, cert = lsq.InteriorPoint().solve(problem)
    assert cert.converged
    ix, f_star = problem.index, problem.objective(theta)
    x_star = ix.vech(theta.reshape(problem.r, problem.n_blocks, problem.r).transpose(1, 0, 2))
    rng = np.random.default_rng(0)
    checked = 0
    for t in range(40):
        S = ix.blocks(x_star) + rng.uniform(0, 1e-3) * linalg.sym(rng.standard_normal(
            (problem.n_blocks, problem.r, problem.r))) * (t % 4 != 0)
        w, Q = np.linalg.eigh(S - EPS * np.eye(problem.r))
        x = ix.vech(linalg.from_eig(np.maximum(w, 0.0) + (t % 3) * 1e-6, Q)) + ix.x_eps(EPS)
        true = (problem.objective_x(x) - f_star) / problem.objective_x(x)
        for ranks in (cert.face_ranks, [problem.r, problem.r], [0, 0], [2, 4]):
            gap, _ = problem.dual_gap(x, ranks=ranks)
            assert gap >= true - 1e-12
            checked += 1
    assert checked == 160


# held-out data (seeds the benchmark does not use) on which the interior point stalled at
# m mu / f ~ 1e-8: before the face multipliers the first two fell back to ADMM and the last
# two ran through ADMM into the barrier, uncertified
STALLED = [("mixed", 12, 10000, 1), ("mixed", 4, 10000, 3), ("rigid", 12, 10000, 6),
           ("mixed", 4, 10000, 15)]


@pytest.mark.parametrize("kind, r, n, seed", STALLED)
def test_interior_point_certifies_held_out_data_where_it_stalls(kind, r, n, seed):
    from dolfinx_lopinf.core import synthetic

    data = synthetic.active_data(kind, r, n, seed)
    with warnings.catch_warnings():
        warnings.simplefilter("error", lo.errors.SolverWarning)
        ops = lo.core.infer_mechanical(*data, eps=EPS)
    c = ops.certificate
    assert c["solver"] == "ipm" and c["converged"] and c["duality_gap"] <= 1e-8
    ref = lo.core.infer_mechanical(*data, eps=EPS, solver=lsq.PSDBlocks(method="admm"))
    assert ops.certificate["objective"] <= ref.certificate["objective"] * (1 + 1e-8)


def _stall_windows(trace, gap_tol=1e-8):
    """Iterations (1-based) that complete a stall: ipm.STALL_RUN steps in a row below
    ipm.STALL_STEP with m mu / f <= ipm.STALL_GAP x gap_tol."""
    ipm = lsq.ipm
    steps = [t[0] for t in trace]
    return [i + 1 for i in range(ipm.STALL_RUN - 1, len(trace))
            if max(steps[i + 1 - ipm.STALL_RUN:i + 1]) < ipm.STALL_STEP
            and trace[i][2] <= ipm.STALL_GAP * gap_tol]


@pytest.mark.parametrize("backend", ["numpy", "auto"])
def test_a_stalled_interior_point_hands_over_to_the_crossover_early(backend):
    """A stall (three steps in a row below ipm.STALL_STEP near the optimum) ends the
    iteration: the crossover or the certificate takes over there. On this held-out set the
    old loop went on for 27 tiny steps after its first stall (it ended only at a step below
    1e-3). Where a run stalls depends on rounding (11-29 iterations over data perturbed at
    1e-14), so the test checks the rule on the data and on perturbed copies: no stall before
    the last iteration, and a certified answer."""
    from dolfinx_lopinf.core import synthetic

    data = synthetic.active_data("rigid", 12, 10000, 16)
    rng = np.random.default_rng(0)
    stalled = 0
    for k in range(4):
        d = [a * (1 + 1e-14 * rng.standard_normal(a.shape)) if k else a for a in data]
        c = lo.core.infer_mechanical(*d, eps=EPS, solver=lsq.Auto(backend=backend)).certificate
        assert c["solver"] == "ipm" and c["converged"] and c["duality_gap"] <= 1e-8
        windows = _stall_windows(c["ipm"]["trace"])
        assert all(i == len(c["ipm"]["trace"]) for i in windows), windows
        stalled += bool(windows)
    assert stalled >= 1  # the rule was exercised


@pytest.mark.parametrize("backend", ["numpy", "auto"])
@pytest.mark.parametrize("kind, r, n", [("chain", 12, 10000), ("mixed", 4, 10000)])
def test_a_flat_step_near_the_tolerance_asks_for_the_certificate(kind, r, n, backend,
                                                                  monkeypatch):
    """m mu / f overstates the certified gap near the optimum: on the held-out chain (r = 12)
    it crept from 1.5e-8 to 1.1e-8 over ten short steps, certified at 3e-9 only when a stall
    finally asked (18 iterations; 9 now). A step that does not halve m mu / f <= NEAR_GAP x
    gap_tol asks for the certificate - once per halving (a certificate costs more than a
    small-r iteration). Checked against the trace on both loops, on the data and a copy
    perturbed at 1e-14: every due ask is made and none other."""
    from dolfinx_lopinf.core import synthetic

    ipm = lsq.ipm
    gap_tol = 1e-8
    asked = []
    real = ipm.PrimalDualIPM._certified

    def spy(self, cert, *args, **kwargs):
        asked.append((cert.iterations, kwargs.get("may_stop", True)))
        return real(self, cert, *args, **kwargs)

    monkeypatch.setattr(ipm.PrimalDualIPM, "_certified", spy)
    data = synthetic.mechanical_data(kind, r, n)
    rng = np.random.default_rng(1)
    near_asks = 0
    for k in range(2):
        asked.clear()
        d = [a * (1 + 1e-14 * rng.standard_normal(a.shape)) if k else a for a in data]
        c = lo.core.infer_mechanical(*d, eps=EPS, solver=lsq.Auto(backend=backend)).certificate
        assert c["converged"] and c["duality_gap"] <= gap_tol
        trace, last, due = c["ipm"]["trace"], np.inf, []
        for i in range(1, len(trace)):
            rel = trace[i][2]
            if ipm._ask_certificate(trace[:i + 1], gap_tol) == 2:
                due.append((i + 1, True))
            elif rel <= ipm.NEAR_GAP * gap_tol and rel > ipm.NEAR_FLAT * trace[i - 1][2] \
                    and rel <= ipm.NEAR_FLAT * last:
                last = rel
                due.append((i + 1, False))
        assert asked[-len(due):] == due, (asked, due)
        near_asks += sum(not may_stop for _, may_stop in due)
    assert near_asks >= 1  # the rule was exercised


def _exact_rigid_data(r, seed):
    """Exact derivatives of a damped system with two rigid-body modes (K has eigenvalue 0 <
    eps: the constraint acts), one input: f* is ~1e-9 of the data's scale."""
    from dolfinx_lopinf.core.ddt import derivatives
    from dolfinx_lopinf.core.synthetic import orthogonal

    rng = np.random.default_rng(seed)
    V = orthogonal(rng, r)
    w2 = np.concatenate([np.zeros(2), np.geomspace(1, 100, r - 2)])
    zeta = np.where(np.arange(r) < 2, 0.0, 0.02)
    K = V @ np.diag(w2) @ V.T
    C = V @ np.diag(2 * zeta * np.sqrt(w2)) @ V.T
    B = rng.standard_normal((r, 1))
    f = rng.uniform(0.5, 3, 3)

    def u(t):
        return np.array([np.sin(f * t).sum()])

    tr = lo.core.LagrangianROM(K=0.5 * (K + K.T), C=0.5 * (C + C.T), B=B, lagrangian=False).simulate(
        rng.standard_normal(r), rng.standard_normal(r), 2e-3, 3007, inputs=u)
    Qh, dQh, ddQh = derivatives(tr.Qh, tr.times)
    return (Qh, dQh, ddQh, np.column_stack([u(t) for t in tr.times])[:, 4:-4]), w2


@pytest.mark.parametrize("r, seed", [(4, 4), (6, 6)])
def test_data_fitted_almost_exactly_are_certified_not_crashed(r, seed):
    """Before: r = 4 raised TypeError inside the compiled loop (a rounding-negative m mu set
    its watch flag with no watch), r = 6 ran into the barrier and came back uncertified with a
    'gap' of 1.9e287 (f ~ 1e-9 of the data: the gap relative to f asked for more digits than
    double precision has; now it is relative to max(f, GAP_FLOOR ||Z||^2))."""
    data, w2 = _exact_rigid_data(r, seed)
    with warnings.catch_warnings():
        warnings.simplefilter("error", lo.errors.SolverWarning)
        ops = lo.core.infer_mechanical(*data, eps=EPS)
    c = ops.certificate
    assert c["converged"] and c["duality_gap"] <= 1e-8
    w = np.linalg.eigvalsh(ops.K)
    assert np.all(w >= EPS * (1 - 1e-9)) and w[:2].max() <= 1e-5  # the rigid modes: ~0
    np.testing.assert_allclose(w[2:], w2[2:], rtol=1e-4)


class _NoNewton:
    """A FaceNewton that never succeeds (the crossover's other way, shut)."""

    def refine(self, x, ranks):
        return None


def test_crossover_takes_the_face_minimiser_where_newton_does_not():
    """The crossover first solves for the exact minimiser on the face the stopped interior
    point shows, its eigenvectors fixed (one solve), before Newton on the face. Held-out
    mixed r = 4 seed 15: in 1 of 40 rounding variants (copies perturbed at 1e-14) the interior
    point wandered at m mu / f ~ 5e-8 (gap 1.5e-8), Newton's first step left the optimum and
    the fit fell back to ADMM; the face minimiser from that point certified at 7e-10. Here:
    the optimum moved into the interior along its active directions (by 1e-7: a gap of 9e-8),
    Newton shut - the face minimiser alone must certify."""
    from dolfinx_lopinf.core.lsq import ipm
    from dolfinx_lopinf.core import synthetic

    (Qs, dQs, ddQs, Us), _, _ = lo.core.inference._unit_scaled(
        *synthetic.active_data("mixed", 4, 10000, 15))
    g = lo.core.inference.gram_data(Qs, dQs, ddQs, Us)
    blocks, _ = lsq.Problem(g.L, g.Z, 2, EPS, g.m).without_free()
    theta, ref = lsq.PSDBlocks(method="admm").solve(blocks)
    assert ref.converged and ref.face_ranks == [3, 3]
    w, Q = np.linalg.eigh(np.stack([theta[:, :4], theta[:, 4:]]) - EPS * np.eye(4))
    w[:, 0] = 1e-7  # the active direction of each block, off the boundary
    x = blocks.index.x_eps(EPS) + blocks.index.vech(linalg.from_eig(w, Q))
    cert = lsq.Certificate("ipm", False, 20, duality_gap=1.5e-8, face_ranks=[3, 3])
    assert blocks.dual_gap(x)[0] > 1e-8
    out = ipm._crossover(blocks, x, cert, _NoNewton(), 1e-8)
    assert cert.converged and cert.duality_gap <= 1e-8 and cert.details["crossover"]
    assert blocks.objective_x(out) <= blocks.objective(theta) * (1 + 1e-8)


def _rank_deficient(r, seed, exact):
    """_exact_rigid_data (exact derivatives: f ~ 1e-13 of the data's scale), or its Qh, dQh
    projected on r - 3 directions with ddQh not (rank-deficient, poorly explained data)."""
    data, _ = _exact_rigid_data(r, seed)
    if exact:
        return data
    rng = np.random.default_rng(seed)
    P = np.linalg.qr(rng.standard_normal((r, r - 3)))[0]
    P = P @ P.T
    return P @ data[0], P @ data[1], P @ data[2] + 1e-6 * rng.standard_normal(data[2].shape), data[3]


@pytest.mark.parametrize("seed, exact", [(0, True), (1, True), (0, False), (2, False)])
def test_rank_deficient_two_block_fits_are_certified_with_the_ridge_raised(seed, exact):
    """r = 16, both blocks, data of numerical rank ~2/3 of the rows: the normal equations
    square the condition (H singular to double precision, or condition ~1e17), so the
    interior point's directions were noise in the weak directions. Before: ADMM then the
    barrier, long and uncertified (a 'gap' of up to 6e287). Now the ridge is raised until
    cond(H) <= COND_MAX (said by an IllConditionedDataWarning) and the interior point
    certifies."""
    data = _rank_deficient(16, seed, exact)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        ops = lo.core.infer_mechanical(*data, eps=EPS)
    c = ops.certificate
    assert c["solver"] == "ipm" and c["converged"] and c["duality_gap"] <= 1e-8
    assert c["ridge_raised_to"] in lsq.problem.RIDGE_STEPS
    assert not any(issubclass(w.category, lo.errors.SolverWarning) for w in seen)
    assert any("ridge raised" in str(w.message) for w in seen
               if issubclass(w.category, lo.errors.IllConditionedDataWarning))
    for S in (ops.K, ops.C):
        assert np.array_equal(S, S.T) and np.linalg.eigvalsh(S).min() >= EPS * (1 - 1e-9)


def test_barrier_answer_on_a_resolved_problem_says_so():
    """r = 20, exact rank-deficient data, solved on the resolved problem (when this test was
    written the interior point and ADMM failed there and the barrier answered, uncertified at
    1.8e-6; today the interior point certifies it at 8.4e-10). Whichever strategy answers,
    the certificate carries the ridge and floor the fit was solved with (before, the
    barrier's did not)."""
    data = _rank_deficient(20, 0, True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c = lo.core.infer_mechanical(*data, eps=EPS).certificate
    assert c["ridge_raised_to"] in lsq.problem.RIDGE_STEPS and c["gap_floor"] > 0


def test_with_ridge_adds_the_ridge_term():
    """f'(Theta) = f(Theta) + gamma^2 ||Theta diag(s)||^2 + const, gamma = ridge sigma_1."""
    rng = np.random.default_rng(0)
    r, p = 3, 6
    L = np.tril(rng.standard_normal((p, p))) + 2 * np.eye(p)
    problem = lsq.Problem(L, rng.standard_normal((r, p)), 2, EPS)
    ridged = problem.with_ridge(1e-3)
    s = np.linalg.norm(L, axis=1)
    gamma = 1e-3 * np.linalg.norm(L / s[:, None], 2)
    diffs = []
    for _ in range(3):
        theta = rng.standard_normal((r, p))
        diffs.append(ridged.objective(theta) - problem.objective(theta)
                     - gamma**2 * np.sum((theta * s) ** 2))
    assert np.ptp(diffs) <= 1e-12 * problem.objective(theta)


def test_resolved_raises_the_floor_with_the_condition():
    """Well conditioned: the problem itself. cond(H) ~1e10 (< COND_MAX): the gap floor rises to
    RESOLUTION u^2 cond(H), no ridge. cond(H) beyond COND_MAX: a ridge of RIDGE_STEPS."""
    rng = np.random.default_rng(1)
    r, p = 3, 6
    U = np.linalg.qr(rng.standard_normal((p, p)))[0]
    for decades, ridge_expected in ((1, False), (5, False), (9, True)):
        L = U @ np.diag(np.logspace(0, -decades, p))  # G = L L^T: condition 10^(2 decades)
        problem = lsq.Problem(L, rng.standard_normal((r, p)), 2, EPS)
        resolved, ridge = problem.resolved()
        cond = problem.spd.condition
        if decades == 1:
            assert resolved is problem and ridge is None
        elif not ridge_expected:
            assert ridge is None and cond <= lsq.problem.COND_MAX
            unit = np.finfo(float).eps
            assert resolved.floor == pytest.approx(lsq.problem.RESOLUTION * unit**2 * cond)
        else:
            assert ridge in lsq.problem.RIDGE_STEPS
            assert resolved.spd.condition <= lsq.problem.COND_MAX < cond


@pytest.mark.parametrize("max_newton", [6, 200])
def test_barrier_reports_the_certified_bound(max_newton):
    """The barrier's gap is the closed-form dual bound at its point (a proof: >= the true
    relative suboptimality), and converged means that bound <= 1e-8; stopped early (6 Newton
    steps) it is uncertified, not the central path's b r / t. Before, b r / t was reported
    whether or not the last centring had converged."""
    problem = _problem(r=5, n_blocks=2, seed=0)
    theta_ref, ref = lsq.InteriorPoint(gap_tol=1e-11).solve(problem)
    f_star = problem.objective(theta_ref)
    theta, cert = lsq.Barrier(max_newton=max_newton).solve(problem)
    f = problem.objective(theta)
    assert cert.duality_gap >= (f - f_star) / f - 1e-12
    assert cert.converged == (cert.duality_gap <= 1e-8)
    assert cert.converged == (max_newton == 200)
    assert "central_path_gap" in cert.details


# -- one certificate vocabulary (issue 28) ------------------------------------------------

def _forced(r=4, n=2000, seed=0):
    from dolfinx_lopinf.core.synthetic import mechanical_data
    return mechanical_data("forced", r, n, seed)


@pytest.mark.parametrize("solver", ["auto", "admm", "cvxpy", "lyapunov"])
def test_every_fit_reports_one_certificate_vocabulary(solver):
    """duality_gap (relative), certified, solver, iterations, seconds - whichever path."""
    if solver == "cvxpy":
        pytest.importorskip("cvxpy")
    Qh, dQh, ddQh, U = _forced()
    args = (Qh, None, ddQh) if solver == "lyapunov" else (Qh, dQh, ddQh, U)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cert = lo.core.infer_mechanical(*args, solver=solver, damping=solver != "lyapunov").certificate
    for key in ("duality_gap", "certified", "solver", "iterations", "seconds"):
        assert key in cert, (solver, key)
    assert cert["certified"] == (cert["duality_gap"] <= 1e-8 and cert["status"] in ("optimal",)
                                 or (solver == "lyapunov" and cert["duality_gap"] == 0.0)), cert
    for other in (lo.core.infer_opinf(Qh, dQh, ddQh, U).certificate,):
        assert other["certified"] and other["duality_gap"] == 0.0


def test_strict_raises_instead_of_returning_an_uncertified_fit():
    Qh, dQh, ddQh, U = _forced(6)
    stopped_early = lsq.PSDBlocks(method="admm", max_iter=2)
    with pytest.warns(lo.errors.SolverWarning):
        cert = lo.core.infer_mechanical(Qh, dQh, ddQh, U, solver=stopped_early).certificate
    assert not cert["certified"]
    with pytest.raises(lo.errors.SolverFailedError, match="not certified"):
        lo.core.infer_mechanical(Qh, dQh, ddQh, U, solver=stopped_early, strict=True)
    assert lo.core.infer_mechanical(Qh, dQh, ddQh, U, strict=True).certificate["certified"]


def test_fallbacks_that_end_with_a_larger_gap_do_not_replace_the_interior_points_answer(monkeypatch):
    """The default's fallbacks (ADMM, then the barrier) run when the interior point stops
    uncertified above blocks.FALLBACK_ABOVE_GAP; where they end uncertified with a larger gap
    (measured on the membrane loop at r = 20: ADMM 1.1e7, the barrier 4.6e-6 against the
    interior point's 2.6e-7), the interior point's point and gap are the answer."""
    from dolfinx_lopinf.core.lsq import barrier, blocks
    from dolfinx_lopinf.core.lsq.problem import Certificate

    problem = _problem(r=4, n_blocks=2, seed=3)
    real = blocks.interior_point

    def uncertified(*args, **kwargs):
        x, ip, details = real(*args, **kwargs)
        ip.converged, ip.duality_gap = False, 3e-5
        return x, ip, details

    def worse(gap, name):
        def run(self, problem, *args):
            return np.zeros((problem.r, problem.L.shape[0])), Certificate(name, False, 1, duality_gap=gap)
        return run

    monkeypatch.setattr(blocks, "interior_point", uncertified)
    monkeypatch.setattr(blocks.FaceADMM, "run", worse(1.1e7, "admm"))
    monkeypatch.setattr(barrier.Barrier, "solve_blocks", worse(4.6e-4, "barrier"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        theta, cert = lsq.Auto().solve(problem)
    assert cert.solver == "ipm" and not cert.converged and cert.duality_gap == 3e-5
    _assert_feasible(theta, problem)
    monkeypatch.setattr(barrier.Barrier, "solve_blocks", worse(2e-5, "barrier"))  # a better bound
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert lsq.Auto().solve(problem)[1].solver == "barrier"


def test_auto_without_fallbacks_returns_the_interior_points_own_answer(monkeypatch):
    """lsq.Auto(fallback=False) (lo.fit's candidates): when the interior point does not
    certify, its own point comes back - feasible, marked uncertified, with its gap - instead
    of ADMM and the barrier (seconds each on ill-conditioned data). The default falls back
    only above blocks.FALLBACK_ABOVE_GAP (below it the fallbacks did no better: measured
    there). Certified answers are the same either way."""
    from dolfinx_lopinf.core.lsq import blocks

    problem = _problem(r=4, n_blocks=2, seed=3)
    theta, cert = lsq.Auto(fallback=False).solve(problem)
    ref, ref_cert = lsq.Auto().solve(problem)
    assert cert.converged and ref_cert.converged and np.array_equal(theta, ref)

    real, gap = blocks.interior_point, [3e-6]

    def uncertified(*args, **kwargs):
        x, ip, details = real(*args, **kwargs)
        ip.converged, ip.duality_gap = False, gap[0]
        return x, ip, details

    monkeypatch.setattr(blocks, "interior_point", uncertified)
    theta, cert = lsq.Auto(fallback=False).solve(problem)
    assert cert.solver == "ipm" and not cert.converged and cert.duality_gap == 3e-6
    _assert_feasible(theta, problem)
    calls = []
    original_run = blocks.FaceADMM.run

    def recorded_run(self, *args):
        calls.append("admm")
        return original_run(self, *args)

    monkeypatch.setattr(blocks.FaceADMM, "run", recorded_run)
    assert 3e-6 <= blocks.FALLBACK_ABOVE_GAP < 3e-5
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        theta, cert = lsq.Auto().solve(problem)  # 3e-6: the interior point's answer
        assert calls == [] and cert.solver == "ipm" and cert.duality_gap == 3e-6
        _assert_feasible(theta, problem)
        gap[0] = 3e-5
        lsq.Auto().solve(problem)
    assert calls == ["admm"]
