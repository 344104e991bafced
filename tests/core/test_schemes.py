"""Time-integration schemes as data relations and ROM steps; identification from the data.

Verified against the schemes' own defining equations (the one-step generalised-alpha update
written out independently here), not against the package's relation code."""

import numpy as np
import pytest

import dolfinx_lopinf as lo
from dolfinx_lopinf.core import schemes as S
from dolfinx_lopinf.core.identify import identify
from dolfinx_lopinf.errors import InputError


def _system(seed=0, r=4, m=2):
    rng = np.random.default_rng(seed)
    R = np.linalg.qr(rng.standard_normal((r, r)))[0]
    K = R @ np.diag(np.linspace(1.0, 30.0, r) ** 2) @ R.T
    C = 0.05 * np.eye(r) + 2e-3 * K
    B = rng.standard_normal((r, m))
    return np.eye(r), C, K, B


def _reference_run(scheme, M, C, K, B, dt, n, q0, v0, load):
    """The generalised-alpha family written out as a user's loop would: solve the balance at
    the alpha levels for a_{n+1}, then the Newmark updates (independent of S.step)."""
    am, af, b, g = scheme.alpha_m, scheme.alpha_f, scheme.beta, scheme.gamma
    u, v = q0.copy(), v0.copy()
    a = np.linalg.solve(M, B @ load(0.0) - C @ v - K @ u)
    U = [u]
    for k in range(n):
        f = load((k + 1 - af) * dt)
        lhs = (1 - am) * M + (1 - af) * g * dt * C + (1 - af) * b * dt**2 * K
        rhs = (B @ f - am * M @ a - C @ (v + (1 - af) * dt * (1 - g) * a)
               - K @ (u + (1 - af) * (dt * v + dt**2 * (0.5 - b) * a)))
        a1 = np.linalg.solve(lhs, rhs)
        u = u + dt * v + dt**2 * ((0.5 - b) * a + b * a1)
        v = v + dt * ((1 - g) * a + g * a1)
        a = a1
        U.append(u)
    return np.array(U).T


FAMILY = [S.Newmark(), S.Newmark(1 / 6, 0.5), S.Newmark(1 / 12, 0.5), S.CentralDifference(),
          S.HHT(0.1), S.HHT(1 / 3), S.GeneralizedAlpha(0.2, 0.4), S.GeneralizedAlpha(rho_inf=0.8),
          S.GeneralizedAlpha(rho_inf=0.0), S.GeneralizedAlpha(0.1, 0.3, 0.4, 0.75)]


def _load(t):
    return np.array([np.sin(3 * t) + (t > 0.5), np.cos(7 * t) ** 3])


@pytest.mark.parametrize("scheme", FAMILY, ids=lambda s: s.spec)
def test_rom_step_and_relations_are_the_scheme(scheme):
    M, C, K, B = _system()
    dt, n = 0.01, 300  # dt omega_max = 0.3 (central differences stable)
    rng = np.random.default_rng(1)
    q0, v0 = rng.standard_normal(4), rng.standard_normal(4)
    ref = _reference_run(scheme, M, C, K, B, dt, n, q0, v0, _load)
    rom = lo.core.LagrangianROM(K=K, C=C, B=B, scheme=scheme)
    tr = rom.simulate(q0, v0, dt, n, inputs=_load, backend="numpy")
    assert np.abs(tr.Qh - ref).max() <= 1e-12 * np.abs(ref).max()
    # the displacement-only relation holds on the samples, the loads taken where they act
    t = dt * np.arange(n + 1)
    t_load = np.union1d(t, t[:-1] + scheme.tau * dt)
    U = np.array([_load(s) for s in t_load]).T
    Qk, Qc, Qm, Uf = scheme.relation(ref, t, U, t_load)
    assert np.linalg.norm(M @ Qm + C @ Qc + K @ Qk - B @ Uf) <= 1e-11 * np.linalg.norm(M @ Qm)
    # and the (u, v, a) relation on the ROM's own velocities and accelerations
    Qk, Qc, Qm, Uf = scheme.state_relation(tr.Qh, tr.Vh, tr.Ah, t, U, t_load)
    assert np.linalg.norm(M @ Qm + C @ Qc + K @ Qk - B @ Uf) <= 1e-11 * np.linalg.norm(M @ Qm)


