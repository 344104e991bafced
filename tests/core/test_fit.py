"""lo.fit: one call from snapshots to a reduced model that matches the user's integrator
(numpy only)."""

import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

import dolfinx_lopinf as lo
from dolfinx_lopinf.core.identify import RESIDUAL_FLOOR
from dolfinx_lopinf.errors import SchemeMismatchWarning


def _system(seed=0, r=4):
    rng = np.random.default_rng(seed)
    R = np.linalg.qr(rng.standard_normal((r, r)))[0]
    K = R @ np.diag([1.0, 9.0, 60.0, 400.0][:r]) @ R.T
    C = 0.01 * np.eye(r) + 1e-3 * K
    B = rng.standard_normal((r, 1))
    return K, C, B


#: the 4 coordinates live in a 6-dimensional state (an orthonormal embedding), so n > r
EMBED = np.linalg.qr(np.random.default_rng(9).standard_normal((6, 4)))[0]


def _newmark(K, C, B, dt, n, q0, u):
    """A Newmark (1/2, 1/4) loop, as a user would write it: states at every step."""
    rom = lo.core.LagrangianROM(K=K, C=C, B=B, scheme="newmark")
    tr = rom.simulate(q0, np.zeros(len(q0)), dt, n, inputs=u)
    t = dt * np.arange(n + 1)
    U = np.array([[u(s)[0] for s in t]])
    return lo.Snapshots(t, EMBED @ tr.Qh, U=U, Y=tr.Qh[:1])


def _in_state(model, A):
    """The reduced operator A in the 4 original coordinates."""
    W = EMBED.T @ model.basis.V
    return W @ A @ W.T


def _load(t):
    return np.array([np.sin(3 * t) + 0.5 * np.sin(11 * t)])


def test_auto_finds_newmark_and_recovers_the_discrete_operators():
    K, C, B = _system()
    dt = 0.02  # dt * omega_max = 0.4: finite differences are biased, the Newmark relation exact
    snaps = _newmark(K, C, B, dt, 1500, np.array([1.0, 0, 0, 0]), _load)
    model = lo.fit(snaps, 4, mass="identity")  # the data's mass is I: the operators themselves
    assert model.scheme == "newmark", model.report
    rho = model.report["identification"]["residuals"]
    assert rho["continuous()"] > 1e6 * rho["newmark(beta=0.25, gamma=0.5)"]  # exact vs biased
    assert model.report["damping"] is True  # the data are damped: the held-back end says so
    # the basis is a rotation of the coordinates: compare the operators in them
    assert np.allclose(_in_state(model, model.rom.K), K, rtol=0, atol=1e-6 * np.abs(K).max())
    assert np.allclose(_in_state(model, model.rom.C), C, rtol=0, atol=1e-6 * np.abs(K).max())
    # and it predicts an unseen load
    test = _newmark(K, C, B, dt, 800, np.zeros(4), lambda t: np.array([np.cos(5 * t)]))
    pred = model.predict(800, inputs=lambda t: np.array([np.cos(5 * t)]))
    assert lo.relative_error(test.Y, pred.Y) < 1e-6


def test_continuous_data_continuous_relation_and_auto():
    """Exact samples of the continuous solution: the 8th-order differences give the continuous
    K (eigenvalues w^2); "auto" judges by the prediction of each candidate's scheme at the
    data's dt, where the three-point relation fitted to the samples is at least as good (it
    absorbs the scheme's phase error), so whichever it picks predicts the held-back data best.
    Both relations hold to ~1e-11 here, so naming "continuous" is not contradicted."""
    t = 0.01 * np.arange(3000)
    w = np.array([1.0, 2.3, 4.1])
    Q = np.cos(w[:, None] * t) * np.array([1.0, 0.5, 0.25])[:, None]
    with warnings.catch_warnings():
        warnings.simplefilter("error", SchemeMismatchWarning)
        cont = lo.fit(lo.Snapshots(t, Q), 3, damping=False, scheme="continuous")
    # the frequencies are the generalised eigenvalues of (Kh, Mh)
    assert np.allclose(scipy.linalg.eigvalsh(cont.rom.K, cont.rom.mass), w**2, rtol=1e-6)
    auto = lo.fit(lo.Snapshots(t, Q), 3, damping=False)
    errors = {k: v for k, v in auto.report["candidate_errors"].items()}
    chosen = f"{auto.report['mass']}/undamped/{auto.scheme.spec}"
    assert errors[chosen] <= 1.5 * min(errors.values())


