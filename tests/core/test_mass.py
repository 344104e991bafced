"""L-OpInf with a learned reduced mass (numpy core): a system whose mass is not I in the user's
coordinates - what a Euclidean POD basis of a black box gives - fitted by our certified
interior point (dolfinx_lopinf.core.lsq.fractional), checked against Clarabel on the same
problem, for coordinate invariance and on bad input."""

import types
import warnings

import numpy as np
import pytest
import scipy.linalg

import dolfinx_lopinf as lo
from dolfinx_lopinf.core import mass as mass_mod
from dolfinx_lopinf.core.lsq import fractional, fractional_bound


def _spd(rng, r, spread):
    Q = np.linalg.qr(rng.standard_normal((r, r)))[0]
    return Q @ np.diag(np.geomspace(1.0, spread, r)) @ Q.T


def _system(seed=0, r=4):
    rng = np.random.default_rng(seed)
    M = _spd(rng, r, 1e-2)              # reduced mass spanning two decades
    K = _spd(rng, r, 100.0)             # omega dt <= 1 at dt = 0.01
    C = 0.02 * M + 1e-3 * K             # Rayleigh damping
    B = rng.standard_normal((r, 1))
    return M, K, C, B


def _load(t):
    return np.array([np.sin(3 * t) + 0.5 * np.sin(11 * t) + 0.3 * np.sin(23 * t)])


def _unseen(t):
    return np.array([np.tanh(4 * t) + 0.4 * np.cos(7 * t)])


def _run(M, K, C, B, u, n=1500, dt=0.01):
    rom = lo.core.LagrangianROM(K=K, M=M, C=C, B=B, scheme="newmark")
    tr = rom.simulate(np.zeros(len(K)), np.zeros(len(K)), dt, n, inputs=u)
    return tr


def _data(Qh, u=_load, dt=0.01):
    t = dt * np.arange(Qh.shape[1])
    U = np.array([u(s)[0] for s in t])[None, :]
    return lo.core.ddt.newmark_data(Qh, t, U)


def _fit(tr, u=_load, dt=0.01, **kw):
    return lo.core.infer_mechanical(*_data(tr.Qh, u, dt), **kw)


def _noisy(Qh, level=1e-4, seed=5):
    return Qh + np.random.default_rng(seed).standard_normal(Qh.shape) * level * np.abs(Qh).max()


def test_learned_mass_recovers_a_non_identity_mass_system():
    M, K, C, B = _system()
    train = _run(M, K, C, B, _load)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", lo.errors.IllConditionedDataWarning)
        learned = _fit(train, mass="learned")
        fixed = _fit(train, mass="identity")
    cert = learned.certificate
    assert cert["certified"] and cert["duality_gap"] <= 1e-8, cert
    assert cert["solver"] == "mass-ipm" and cert["iterations"] > 0 and cert["seconds"] > 0
    for A in (learned.M, learned.K, learned.C):
        assert np.array_equal(A, A.T) and np.linalg.eigvalsh(A).min() > 0
    # the data determine Mh^-1 Kh (the modal masses they do not): the frequencies (exact data:
    # the regulariser acts at F_FLOOR of the data's scale; measured 5e-4 relative)
    assert np.allclose(scipy.linalg.eigvalsh(learned.K, learned.M), scipy.linalg.eigvalsh(K, M),
                       rtol=1e-3)
    test = _run(M, K, C, B, _unseen, n=800)
    errors = {}
    for name, ops in (("learned", learned), ("identity", fixed)):
        rom = lo.core.LagrangianROM(K=ops.K, M=ops.M, C=ops.C, B=ops.B, scheme="newmark")
        pred = rom.simulate(np.zeros(4), np.zeros(4), 0.01, 800, inputs=_unseen)
        errors[name] = lo.relative_error(test.Qh, pred.Qh)
    # measured: learned ~1e-6, identity ~0.3 (wrong model form)
    assert errors["learned"] < 1e-3, errors
    assert errors["identity"] > 100 * errors["learned"], errors


def _dynamics(o, T):
    """M^-1 K, M^-1 C, M^-1 B of o seen in the coordinates q = T q~."""
    M = T.T @ o.M @ T
    return [np.linalg.solve(M, T.T @ X @ T) for X in (o.K, o.C)] + [np.linalg.solve(M, T.T @ o.B)]


