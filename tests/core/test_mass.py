"""L-OpInf with a learned reduced mass (numpy only): a system whose mass is not I in the
user's coordinates - what a Euclidean POD basis of a black box gives."""

import types
import warnings

import numpy as np
import pytest
import scipy.linalg

import dolfinx_lopinf as lo


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
    rom = lo.LagrangianROM(K=K, M=M, C=C, B=B, scheme="newmark")
    tr = rom.simulate(np.zeros(len(K)), np.zeros(len(K)), dt, n, inputs=u)
    return tr


def _fit(tr, u, dt=0.01, **kw):
    t = dt * np.arange(tr.Qh.shape[1])
    U = np.array([u(s)[0] for s in t])[None, :]
    Qbar, D1, D2, Ubar = lo.newmark_data(tr.Qh, t, U)
    return lo.infer_mechanical(Qbar, D1, D2, Ubar, **kw)


def test_learned_mass_recovers_a_non_identity_mass_system():
    M, K, C, B = _system()
    train = _run(M, K, C, B, _load)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", lo.errors.IllConditionedDataWarning)
        learned = _fit(train, _load, mass="learned")
        fixed = _fit(train, _load, mass="identity")
    # structure by construction
    for A in (learned.M, learned.K, learned.C):
        assert np.array_equal(A, A.T) and np.linalg.eigvalsh(A).min() > 0
    # the data determine Mh^-1 Kh (the modal masses they do not): the frequencies
    # (measured <= 1.1e-4 relative: Clarabel's interior point accuracy on exact data)
    assert np.allclose(scipy.linalg.eigvalsh(learned.K, learned.M), scipy.linalg.eigvalsh(K, M),
                       rtol=1e-3)
    test = _run(M, K, C, B, _unseen, n=800)
    errors = {}
    for name, ops in (("learned", learned), ("identity", fixed)):
        rom = lo.LagrangianROM(K=ops.K, M=ops.M, C=ops.C, B=ops.B, scheme="newmark")
        pred = rom.simulate(np.zeros(4), np.zeros(4), 0.01, 800, inputs=_unseen)
        errors[name] = lo.relative_error(test.Qh, pred.Qh)
    print(errors)
    # measured: learned ~1e-6 (Clarabel's accuracy), identity ~0.3 (wrong model form)
    assert errors["learned"] < 1e-3, errors
    assert errors["identity"] > 100 * errors["learned"], errors


@pytest.mark.xfail(strict=True, reason="the problem is coordinate-invariant but Clarabel's "
                   "answer is not: frequencies 8 % apart after q = T q~ (measured); refining in "
                   "the mass coordinates fixes this but switches modes off elsewhere (mass.py)")
def test_learned_mass_does_not_depend_on_the_coordinates():
    """q = T q~: the fitted model in q~ is the same dynamics (frequencies, prediction)."""
    M, K, C, B = _system(1)
    train = _run(M, K, C, B, _load)
    T = np.linalg.qr(np.random.default_rng(5).standard_normal((4, 4)))[0] @ np.diag([1, 10, 0.1, 3.0])
    moved = lo.Trajectory(train.times, np.linalg.solve(T, train.Qh), np.linalg.solve(T, train.Vh), None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", lo.errors.IllConditionedDataWarning)
        a = _fit(train, _load, mass="learned")
        b = _fit(moved, _load, mass="learned")
    assert np.allclose(scipy.linalg.eigvalsh(a.K, a.M), scipy.linalg.eigvalsh(b.K, b.M), rtol=1e-3)


def test_learned_mass_bad_input_is_named():
    M, K, C, B = _system(2)
    train = _run(M, K, C, B, _load, n=300)
    with pytest.raises(lo.errors.InputError, match="mass must be"):
        _fit(train, _load, mass="lumped")
    t = 0.01 * np.arange(301)
    with pytest.raises(lo.errors.InputError, match="dQh"):
        lo.infer_mechanical(train.Qh, None, train.Qh, mass="learned")
    with pytest.raises(lo.errors.InputError, match="static"):
        lo.infer_mechanical(train.Qh, train.Qh, 0 * train.Qh, mass="learned")
    with pytest.raises(lo.errors.InputError, match="mass must be"):
        lo.fit(lo.Snapshots(t, train.Qh), 2, mass="diagonal")


def test_learned_mass_certificate_bounds_the_optimum():
    """The certificate's lower bound is a weak-duality bound: f - bound >= 0 always (a wrong
    sign or a missing term in _dual_bound breaks it), and on noisy data, where the optimum is
    an interior point the SDP solver reaches, it certifies the fit (measured 2e-9 .. 2e-8)."""
    M, K, C, B = _system(seed=1)
    train = _run(M, K, C, B, _load)
    noisy = np.random.default_rng(5).standard_normal(train.Qh.shape) * 1e-4 * np.abs(train.Qh).max()
    for Qh, certified in ((train.Qh, False), (train.Qh + noisy, True)):
        tr = types.SimpleNamespace(Qh=Qh)  # the _fit helper only reads .Qh
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", lo.errors.IllConditionedDataWarning)
            cert = _fit(tr, _load, mass="learned").certificate
        assert cert["gap"] >= -1e-12, cert
        assert cert["dual_infeasibility"] < 1e-10, cert
        if certified:
            assert cert["gap"] < 1e-6, cert
