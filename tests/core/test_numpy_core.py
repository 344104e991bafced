"""The numpy core without DOLFINx: finite differences, POD, inference structure, ROM."""

import numpy as np
import pytest

import dolfinx_lopinf as lo
from dolfinx_lopinf.core import ddt


@pytest.mark.parametrize("which", ["first", "second"])
def test_eighth_order_differences_converge_at_order_eight(which):
    errs = []
    for dt in (0.1, 0.05):
        t = np.arange(0, 4 + dt / 2, dt)
        q = np.sin(3 * t)[None]
        if which == "first":
            d, exact = ddt.first_derivative(q, dt), 3 * np.cos(3 * t[4:-4])
        else:
            d, exact = ddt.second_derivative(q, dt), -9 * np.sin(3 * t[4:-4])
        errs.append(np.abs(d[0] - exact).max())
    order = np.log2(errs[0] / errs[1])
    assert 7.5 < order < 8.7, order


def test_derivatives_align_columns_and_reject_bad_grids():
    t = np.linspace(0, 1, 50)
    Q = np.vstack([t**2, t**3])
    Qh, dQh, ddQh = lo.core.derivatives(Q, t)
    assert Qh.shape == dQh.shape == ddQh.shape == (2, 42)
    assert np.allclose(Qh, Q[:, 4:-4])
    assert np.allclose(ddQh[0], 2.0) and np.allclose(ddQh[1], 6 * t[4:-4])
    with pytest.raises(ValueError, match="at least 9 time samples"):
        lo.core.derivatives(Q[:, :8], t[:8])
    with pytest.raises(ValueError, match="uniformly spaced"):
        lo.core.derivatives(Q, t**2)
    bad = Q.copy()
    bad[1, 7] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        lo.core.derivatives(bad, t)


def test_pod_projection_reconstruction_round_trip():
    rng = np.random.default_rng(0)
    n, k = 60, 40
    blocks = {"w": np.arange(30), "theta": np.arange(30, 60)}
    Q = rng.standard_normal((n, k))
    basis = lo.pod(Q, 10, blocks=blocks)
    V = basis.V
    assert np.allclose(V.T @ V, np.eye(10), atol=1e-12)
    assert np.all(V[30:, :5] == 0) and np.all(V[:30, 5:] == 0)  # block-diagonal
    inside = V @ rng.standard_normal((10, 7))  # states in the span round-trip exactly
    assert np.allclose(basis.reconstruct(basis.project(inside)), inside, atol=1e-12)
    rows = np.array([3, 17, 44])
    assert np.allclose(basis.reconstruct(basis.project(Q), rows=rows),
                       basis.reconstruct(basis.project(Q))[rows])
    plain = lo.pod(Q, 6)
    s = plain.singular_values["all"]
    assert plain.projection_error(Q) == pytest.approx(np.sqrt((s[6:] ** 2).sum() / (s**2).sum()))
    assert np.allclose(np.abs(lo.pod(Q, 8).truncate(6).V), np.abs(plain.V))


def test_weighted_pod_is_weight_orthonormal():
    rng = np.random.default_rng(1)
    A = rng.standard_normal((20, 20))
    W = A @ A.T + 20 * np.eye(20)
    basis = lo.pod(rng.standard_normal((20, 15)), 5, weight=W)
    assert np.allclose(basis.V.T @ W @ basis.V, np.eye(5), atol=1e-10)


def test_pod_errors():
    Q = np.outer(np.arange(10.0), np.ones(12))  # rank 1
    with pytest.raises(ValueError, match="numerical rank 1"):
        lo.pod(Q, 3)
    with pytest.raises(ValueError, match="multiple of the number of blocks"):
        lo.pod(np.random.default_rng(0).standard_normal((10, 12)), 3,
               blocks={"a": np.arange(5), "b": np.arange(5, 10)})


def _oscillator_data(K_true, n=2000, dt=2e-3, seed=0):
    rng = np.random.default_rng(seed)
    w2, P = np.linalg.eigh(K_true)
    w = np.sqrt(w2)
    t = dt * np.arange(n)
    a, b = rng.standard_normal(len(w)), rng.standard_normal(len(w))
    modal = a[:, None] * np.cos(np.outer(w, t)) + b[:, None] * np.sin(np.outer(w, t))
    return lo.core.derivatives(P @ modal, t)


def test_conservative_lopinf_recovers_spd_stiffness():
    rng = np.random.default_rng(3)
    A = rng.standard_normal((5, 5))
    K_true = A @ A.T + np.eye(5)
    Qh, _, ddQh = _oscillator_data(K_true)
    ops = lo.core.infer_mechanical(Qh, None, ddQh, damping=False)
    assert np.linalg.norm(ops.K - K_true) / np.linalg.norm(K_true) < 1e-6
    assert np.array_equal(ops.K, ops.K.T)
    assert ops.certificate["min_eig_K"] >= 1e-8