def test_learned_mass_does_not_depend_on_orthogonal_coordinates():
    """q = T q~ with T orthogonal: the fitted model in q~ is the same model (M~ = T^T M T, K, C
    alike, B~ = T^T B) to the certificate's accuracy - the problem, its regulariser and the
    normalisation's isotropic floor are invariant, and so are the solver's balanced
    coordinates."""
    M, K, C, B = _system(1)
    train = _run(M, K, C, B, _load)
    Qh = _noisy(train.Qh)
    T = np.linalg.qr(np.random.default_rng(5).standard_normal((4, 4)))[0]
    a = lo.core.infer_mechanical(*_data(Qh), mass="learned")
    b = lo.core.infer_mechanical(*_data(np.linalg.solve(T, Qh)), mass="learned")
    assert a.certificate["certified"] and b.certificate["certified"]
    # the dynamics M^-1 K, M^-1 C, M^-1 B are what the data determine sharply; M's modal scales
    # only through the regulariser, to ~sqrt(gap / rho) (measured ~1e-3 relative)
    for X, Y in zip(_dynamics(a, T), _dynamics(b, np.eye(4))):
        assert np.allclose(X, Y, rtol=1e-6, atol=1e-6 * np.abs(Y).max())
    Ma = T.T @ a.M @ T  # the operators themselves, up to the scale of tr(M W) = 1
    c = np.sum(Ma * b.M) / np.sum(Ma * Ma)
    for X, Y in ((a.M, b.M), (a.K, b.K), (a.C, b.C)):
        assert np.allclose(c * T.T @ X @ T, Y, rtol=1e-5, atol=1e-5 * np.abs(Y).max())


def test_a_scaled_basis_changes_only_the_prior_of_the_floor(monkeypatch):
    """q = T q~ with T scaling the coordinates by 0.1 .. 10 (state variances over 1e4): the
    normalisation's isotropic floor (mass.W_FLOOR, in the user's coordinates) is the one part
    of the problem that is not invariant - without it the two fits are the same model; with
    it the noisy fit (1e-4 sensor noise) predicts the unseen load within 1.5x of the
    unscaled one (measured 0.127 vs 0.177)."""
    M, K, C, B = _system(1)
    train, test = _run(M, K, C, B, _load), _run(M, K, C, B, _unseen, n=800)
    Qh = _noisy(train.Qh)
    T = np.linalg.qr(np.random.default_rng(5).standard_normal((4, 4)))[0] @ np.diag([1, 10, 0.1, 3.0])

    def both():
        a = lo.core.infer_mechanical(*_data(Qh), mass="learned")
        b = lo.core.infer_mechanical(*_data(np.linalg.solve(T, Qh)), mass="learned")
        assert a.certificate["certified"] and b.certificate["certified"]
        return a, b

    def error(o, T):
        rom = lo.core.LagrangianROM(K=o.K, M=o.M, C=o.C, B=o.B, scheme="newmark")
        return lo.relative_error(test.Qh, T @ rom.simulate(np.zeros(4), np.zeros(4), 0.01, 800,
                                                           inputs=_unseen).Qh)

    a, b = both()
    assert error(b, T) <= 1.5 * error(a, np.eye(4))
    monkeypatch.setattr(mass_mod, "W_FLOOR", 0.0)
    a, b = both()
    for X, Y in zip(_dynamics(a, T), _dynamics(b, np.eye(4))):
        assert np.allclose(X, Y, rtol=1e-5, atol=1e-5 * np.abs(Y).max())


def test_learned_mass_bad_input_is_named():
    M, K, C, B = _system(2)
    train = _run(M, K, C, B, _load, n=300)
    with pytest.raises(lo.errors.InputError, match="mass must be"):
        _fit(train, mass="lumped")
    t = 0.01 * np.arange(301)
    with pytest.raises(lo.errors.InputError, match="dQh"):
        lo.core.infer_mechanical(train.Qh, None, train.Qh, mass="learned")
    with pytest.raises(lo.errors.InputError, match="static"):
        lo.core.infer_mechanical(train.Qh, train.Qh, 0 * train.Qh, mass="learned")
    with pytest.raises(lo.errors.InputError, match="mass must be"):
        lo.fit(lo.Snapshots(t, train.Qh), 2, mass="diagonal")
    with pytest.raises(lo.errors.InputError, match="'auto'.*'cvxpy'"):
        _fit(train, mass="learned", solver="admm")


def _prepared(seed=1, r=4, noise=1e-4, rho=fractional.RHO):
    M, K, C, B = _system(seed, r)
    train = _run(M, K, C, B, _load)
    Qbar, D1, D2, Ubar = _data(_noisy(train.Qh, noise))
    return mass_mod.prepare(Qbar, D1, D2, Ubar, damping=True, eps=1e-8, ridge=1e-9, strict=False,
                            rho=rho)