def test_several_trajectories_are_stacked_per_trajectory():
    K, C, B = _system(1)
    dt = 0.02
    trajs = [_newmark(K, C, B, dt, 400, q0, _load) for q0 in (np.array([1.0, 0, 0, 0]),
                                                              np.array([0, 0.3, 0.5, 0.1]))]
    model = lo.fit(trajs, 4)
    assert model.report["trajectories"] == 2 and model.scheme == "newmark"
    # learned mass: the modal masses are not determined by the data, Mh^-1 Kh and Mh^-1 Ch are
    for fitted, true in ((model.rom.K, K), (model.rom.C, C)):
        got = _in_state(model, np.linalg.solve(model.rom.mass, fitted))
        assert np.allclose(got, true, rtol=0, atol=1e-6 * np.abs(K).max())
    # a full-state initial condition is projected
    tr = model.predict(t_end=1.0, q0=trajs[1].Q[:, 0], inputs=_load)
    assert lo.relative_error(trajs[1].Q[:, :51], model.reconstruct(tr.Qh)) < 1e-6


def test_a_contradicted_scheme_claim_warns():
    """Newmark data at dt omega = 0.4, claimed to be continuous: the claim is named wrong."""
    K, C, B = _system()
    snaps = _newmark(K, C, B, 0.02, 1500, np.array([1.0, 0, 0, 0]), _load)
    with pytest.warns(SchemeMismatchWarning, match=r"scheme=continuous\(\).*newmark\(beta=0.25"):
        lo.fit(snaps, 4, scheme="continuous")


def test_save_and_load_round_trip(tmp_path):
    K, C, B = _system(2)
    model = lo.fit(_newmark(K, C, B, 0.02, 600, np.array([1.0, 0, 0, 0]), _load), 4)
    path = model.save(tmp_path / "m")
    back = lo.ReducedModel.load(path)
    assert back.scheme == model.scheme and back.dt == model.dt
    a = model.predict(100, inputs=_load)
    b = back.predict(100, inputs=_load)
    assert np.array_equal(a.Qh, b.Qh) and np.array_equal(a.Y, b.Y)


def test_a_model_in_a_weighted_basis_projects_full_states_the_same_after_loading(tmp_path):
    """A model fitted in a mass-orthonormal basis (basis=lo.pod(Q, r, weight=M), the accurate
    path) projects a full initial state with W: the file keeps W V. Before, the loaded model
    projected with the Euclidean product - a prediction from a full q0 off by 17x its size."""
    from dolfinx_lopinf.core import synthetic

    M, K, C, B = synthetic._bar(40)
    dt, n = 0.05, 300
    t = dt * np.arange(n + 1)
    U = np.array([synthetic._bar_train(s) for s in t]).T
    rom = lo.core.LagrangianROM(K=K, M=M, C=C, B=B, scheme="newmark", lagrangian=False)
    Q = rom.simulate(np.zeros(len(K)), np.zeros(len(K)), dt, n, inputs=U).Qh
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = lo.fit(lo.Snapshots(t, Q, U=U), 5, basis=lo.pod(Q, 5, weight=M), mass="identity")
    back = lo.ReducedModel.load(model.save(tmp_path / "weighted"))
    q0 = Q[:, 150]
    np.testing.assert_allclose(back.basis.project(q0), model.basis.project(q0), rtol=0,
                               atol=1e-13 * np.abs(model.basis.project(q0)).max())
    a = model.predict(40, q0=q0, inputs=U[:, 150:191])
    b = back.predict(40, q0=q0, inputs=U[:, 150:191])
    assert np.abs(a.Qh - b.Qh).max() <= 1e-12 * np.abs(a.Qh).max()
    # a basis that carries W V keeps projecting with it when truncated
    b5 = model.basis
    held = lo.core.Basis(b5.V, b5.singular_values, b5.blocks, dual=M @ b5.V)
    np.testing.assert_allclose(held.truncate(3).project(q0), b5.truncate(3).project(q0),
                               rtol=0, atol=1e-13 * np.abs(b5.project(q0)).max())