def test_standard_opinf_is_unconstrained():
    rng = np.random.default_rng(4)
    Qh = rng.standard_normal((3, 400))
    K_ns = np.array([[2.0, 1.0, 0.0], [-1.0, 1.0, 0.5], [0.0, 0.3, -0.5]])  # neither sym nor PD
    ddQh = -K_ns @ Qh
    op = lo.core.infer_opinf(Qh, None, ddQh, damping=False)
    assert np.allclose(op.K, K_ns, atol=1e-10)
    lop = lo.core.infer_mechanical(Qh, None, ddQh, damping=False)
    assert np.array_equal(lop.K, lop.K.T) and lop.certificate["min_eig_K"] >= 1e-8
    assert lop.certificate["objective"] >= op.certificate["objective"]


def test_rom_conserves_its_energy_and_is_second_order():
    K = np.diag([1.0, 9.0])
    M = np.array([[2.0, 0.3], [0.3, 1.0]])
    rom = lo.core.LagrangianROM(K=K, M=M)
    tr = rom.simulate(np.array([1.0, -0.5]), np.array([0.2, 0.0]), 0.01, 10_000)
    e = rom.energy(tr.Qh, tr.Vh)
    assert np.abs(e - e[0]).max() / e[0] < 1e-12
    exact = lambda t: np.cos(np.sqrt(2.0) * t)  # noqa: E731  q'' = -2 q for K=2, M=1
    one = lo.core.LagrangianROM(K=[[2.0]])
    errs = [abs(one.simulate([1.0], [0.0], dt, int(round(3 / dt))).Qh[0, -1] - exact(3.0))
            for dt in (0.02, 0.01)]
    assert 3.6 < errs[0] / errs[1] < 4.4


def test_snapshots_window_save_load(tmp_path):
    t = np.linspace(0, 1, 11)
    Q = np.vstack([t, t**2])
    s = lo.Snapshots(times=t, Q=Q, blocks={"a": [0], "b": [1]}, U=t[None])
    w = s.window(0.2, 0.5)
    assert np.allclose(w.times, t[2:6]) and w.Q.shape == (2, 4) and w.U.shape == (1, 4)
    loaded = lo.Snapshots.load(s.save(tmp_path / "s.npz"))
    assert np.array_equal(loaded.Q, Q) and np.array_equal(loaded.blocks["b"], [1])
    with pytest.raises(ValueError, match="non-finite"):
        lo.Snapshots(times=t, Q=np.where(Q > 0.5, np.nan, Q))
    with pytest.raises(ValueError, match="outside"):
        lo.Snapshots(times=t, Q=Q, blocks={"a": [5]})


def test_metrics():
    assert lo.relative_error(np.ones(4), np.zeros(4)) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="shapes differ"):
        lo.relative_error(np.ones(4), np.ones(3))
    assert not lo.core.metrics.is_stable(np.array([[np.nan]]), np.array([0.0]))
    assert not lo.core.metrics.is_stable(np.zeros((1, 2)), np.array([0.0, 1.5]))
    assert lo.core.metrics.is_stable(np.zeros((1, 2)), np.array([0.0, 0.5]))


def test_choose_r_picks_the_smallest_sufficient_dimension():
    rng = np.random.default_rng(7)
    n, r_true = 40, 6
    P = np.linalg.qr(rng.standard_normal((n, r_true)))[0]
    w = np.array([1.0, 1.7, 2.3, 3.1, 4.4, 5.2])
    t = np.arange(0, 6, 0.01)
    amps = np.array([1.0, 0.3, 0.1, 0.03, 0.01, 0.003])
    phase = rng.uniform(0, 6, r_true)
    Q = P @ (amps[:, None] * np.cos(np.outer(w, t) + phase[:, None]))
    V0 = P @ (-amps * w * np.sin(phase))
    loose = lo.core.choose_r(Q, t, [1, 2, 3, 4, 5, 6], 0.1, V0=V0)
    tight = lo.core.choose_r(Q, t, [1, 2, 3, 4, 5, 6], 1e-3, V0=V0)
    assert loose.r is not None and tight.r is not None and loose.r < tight.r
    assert [s["r"] for s in tight.scores] == list(range(1, tight.r + 1))  # stops at the first hit
    assert all(s["met"] == (s["holdout_error"] <= 1e-3) for s in tight.scores)
    assert lo.core.choose_r(Q, t, [1], 1e-12, V0=V0).r is None
    with pytest.raises(ValueError, match="holdout"):
        lo.core.choose_r(Q, t, [2], 0.1, holdout=1.5)