def test_certificate_is_a_lower_bound_everywhere_and_tight_at_the_answer():
    """Weak duality: phi at any feasible point (random ones, the answer moved along the
    normalisation) is >= the certified bound; at the answer phi - bound <= 1e-8 phi."""
    prep = _prepared()
    p = prep.problem
    xs, Y, tau, cert = fractional.MassInteriorPoint().solve(p)
    assert cert.converged and cert.duality_gap <= 1e-8
    bound = cert.details["bound"]
    rng = np.random.default_rng(0)
    ix = p.index
    S_star = ix.blocks(xs) + p.floors
    for _ in range(20):
        S = S_star * np.exp(0.3 * rng.standard_normal((p.n_blocks, 1, 1)))
        A = rng.standard_normal((p.n_blocks, p.r, p.r))
        S = S + 0.05 * np.abs(S_star).max() * A @ A.transpose(0, 2, 1) / p.r
        S[0] /= np.sum(S[0] * p.W)  # <W, M> = 1
        X = S - p.floors
        if np.linalg.eigvalsh(X).min() <= 0:
            continue
        x = ix.vech(X)
        phi = p.misfit(x) - tau * np.linalg.slogdet(X[0])[1]
        assert phi >= bound - 1e-12 * abs(bound)
    phi_star = p.misfit(xs) - tau * np.linalg.slogdet(ix.blocks(xs)[0])[1]
    assert 0 <= phi_star - bound <= 1e-8 * p.misfit(xs) + 1e-12 * abs(bound)


@pytest.mark.parametrize("seed,noise", [(1, 1e-4), (3, 1e-3)])
def test_the_interior_point_agrees_with_clarabel_on_the_same_problem(seed, noise):
    """Clarabel on the same regularised problem (same tau): its objective is >= our bound and
    within the combined tolerances of ours; the operators agree."""
    pytest.importorskip("cvxpy")
    prep = _prepared(seed, noise=noise)
    p = prep.problem
    xs, Y, tau, cert = fractional.MassInteriorPoint().solve(p)
    assert cert.converged
    theta_ref, info = mass_mod.solve_cvxpy(p, tau=tau, options=mass_mod.TIGHT)
    phi = lambda th: p.misfit(p.index.vech(th.reshape(p.r, p.n_blocks, p.r).transpose(1, 0, 2))  # noqa: E731
                              - p.x_floor) - tau * np.linalg.slogdet(th[:, :p.r] - p.floors[0])[1]
    ours, ref = phi(p.theta(xs)), phi(theta_ref)
    scale = p.misfit(xs)
    assert ref >= cert.details["bound"] - 1e-9 * scale   # Clarabel cannot beat the proof
    assert ours <= ref + 1e-6 * scale                   # and we are at least as good
    # the dynamics agree, to the reference's accuracy (measured: M^-1 K to 5e-5 relative with
    # Clarabel's tightest tolerances; M^-1 C, weakly determined by noisy damping data, to
    # 1.3e-3 at seed 3 - our own fits at gaps 5e-9 and 1e-11 differ by 3e-3 there)
    r = p.r
    for k, tol in ((1, 1e-3), (2, 1e-2)):
        X, Y = (np.linalg.solve(th[:, :r], th[:, k * r:(k + 1) * r]) for th in (p.theta(xs), theta_ref))
        assert np.allclose(X, Y, rtol=tol, atol=tol * np.abs(Y).max())


def test_learned_mass_solver_cvxpy_is_the_reference_path():
    pytest.importorskip("cvxpy")
    M, K, C, B = _system(1)
    train = _run(M, K, C, B, _load)
    ours = _fit(types.SimpleNamespace(Qh=_noisy(train.Qh)), mass="learned")
    ref = _fit(types.SimpleNamespace(Qh=_noisy(train.Qh)), mass="learned", solver="cvxpy")
    assert ref.certificate["solver"] == "cvxpy-clarabel"
    assert np.allclose(scipy.linalg.eigvalsh(ours.K, ours.M), scipy.linalg.eigvalsh(ref.K, ref.M),
                       rtol=1e-4)


def test_certificate_vocabulary():
    M, K, C, B = _system(1)
    cert = _fit(_run(M, K, C, B, _load), mass="learned").certificate
    for key in ("duality_gap", "certified", "solver", "iterations", "seconds"):
        assert key in cert, key
    assert "gap" not in cert  # one vocabulary: duality_gap


def test_strict_raises_instead_of_returning_an_uncertified_model():
    M, K, C, B = _system(1)
    train = _run(M, K, C, B, _load)
    data = _data(_noisy(train.Qh))
    with pytest.raises(lo.errors.SolverFailedError, match="not certified"):
        mass_mod.infer_with_mass(*data, ridge=1e-9, strict=True, gap_tol=1e-30)
    with pytest.warns(lo.errors.SolverWarning, match="not certified"):
        ops = mass_mod.infer_with_mass(*data, ridge=1e-9, gap_tol=1e-30)
    assert not ops.certificate["certified"] and ops.certificate["status"] == "not certified"