def test_midpoint_relation_and_step():
    M, C, K, B = _system(2)
    dt, n = 0.01, 200
    rom = lo.core.LagrangianROM(K=K, C=C, B=B, scheme=S.Midpoint())
    tr = rom.simulate(np.ones(4), np.zeros(4), dt, n, inputs=_load)
    t = dt * np.arange(n + 1)
    t_load = np.union1d(t, t[:-1] + 0.5 * dt)
    U = np.array([_load(s) for s in t_load]).T
    Qk, Qc, Qm, Uf = S.Midpoint().relation(tr.Qh, t, U, t_load)
    assert np.linalg.norm(M @ Qm + C @ Qc + K @ Qk - B @ Uf) <= 1e-11 * np.linalg.norm(M @ Qm)


def test_no_four_parameter_refinement_on_recorded_states():
    """On recorded (u, v, a) the relation holds alpha_m and alpha_f alone (state_relation), so
    the refinements stop at two parameters (beta, gamma would be dead ones, their forward
    differences evaluations thrown away); on u alone with loads the four-parameter fit runs."""
    from dolfinx_lopinf.core.identify import Residual, _refinements

    M, C, K, B = _system(3, m=1)
    truth, dt, n = S.GeneralizedAlpha(0.2, 0.4), 0.01, 300
    rom = lo.core.LagrangianROM(K=K, C=C, B=B, scheme=truth)
    load = (lambda t: np.array([np.sin(2 * t) + (t > 1.0)]))
    tr = rom.simulate(np.ones(4), np.zeros(4), dt, n, inputs=load, backend="numpy")
    t = dt * np.arange(n + 1)
    t_load = np.union1d(t, t[:-1] + truth.tau * dt)
    U = np.array([load(s) for s in t_load]).T
    for pieces, most in (([(tr.Qh, t, U, t_load, tr.Vh, tr.Ah)], 2), ([(tr.Qh, t, U, t_load, None, None)], 4)):
        residual = Residual(pieces)
        rho = {m: residual(m) for m in (truth, S.Newmark(), S.HHT(0.1))}
        sizes = [n_params for n_params, *_ in _refinements(residual, rho)]
        assert sizes and max(sizes) == most, sizes


@pytest.mark.parametrize("truth", [S.HHT(0.17), S.GeneralizedAlpha(rho_inf=0.73),
                                   S.GeneralizedAlpha(0.12, 0.31, 0.42, 0.72), S.Newmark(0.3, 0.6)],
                         ids=lambda s: s.spec)
def test_identification_recovers_parameters_and_operators(truth):
    """Data generated by a scheme on known reduced operators (Mh = I), loads with jumps and a
    random component (they pin every parameter): parameters and operators to 1e-6."""
    M, C, K, B = _system(3, m=1)
    dt, n = 0.01, 400
    rng = np.random.default_rng(4)
    kicks = rng.standard_normal(n + 2)
    load = (lambda t: np.array([np.sin(2 * t) + kicks[int(np.floor(t / dt + 1e-9))]]))
    t = dt * np.arange(n + 1)
    t_load = t[:-1] + truth.tau * dt  # the user recorded the loads their loop applied
    U = np.array([load(s) for s in t_load]).T
    Q = _reference_run(truth, M, C, K, B, dt, n, rng.standard_normal(4), np.zeros(4), load)
    found, report = identify([(Q, t, U, t_load, None, None)])
    for name in ("alpha_m", "alpha_f", "beta", "gamma"):
        assert abs(getattr(found, name) - getattr(truth, name)) < 1e-6, (found, report["why"])
    snaps = lo.Snapshots(t, Q, U=U, input_times=t_load)
    model = lo.fit(snaps, 4, basis=lo.core.Basis(np.eye(4), {}, {}), mass="identity", damping=True)
    for name in ("alpha_m", "alpha_f", "beta", "gamma"):  # identified in POD coordinates
        assert abs(getattr(model.scheme, name) - getattr(truth, name)) < 1e-6
    for fitted, true in ((model.rom.K, K), (model.rom.C, C), (model.rom.B, B)):
        assert np.abs(fitted - true).max() <= 1e-6 * np.abs(true).max()


