"""The opinf peer baseline (dolfinx_lopinf.studies.peers): on a known linear oscillator hidden in a
random orthonormal basis it recovers the system - the eigenvalues of its first-order operator
and the trajectory beyond the training window - to measured tolerances, with and without
recorded velocities and with an input; bad arguments are refused by name; without opinf the
error says how to install it."""

import sys

import numpy as np
import pytest
import scipy.integrate
import scipy.linalg

from dolfinx_lopinf.errors import InputError

N, OMEGA, ZETA = 60, np.array([1.0, 2.3, 3.7]), 0.02
DT, T_TRAIN, T_END = 0.01, 8.0, 16.0


def _modal_matrices(damped):
    """First-order modal system z = [eta; eta_t]: z_t = A z + b u."""
    m = len(OMEGA)
    C = np.diag(2 * ZETA * OMEGA) if damped else np.zeros((m, m))
    A = np.block([[np.zeros((m, m)), np.eye(m)], [-np.diag(OMEGA**2), -C]])
    b = np.concatenate([np.zeros(m), [1.0, -0.5, 0.25]])
    return A, b


def _load(t):
    return np.sin(1.3 * t) + 0.5 * np.cos(0.4 * t)


def _oscillator(damped=True, forced=False):
    """(times, Q, V, U, Phi, A): three modes q = Phi eta in R^60 (Phi orthonormal, seeded)."""
    rng = np.random.default_rng(7)
    Phi = np.linalg.qr(rng.standard_normal((N, len(OMEGA))))[0]
    A, b = _modal_matrices(damped)
    z0 = np.array([1.0, -0.6, 0.3, 0.0, 0.8, -0.4])
    times = np.arange(int(round(T_END / DT)) + 1) * DT
    rhs = (lambda t, z: A @ z + b * _load(t)) if forced else (lambda t, z: A @ z)
    Z = scipy.integrate.solve_ivp(rhs, (0, T_END), z0, t_eval=times, method="DOP853",
                                  rtol=1e-12, atol=1e-14).y
    m = len(OMEGA)
    U = _load(times)[None, :] if forced else None
    return times, Phi @ Z[:m], Phi @ Z[m:], U, Phi, A


def _rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(a)


def _eig_error(A_peer, A_true):
    # distinct imaginary parts +-omega: sort by them (real parts are ~0 and rounding-ordered)
    ev, ev_true = (sorted(np.linalg.eigvals(a), key=lambda z: z.imag) for a in (A_peer, A_true))
    ev, ev_true = np.array(ev), np.array(ev_true)
    return np.max(np.abs(ev - ev_true)) / np.max(np.abs(ev_true))


@pytest.fixture(scope="module")
def peers():
    pytest.importorskip("opinf")
    from dolfinx_lopinf.studies import peers as module

    return module


@pytest.mark.parametrize("damped", [True, False])
def test_recovers_free_oscillator(peers, damped):
    times, Q, V, _, _, A = _oscillator(damped)
    k = int(round(T_TRAIN / DT)) + 1
    peer = peers.opinf_first_order(Q[:, :k], times[:k], 3, velocities=V[:, :k])
    assert peer.operators == "A" and peer.A.shape == (6, 6) and peer.velocity_source == "recorded"
    # measured (opinf ord6 differences at dt = 0.01): eigenvalue error 1.7e-11, state and
    # velocity error on the window after training (as long again) 1e-10 .. 4e-10
    assert _eig_error(peer.A, A) < 1e-8
    pred = peer.predict(Q[:, 0], V[:, 0], times)
    assert pred.finite and pred.Q.shape == Q.shape and pred.V.shape == V.shape
    assert _rel(Q[:, k:], pred.Q[:, k:]) < 1e-7
    assert _rel(V[:, k:], pred.V[:, k:]) < 1e-7


def test_estimates_velocities_and_uses_a_given_basis(peers):
    times, Q, V, _, Phi, A = _oscillator(damped=False)
    k = int(round(T_TRAIN / DT)) + 1
    peer = peers.opinf_first_order(Q[:, :k], times[:k], 3)  # no velocities: opinf's ord6 of q
    assert peer.velocity_source.startswith("opinf ord6")
    assert _eig_error(peer.A, A) < 1e-8  # measured 9e-11
    assert _rel(Q[:, k:], peer.predict(Q[:, 0], V[:, 0], times).Q[:, k:]) < 1e-7  # 1e-9
    # the modes span the data: the peer's basis holds the states to rounding
    assert peer.projection_error(Q, V) < 1e-10 and peer.projection_error(Q, times=times) < 1e-10
    given = peers.opinf_first_order(Q[:, :k], times[:k], 3, velocities=V[:, :k], basis=Phi)
    assert given.basis_kind == "given"
    assert _eig_error(given.A, A) < 1e-8
    # energy of the reconstruction with M = I, K = Phi diag(omega^2) Phi^T: conserved (1e-11)
    Kfull = Phi @ np.diag(OMEGA**2) @ Phi.T
    long = given.predict(Q[:, 0], V[:, 0], times, full=False)
    E = given.energy(long.Xh, np.eye(N), Kfull)
    assert np.max(np.abs(E - E[0])) / E[0] < 1e-8
    blocks = peers.opinf_first_order(Q[:, :k], times[:k], [2, 3], velocities=V[:, :k], basis="blocks")
    assert [p.r for p in blocks] == [2, 3] and blocks[1].basis_kind == "blocks"
    assert _eig_error(blocks[1].A, A) < 1e-8
    fast = peers.opinf_first_order(Q[:, :k], times[:k], 3, velocities=V[:, :k], svdsolver="randomized")
    assert _eig_error(fast.A, A) < 1e-8


