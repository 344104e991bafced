"""Sine-Gordon: FOM against exact solutions, gray-box nonlinearity, wave ROM, hyper-reduction."""

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

import ufl  # noqa: E402

import dolfinx_lopinf as lo  # noqa: E402
from dolfinx_lopinf.core import hyper  # noqa: E402
from dolfinx_lopinf.fem import nonlinear
from dolfinx_lopinf.fem._dolfinx import MPI, dolfinx  # noqa: E402
from dolfinx_lopinf.scenes import sine_gordon as scene  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def _run(sg, q0, v0, dt, t_end, every=None):
    every = every or int(round(t_end / dt))
    snaps, info = lo.run(sg.system, q0, v0, dt, t_end, state_map=sg.state_map,
                         record_every=every, record_velocity=False, progress=False)
    return snaps, info


def test_kink_antikink_converges_at_second_order():
    errs = []
    for n, dt in ((400, 0.04), (800, 0.02)):
        sg = scene.build(n)
        snaps, _ = _run(sg, np.zeros_like(sg.x_local), 4 / np.cosh(sg.x_local), dt, 4.0)
        errs.append(np.abs(snaps.Q[:, -1] - scene.exact_kink_antikink(sg.x, 4.0)).max())
    rate = np.log2(errs[0] / errs[1])
    assert 1.8 < rate < 2.2, (errs, rate)


def test_breather_converges_at_second_order_with_bounded_energy():
    w = 0.5
    k = np.sqrt(1 - w**2)
    errs = []
    for n, dt in ((400, 0.04), (800, 0.02)):
        sg = scene.build(n)
        t_end = round(2 * np.pi / w / dt) * dt  # about one breather period
        snaps, info = _run(sg, np.zeros_like(sg.x_local), 4 * k / np.cosh(k * sg.x_local), dt,
                           t_end, every=10)
        errs.append(np.abs(snaps.Q[:, -1] - scene.exact_breather(sg.x, snaps.times[-1], w)).max())
        assert info["energy_drift"] < 1e-3
    rate = np.log2(errs[0] / errs[1])
    assert errs[1] < 5e-3 and 1.8 < rate < 2.2, (errs, rate)


def test_moving_kink_on_an_interval():
    v = 0.5
    sg = scene.build(801, periodic=False)
    x = sg.x_local
    q0 = scene.exact_kink(x, 0.0, v)
    s = x / np.sqrt(1 - v**2)
    v0 = -2 * v / np.sqrt(1 - v**2) / np.cosh(s)
    snaps, _ = _run(sg, q0, v0, 0.02, 4.0)
    assert np.abs(snaps.Q[:, -1] - scene.exact_kink(sg.x, 4.0, v)).max() < 5e-3


def test_nonlinearity_is_found_in_the_form():
    sg = scene.build(100)
    nl = nonlinear.identify(sg.system)
    z = np.linspace(-4, 4, 9)
    assert np.allclose(nl.g(z), np.sin(z)) and np.allclose(nl.dg(z), np.cos(z))
    # a consistent (non-lumped) mass makes f_nl non-pointwise: refused with the reason
    msh = dolfinx.mesh.create_interval(MPI.COMM_WORLD, 20, [0, 1])
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
    q, qt = dolfinx.fem.Function(V), dolfinx.fem.Function(V)
    L = (0.5 * qt**2 - 0.5 * q.dx(0) ** 2 - (1 - ufl.cos(q))) * ufl.dx
    with pytest.raises(ValueError, match="vertex quadrature"):
        nonlinear.identify(lo.LagrangianSystem(L, q, qt))


def test_wave_rom_conserves_energy_and_ecsw_keeps_structure():
    rng = np.random.default_rng(0)
    n, r = 300, 6
    V = np.linalg.qr(rng.standard_normal((n, r)))[0]
    A = rng.standard_normal((r, r))
    K = -(A @ A.T) - np.eye(r)
    rom = lo.core.WaveROM(K=K, V=V, g=np.sin, dg=np.cos, U=lambda z: 1 - np.cos(z))
    tr = rom.simulate(np.zeros(r), 2 * rng.standard_normal(r), 0.01, 3000)
    e = rom.energy(tr.Qh, tr.Vh)
    # symplectic midpoint on a non-quadratic L: small bounded oscillation, no drift
    err = np.abs(e - e[0]) / abs(e[0])
    assert err.max() < 1e-5
    assert err[1500:].max() < 2 * err[:1500].max()
    sample = hyper.ecsw(V, tr.Qh[:, ::30], np.sin, tol=1e-3)
    assert 0 < len(sample.rows) < n / 2 and np.all(sample.weights > 0) and sample.residual <= 1e-3
    hr = lo.core.WaveROM(K=K, V=V[sample.rows], g=np.sin, dg=np.cos, U=lambda z: 1 - np.cos(z),
                    weights=sample.weights)
    tr2 = hr.simulate(np.zeros(r), tr.Vh[:, 0], 0.01, 3000)
    e2 = hr.energy(tr2.Qh, tr2.Vh)
    err2 = np.abs(e2 - e2[0]) / abs(e2[0])  # still a Lagrangian ROM: same bounded behaviour
    assert err2.max() < 1e-5 and err2[1500:].max() < 2 * err2[:1500].max()
    assert lo.relative_error(tr.Qh[:, :500], tr2.Qh[:, :500]) < 5e-2


def test_sine_gordon_demo_quick(quick_demo):
    tmp_path, m = quick_demo("sine_gordon")
    assert m["scene"] == "sine_gordon" and m["fom_error_vs_exact"] < 5e-3
    best = min(r["test_error"] for r in m["roms"] if r["method"] == "lopinf")
    assert best < 2e-2
    for name in ("error_vs_r", "wave_shapes", "energy_error"):
        assert (tmp_path / f"{name}.png").stat().st_size > 10_000