def test_free_response_keeps_the_standard_member():
    """A free response of Newmark(0.3, 0.6) obeys every three-point relation with free
    operators: nothing pins beta and gamma, the standard member is kept (same prediction)."""
    M, C, K, B = _system(5, m=1)
    dt, n = 0.01, 300
    Q = _reference_run(S.Newmark(0.3, 0.6), M, C, K, B, dt, n, np.ones(4), np.zeros(4),
                       lambda t: np.zeros(1))
    found, report = identify([(Q, dt * np.arange(n + 1), None, None, None, None)])
    assert found == S.Newmark() and "no refinement is 2x better" in report["why"]


def test_equivalence_classes_of_relations():
    """What the data can see of a relation (M = I, C, K, B free): every Newmark(beta, 1/2),
    the midpoint rule and central differences are one relation on free responses and on loads
    linear between bends; the loads' curvature separates them; gamma != 1/2 (numerical
    dissipation) and generalised-alpha never join them."""
    from dolfinx_lopinf.core.identify import _equivalent

    same_linear = [S.Midpoint(), S.Newmark(1 / 6, 0.5), S.Newmark(1 / 12, 0.5), S.CentralDifference()]
    for other in same_linear:
        assert _equivalent(S.Newmark(), other, "none") and _equivalent(S.Newmark(), other, "linear")
    assert _equivalent(S.Newmark(), S.Midpoint(), "general")  # (f- + 2 f + f+)/4 both
    for other in same_linear[1:]:
        assert not _equivalent(S.Newmark(), other, "general")
    for other in (S.HHT(0.1), S.GeneralizedAlpha(0.2, 0.4), S.GeneralizedAlpha(rho_inf=0.8)):
        for loads in ("none", "linear", "general"):
            assert not _equivalent(S.Newmark(), other, loads)
    assert not _equivalent(S.Newmark(), S.Newmark(0.3, 0.6), "linear")


def test_members_the_data_cannot_tell_apart_are_decided_by_the_list():
    """The residuals of the own-loop demo's average-acceleration Newmark loop in 24 POD
    coordinates (a ramp-hold-release load, so linear between bends): the truncated modes'
    closure ranks central differences and linear acceleration 4-6x below the loop's own
    scheme. They are one relation on such data, so the first of the class in the list -
    average acceleration - is chosen; loads with curvature would have separated them."""
    from dolfinx_lopinf.core.identify import _by_residual, standard_members

    members = standard_members()
    rho = {m: 1e-3 for m in members}
    rho.update({S.Newmark(): 1.71e-7, S.Midpoint(): 1.71e-7, S.Newmark(1 / 6, 0.5): 4.5e-8,
                S.Newmark(1 / 12, 0.5): 3.33e-8, S.CentralDifference(): 2.91e-8,
                S.GeneralizedAlpha(rho_inf=0.9): 5.76e-8})
    chosen, why = _by_residual(members, rho, [], {}, "linear")
    assert chosen == S.Newmark() and "cannot tell it from the best" in why
    chosen, _ = _by_residual(members, rho, [], {}, "general")  # curvature shows beta
    assert chosen != S.Newmark()


@pytest.mark.parametrize("bad, match", [
    (lambda: S.Newmark(0.25, 0.4), "gamma = 0.4 < 1/2"),
    (lambda: S.GeneralizedAlpha(rho_inf=1.2), r"rho_inf must lie in \[0, 1\]"),
    (lambda: S.GeneralizedAlpha(rho_inf=-0.1), r"rho_inf must lie in \[0, 1\]"),
    (lambda: S.GeneralizedAlpha(0.6, 0.4), r"alpha_m = 0.6 outside \[-1, 1/2\]"),
    (lambda: S.GeneralizedAlpha(0.2, 0.7), r"alpha_f = 0.7 outside \[0, 1/2\]"),
    (lambda: S.HHT(-0.1), "pass alpha=0.1"),
    (lambda: S.GeneralizedAlpha(rho_inf=0.5, alpha_m=0.1), "not both"),
    (lambda: S.Newmark(float("nan")), "finite"),
    (lambda: S.from_spec("generalized_alpha(alpha_m=0.2; alpha_f=0.4)"), "cannot read"),
])
def test_parameters_outside_the_stable_range_are_refused(bad, match):
    with pytest.raises(InputError, match=match):
        bad()


