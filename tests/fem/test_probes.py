"""Black-box probes (dolfinx_lopinf.fem.probes) on the SVK cantilever: the Richardson
accelerations equal the Galerkin ones V^T(-f(Vq) - C V v + b u) of the FOM (to 1e-5; one
step alone is far off), a polynomial L-OpInf fit of them is the Galerkin reduced force,
and bad input is named; 2 ranks give the serial accelerations."""

from pathlib import Path

import numpy as np
import pytest

import dolfinx_lopinf as lo
from dolfinx_lopinf.core import polynomial as pl
from dolfinx_lopinf.errors import InputError
from dolfinx_lopinf.fem import probes
from dolfinx_lopinf.fem.intrusive import dense_state_matrix
from dolfinx_lopinf.scenes import svk_cantilever as scene


@pytest.fixture(scope="module")
def setup():
    cant = scene.build("svk", (4, 1, 1))
    cant.amplitude.value = 250.0
    snaps, _ = lo.run(cant.system, *cant.initial_state(), scene.DT, 0.4,
                      output_matrix=cant.output_matrix, state_map=cant.state_map,
                      progress=False, record_velocity=False, energy_every=0)
    M = dense_state_matrix(cant.system.mass_form, cant.V, cant.state_map)
    basis = lo.pod(snaps.Q, 3, weight=M)
    Qh = basis.project(snaps.Q)
    return cant, M, basis.V, Qh, np.gradient(Qh, scene.DT, axis=1)


def _galerkin(cant, V, Q, Vel, U):
    """The Galerkin acceleration, with V^T K0 V by central differences (exact for its
    quadratic part)."""
    eps = 1e-6
    K0V = np.column_stack([(cant.internal_force(eps * V[:, [j]]) - cant.internal_force(-eps * V[:, [j]]))[:, 0]
                           / (2 * eps) for j in range(V.shape[1])])
    alpha, beta = scene.RAYLEIGH
    Ch = alpha * np.eye(V.shape[1]) + beta * 0.5 * (V.T @ K0V + K0V.T @ V)
    return -(V.T @ cant.internal_force(V @ Q) + Ch @ Vel) + (V.T @ cant.load_vector())[:, None] * U


def test_probe_accelerations_are_the_galerkin_ones(setup):
    cant, M, V, Qh, Vh = setup
    rng = np.random.default_rng(0)
    Q, Vel, U = probes.probe_points(Qh, Vh, 6, rng=rng, inputs_range=(0, 250))
    pd = probes.probe(cant.system, V, cant.state_map, Q, Vel, U, set_input=cant.set_probe_input,
                      step_size=4e-6)
    exact = _galerkin(cant, V, Q, Vel, U)
    err = np.linalg.norm(pd.A - exact, axis=0) / np.linalg.norm(exact, axis=0)
    assert err.max() < 1e-5, err
    assert pd.error_estimate.max() < 1e-5  # the estimate agrees that the data are good
    # one step alone is far off (the Richardson extrapolation is what makes it exact)
    one = probes.probe(cant.system, V, cant.state_map, Q, Vel, U, set_input=cant.set_probe_input,
                       step_size=4e-6, levels=2, step_tol=None)
    err2 = np.linalg.norm(one.A - exact, axis=0) / np.linalg.norm(exact, axis=0)
    assert err.max() < err2.max()
    assert pd.summary()["samples"] == Q.shape[1]
    assert pd.fom_steps == 5 * (Q.shape[1] + len(pd.step_search) * min(6, Q.shape[1]))
    assert pd.step_search[0][0] == 4e-6 and pd.step_search[0][1] <= 1e-6  # no refinement needed


def test_the_step_search_refines_a_too_large_step(setup):
    """From h = 1e-4 (estimate ~1e-2 on this mesh) the search divides h by 4 until the
    estimate meets 1e-6, and the data are then as accurate as from a good h."""
    cant, M, V, Qh, Vh = setup
    rng = np.random.default_rng(3)
    Q, Vel, U = probes.probe_points(Qh, Vh, 3, rng=rng, inputs_range=(0, 250))
    pd = probes.probe(cant.system, V, cant.state_map, Q, Vel, U, set_input=cant.set_probe_input,
                      step_size=1e-4)
    hs = [h for h, _ in pd.step_search]
    assert hs[0] == 1e-4 and len(hs) > 1 and pd.step_size < 1e-4 and pd.step_search[-1][1] <= 1e-6
    exact = _galerkin(cant, V, Q, Vel, U)
    assert (np.linalg.norm(pd.A - exact, axis=0) / np.linalg.norm(exact, axis=0)).max() < 1e-5