def test_bad_trajectory_lists_are_named():
    K, C, B = _system(3)
    a = _newmark(K, C, B, 0.02, 300, np.array([1.0, 0, 0, 0]), _load)
    b = _newmark(K, C, B, 0.01, 300, np.array([1.0, 0, 0, 0]), _load)
    with pytest.raises(lo.errors.InputError, match=r"snapshots\[1\] has dt"):
        lo.fit([a, b], 4)
    c = lo.Snapshots(a.times, a.Q)  # no inputs
    with pytest.raises(lo.errors.InputError, match=r"snapshots\[1\].*inputs"):
        lo.fit([a, c], 4)
    with pytest.raises(lo.errors.InputError, match=r"snapshots\[1\] has 5 state rows"):
        lo.fit([a, lo.Snapshots(a.times, a.Q[:5], U=a.U)], 3)
    with pytest.raises(lo.errors.InputError, match="not a Snapshots"):
        lo.fit([a.Q], 4)
    short = lo.Snapshots(a.times[:10], a.Q[:, :10], U=a.U[:, :10], Y=a.Y[:, :10])
    with pytest.raises(lo.errors.InputError, match=r"snapshots\[1\] has 10 samples: too short"):
        lo.fit([a, short], 4)
    broken = lo.Snapshots(a.times, a.Q.copy(), U=a.U.copy(), Y=a.Y.copy())
    broken.Q[2, 7] = np.nan  # written after the Snapshots were built: lo.fit checks again
    with pytest.raises(lo.errors.InputError, match=r"snapshots\.Q contains 1 non-finite.*\(2, 7\)"):
        lo.fit(broken, 4)
    broken.Q[2, 7], broken.U[0, 3] = 0.0, np.inf
    with pytest.raises(lo.errors.InputError, match=r"snapshots\[1\]\.U contains 1 non-finite"):
        lo.fit([a, broken], 4)
    with pytest.raises(lo.errors.InputError, match="unknown scheme 'generalised-alpha'.*GeneralizedAlpha"):
        lo.fit(a, 4, scheme="generalised-alpha")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = lo.fit(a, 4)
    with pytest.raises(lo.errors.InputError, match="full"):
        model.predict(10, q0=np.zeros(7), inputs=_load)


def _shake(t):
    """The own-loop demo's unseen load: a 1.6 Hz shake fading in, a reversed push at 1.2 s."""
    return 0.7 * np.sin(2 * np.pi * 1.6 * t) * (1 - np.exp(-t / 0.3)) \
        - 0.8 * np.exp(-((t - 1.2) / 0.08) ** 2)


