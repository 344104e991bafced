"""The FOM-assembled Galerkin force of a hyperelastic energy and its ECSW hyper-reduction
(dolfinx_lopinf.fem.galerkin_nonlinear): exact against the scene's full-order force, the
Jacobian by finite differences, ECSW with all cells = the full force, the ROM loop, the same
numbers on 2 ranks, named input errors."""

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

from dolfinx_lopinf.core import polynomial as pl  # noqa: E402
from dolfinx_lopinf.errors import InputError  # noqa: E402
from dolfinx_lopinf.fem import galerkin_nonlinear as gn  # noqa: E402
from dolfinx_lopinf.scenes import svk_cantilever as scene  # noqa: E402


def _basis(cant, r=3, amp=0.02):
    n = len(cant.state_map.order)
    x = np.linspace(0.0, 1.0, n)
    V = np.column_stack([x * np.sin((a + 1) * 2.1 * x + a) for a in range(r)]) * amp
    V[cant.clamped_rows] = 0.0
    return V


@pytest.fixture(scope="module", params=["svk", "neo-hookean"])
def setup(request):
    cant = scene.build(request.param, (4, 1, 1))
    V = _basis(cant)
    return cant, V, gn.GalerkinForce(cant.energy_form, cant.system.q, V, cant.state_map)


def test_force_energy_and_jacobian_are_the_fom_ones(setup):
    cant, V, gf = setup
    q = np.array([0.6, -0.4, 0.3])
    f, J = gf.force_and_jacobian(q)
    f_fom = V.T @ cant.internal_force(V @ q)[:, 0]
    assert np.abs(f - f_fom).max() <= 1e-12 * np.abs(f_fom).max()
    assert abs(gf.value(q) - cant.potential(V @ q)[0]) <= 1e-12 * abs(gf.value(q))
    dq, h = np.array([0.3, 0.5, -0.2]), 1e-6
    Jfd = (gf.force(q + h * dq) - gf.force(q - h * dq)) / (2 * h)
    assert np.abs(J @ dq - Jfd).max() <= 1e-7 * np.abs(Jfd).max()
    assert np.allclose(J, J.T)
    np.testing.assert_allclose(gf.gradient(np.column_stack([q, -q]))[:, 0], f, rtol=1e-14)
    # the scene's Function is untouched (the force works on a private copy)
    assert not np.any(cant.system.q.x.array)


def test_ecsw_all_cells_is_the_full_force_and_fits_to_tol(setup):
    cant, V, gf = setup
    q = np.array([0.2, 0.5, -0.3])
    every = gn.CellSampling(np.arange(4), np.ones(4), 0.0, 4)
    ge = gn.GalerkinForce(cant.energy_form, cant.system.q, V, cant.state_map, sampling=every)
    f, J = gf.force_and_jacobian(q)
    fe, Je = ge.force_and_jacobian(q)
    assert np.abs(fe - f).max() <= 1e-13 * np.abs(f).max()
    assert np.abs(Je - J).max() <= 1e-13 * np.abs(J).max()
    Qh = 0.4 * np.random.default_rng(0).standard_normal((3, 10))
    for tol in (0.05, 1e-8):
        s = gn.ecsw_sampling(cant.energy_form, cant.system.q, V, cant.state_map, Qh, tol=tol)
        assert s.residual <= tol and s.n_cells == 4 and np.all(s.weights > 0)
        ge = gn.GalerkinForce(cant.energy_form, cant.system.q, V, cant.state_map, sampling=s)
        F = gf.gradient(Qh)
        assert np.linalg.norm(ge.gradient(Qh) - F) <= 1.0001 * tol * np.linalg.norm(F)
        assert ge.n_cells_used == len(s.cells)


def test_offset_state_and_cell_budget(setup):
    """u0 shifts the linearisation point (f_r(q; u0 = V a) = f_r(q + a)); max_cells caps ECSW."""
    cant, V, gf = setup
    a, q = np.array([0.2, -0.1, 0.3]), np.array([0.1, 0.3, -0.2])
    shifted = gn.GalerkinForce(cant.energy_form, cant.system.q, V, cant.state_map, u0=V @ a)
    f, J = shifted.force_and_jacobian(q)
    f0, J0 = gf.force_and_jacobian(q + a)
    assert np.abs(f - f0).max() <= 1e-12 * np.abs(f0).max()
    assert np.abs(J - J0).max() <= 1e-12 * np.abs(J0).max()
    Qh = 0.4 * np.random.default_rng(3).standard_normal((3, 10))
    s = gn.ecsw_sampling(cant.energy_form, cant.system.q, V, cant.state_map, Qh, tol=1e-12,
                         max_cells=2)
    assert len(s.cells) <= 2 and s.residual > 1e-12


