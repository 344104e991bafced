"""The FOM layer: UFL Lagrangian -> forms -> midpoint VI, checked against physics."""

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

import scipy.sparse
import scipy.sparse.linalg
import ufl

import dolfinx_lopinf as lo
from dolfinx_lopinf.fem._dolfinx import MPI, PETSc, dolfinx
from dolfinx_lopinf.fem.state import output_matrix_in_state
from dolfinx_lopinf.fem.intrusive import dense_state_matrix
from dolfinx_lopinf.scenes import beam as scene


def _csr(form, bcs=()):
    A = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(form), bcs=list(bcs))
    A.assemble()
    indptr, indices, values = A.getValuesCSR()
    return scipy.sparse.csr_matrix((values, indices, indptr), shape=A.getSize())


def test_beam_frequencies_match_analytic(beam):
    """First four eigenfrequencies of the UFL-derived M, K vs (k pi / l)^2 sqrt(EI / mu)."""
    M, K = _csr(beam.system.mass_form), _csr(beam.system.stiffness_form)
    fixed = beam.system.bcs[0].dof_indices()[0]
    free = np.setdiff1d(np.arange(M.shape[0]), fixed)
    Mf, Kf = M[free][:, free], K[free][:, free]
    # shift-invert about 0 resolves the small eigenvalues to full relative precision
    lam = np.sort(scipy.sparse.linalg.eigsh(Kf.tocsc(), k=4, M=Mf.tocsc(), sigma=0.0)[0])
    omega = np.sqrt(lam)
    exact = scene.analytic_frequencies(np.arange(1, 5))
    assert np.max(np.abs(omega / exact - 1)) < 1e-6, omega / exact - 1


def test_mass_and_stiffness_are_symmetric_positive(beam):
    M, K = _csr(beam.system.mass_form).toarray(), _csr(beam.system.stiffness_form).toarray()
    assert np.abs(M - M.T).max() <= 1e-14 * np.abs(M).max()
    assert np.abs(K - K.T).max() <= 1e-14 * np.abs(K).max()
    assert np.linalg.eigvalsh(M).min() > 0
    assert beam.system.is_quadratic


def test_hermite_dofs_mean_value_and_scaled_slope(beam):
    """Interpolating a cubic through (w, J w') reproduces it exactly, and the state map
    turns the derivative dofs into the physical slope theta = w'."""
    V = beam.system.V
    w = dolfinx.fem.Function(V)
    cubic = lambda x: 0.3 - x + 2 * x**2 - 1.5 * x**3  # noqa: E731
    dcubic = lambda x: -1 + 4 * x - 4.5 * x**2  # noqa: E731
    w.x.array[beam.value_dofs] = cubic(beam.x_local)
    w.x.array[beam.slope_dofs] = beam.jacobian * dcubic(beam.x_local)
    pts = np.array([[0.123, 0, 0], [0.5, 0, 0], [0.987, 0, 0]])
    E = dolfinx_lopinf_point_matrix(V, pts)
    assert np.allclose(E @ w.x.array, cubic(pts[:, 0]), atol=1e-13)
    from dolfinx_lopinf.fem.state import gather_states

    state = gather_states(V, w.x.array[: V.dofmap.index_map.size_local][:, None], beam.state_map)
    n = len(beam.x_nodes)
    assert np.allclose(state[:n, 0], cubic(beam.x_nodes), atol=1e-14)
    assert np.allclose(state[n:, 0], dcubic(beam.x_nodes), atol=1e-12)


def dolfinx_lopinf_point_matrix(V, pts):
    return lo.point_output_matrix(V, pts)


def test_nonuniform_hermite_mesh_is_rejected():
    import basix.ufl

    from dolfinx_lopinf.scenes.beam import _hermite_nodes

    msh = dolfinx.mesh.create_interval(MPI.COMM_SELF, 10, [0.0, 1.0])
    x = msh.geometry.x
    x[:, 0] = x[:, 0] ** 1.5  # graded mesh
    V = dolfinx.fem.functionspace(msh, basix.ufl.element(basix.ElementFamily.Hermite, "interval", 3))
    with pytest.raises(ValueError, match="uniform mesh"):
        _hermite_nodes(V)