def test_auto_keeps_the_loops_own_scheme_where_closure_favours_a_dissipative_one():
    """The own-loop demo's average-acceleration Newmark cantilever (1,575 dofs; stored as its
    64 leading POD coordinates, the rest are below 1e-15): trained on a ramp-hold-release
    load - linear between bends, so the data do not show where the loop samples it - the
    relation residual in the identification's 24 coordinates favours generalised-alpha
    (rho_inf 0.9, refined towards alpha_m = alpha_f = 1/2) over Newmark by 4x through the
    truncated modes, and at r = 12-20 that scheme also predicts the held-back end 2-5x better.
    The unseen smooth load shows the cost: 4.3e-4 with it, 4e-6 (r = 8) to 3e-7 (r = 16) with
    the loop's own. lo.fit keeps the most standard member the residual cannot rule out unless
    another relation predicts 10x better."""
    d = np.load(Path(__file__).with_name("data") / "own_loop_newmark_pod64.npz")
    train = lo.Snapshots(d["train_times"], d["train_Q"], U=d["train_U"])
    # measured: 4.0e-6 (r = 8) and 2.9e-7 (r = 16); the dissipative scheme's 4.3e-4 at both
    for r, bound in ((8, 2e-5), (16, 3e-6)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = lo.fit(train, r)
        assert model.scheme == "newmark", (r, model.report["why"])
        assert model.report["identification"]["conservative_member"] == "newmark(beta=0.25, gamma=0.5)"
        tr = model.predict(n_steps=len(d["test_times"]) - 1, inputs=lambda t: np.array([_shake(t)]))
        err = np.linalg.norm(model.reconstruct(tr.Qh) - d["test_Q"]) / np.linalg.norm(d["test_Q"])
        assert err < bound, (r, err)


def test_learned_mass_candidates_are_scored_as_the_fit_returns_them():
    """lo.fit scores a learned-mass candidate with the ridge raised where its first fit is not
    certified, as the chosen model is returned: a stalled fit's held-back error is not
    reproducible. Data: the COMET generalised-alpha cantilever (studies.loops, recorded at
    the load times) in its 16 leading POD coordinates; at r = 12 the states span 10
    directions. Copies differing at 1e-15 gave the stalled candidate held-back errors of 0.7 -
    1.4 in three of six copies and lo.fit chose Mh = I there (prediction error 3e-2 against
    1e-7); scored after the raise, 6e-10 .. 1.0e-9 in all six."""
    d = np.load(Path(__file__).with_name("data") / "comet_gen_alpha_at_t_pod16.npz")
    for seed in (0, 2, 3):
        Q = d["train_Q"].copy()
        if seed:
            Q *= 1 + 1e-15 * np.random.default_rng(seed).standard_normal(Q.shape)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = lo.fit(lo.Snapshots(d["train_times"], Q, U=d["train_U"]), 12)
        rep = model.report
        learned = {k: e for k, e in rep["candidate_errors"].items()
                   if k.startswith("learned/damped/generalized_alpha")}
        assert learned and max(learned.values()) < 1e-6, (seed, learned)
        assert rep["mass"] == "learned" and rep["scheme"].startswith("generalized_alpha"), (seed, rep["why"])
        assert rep["certificate"]["certified"], (seed, rep["certificate"])


def test_an_uncertified_learned_mass_fit_is_refitted_with_a_larger_ridge(monkeypatch):
    """infer_mechanical(mass="learned") - lo.fit's candidates and final fit and a user's call
    alike: uncertified at the default ridge -> the ridge raised 100x, 1000x until certified;
    that fit is returned, its certificate names the ridge and a SolverWarning says so. None
    certified: the first fit and its own warnings (strict: its SolverFailedError). A ridge the
    user passes (even the default's value), raise_ridge=False and Mh = I are never refitted.
    lo.fit's final fit starts at the factor its chosen candidate was certified with
    (_ridge_factor)."""
    import importlib

    from dolfinx_lopinf.core import mass as mass_module
    from dolfinx_lopinf.core.gram import MechanicalOperators
    from dolfinx_lopinf.errors import SolverFailedError, SolverWarning

    inference = importlib.import_module("dolfinx_lopinf.core.inference")
    ridge0 = inference.RIDGE
    calls = []

    def fake(certified_from):
        def infer_with_mass(Qh, dQh, ddQh, U, *, ridge, strict, **kwargs):
            calls.append(ridge)
            ok = ridge >= certified_from * (1 - 1e-12)
            if not ok:
                if strict:
                    raise SolverFailedError("not certified")
                warnings.warn("learned-mass fit not certified", SolverWarning, stacklevel=2)
            return MechanicalOperators(K=np.eye(2), C=None, B=None, M=np.eye(2),
                                       certificate={"certified": ok, "duality_gap": 0.0 if ok else 1e-5})
        return infer_with_mass

    rng = np.random.default_rng(0)
    Q, ddQ = rng.standard_normal((2, 50)), rng.standard_normal((2, 50))
    fit = lambda **kw: lo.core.infer_mechanical(Q, None, ddQ, damping=False, mass="learned", **kw)  # noqa: E731
    monkeypatch.setattr(mass_module, "infer_with_mass", fake(1000 * ridge0))
    with pytest.warns(SolverWarning, match="certified with the ridge 1e-06"):
        ops = fit()
    assert ops.certificate["certified"] and ops.certificate["ridge"] == pytest.approx(1000 * ridge0)
    assert calls == pytest.approx([ridge0, 100 * ridge0, 1000 * ridge0])

    calls.clear()  # lo.fit's final fit, its candidate certified at 100x
    monkeypatch.setattr(mass_module, "infer_with_mass", fake(100 * ridge0))
    with pytest.warns(SolverWarning, match="certified with the ridge 1e-07"):
        ops = fit(_ridge_factor=100.0)
    assert ops.certificate["certified"] and ops.certificate["ridge"] == pytest.approx(100 * ridge0)
    assert calls == pytest.approx([100 * ridge0])

    calls.clear()
    monkeypatch.setattr(mass_module, "infer_with_mass", fake(np.inf))
    with pytest.warns(SolverWarning, match="learned-mass fit not certified"):
        ops = fit()
    assert not ops.certificate["certified"] and "ridge" not in ops.certificate and len(calls) == 3
    with pytest.raises(SolverFailedError):
        fit(strict=True)
    calls.clear()
    with pytest.warns(SolverWarning, match="learned-mass fit not certified"):
        ops = fit(_ridge_factor=100.0)  # none certified from the hint on: the hinted fit, named
    assert not ops.certificate["certified"] and ops.certificate["ridge"] == pytest.approx(100 * ridge0)
    assert calls == pytest.approx([100 * ridge0, 1000 * ridge0])

    calls.clear()
    with pytest.warns(SolverWarning):
        fit(ridge=1e-7)  # the user's ridge
        fit(ridge=ridge0)  # the default's value, but chosen: the warning's "pass ridge=" holds
        fit(raise_ridge=False)
    assert calls == [1e-7, ridge0, ridge0]
    for bad in (-1e-9, 1.0, float("nan"), "1e-9", True):
        with pytest.raises(lo.errors.InputError, match="ridge must be a number in"):
            fit(ridge=bad)


def test_fit_on_large_data_uses_the_leading_modes_and_refuses_r_above_the_rank(monkeypatch):
    """lo.fit's basis and identification from the leading singular triplets when the data are
    large (basis.leading_svd): the refusal of an r above the numerical rank names the rank as
    the full SVD does."""
    import importlib

    F = importlib.import_module("dolfinx_lopinf.core.fit")
    rng = np.random.default_rng(2)
    t = 0.01 * np.arange(400)
    Q = rng.standard_normal((300, 10)) @ np.vstack([np.sin((j + 1) * t) for j in range(10)])
    snaps = lo.Snapshots(t, Q)
    used = []
    real = F.leading_svd
    monkeypatch.setattr(F, "leading_svd", lambda *a, **k: used.append(a[1]) or real(*a, **k))
    with pytest.raises(lo.errors.InputError, match="numerical rank 10"):
        lo.fit(snaps, 12)
    assert used == [max(12, F.ID_MAX_R) + F.LEADING_EXTRA]


def test_a_chosen_model_that_cannot_predict_its_own_data_is_flagged():
    """lo.fit warns (PoorPredictionWarning) when the chosen model's held-back error exceeds
    HELD_BACK_WARN: a loop recorded every third step obeys no relation with symmetric reduced
    operators, and without the warning lo.fit returned a model 10% off on its own data with
    no sign (a user's implicit loop: 0.24 on an unseen load). The same loop recorded every
    step fits to 1e-4 and is not flagged. Data: a damped bar (synthetic._bar), Newmark,
    under a piecewise-constant random load."""
    import importlib

    from dolfinx_lopinf.core import synthetic
    from dolfinx_lopinf.core.rom import LagrangianROM
    from dolfinx_lopinf.errors import PoorPredictionWarning

    threshold = importlib.import_module("dolfinx_lopinf.core.fit").HELD_BACK_WARN
    M, K, C, B = synthetic._bar(60)
    dt, n = 0.05, 900
    U = np.random.default_rng(0).standard_normal(n // 15 + 2)[np.arange(n + 1) // 15][None, :]
    rom = LagrangianROM(K=K, M=M, C=C, B=B, scheme="newmark", lagrangian=False)
    Q = rom.simulate(np.zeros(len(K)), np.zeros(len(K)), dt, n, inputs=U).Qh
    t = dt * np.arange(n + 1)
    for every, flagged in ((1, False), (3, True)):
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            model = lo.fit(lo.Snapshots(t[::every], Q[:, ::every], U=U[:, ::every]), 4)
        poor = [w for w in seen if issubclass(w.category, PoorPredictionWarning)]
        best = min(model.report["candidate_errors"].values())
        assert bool(poor) == flagged, (every, best, [str(w.message)[:80] for w in seen])
        assert (best > threshold) if flagged else (best < threshold / 100), (every, best)
        if flagged:
            assert "every step" in str(poor[0].message) and poor[0].filename == __file__


@pytest.mark.parametrize("named, best, warns", [(3.6e-5, 1.8e-14, True), (1.24e-7, 1.78e-8, False),
                                                (7.9e-3, 2.0e-3, False), (2e-9, 2e-10, False)])
def test_a_named_scheme_is_contradicted_only_by_a_relation_that_holds_to_rounding(monkeypatch, named, best, warns):
    """SchemeMismatchWarning needs another member whose relation holds to the data's rounding
    (RESIDUAL_FLOOR): at the truncated modes' closure level another member can fit better
    than the loop's own. Residuals of new users' data: exact Newmark recordings of a
    cantilever, named 1.24e-7 against 1.78e-8 for a generalised-alpha member whose model
    predicted an unseen load 15x worse; a 13-sample record, 7.9e-3 against 2.0e-3; and the
    contradicted claim of test_a_contradicted_scheme_claim_warns, 3.6e-5 against 1.8e-14."""
    import importlib

    fit_module = importlib.import_module("dolfinx_lopinf.core.fit")
    other = lo.schemes.GeneralizedAlpha(alpha_m=0.125, alpha_f=0.375)
    monkeypatch.setattr(fit_module, "Residual", lambda pieces: (lambda scheme: named))
    monkeypatch.setattr(fit_module, "identify", lambda pieces, **kw: (other, {"residual": best}))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        _, ident = fit_module._relation_for(lo.schemes.Newmark(0.25, 0.5), [], 4)
    assert ident["residual"] == named and ident["best_residual"] == best
    assert any(issubclass(w.category, SchemeMismatchWarning) for w in seen) == warns


GA_LOOP = lo.schemes.GeneralizedAlpha(rho_inf=0.8)


def _chain_loop(record_shift=0.0, input_time=True):
    """A generalised-alpha loop (rho_inf = 0.8) on a 30-mass chain, loads with random kicks
    every 15 steps, recorded as a user would: the applied value with its time (the default),
    ``record_shift`` steps late, or (``input_time=False``) without input_time."""
    n = 30
    K = (np.diag(np.full(n, 2.0)) - np.diag(np.ones(n - 1), 1) - np.diag(np.ones(n - 1), -1)) * 400.0
    C = 0.02 * np.eye(n) + 2e-3 * K
    x = (np.arange(n) + 1) / (n + 1)
    B = np.exp(-((x - 0.3) / 0.15) ** 2)[:, None]
    dt, steps = 0.01, 800
    kicks = np.random.default_rng(0).standard_normal(200)

    def load(t):
        return np.array([np.sin(2.0 * t) + kicks[int(max(t, 0.0) // 0.15)]])

    tr = lo.core.LagrangianROM(K=K, C=C, B=B, scheme=GA_LOOP).simulate(np.zeros(n), np.zeros(n), dt, steps,
                                                                          inputs=load)
    t = dt * np.arange(steps + 1)
    ti = t[:-1] + GA_LOOP.tau * dt  # where the loop applies its loads
    U = np.array([load(s - record_shift * dt)[0] for s in ti])[None, :]
    return lo.Snapshots(t[1:], tr.Qh[:, 1:], U=U, input_times=ti if input_time else t[1:])


def test_a_wrong_named_scheme_on_truncated_data_is_flagged_by_its_held_back_prediction():
    """The chain loop of 30 coordinates, identified in 24: the best relation holds to the
    truncated modes' closure only (4e-8, above RESIDUAL_FLOOR), so the residual alone does
    not contradict a named scheme; the held-back predictions of the free fits do. Named
    Newmark or central differences: SchemeMismatchWarning, both errors in the report (8e-5
    against 1e-9); the loop's own scheme: no warning."""
    snaps, truth = _chain_loop(), GA_LOOP
    for named, flagged in ((lo.schemes.Newmark(0.25, 0.5), True), ("central_difference", True), (truth, False)):
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            model = lo.fit(snaps, 6, scheme=named)
        ident = model.report["identification"]
        assert ident["best_residual"] > RESIDUAL_FLOOR  # truncated: not "exact"
        mismatch = [w for w in seen if issubclass(w.category, SchemeMismatchWarning)]
        assert bool(mismatch) == flagged, (named, ident)
        if flagged:
            errors = ident["held_back"]
            assert errors[ident["named"]] > 1e3 * errors[ident["best_member"]]
            assert "input_time=" in str(mismatch[0].message) and mismatch[0].filename == __file__


@pytest.mark.parametrize("shift, input_time, expected", [(0.0, True, None), (1.0, True, -1.0),
                                                         (-3.0, True, 3.0), (0.0, False, -0.44)])
def test_loads_recorded_at_other_times_than_applied_are_flagged_with_the_shift(shift, input_time, expected):
    """The named relation against the recorded input times moved by whole and fractional
    steps: a load recorded one step late (the value of the step before: it acts one step
    earlier than its recorded time) or three early fits 10x better moved, and a
    forgotten input_time= of a generalised-alpha loop at -alpha_f steps (the message says
    so); the correct recording is not flagged."""
    snaps = _chain_loop(shift, input_time)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        model = lo.fit(snaps, 6, scheme=GA_LOOP, mass="identity")
    found = model.report["identification"].get("load_shift")
    timing = [w for w in seen if issubclass(w.category, SchemeMismatchWarning) and "input times moved" in str(w.message)]
    if expected is None:
        assert found is None and not timing
    else:
        assert abs(found["steps"] - expected) <= 0.02 and timing, (found, [str(w.message) for w in seen])
        assert ("alpha_f dt" in str(timing[0].message)) == (not input_time)


def test_the_standard_member_beside_a_refinement_is_the_nearest_in_the_residual(monkeypatch):
    """A refined scheme competes with the standard member nearest to it in the relation
    residual - not the first member within 1.5x of the best, which on a new user's
    generalised-alpha loop (r = 12) was hht(alpha=0.15) at 1.496x the loop's own member and
    gave a model 1,000x worse on an unseen load."""
    import importlib

    fit_module = importlib.import_module("dolfinx_lopinf.core.fit")
    own = lo.schemes.GeneralizedAlpha(rho_inf=0.8)
    refined = lo.schemes.GeneralizedAlpha(0.3778, 0.448)
    members = fit_module.standard_members() + [lo.schemes.FiniteDifferences()]
    residuals = {m.spec: 1e-6 for m in members}
    residuals[lo.schemes.HHT(0.15).spec] = 5.19e-10
    residuals[own.spec] = 3.47e-10
    assert own.spec in residuals and members.index(lo.schemes.HHT(0.15)) < members.index(own)
    monkeypatch.setattr(fit_module, "identify", lambda pieces, **kw: (refined, {"residuals": residuals,
                                                                                "loads": "general"}))
    _, ident = fit_module._relation_for("auto", [(np.zeros((4, 10)), np.arange(10.0), None, None, None, None)], 4)
    assert ident["best_member"] == own.spec


def test_recorded_velocities_and_accelerations_fix_beta_and_gamma():
    """An explicit central-difference loop recorded with (u, v, a): the balance fitted on
    them is average acceleration's too (no beta, gamma in it), and the Newmark updates of
    the records decide - beta = 0, gamma = 1/2 to rounding. lo.fit returns central
    differences (it returned newmark(0.25, 0.5), the first in the list); Newmark named on
    the same records is kept, with a SchemeMismatchWarning naming beta = 0; the 1-D input
    array is one channel."""
    K, C, B = _system(4)
    dt, n = 0.01, 600
    tr = lo.core.LagrangianROM(K=K, C=C, B=B, scheme="central_difference").simulate(
        np.array([1.0, 0.0, 0.5, 0.0]), np.zeros(4), dt, n, inputs=_load)
    t = dt * np.arange(n + 1)
    snaps = lo.Snapshots(t, EMBED @ tr.Qh, V=EMBED @ tr.Vh, A=EMBED @ tr.Ah,
                         U=np.array([_load(s)[0] for s in t]))
    assert snaps.U.shape == (1, n + 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = lo.fit(snaps, 4)
    kin = model.report["identification"]["kinematics"]
    assert model.scheme == lo.schemes.CentralDifference(), model.report["why"]
    assert (kin["beta"], kin["gamma"]) == (0.0, 0.5) and kin["residual"] < 1e-12
    with pytest.warns(SchemeMismatchWarning, match=r"beta=0, gamma=0.5"):
        named = lo.fit(snaps, 4, scheme="newmark")
    assert named.scheme == lo.schemes.Newmark()


def test_an_unforced_run_with_zero_loads_is_refused_without_a_warning_about_a_model():
    """inputs=[0.0] at every step of an unforced run: no input matrix can be fitted, so
    RankDeficientDataError with the lo.fit-level advice - and no PoorPredictionWarning about
    a "chosen model" first (every candidate failed; none was chosen)."""
    t = np.arange(400) * 0.01
    snaps = lo.Snapshots(t, np.vstack([np.cos(t), np.sin(t), np.cos(2 * t)]), U=np.zeros((1, t.size)))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        with pytest.raises(lo.errors.RankDeficientDataError, match="together with forced ones"):
            lo.fit(snaps, 3)
    assert not [w for w in seen if issubclass(w.category, lo.errors.PoorPredictionWarning)]


def test_the_report_gives_the_basis_error_on_the_training_states():
    """report["projection_error"]: Basis.projection_error of the training states (the floor
    the held-back errors in reduced coordinates do not show): 0 where r spans the data, the
    basis' own figure where it does not."""
    K, C, B = _system(5)
    snaps = _newmark(K, C, B, 0.02, 400, np.array([1.0, 0.3, 0, 0]), _load)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        full, cut = lo.fit(snaps, 4), lo.fit(snaps, 2, damping=True, mass="identity")
    assert full.report["projection_error"] < 1e-12
    assert cut.report["projection_error"] > 1e-3
    assert abs(cut.report["projection_error"] - cut.basis.projection_error(snaps.Q)) <= 1e-12