def test_singular_state_covariance_warns_naming_the_dimension_or_raises_with_strict():
    """r = 3 coordinates that are two modes and their sum: W has rank 2 of 3."""
    M, K, C, B = _system(4, r=2)
    train = _run(M, K, C, B, _load)
    Qh = _noisy(train.Qh, 1e-6)
    data = _data(np.vstack([Qh, Qh[0] + Qh[1]]))
    with pytest.warns(lo.errors.IllConditionedDataWarning, match="only 2 of the r = 3"):
        ops = lo.core.infer_mechanical(*data, mass="learned")
    assert np.isfinite(ops.M).all() and np.linalg.eigvalsh(ops.M).min() > 0
    with pytest.raises(lo.errors.RankDeficientDataError, match="only 2 of the r = 3"):
        lo.core.infer_mechanical(*data, mass="learned", strict=True)


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_a_refused_certificate_lets_the_iteration_go_on(backend, monkeypatch):
    """The loop asks for a certificate once the estimate is small; when that certificate
    fails (here: the first two are made to), the iteration goes on from where it was and
    certifies later - the state and the step's workspaces untouched by the attempt."""
    from dolfinx_lopinf.core import compiled

    if backend == "numba" and not compiled.available():
        pytest.skip("numba unavailable")
    p = _prepared(2).problem
    ref = fractional.MassInteriorPoint(backend=backend).solve(p)[3]
    real, calls = fractional.FractionalProblem.certify_best, []

    def refuse_twice(self, *args):
        calls.append(1)
        c = real(self, *args)
        return dict(c, duality_gap=1.0) if len(calls) <= 2 else c

    monkeypatch.setattr(fractional.FractionalProblem, "certify_best", refuse_twice)
    cert = fractional.MassInteriorPoint(backend=backend).solve(p)[3]
    assert ref.converged and cert.converged and cert.details["stopped"] == "certified"
    assert len(calls) >= 3 and cert.iterations >= ref.iterations + 2


def test_a_jam_stops_at_any_level_but_a_plateau_with_a_falling_misfit_does_not():
    """fractional._stalled on traces of (step, sigma, estimate, misfit): the jam of a damped
    fit on near-exact data (the membrane loop at r = 20: centring steps alternating 0.98 /
    0.5, estimate 1.3e-4 and misfit 1.1e-8 unchanged) stops once STALL_FLAT iterations show
    it, far above the old threshold; the early plateau of the estimate on the COMET loop,
    where the misfit falls 10x per iteration, does not."""
    gap_tol, n = 1e-8, fractional.STALL_FLAT
    assert 1.3e-4 > fractional.STALL_GAP * gap_tol  # the old rules never looked at this level
    jam = [(0.98 if k % 2 else 0.5, 1.0, 1.3e-4 * (1 + 0.01 * (-1) ** k), 1.1e-8) for k in range(n + 1)]
    assert fractional._stalled(jam, jam[-1][2], gap_tol)
    assert not fractional._stalled(jam[:n], jam[n - 1][2], gap_tol)  # not enough history yet
    plateau = [(0.82, 0.07, 5.0, 10.0 ** (6 - k)) for k in range(3 * n)]
    assert not fractional._stalled(plateau, 5.0, gap_tol)
    falling = [(0.82, 0.07, 10.0 ** -k, 1.0) for k in range(3 * n)]  # the gap falls, f is settled
    assert not fractional._stalled(falling, falling[-1][2], gap_tol)


def test_the_start_keeps_the_unconstrained_spectra_above_the_spread():
    """fractional.start: the stiffness and damping blocks of the unconstrained minimiser for
    M_0 = I / tr W keep their eigenvalues (absolute values) above START_SPREAD times the
    largest, and only those below are lifted; SAFE_SPREAD lifts everything below its spread."""
    p = _prepared(3).problem
    ix = p.index
    for spread in (fractional.START_SPREAD, fractional.SAFE_SPREAD):
        X = ix.blocks(fractional.start(p, spread))
        for k in range(1, p.n_blocks):
            w = np.linalg.eigvalsh(X[k])
            assert w[0] >= spread * w[-1] * (1 - 1e-12)
    tight = np.linalg.eigvalsh(ix.blocks(fractional.start(p))[1])
    safe = np.linalg.eigvalsh(ix.blocks(fractional.start(p, fractional.SAFE_SPREAD))[1])
    keep = tight >= fractional.SAFE_SPREAD * tight[-1]  # above both floors: the same eigenvalues
    assert np.allclose(tight[keep], safe[keep], rtol=1e-10)
    assert (safe >= tight * (1 - 1e-12)).all()