def test_fit_of_probe_data_is_the_galerkin_reduced_force(setup):
    cant, M, V, Qh, Vh = setup
    rng = np.random.default_rng(1)
    r = V.shape[1]
    n = int(2 * pl.n_unknowns(r, 1)["total"] / r) + 10
    Q, Vel, U = probes.probe_points(Qh, Vh, n, rng=rng, inputs_range=(0, 250))
    pd = probes.probe(cant.system, V, cant.state_map, Q, Vel, U, set_input=cant.set_probe_input,
                      step_size=4e-6)
    ops = pl.fit_polynomial(pd.data(), constraint="none")
    Qt = 1.2 * Qh[:, rng.integers(0, Qh.shape[1], 20)]  # unseen states, beyond the samples' scale
    F = V.T @ cant.internal_force(V @ Qt)
    assert np.linalg.norm(ops.potential.gradient(Qt) - F) / np.linalg.norm(F) < 1e-6
    assert np.linalg.norm(ops.B[:, 0] - V.T @ cant.load_vector()) / np.linalg.norm(ops.B) < 1e-6
    assert np.linalg.eigvalsh(ops.C).min() > 0


def test_probe_names_bad_input(setup):
    cant, M, V, Qh, Vh = setup
    Q, Vel = Qh[:, :2], Vh[:, :2]
    args = (cant.system, V, cant.state_map)
    with pytest.raises(InputError, match="M-orthonormal"):
        probes.probe(cant.system, 2 * V, cant.state_map, Q, Vel, step_size=1e-6)
    with pytest.raises(InputError, match="set_input"):
        probes.probe(*args, Q, Vel, np.ones((1, 2)), step_size=1e-6)
    with pytest.raises(InputError, match="levels"):
        probes.probe(*args, Q, Vel, step_size=1e-6, levels=1)
    with pytest.raises(InputError, match="step_size"):
        probes.probe(*args, Q, Vel, step_size=0.0)
    with pytest.raises(InputError, match="must both be"):
        probes.probe(*args, Q, Vel[:, :1], step_size=1e-6)
    with pytest.raises(InputError, match="black_box"):
        probes.probe("fom", V, cant.state_map, Q, Vel, step_size=1e-6)
    with pytest.raises(InputError, match="scale_max"):
        probes.probe_points(Qh, Vh, 3, rng=np.random.default_rng(0), scale_max=0.5)


@pytest.mark.mpi
def test_two_ranks_equal_serial(serial_and_parallel):
    a, b = serial_and_parallel(Path(__file__).with_name("mpi_probes.py"))
    assert np.abs(a["G"] - b["G"]).max() <= 1e-12 * np.abs(a["G"]).max()
    # the accelerations come out of a nonlinear solve per step: equal well below their own
    # accuracy (~1e-7; measured 4e-10 apart)
    assert np.abs(a["A"] - b["A"]).max() <= 1e-7 * np.abs(a["A"]).max(), np.abs(a["A"] - b["A"]).max()


def test_a_callable_black_box_is_checked(setup):
    cant, M, V, Qh, Vh = setup
    with pytest.raises(InputError, match="mass_matrix"):
        probes.probe(lambda h: object(), V, cant.state_map, Qh[:, :2], Vh[:, :2], step_size=1e-6)
    # a MidpointIntegrator factory works like the system itself
    Q, Vel = Qh[:, :2], Vh[:, :2]
    a = probes.probe(lambda h: lo.fem.MidpointIntegrator(cant.system, h), V, cant.state_map, Q, Vel,
                     step_size=4e-6, levels=3)
    b = probes.probe(cant.system, V, cant.state_map, Q, Vel, step_size=4e-6, levels=3)
    assert np.abs(a.A - b.A).max() <= 1e-12 * np.abs(b.A).max()