def test_galerkin_rom_of_svk_equals_its_polynomial_tensors():
    """On SVK the genuine Galerkin ROM (FOM assembly per Newton iterate) and the polynomial
    ROM with the exact reduced tensors integrate the same equations."""
    cant = scene.build("svk", (4, 1, 1))
    V = _basis(cant)
    gf = gn.GalerkinForce(cant.energy_form, cant.system.q, V, cant.state_map)
    r = 3
    X = 0.5 * np.random.default_rng(1).standard_normal((r, 60))
    blocks = [pl.monomial_gradients(X, pl.monomials(r, d)) for d in (2, 3, 4)]
    A = np.concatenate(blocks, axis=1).transpose(0, 2, 1).reshape(r * X.shape[1], -1)
    theta = np.linalg.lstsq(A, gf.gradient(X).reshape(-1), rcond=None)[0]
    pot = pl.PolynomialPotential.from_coefficients(theta, r)
    assert np.abs(pot.gradient(X) - gf.gradient(X)).max() <= 1e-9 * np.abs(gf.gradient(X)).max()
    q0 = np.array([0.3, -0.2, 0.1])
    a = pl.PolynomialROM(gf).simulate(q0, np.zeros(r), 1e-3, 40, tol=1e-11)
    b = pl.PolynomialROM(pot).simulate(q0, np.zeros(r), 1e-3, 40, tol=1e-11, backend="numpy")
    assert a.stable and b.stable and a.backend == "numpy"
    assert np.abs(a.Qh - b.Qh).max() <= 1e-8 * np.abs(b.Qh).max()
    assert np.abs(a.info["energy"] - b.info["energy"]).max() <= 1e-8 * np.abs(b.info["energy"]).max()


def test_bad_inputs_are_named(setup):
    cant, V, gf = setup
    u, form, smap = cant.system.q, cant.energy_form, cant.state_map
    with pytest.raises(InputError, match="basis"):
        gn.GalerkinForce(form, u, V[:-1], smap)
    with pytest.raises(InputError, match="UFL form"):
        gn.GalerkinForce(3.0, u, V, smap)
    with pytest.raises(InputError, match="scalar form"):
        gn.GalerkinForce(cant.force_form, u, V, smap)
    with pytest.raises(InputError, match="u0"):
        gn.GalerkinForce(form, u, V, smap, u0=np.zeros(5))
    with pytest.raises(InputError, match="mesh of 7 cells"):
        gn.GalerkinForce(form, u, V, smap, sampling=gn.CellSampling(np.arange(2), np.ones(2), 0.0, 7))
    with pytest.raises(InputError, match="positive"):
        gn.CellSampling(np.arange(2), np.array([1.0, 0.0]), 0.0, 4)
    with pytest.raises(InputError, match="q must have"):
        gf.force(np.zeros(5))
    with pytest.raises(InputError, match="Qh"):
        gn.ecsw_sampling(form, u, V, smap, np.zeros((2, 4)))
    with pytest.raises(InputError, match="tol"):
        gn.ecsw_sampling(form, u, V, smap, np.ones((3, 4)), tol=-1.0)
    if cant.material == "svk":  # (neo-Hookean: rounding-level forces at u = 0, not exactly 0)
        with pytest.raises(InputError, match="zero"):
            gn.ecsw_sampling(form, u, V, smap, np.zeros((3, 4)))
    else:  # inverted elements
        with pytest.raises(InputError, match="not finite at training state 1"):
            gn.ecsw_sampling(form, u, V, smap, np.column_stack([np.ones(3), 80 * np.ones(3)]))


@pytest.mark.mpi
def test_two_ranks_equal_serial(serial_and_parallel):
    a, b = serial_and_parallel(Path(__file__).with_name("mpi_galerkin_nonlinear.py"))
    for key in a.files:
        if key.endswith(("cells",)):
            np.testing.assert_array_equal(a[key], b[key])
        else:
            scale = max(np.abs(a[key]).max(), 1e-300)
            assert np.abs(a[key] - b[key]).max() <= 1e-12 * scale, key