def test_a_jam_is_run_again_from_the_cautious_start_and_the_better_certificate_kept(monkeypatch):
    """MassInteriorPoint.solve: a run that ends uncertified with collapsed steps is run again
    from start(p, SAFE_SPREAD); the answer is the better of the two, its iterations the sum.
    A run stopped with long steps is not - whether its estimate sits far above the tolerance
    (there a second start certified nothing and cost 0.3 s of a fit) or below it (a converged
    point the certificate could not resolve)."""
    tol = 1e-8
    jam = [(0.9, 0.1, 1.0, 1.0)] * 3 + [(2e-2, 0.5, 4e-2, 2e-2), (6e-4, 0.5, 4e-2, 2e-2), (1e-5, 0.5, 4e-2, 2e-2)]
    assert fractional._jammed({"duality_gap": 4e-2}, jam, tol)
    assert fractional._jammed(None, [], tol)  # a numerical failure at the first step
    high = [(0.6, 0.5, 3e-5, 1.0)] * 4  # stalled with the estimate above STALL_GAP gap_tol
    assert not fractional._jammed({"duality_gap": 1e-3}, high, tol)
    resolved = [(0.9, 0.1, 1e-12, 1.0)] * 4  # converged; the certificate could not resolve it
    assert not fractional._jammed({"duality_gap": 2e-8}, resolved, tol)
    assert not fractional._jammed({"duality_gap": 1e-9}, jam, tol)  # certified: nothing to redo

    p = _prepared(2).problem
    real, starts = fractional._run_numpy, []

    def first_jams(problem, xs, gap_tol, max_iter):
        starts.append(np.array(xs))
        if len(starts) == 1:
            return xs, np.zeros((problem.r, problem.L.shape[0])), 1.0, 6, None, "stalled at iteration 6", jam
        return real(problem, xs, gap_tol, max_iter)

    monkeypatch.setattr(fractional, "_run_numpy", first_jams)
    xs, Y, tau, cert = fractional.MassInteriorPoint(backend="numpy").solve(p)
    assert len(starts) == 2 and np.array_equal(starts[1], fractional.start(p, fractional.SAFE_SPREAD))
    assert cert.converged and cert.details["stopped"] == "certified (second start)"
    assert cert.iterations == 6 + len(cert.details["trace"])


def test_a_certificate_that_stops_improving_ends_the_run_but_a_late_one_does_not():
    """fractional._proof_stalled on the best certified gap after each attempt: flat over
    STALL_FLAT attempts stops; the sequence of a held-out fit that certified at its eleventh
    attempt (six at 1e-4, then 2e-5, 2e-5, 9e-7, 2e-8, 1e-9) is never stopped."""
    n = fractional.STALL_FLAT
    flat = [2.7e-3] * (n + 1)
    assert fractional._proof_stalled(flat)
    assert not fractional._proof_stalled(flat[:n])  # not enough attempts yet
    late = [1e-4] * 6 + [2e-5, 2e-5, 9e-7, 2e-8, 1e-9]
    assert not any(fractional._proof_stalled(late[:k]) for k in range(1, len(late) + 1))


def test_the_projected_dual_is_tried_again_only_while_its_gap_halves():
    """fractional._Attempts: the projection (a QR of (r p) x ((b - 1) r (r + 1) / 2), 40 ms at
    r = 20) is asked for at the first attempt and the second, and after that only while its
    gap halves from one attempt to the next; attempts that did not try it leave that as it is."""
    a = fractional._Attempts()
    assert a.project
    a.record({"duality_gap": 1e-3, "projected_gap": 1e-4}, {"duality_gap": 1e-4})
    assert a.project  # one projected gap: nothing to compare yet
    a.record({"duality_gap": 1e-3, "projected_gap": 4e-5}, {"duality_gap": 4e-5})
    assert a.project  # halved
    a.record({"duality_gap": 1e-3, "projected_gap": 3e-5}, {"duality_gap": 3e-5})
    assert not a.project  # not halved: no more projections in this run
    a.record({"duality_gap": 2e-5}, {"duality_gap": 2e-5})
    assert not a.project and a.proven == [1e-4, 4e-5, 3e-5, 2e-5]


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_a_run_whose_certificates_do_not_improve_stops_after_stall_flat_attempts(backend, monkeypatch):
    """Every certificate refused (gap 1e-3): the run stops STALL_FLAT attempts after the
    first instead of iterating to max_iter, and says why. The tolerance 1e-5 starts the
    attempts at iteration 9 (estimate 8e-6), so the stop comes at 15 with steps of 0.96, far
    from the rounding floor: at 1e-8 it came at iteration 19 on a step of 0.02 with the
    estimate at 4e-15, where the estimate's own stall (three short steps) was two iterations
    away and could come first on another machine's rounding."""
    from dolfinx_lopinf.core import compiled

    if backend == "numba" and not compiled.available():
        pytest.skip("numba unavailable")
    p = _prepared(2).problem
    real, calls = fractional.FractionalProblem.certify_best, []

    def refuse(self, *args):
        calls.append(1)
        return dict(real(self, *args), duality_gap=1e-3)

    monkeypatch.setattr(fractional.FractionalProblem, "certify_best", refuse)
    cert = fractional.MassInteriorPoint(gap_tol=1e-5, backend=backend, max_iter=80).solve(p)[3]
    assert not cert.converged and "not halved" in cert.details["stopped"]
    assert len(calls) == fractional.STALL_FLAT + 1 and cert.iterations < 80