def test_variational_data_recover_the_midpoint_operator_exactly():
    """On a midpoint-VI trajectory with stiff modes (dt omega ~ 0.5), fitting the discrete
    Euler-Lagrange relation recovers K to rounding; 8th-order differences cannot."""
    K = np.diag([1.0, 400.0, 2500.0])
    rom = lo.core.LagrangianROM(K=K)
    dt = 0.01
    tr = rom.simulate(np.array([1.0, 0.5, 0.2]), np.array([0.0, 1.0, -2.0]), dt, 3000)
    Qbar, D2 = lo.core.ddt.variational_data(tr.Qh, tr.times)
    exact = lo.core.infer_mechanical(Qbar, None, D2, damping=False).K
    Qh, _, ddQh = lo.core.derivatives(tr.Qh, tr.times)
    fd = lo.core.infer_mechanical(Qh, None, ddQh, damping=False).K
    assert np.linalg.norm(exact - K) / np.linalg.norm(K) < 1e-8
    assert np.linalg.norm(fd - K) / np.linalg.norm(K) > 1e-3


def test_newmark_data_recover_the_discrete_operators_exactly():
    """On a Newmark trajectory of a forced, damped system whose time step does not resolve the
    fastest mode (dt omega_max = 2), the three-point Newmark data give back K, C, B to round-off
    and finite differences do not."""
    from dolfinx_lopinf.core import LagrangianROM, derivatives, infer_mechanical
    from dolfinx_lopinf.core.ddt import newmark_data

    rng = np.random.default_rng(3)
    r, dt = 4, 1e-3
    w = np.array([30.0, 150.0, 700.0, 2000.0])
    Qo = np.linalg.qr(rng.standard_normal((r, r)))[0]
    K = Qo @ np.diag(w**2) @ Qo.T
    C = 1e-4 * np.eye(r) + 2e-4 * K
    B = rng.standard_normal((r, 1))
    u = lambda t: np.array([np.where(t < 0.1, 0.0, 5000.0) + 800 * np.sin(37 * t)])  # noqa: E731
    tr = LagrangianROM(K=K, C=C, B=B, scheme="newmark").simulate(np.zeros(r), np.zeros(r), dt, 600, inputs=u)
    U = np.column_stack([u(t) for t in tr.times])
    Qbar, D1, D2, Ubar = newmark_data(tr.Qh, tr.times, U)
    ops = infer_mechanical(Qbar, D1, D2, Ubar)
    for fit, true in ((ops.K, K), (ops.C, C), (ops.B, B)):
        assert np.abs(fit - true).max() < 1e-6 * np.abs(true).max()
    Qh, dQh, ddQh = derivatives(tr.Qh, tr.times)
    fd = infer_mechanical(Qh, dQh, ddQh, U[:, 4:-4])
    assert np.abs(fd.K - K).max() > 1e-2 * np.abs(K).max()  # the bias the Newmark data remove
    with pytest.raises(ValueError, match="columns"):
        newmark_data(tr.Qh, tr.times, U[:, :-1])


def test_leading_svd_matches_the_full_svd_to_the_datas_rounding():
    """basis.leading_svd (lo.fit's SVD on large data): singular values exact to ~1e-16 s_1,
    the leading vectors as close to the full thin SVD's as that SVD is to itself on the data
    perturbed by 2e-16; bit-for-bit the same on a second call (seeded start)."""
    from dolfinx_lopinf.core.basis import leading_svd

    rng = np.random.default_rng(11)
    n, K, k = 700, 500, 40
    U0 = np.linalg.qr(rng.standard_normal((n, K)))[0]
    W0 = np.linalg.qr(rng.standard_normal((K, K)))[0]
    s0 = 10.0 ** (-0.6 * np.arange(K))  # a POD-like decay to far below rounding
    Q = (U0 * s0) @ W0.T
    U, s, _ = np.linalg.svd(Q, full_matrices=False)
    Ul, sl = leading_svd(Q, k)
    assert Ul.shape == (n, k) and sl.shape == (k,)
    # absolute error at rounding (observed 3e-15 s_1; lo.fit's rank thresholds are 1e-12 and
    # 1e-10 of s_1), relative error of the ones well above it
    assert np.abs(sl - s[:k]).max() <= 1e-13 * s[0]
    big = s[:k] > 5e-7 * s[0]  # between the decay's values 1e-6 and 2.5e-7: no value on the edge
    assert np.abs(sl[big] / s[:k][big] - 1).max() <= 1e-10
    Up = np.linalg.svd(Q * (1 + 2e-16 * rng.standard_normal(Q.shape)), full_matrices=False)[0]

    def angle(A, B, r):
        c = np.linalg.svd(A[:, :r].T @ B[:, :r], compute_uv=False)
        return float(np.sqrt(max(0.0, 1.0 - c.min() ** 2)))

    for r in (4, 8, 12):  # gaps of 4x: the SVD itself moves these by ~1e-15 / s_r
        assert angle(U, Ul, r) <= max(10 * angle(U, Up, r), 1e-12), (r, angle(U, Ul, r), angle(U, Up, r))
    again = leading_svd(Q, k)
    assert np.array_equal(again[0], Ul) and np.array_equal(again[1], sl)