def test_energy_is_conserved_by_the_midpoint_integrator(beam):
    q0, v0 = beam.initial_state()
    snaps, info = lo.run(beam.system, q0, v0, scene.DT, 0.05, state_map=beam.state_map,
                         record_every=50, progress=False)
    assert info["steps"] == 5000
    assert info["energy_drift"] < 1e-10
    # and the UFL energy at t=0 is the analytic strain energy of the initial shape:
    # 1/2 EI int (w0'')^2 = 1/2 EI 1e-6 * 144 / 30
    assert snaps.energy[0] == pytest.approx(0.5 * scene.EI * 1e-6 * 144 / 30, rel=1e-6)
    # the snapshots carry the system's mass (Hermite scales included) as their inner product
    M = dense_state_matrix(beam.system.mass_form, beam.system.V, beam.state_map)
    assert np.abs(snaps.weight.toarray() - M).max() <= 1e-13 * np.abs(M).max()


def test_black_box_advance_equals_step_and_keeps_state(beam):
    it = lo.fem.MidpointIntegrator(beam.system, scene.DT, prefix="bb_test_")
    q0, v0 = beam.initial_state()
    it.initialize(q0, v0)
    for _ in range(3):
        it.step()
    q_before, p_before = it.q.x.array.copy(), it.p.array.copy()
    q1, p1 = it.advance(it.q.x.array.copy(), it.p)
    assert np.array_equal(it.q.x.array, q_before) and np.array_equal(it.p.array, p_before)
    it.step()
    assert np.allclose(q1, it.q.x.array, rtol=0, atol=1e-18)
    assert np.allclose(p1.array, it.p.array, rtol=0, atol=1e-18)


def test_galerkin_rom_equals_dense_projection(beam):
    rng = np.random.default_rng(1)
    n = len(beam.state_map.order)
    V = np.linalg.qr(rng.standard_normal((n, 6)))[0]
    rom = lo.fem.galerkin_rom(beam.system, V, beam.state_map)
    M = dense_state_matrix(beam.system.mass_form, beam.system.V, beam.state_map)
    K = dense_state_matrix(beam.system.stiffness_form, beam.system.V, beam.state_map)
    assert np.allclose(rom.M, V.T @ M @ V, rtol=1e-12, atol=0)
    assert np.allclose(rom.K, V.T @ K @ V, rtol=1e-10, atol=1e-12 * np.abs(rom.K).max())


def test_midpoint_output_functional(beam):
    E = output_matrix_in_state(beam.system.V, beam.output_matrix, beam.state_map)
    n = len(beam.x_nodes)
    # A state that is the Hermite interpolant of sin(pi x): y = w(0.5) ~ 1
    x = beam.x_nodes
    state = np.concatenate([np.sin(np.pi * x), np.pi * np.cos(np.pi * x)])
    assert E.shape == (1, 2 * n)
    assert E @ state == pytest.approx(1.0, abs=1e-8)


# -- the Lagrangian layer's input checks -----------------------------------------------------

@pytest.fixture(scope="module")
def p1_space():
    msh = dolfinx.mesh.create_interval(MPI.COMM_WORLD, 16, [0.0, 1.0])
    return dolfinx.fem.functionspace(msh, ("Lagrange", 1))


def test_lagrangian_must_be_a_scalar_form(p1_space):
    q, qt = dolfinx.fem.Function(p1_space), dolfinx.fem.Function(p1_space)
    v = ufl.TestFunction(p1_space)
    with pytest.raises(ValueError, match="scalar form"):
        lo.LagrangianSystem(qt * v * ufl.dx, q, qt)
    with pytest.raises(TypeError, match="UFL Form"):
        lo.LagrangianSystem(0.5 * qt**2, q, qt)
    with pytest.raises(ValueError, match="does not depend on q_t"):
        lo.LagrangianSystem(-0.5 * q.dx(0) ** 2 * ufl.dx, q, qt)
    with pytest.raises(NotImplementedError, match="mass"):
        lo.LagrangianSystem((0.5 * (1 + q**2) * qt**2 - 0.5 * q**2) * ufl.dx, q, qt)
    with pytest.raises(TypeError, match="dolfinx.fem.Function"):
        lo.LagrangianSystem((0.5 * qt**2) * ufl.dx, q.x.array, qt)


def _sine_gordon(space):
    q, qt = dolfinx.fem.Function(space), dolfinx.fem.Function(space)
    dxv = ufl.dx(metadata={"quadrature_rule": "vertex", "quadrature_degree": 1})
    L = 0.5 * qt**2 * dxv - 0.5 * q.dx(0) ** 2 * ufl.dx - (1 - ufl.cos(q)) * dxv
    return lo.LagrangianSystem(L, q, qt)