@pytest.mark.parametrize("backend", ["numba"])
def test_compiled_iteration_is_the_numpy_iteration(backend):
    """The compiled iteration (_fractional_compiled) reproduces the numpy one to rounding:
    same iterations, objectives to 1e-9, both certified."""
    from dolfinx_lopinf.core import compiled

    if not compiled.available():
        pytest.skip("numba unavailable")
    for seed in (1, 3):
        p = _prepared(seed).problem
        a = fractional.MassInteriorPoint(backend="numpy").solve(p)
        b = fractional.MassInteriorPoint(backend=backend).solve(p)
        assert a[3].converged and b[3].converged
        assert abs(a[3].iterations - b[3].iterations) <= 1
        assert abs(p.misfit(a[0]) - p.misfit(b[0])) <= 1e-9 * p.misfit(a[0])


@pytest.mark.parametrize("kind", ["modal", "chainpod", "active", "nearexact", "nearbeam"])
@pytest.mark.parametrize("r", [2, 4, 8, 12])
def test_held_out_style_sets_are_certified(kind, r):
    """The benchmark's learned-mass kinds (non-identity mass, POD coordinates with an
    ill-conditioned W, active K and C floors, near-exact beam data): the user's call certifies
    to 1e-8 at every r (nearbeam from r = 10 on with the ridge raised to 1e-7 sigma_1: at the
    default ridge the interior point stops at 1e-4)."""
    from dolfinx_lopinf.core.synthetic import mass_data

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", lo.errors.IllConditionedDataWarning)
        cert = lo.core.infer_mechanical(*mass_data(kind, r), mass="learned").certificate
    assert cert["certified"] and cert["duality_gap"] <= 1e-8, cert


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["modal", "chainpod", "active", "nearexact", "nearbeam"])
@pytest.mark.parametrize("r", [16, 20])
def test_held_out_style_sets_are_certified_at_large_r(kind, r):
    test_held_out_style_sets_are_certified(kind, r)


@pytest.mark.parametrize("kind,r", [("chainpod", 8), ("active", 8), ("nearexact", 12)])
def test_rounding_does_not_decide_the_fit(kind, r):
    """Every input perturbed at 1e-15 relative (the rounding of another BLAS): still certified,
    the same iterations within a few, the dynamics M^-1 K, M^-1 C, M^-1 B to 1e-6 - on an
    ill-conditioned W (chainpod) and with floors active (active)."""
    from dolfinx_lopinf.core.synthetic import mass_data

    data = mass_data(kind, r)
    rng = np.random.default_rng(7)
    bent = [X * (1.0 + 1e-15 * rng.standard_normal(X.shape)) for X in data]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", lo.errors.IllConditionedDataWarning)
        a, b = (lo.core.infer_mechanical(*d, mass="learned") for d in (data, bent))
    assert a.certificate["certified"] and b.certificate["certified"]
    assert abs(a.certificate["iterations"] - b.certificate["iterations"]) <= 4
    for X, Y in zip((a.K, a.C, a.B), (b.K, b.C, b.B)):
        X, Y = np.linalg.solve(a.M, X), np.linalg.solve(b.M, Y)
        assert np.allclose(X, Y, rtol=1e-6, atol=1e-6 * np.abs(X).max())


@pytest.mark.parametrize("r", [8, 12, 16])
def test_near_exact_data_predict_at_the_free_fit_and_intrusive_level(r):
    """Near-exact data (a bar in its Euclidean POD basis, no noise: the fit's residual is the
    truncation alone). The W-normalised centre gave the last POD directions masses 1e7 ..
    1e9 times the first's and the fit weighted their truncation residual over the leading
    equations: 3.4e-6 / 9.2e-6 / 2.1e-5 against the free fit's 4.4e-7 / 1.4e-7 / 4.2e-8 (r = 8 /
    12 / 16). With the isotropic floor: certified, within 3x of the better of the free fit
    and the intrusive ROM (measured 1.0x / 1.5x / 1.1x)."""
    from dolfinx_lopinf.core.synthetic import near_exact

    d = near_exact(r)
    ops = lo.core.infer_mechanical(*d["relation"], mass="learned")
    assert ops.certificate["certified"], ops.certificate
    assert d["predict"](ops.M, ops.K, ops.C, ops.B) <= 3.0 * max(d["free"], d["intrusive"])