def test_specs_round_trip():
    for s in FAMILY + [S.Midpoint(), S.FiniteDifferences()]:
        assert S.from_spec(s.spec) == s and S.from_spec(s.spec).spec == s.spec


def test_inputs_are_interpolated_to_the_schemes_times():
    ti = np.array([0.0, 0.1, 0.2])
    U = np.array([[0.0, 1.0, 4.0]])
    np.testing.assert_allclose(S.sample_inputs(U, ti, [0.0, 0.05, 0.1, 0.16]), [[0, 0.5, 1, 2.8]])
    with pytest.raises(InputError, match="recorded over"):
        S.sample_inputs(U, ti, [0.25])


def test_undamped_data_give_a_conservative_energy_conserving_rom():
    """Undamped average-acceleration data: damping="auto" keeps the conservative model, and its
    ROM conserves the reduced energy to rounding over a free run 10x the training window."""
    M, C, K, B = _system(6, m=1)
    dt, n = 0.01, 400
    load = (lambda t: np.array([np.sin(4 * t) * (t < 2.0)]))
    Q = _reference_run(S.Newmark(), M, 0 * C, K, B, dt, n, np.ones(4), np.zeros(4), load)
    t = dt * np.arange(n + 1)
    snaps = lo.Snapshots(t, Q, U=np.array([load(s) for s in t]).T)
    model = lo.fit(snaps, 4, basis=lo.core.Basis(np.eye(4), {}, {}), mass="identity")
    assert model.report["damping"] is False and model.rom.C is None, model.report["why"]
    assert model.scheme == "newmark"
    free = model.predict(10 * n, q0=Q[:, -1], v0=np.ones(4))  # inputs=None: the free response
    e = model.rom.energy(free.Qh, free.Vh)
    assert np.ptp(e) <= 1e-12 * e[0]


def test_a_forced_model_predicts_its_free_response_without_inputs():
    M, C, K, B = _system(7, m=1)
    rom = lo.core.LagrangianROM(K=K, C=C, B=B, scheme="newmark")
    free = rom.simulate(np.ones(4), np.zeros(4), 0.01, 50)
    zero = rom.simulate(np.ones(4), np.zeros(4), 0.01, 50, inputs=lambda t: np.zeros(1))
    np.testing.assert_array_equal(free.Qh, zero.Qh)
    with pytest.raises(InputError, match="unforced"):
        lo.core.LagrangianROM(K=K, scheme="newmark").simulate(np.ones(4), np.zeros(4), 0.01, 5,
                                                        inputs=lambda t: np.ones(1))


def test_one_simulate_contract_for_linear_and_wave_roms():
    """The same call and result for both ROMs; a failing Newton step raises by default and
    ends the run with NaN after it with on_failure="stop"."""
    K = -np.diag([1.0, 4.0])
    V = np.eye(2)
    wave = lo.core.WaveROM(K=K, V=V, g=np.sin, dg=np.cos, U=lambda z: 1 - np.cos(z))
    lin = lo.core.LagrangianROM(K=-K, scheme="newmark")
    for rom in (wave, lin):
        tr = rom.simulate(np.array([0.1, 0.0]), np.zeros(2), 0.01, 20, inputs=None, every=2,
                          backend="numpy", on_failure="raise")
        assert isinstance(tr, lo.core.Trajectory) and tr.Qh.shape == (2, 11) and tr.stable
    with pytest.raises(InputError, match="no input operator"):
        wave.simulate(np.zeros(2), np.zeros(2), 0.01, 5, inputs=lambda t: np.ones(1))
    with pytest.raises(InputError, match="on_failure"):
        lin.simulate(np.zeros(2), np.zeros(2), 0.01, 5, on_failure="ignore")
    big = np.array([50.0, 0.0])  # Newton cannot converge in 1 iteration from this state
    with pytest.raises(lo.errors.StepFailedError, match="step 1 "):
        wave.simulate(big, np.zeros(2), 1.0, 10, max_newton=1, backend="numpy")
    tr = wave.simulate(big, np.zeros(2), 1.0, 10, max_newton=1, backend="numpy", on_failure="stop")
    assert not tr.stable and np.all(np.isnan(tr.Qh[:, 1:])) and "step 1" in tr.info["failure"]