def test_nonlinear_lagrangian_uses_newton_and_conserves_energy():
    msh = dolfinx.mesh.create_interval(MPI.COMM_WORLD, 200, [-20.0, 20.0])
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
    system = _sine_gordon(V)
    assert not system.is_quadratic
    x = V.tabulate_dof_coordinates()[:, 0]
    v0 = 4.0 / np.cosh(x)
    _, info = lo.run(system, np.zeros_like(x), v0, 0.02, 4.0, record_every=10, progress=False,
                     record_velocity=False)
    assert info["energy_drift"] < 1e-3  # symplectic: bounded oscillation, no secular drift


def test_newton_failure_names_step_and_residual():
    msh = dolfinx.mesh.create_interval(MPI.COMM_WORLD, 50, [-20.0, 20.0])
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
    system = _sine_gordon(V)
    x = V.tabulate_dof_coordinates()[:, 0]
    it = lo.fem.MidpointIntegrator(system, 0.5, prefix="fail_test_",
                               petsc_options={"snes_max_it": 1, "snes_rtol": 1e-14,
                                              "snes_atol": 1e-14})
    it.initialize(np.zeros_like(x), 4.0 / np.cosh(x))
    with pytest.raises(lo.errors.StepFailedError, match=r"step 1 .*residual norm"):
        it.step()