@pytest.mark.parametrize("r", [8, 12, 16])
def test_the_bound_is_never_above_the_objective_on_near_exact_data(r):
    """On near-exact data the K, C rows of L span 1e14 and the interior point's dual residual
    lies along their weak directions: the least-norm repair of G_k >= 0 there was solved on
    the normal matrix and missed the cone, leaving a 'bound' above the objective (negative
    gaps, certified). Every bound - from the interior point's Y and from its projection -
    is now at or below phi (to the rounding of phi), or absent (gap inf)."""
    from dolfinx_lopinf.core.synthetic import near_exact

    d = near_exact(r)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", lo.errors.IllConditionedDataWarning)
        prep = mass_mod.prepare(*d["relation"], damping=True, eps=1e-8, ridge=1e-9, strict=False,
                                rho=fractional.RHO)
    p = prep.problem
    xs, Y, tau, cert = fractional.MassInteriorPoint().solve(p)
    assert cert.converged
    for dual in (Y, fractional_bound.projected_dual(p, xs, Y)):
        c = p.certify(xs, dual, tau)
        assert c["bound"] <= c["phi"] + 1e-13 * abs(c["phi"]), c


def test_a_cold_cache_fits_with_numpy_and_builds_the_kernels_aside(monkeypatch):
    """backend="auto" with the compiled iteration not ready (a fresh machine: tens of seconds
    of compilation): that fit runs the numpy iteration and the build starts in the background;
    once ready, the compiled one. backend="numba" never falls back."""
    from dolfinx_lopinf.core import compiled
    from dolfinx_lopinf.core.lsq import _fractional_compiled as fc

    if not compiled.available():
        pytest.skip("numba unavailable")
    p = _prepared().problem
    started = []
    monkeypatch.setattr(fc, "ready", lambda: False)
    monkeypatch.setattr(fc, "compile_in_background", lambda: started.append(True))
    cold = fractional.MassInteriorPoint().solve(p)[3]
    assert cold.converged and cold.details["backend"] == "numpy" and started == [True]
    assert fractional.MassInteriorPoint(backend="numba").solve(p)[3].details["backend"] == "numba"
    monkeypatch.setattr(fc, "ready", lambda: True)
    assert fractional.MassInteriorPoint().solve(p)[3].details["backend"] == "numba"


