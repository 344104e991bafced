"""Fishtail scene: geometry, two materials, chamber pressure inputs, Newmark FOM, rigid-body
modes for GAMG, and the quick demo end to end."""

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

from dolfinx_lopinf.fem._dolfinx import MPI  # noqa: E402
from dolfinx_lopinf.fem.newmark import NewmarkIntegrator  # noqa: E402
from dolfinx_lopinf.scenes import fishtail as ft  # noqa: E402


@pytest.fixture(scope="module")
def small():
    return ft.build(0.012)


def _tip_history(f, nm, u, steps=40):
    """Newmark through the one time loop, with an output and an energy probe."""
    from dolfinx_lopinf.fem.fom import run

    from dolfinx_lopinf.fem.loop import EnergyProbe, OutputProbe

    nm.initialize(f.chamber_pressures(0.0))
    y, e = OutputProbe(f.output_matrix), EnergyProbe()
    run(nm, steps, sinks=[y, e], inputs=lambda t: f.chamber_pressures(u))
    return np.array(y.values)[1:, 0], np.array(e.values[1:])


def test_geometry_tags_and_materials(small):
    tags = small.cell_tags
    assert len(tags.find(1)) > 0 and len(tags.find(2)) > 0  # hull and beam cells
    for tag in (11, 12, 20):
        n = MPI.COMM_WORLD.allreduce(len(small.facet_tags.find(tag)))
        assert n > 0, tag
    assert small.system.is_quadratic


def test_chamber_pressure_bends_the_tail_antisymmetrically(small):
    """Mirror-symmetric geometry: swapping the chamber pressures (u -> -u) mirrors the
    lateral tip displacement (up to the asymmetry of the unstructured mesh)."""
    nm = NewmarkIntegrator(small.system, ft.DT, rayleigh=ft.RAYLEIGH, input_forms=small.input_forms,
                           prefix="ft_test_")
    y_plus, e_plus = _tip_history(small, nm, 5000.0)
    y_minus, _ = _tip_history(small, nm, -5000.0)
    assert np.all(np.isfinite(y_plus)) and np.abs(y_plus).max() > 1e-5
    assert np.abs(y_plus + y_minus).max() < 0.05 * np.abs(y_plus).max()
    assert e_plus[-1] > 0


def test_fishtail_demo_quick(quick_demo):
    tmp_path, m = quick_demo("fishtail")
    lop = [r for r in m["roms"] if r["method"] == "lopinf"]
    assert all(r["min_eig_K"] > 0 and r["min_eig_C"] > 0 and r["stable"] for r in lop)
    by_r = {r["r"]: r["output_errors"] for r in lop}
    assert by_r[2]["sine"] < 1e-2  # the paper's level on the training input (measured 4e-4)
    assert by_r[4]["step"] < 5e-2  # unseen step input
    assert m["data"] == "newmark" and m["hull_density"] == ft.HULL_DENSITIES["paper"]
    assert m["snapshot_disk_bytes"] == 2 * 401 * 8 * m["n_dofs"]  # training states + M q on disk
    assert (tmp_path / "poi_step.png").stat().st_size > 10_000


def test_rigid_body_modes_span_the_kernel_of_free_elasticity():
    from dolfinx_lopinf.fem._dolfinx import dolfinx, ufl
    import dolfinx.fem.petsc
    from dolfinx_lopinf.fem.newmark import rigid_body_modes

    msh = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [1, 0.5, 0.3]], [4, 3, 2])
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 2, (3,)))
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    eps = lambda w: ufl.sym(ufl.grad(w))  # noqa: E731
    K = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(
        ufl.inner(2 * eps(u) + ufl.tr(eps(u)) * ufl.Identity(3), eps(v)) * ufl.dx))
    K.assemble()
    ns = rigid_body_modes(V)
    vecs = ns.getVecs()
    assert len(vecs) == 6
    y = K.createVecLeft()
    for i, a in enumerate(vecs):
        assert abs(a.norm() - 1) < 1e-12
        K.mult(a, y)
        assert y.norm() < 1e-10 * K.norm()
        for b in vecs[:i]:
            assert abs(a.dot(b)) < 1e-12
    assert ns.test(K)


def test_hull_density_is_checked():
    with pytest.raises(ValueError, match="hull_density"):
        ft.build(0.012, hull_density="water")
    with pytest.raises(ValueError, match="positive"):
        ft.build(0.012, hull_density=-1.0)


def test_newmark_initial_acceleration_is_consistent(small):
    """initialize(u0) with a non-zero input solves M a0 = B u0 (CG on the mass matrix)."""
    nm = NewmarkIntegrator(small.system, ft.DT, rayleigh=ft.RAYLEIGH, input_forms=small.input_forms,
                           prefix="ft_init_")
    u0 = small.chamber_pressures(5000.0)
    nm.initialize(u0)
    rhs = nm._load(u0, nm.M.createVecLeft()).copy()
    Ma = nm.M.createVecLeft()
    nm.M.mult(nm.a.x.petsc_vec, Ma)
    Ma.axpy(-1.0, rhs)
    assert rhs.norm() > 0 and Ma.norm() < 1e-10 * rhs.norm()



@pytest.mark.parametrize("every", ["0", "-5", "601"])
def test_demo_refuses_an_energy_stride_outside_the_run_before_building(every, capsys):
    """--energy-every N must be in 1..steps (the quick run has 600); 0 must not fall back
    to the default silently, and the refusal comes before the mesh is built."""
    from conftest import load_demo

    with pytest.raises(SystemExit):
        load_demo("fishtail").main(["--quick", "--energy-every", every])
    assert "--energy-every must be in 1..600" in capsys.readouterr().err