def test_bad_initial_state_is_rejected(beam):
    it = lo.fem.MidpointIntegrator(beam.system, scene.DT, prefix="bad_init_")
    q0, v0 = beam.initial_state()
    with pytest.raises(ValueError, match="local dofs"):
        it.initialize(q0[:-1], v0)
    q0[3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        it.initialize(q0, v0)
    with pytest.raises(ValueError, match="whole number of steps"):
        lo.run(beam.system, v0, v0, scene.DT, 1.00000123e-3)


def test_reprojection_matches_projected_trajectory_for_a_full_basis(beam):
    """With a (nearly) complete M-orthonormal basis, stepping the black-box FOM from lifted
    reduced states reproduces the projected FOM trajectory."""
    from dolfinx_lopinf.studies.reprojection import reprojected_trajectory

    q0, v0 = beam.initial_state()
    snaps, _ = lo.run(beam.system, q0, v0, scene.DT, 2e-4, state_map=beam.state_map, progress=False)
    M = dense_state_matrix(beam.system.mass_form, beam.system.V, beam.state_map)
    L = np.linalg.cholesky(M)
    V_full = np.linalg.inv(L.T)  # V^T M V = I, all n directions
    it = lo.fem.MidpointIntegrator(beam.system, scene.DT, prefix="reproj_test_")
    Qh = reprojected_trajectory(it, V_full, M, beam.state_map, snaps.Q[:, 0], snaps.V[:, 0], 20)
    ref = V_full.T @ M @ snaps.Q
    assert np.abs(Qh - ref).max() <= 1e-8 * np.abs(ref).max()


def _option_names(prefix):
    return [k for k in PETSc.Options().getAll() if k.startswith(prefix)]


def test_integrators_share_one_protocol_and_leave_no_petsc_options(beam):
    """Midpoint (linear and Newton) and Newmark are Integrators; each gets its own options
    prefix; the options are gone from the global database once read; close() destroys."""
    from dolfinx_lopinf.fem.integrators import Integrator

    from dolfinx_lopinf.fem.newmark import NewmarkIntegrator

    msh = dolfinx.mesh.create_interval(MPI.COMM_WORLD, 50, [-20.0, 20.0])
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
    x = V.tabulate_dof_coordinates()[:, 0]
    with lo.fem.MidpointIntegrator(beam.system, scene.DT, petsc_options={"mat_mumps_icntl_14": 40}) as lin, \
            lo.fem.MidpointIntegrator(_sine_gordon(V), 0.1, petsc_options={"snes_max_it": 30}) as newton, \
            NewmarkIntegrator(beam.system, scene.DT, petsc_options={"ksp_error_if_not_converged": True}) as nm:
        prefixes = {lin.prefix, newton.prefix, nm.prefix}
        assert len(prefixes) == 3 and all(p.startswith("lopinf_") for p in prefixes)
        assert [i.scheme for i in (lin, newton, nm)] == ["midpoint", "midpoint", "newmark"]
        for it in (lin, newton, nm):
            assert isinstance(it, Integrator)
        assert not _option_names(lin.prefix) and not _option_names(nm.prefix)
        assert _option_names(newton.prefix)  # SNES: kept until its first step has read them
        newton.initialize(np.zeros_like(x), 4.0 / np.cosh(x))
        assert newton.step() is newton.q
        assert not _option_names(newton.prefix)
        nm.initialize()
        assert nm.step() is nm.q and nm.energy() == 0.0
    assert lin._ksp is None and newton._snes is None and nm.M is None


def test_one_loop_drives_both_schemes_with_sinks(beam):
    """fom.run(integrator, n, sinks=...) is the loop run(system, ...) uses: the same states,
    outputs and energies; it drives Newmark too."""
    from dolfinx_lopinf.fem.fom import run
    from dolfinx_lopinf.fem.loop import EnergyProbe, FieldSnapshots, OutputProbe
    from dolfinx_lopinf.fem.newmark import NewmarkIntegrator

    q0, v0 = beam.initial_state()
    snaps, info = lo.run(beam.system, q0, v0, scene.DT, 20 * scene.DT, output_matrix=beam.output_matrix,
                         state_map=beam.state_map, progress=False)
    with lo.fem.MidpointIntegrator(beam.system, scene.DT) as it:
        it.initialize(q0, v0)
        y, e, fields = OutputProbe(beam.output_matrix), EnergyProbe(every=5), FieldSnapshots([0, 20])
        calls = []
        out = run(it, 20, sinks=[y, e, fields, lambda s: calls.append(s.k)])
        assert out["steps"] == 20 and calls == list(range(21))
        assert np.array_equal(np.array(y.values).T, snaps.Y)
        assert np.array_equal(e.values, info["energy"][::5])
        assert set(fields.fields) == {0, 20}
    with NewmarkIntegrator(beam.system, scene.DT) as nm:
        nm.initialize()
        e = EnergyProbe()
        run(nm, 3, sinks=[e])
        assert e.values == [0.0] * 4  # from rest, no input: stays at rest
    with pytest.raises(ValueError, match="Integrator"):
        run(object(), 3)


def test_snapshot_recorder_is_a_sink_of_the_loop(beam):
    """SnapshotRecorder.sink(): the same states and velocities as run(system, ...), and the
    integrator's scheme."""
    from dolfinx_lopinf.fem.fom import run

    q0, v0 = beam.initial_state()
    snaps, _ = lo.run(beam.system, q0, v0, scene.DT, 10 * scene.DT, record_every=2,
                      state_map=beam.state_map, progress=False)
    rec = lo.SnapshotRecorder(beam.system.V, state_map=beam.state_map)
    with lo.fem.MidpointIntegrator(beam.system, scene.DT) as it:
        it.initialize(q0, v0)
        run(it, 10, sinks=[rec.sink(every=2, velocity=True)])
    got = rec.snapshots()
    if got is not None:  # rank 0
        assert got.scheme == "midpoint" and np.array_equal(got.Q, snaps.Q)
        assert np.array_equal(got.V, snaps.V) and np.allclose(got.times, snaps.times, rtol=1e-12)


def test_run_snapshots_name_their_scheme_and_row_order():
    """lo.run's snapshots carry the integrator's scheme ("midpoint": lo.fit fits that relation
    instead of identifying one) and info["state_map"] gives their row order (by dof
    coordinates) to write_vtx / states_to_function, whose default is the recorder's dof
    order - without it a new user's field came back scrambled (up to 1.4 on a 1.5 field)."""
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 8, 8)
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
    q, qt = dolfinx.fem.Function(V), dolfinx.fem.Function(V)
    L = (0.5 * qt**2 - 0.5 * ufl.inner(ufl.grad(q), ufl.grad(q))) * ufl.dx
    facets = dolfinx.mesh.locate_entities_boundary(msh, 1, lambda x: np.full(x.shape[1], True))
    bc = dolfinx.fem.dirichletbc(0.0, dolfinx.fem.locate_dofs_topological(V, 1, facets), V)
    system = lo.LagrangianSystem(L, q, qt, bcs=[bc])
    q0 = dolfinx.fem.Function(V)
    q0.interpolate(lambda x: np.sin(np.pi * x[0]) * np.sin(np.pi * x[1]) * (1 + x[0]))
    snaps, info = lo.run(system, q0, dolfinx.fem.Function(V), 0.01, 0.05, progress=False)
    back = lo.fem.vtx.states_to_function(V, snaps.Q[:, 0] if snaps is not None else None,
                                         state_map=info["state_map"])
    n_owned = V.dofmap.index_map.size_local
    assert np.abs(back.x.array[:n_owned] - q0.x.array[:n_owned]).max() < 1e-14
    if snaps is not None:
        assert snaps.scheme == "midpoint"