def test_a_background_build_running_at_exit_is_waited_for():
    """A program that ends while the background build runs waits for it, says so on stderr
    and exits normally (a daemon thread left inside LLVM at shutdown can abort the process).
    The build is replaced by a 2 s sleep in a fresh process."""
    import subprocess
    import sys

    from dolfinx_lopinf.core import compiled

    if not compiled.available():
        pytest.skip("numba unavailable")
    code = ("import time\n"
            "import dolfinx_lopinf.core.lsq._fractional_compiled as fc\n"
            "fc._build_quietly = lambda: (time.sleep(2), print('built', flush=True))\n"
            "fc.compile_in_background()\n"
            "print('work done', flush=True)\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["work", "done", "built"], run.stdout
    assert "finishing the one-time build" in run.stderr


def test_ready_reads_the_cache_of_this_source():
    """ready() is True once the kernels are built (here or in numba's cache) - the check that
    decides between the compiled and the numpy iteration must not claim a cold cache warm."""
    from dolfinx_lopinf.core import compiled
    from dolfinx_lopinf.core.lsq import _fractional_compiled as fc

    if not compiled.available():
        pytest.skip("numba unavailable")
    fc.warm_up()
    assert fc.ready()
    assert fc._cached(fc._step.py_func)  # the index of this source and machine


def _noop(a, b):
    return a + b


def test_a_function_never_compiled_is_not_cached():
    from dolfinx_lopinf.core import compiled
    from dolfinx_lopinf.core.lsq import _fractional_compiled as fc

    if not compiled.available():
        pytest.skip("numba unavailable")
    assert not fc._cached(_noop)


def test_the_compensated_product_is_exact_where_extended_precision_is_not():
    """G_k = sym(Y L_k^T) of near-exact data is a small difference of large terms (Y nearly
    orthogonal to L_k's rows): _dot2 / _sym2 stay within their stated bound of the exact
    value (rational arithmetic), where numpy's extended precision errs by ~1e-15 on a
    1e-11 result."""
    from fractions import Fraction

    rng = np.random.default_rng(0)
    A = rng.standard_normal((5, 30)) * 1e3
    B = rng.standard_normal((5, 30))
    A = A - (A @ np.linalg.pinv(B)) @ B  # A B^T ~ 1e-11 from terms ~1e3
    exact = np.array([[float(sum(Fraction(a) * Fraction(b) for a, b in zip(A[i], B[j]))) for j in range(5)]
                      for i in range(5)])
    hi, lo, bound = fractional_bound._dot2(A, B)
    assert np.all(np.abs(hi + lo - exact) <= bound + 1e-300)
    assert np.abs(hi + lo - exact).max() <= 1e-12 * np.abs(exact).max()
    G, err = fractional_bound._sym2(hi, lo, bound)
    assert np.all(np.abs(G - 0.5 * (exact + exact.T)) <= err)


def test_the_certificates_compiled_loops_are_its_numpy_arithmetic():
    """The certificate's compensated product and nu bisection run compiled once the learned-mass
    kernels are loaded: bit for bit the numpy results (graded data over 16 orders, r = 1..40,
    numpy's pairwise order of the sums), so which path certified a fit cannot change its
    verdict."""
    from dolfinx_lopinf.core import compiled
    from dolfinx_lopinf.core.lsq import _fractional_compiled as fc

    if not compiled.available():
        pytest.skip("numba unavailable")
    kernels = fc.kernels()
    rng = np.random.default_rng(3)
    for _ in range(60):
        r, b = int(rng.integers(1, 41)), int(rng.integers(2, 4))
        A = rng.standard_normal((r, b * r)) * 10.0 ** rng.uniform(-8, 8, (1, b * r))
        B = rng.standard_normal(((b - 1) * r, b * r)) * 10.0 ** rng.uniform(-8, 8, ((b - 1) * r, 1))
        s, e = np.zeros((r, (b - 1) * r)), np.zeros((r, (b - 1) * r))
        kernels["_dot2_loops"](A, B, s, e)
        with pytest.MonkeyPatch.context() as mp:  # the numpy path: as if nothing were loaded
            mp.setattr(fractional_bound, "_loaded_kernels", lambda: None)
            hi, lo_, _ = fractional_bound._dot2(A, B)
        assert np.array_equal(s, hi) and np.array_equal(e, lo_)
        lam = np.sort(rng.standard_normal(r) * 10.0 ** rng.uniform(-6, 6, r))
        tau, c = 10.0 ** rng.uniform(-12, 0), 10.0 ** rng.uniform(-3, 3)
        assert kernels["_best_nu_loops"](lam, tau, c) == fractional_bound._best_nu_numpy(lam, tau, c)


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_omega_and_the_floor_multipliers_stay_exactly_symmetric(backend):
    """Omega and Lambda_k start from computed inverses (not exactly symmetric) and take
    symmetric steps: they are symmetrised at the start and Omega after each update, so no
    antisymmetric part survives to meet the tiny eigenvalues of an inactive floor's
    multiplier (numpy iteration and compiled kernel alike)."""
    from dolfinx_lopinf.core import compiled

    p = _prepared(3, r=6, noise=1e-8).problem
    st = fractional._State.initial(p, fractional.start(p))
    if backend == "numpy":
        for _ in range(8):
            st.step()
        Om, Lam = st.Om, st.Lam
    else:
        if not compiled.available():
            pytest.skip("numba unavailable")
        from dolfinx_lopinf.core.lsq import _fractional_compiled as fc

        K, ix = fc.kernels(), p.index
        Om, Lam = np.ascontiguousarray(st.Om), np.ascontiguousarray(st.Lam)
        xs, Y = np.ascontiguousarray(st.xs), np.ascontiguousarray(st.Y)
        state = np.array([st.nu, st.tau, 0.0, 0.0, 0.0, 0.0])
        work = np.empty((ix.n, ix.n)), np.empty((ix.n, ix.n))
        for _ in range(8):
            K["_step"](xs, Y, Om, Lam, state, np.ascontiguousarray(p.L), np.ascontiguousarray(p.a),
                       np.ascontiguousarray(p.x_floor), np.array(ix.full, dtype=np.int64),
                       np.array(ix.iu[0], dtype=np.int64), np.array(ix.iu[1], dtype=np.int64),
                       np.ascontiguousarray(ix.Dw[:ix.nv]), p.r, p.n_blocks, p.rho,
                       p.tau_of(0.0) * p.r / p.rho, *work)
            assert not state[4]
    assert np.array_equal(Om, Om.T)
    for k in range(p.n_blocks):
        assert np.array_equal(Lam[k], Lam[k].T)