def _forced_run(truth, n=300, dt=0.01):
    M, C, K, B = _system(3, m=1)
    rng = np.random.default_rng(5)
    kicks = rng.standard_normal(n + 2)
    load = (lambda t: np.array([np.sin(2 * t) + kicks[int(np.floor(t / dt + 1e-9))]]))
    t = dt * np.arange(n + 1)
    U = np.array([load(s) for s in t]).T
    Q = _reference_run(truth, M, C, K, B, dt, n, rng.standard_normal(4), np.zeros(4), load)
    return [(Q, t, U, None, None, None)]


def test_refinement_jacobian_is_the_derivative_of_the_residual():
    """The variable-projection Jacobian of the compressed relation residual (one evaluation
    gives both) against central differences of the residual itself, at a point away from the
    data's scheme (a residual well above rounding)."""
    from dolfinx_lopinf.core.identify import Residual

    residual = Residual(_forced_run(S.GeneralizedAlpha(rho_inf=0.7)))
    lo_, hi = [-1.0, 0.0, 0.0, 0.5], [0.5, 0.5, 1.5, 1.5]
    fun, jac = residual.projected(lambda x: S.GeneralizedAlpha(*x), lo_, hi)
    x = np.array([0.1, 0.3, 0.4, 0.7])
    assert np.allclose(fun(x), residual.vector(S.GeneralizedAlpha(*x)), rtol=0, atol=1e-14)
    J = jac(x)
    for i in range(4):
        h = 1e-5
        e = np.zeros(4)
        e[i] = h
        fd = (fun(x + e) - fun(x - e)) / (2 * h)
        assert np.abs(J[:, i] - fd).max() <= 1e-5 * np.abs(fd).max(), i


def test_blown_up_free_predictions_do_not_choose_the_scheme(monkeypatch):
    """A held-back prediction with relative error >= 1 (free operators that blow up) says
    nothing: such errors take no part in the choice and are not reported as evidence (on a
    held-out Newmark cantilever a refinement's 1.5e14 'beat' Newmark's 5.8e14 and was chosen;
    here the report said Newmark 'predicts the held-back samples best (1e+14)')."""
    import importlib

    ID = importlib.import_module("dolfinx_lopinf.core.identify")  # the module, not the function
    pieces = _forced_run(S.Newmark())
    honest, _ = identify(pieces)
    # the blown-up predictions favour generalised-alpha 100x, as rounding may
    monkeypatch.setattr(ID, "prediction_error", lambda ops, scheme, *a, **k:
                        1e12 if scheme.spec.startswith("generalized_alpha") else 1e14)
    found, report = identify(pieces)
    assert found == honest == S.Newmark(), report["why"]
    assert "held-back" not in report["why"] and "predictions" not in report, report["why"]


def test_where_the_residuals_choice_blows_up_a_member_that_predicts_well_is_chosen():
    """Exact Newmark recordings of a damped clamped beam under a multi-sine load: in the
    identification's truncated coordinates the dropped modes' closure gives a 4-level
    generalised-alpha member the lowest relation residual, but its free fit blows up on the
    held-back samples where Newmark's predicts them to 1e-9 (PREDICTS_WELL). The predictions
    now judge; before, any blow-up of the residual's choice discarded them, and lo.fit fitted
    generalised-alpha (unseen-load errors 6.8e-5 / 2.7e-5 at r = 4 / 8, against 2.3e-5 /
    1.3e-5; 15x at r = 8 on a new user's cantilever)."""
    from dolfinx_lopinf.core import synthetic

    M, K, C, B = synthetic._beam(20)
    dt, n = 0.01, 800
    t = dt * np.arange(n + 1)
    U = 0.01 * (np.sin(2.0 * t) + 0.7 * np.sin(5.3 * t) + 0.5 * np.sin(13.1 * t + 0.4))[None, :]
    rom = lo.core.LagrangianROM(K=K, M=M, C=C, B=B, scheme="newmark", lagrangian=False)
    Q = rom.simulate(np.zeros(len(K)), np.zeros(len(K)), dt, n, inputs=U).Qh
    model = lo.fit(lo.Snapshots(t, Q, U=U), 4, mass="identity", damping=True)
    ident = model.report["identification"]
    assert model.scheme == "newmark", ident["why"]
    assert ident["predictions"]["newmark(beta=0.25, gamma=0.5)"] < 1e-7, ident["predictions"]