def test_recovers_forced_oscillator_and_outputs(peers):
    times, Q, V, U, Phi, A = _oscillator(damped=True, forced=True)
    k = int(round(T_TRAIN / DT)) + 1
    E = np.zeros((1, N))
    E[0, 5] = 1.0
    peer = peers.opinf_first_order(Q[:, :k], times[:k], 3, velocities=V[:, :k], inputs=U[:, :k],
                                   output_matrix=E)
    assert peer.operators == "AB" and peer.B.shape == (6, 1)
    assert _eig_error(peer.A, A) < 1e-8  # measured 1.7e-11
    for inputs in (_load, U):  # a callable or the sampled inputs at the output times
        pred = peer.predict(Q[:, 0], V[:, 0], times, inputs)
        # measured 1.3e-5: the input is taken linear between the samples (dt = 0.01)
        assert _rel(Q[:, k:], pred.Q[:, k:]) < 1e-4
        assert _rel(E @ Q, pred.Y) < 1e-4
    bdf = peers.opinf_first_order(Q[:, :k], times[:k], 3, velocities=V[:, :k], inputs=_load,
                                  integrator="BDF", candidates=[1e-10, 1e-8])
    assert bdf.integrator == "BDF"
    # solve_ivp's BDF at its default rtol 1e-3: measured 4.7e-4
    assert _rel(Q[:, :k], bdf.predict(Q[:, 0], V[:, 0], times[:k], _load).Q) < 5e-3


def test_bad_input(peers):
    times, Q, V, U, _, _ = _oscillator(damped=True, forced=True)
    Qk, tk, Vk = Q[:, :200], times[:200], V[:, :200]
    fit = peers.opinf_first_order
    bad = Qk.copy()
    bad[3, 7] = np.nan
    cases = [
        (lambda: fit(bad, tk, 3), "Q"),
        (lambda: fit(Qk, tk[:-1], 3), "times has 199 entries"),
        (lambda: fit(Qk, tk[::-1], 3), "strictly increasing"),
        (lambda: fit(Qk, np.r_[tk[:-1], tk[-1] + 0.5], 3), "uniform"),
        (lambda: fit(Qk, tk, 3, velocities=Vk[:, :-1]), "velocities has shape"),
        (lambda: fit(Qk, tk, 0), "positive integer"),
        (lambda: fit(Qk, tk, 2.5), "positive integer"),
        (lambda: fit(Qk, tk, 61, basis="blocks"), "per variable"),
        (lambda: fit(Qk, tk, 3, basis="pod"), "basis must be one of"),
        (lambda: fit(Qk, tk, 4, basis=np.eye(N)[:, :3]), "given basis has 3 columns"),
        (lambda: fit(Qk, tk, 3, inputs=U[:, :150]), "inputs has shape"),
        (lambda: fit(Qk, tk, 3, output_matrix=np.ones((1, 5))), "output_matrix"),
        (lambda: fit(Qk, tk, 3, integrator="RK45"), "integrator"),
        (lambda: fit(Qk, tk, 3, svdsolver="eigh"), "svdsolver"),
        (lambda: fit(Qk[:, :5], tk[:5], 1), "at least 7"),
    ]
    for call, match in cases:
        with pytest.raises(InputError, match=match):
            call()
    peer = fit(Qk, tk, 3, velocities=Vk)
    with pytest.raises(InputError, match="q0 has shape"):
        peer.predict(Qk[:5, 0], Vk[:, 0], tk)
    with pytest.raises(InputError, match="fitted without inputs"):
        peer.predict(Qk[:, 0], Vk[:, 0], tk, _load)
    forced = fit(Qk, tk, 3, velocities=Vk, inputs=U[:, :200])
    with pytest.raises(InputError, match="pass inputs"):
        forced.predict(Qk[:, 0], Vk[:, 0], tk)
    with pytest.raises(InputError, match=r"inputs has shape \(1, 10\)"):
        forced.predict(Qk[:, 0], Vk[:, 0], tk, U[:, :10])


def test_missing_opinf_says_how_to_install(monkeypatch):
    from dolfinx_lopinf.studies import peers as module

    monkeypatch.setitem(sys.modules, "opinf", None)  # import opinf -> ImportError
    assert not module.have_opinf()
    with pytest.raises(ImportError, match=r"pip install 'dolfinx_lopinf\[peers\]'"):
        module.opinf_first_order(np.ones((4, 10)), np.arange(10.0), 1)


def test_opinf_peer_imports_after_dolfinx_fem_petsc():
    """numba + the DOLFINx wheel load libpetsc (and its HDF5) globally; the opinf peer must
    still import (and h5py read and write) when the script imported dolfinx.fem.petsc first.
    It failed with h5py's 'Not a datatype' before the peer bound h5py to its own HDF5."""
    import importlib.util
    import subprocess
    import sys

    if not all(importlib.util.find_spec(m) for m in ("h5py", "dolfinx", "opinf")):
        pytest.skip("needs h5py, dolfinx and opinf")
    code = ("import dolfinx_solver, dolfinx, dolfinx.fem.petsc, numpy as np, sys\n"
            "from dolfinx_lopinf.studies import peers\n"
            "assert peers.have_opinf()\n"
            "import h5py\n"
            "p = sys.argv[1]\n"
            "with h5py.File(p, 'w') as f: f['a'] = np.arange(3.0)\n"
            "with h5py.File(p, 'r') as f: assert list(f['a'][:]) == [0.0, 1.0, 2.0]\n")
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        proc = subprocess.run([sys.executable, "-c", code, f"{d}/t.h5"], capture_output=True,
                              text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
