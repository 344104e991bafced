"""Derived outputs: UFL expressions of the reconstructed field at points and as a field,
checked on fields whose expression is known in closed form."""

import numpy as np
import pytest

import dolfinx_lopinf as lo
from dolfinx_lopinf.errors import InputError

fem = pytest.importorskip("dolfinx_lopinf.fem._dolfinx")
dolfinx, ufl, MPI = fem.dolfinx, fem.ufl, fem.MPI

LAM, MU = 2.0, 0.5


def _sigma(w):
    eps = ufl.sym(ufl.grad(w))
    return LAM * ufl.tr(eps) * ufl.Identity(2) + 2 * MU * eps


def _von_mises(w):
    s = _sigma(w)
    dev = s - ufl.tr(s) / 3 * ufl.Identity(2)
    return ufl.sqrt(1.5 * ufl.inner(dev, dev))


def _affine(c):
    """u = (c0 x + c1 y, c2 x + c3 y): constant strain, stress in closed form."""
    def f(x):
        return np.vstack([c[0] * x[0] + c[1] * x[1], c[2] * x[0] + c[3] * x[1]])
    eps = np.array([[c[0], 0.5 * (c[1] + c[2])], [0.5 * (c[1] + c[2]), c[3]]])
    sig = LAM * np.trace(eps) * np.eye(2) + 2 * MU * eps
    dev = sig - np.trace(sig) / 3 * np.eye(2)
    return f, np.sqrt(1.5 * np.sum(dev * dev)), sig


@pytest.fixture(scope="module")
def recorded():
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 5, 4)
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 2, (2,)))
    u = dolfinx.fem.Function(V)
    rec = lo.SnapshotRecorder(u)
    rng = np.random.default_rng(0)
    coeffs = [rng.standard_normal(4) for k in range(3)]
    for k, c in enumerate(coeffs):
        u.interpolate(_affine(c)[0])
        rec.record(0.1 * k, u)
    return u, rec, rec.snapshots(), coeffs


def test_von_mises_at_points_from_states_and_reduced(recorded):
    u, rec, snaps, coeffs = recorded
    pts = [[0.33, 0.71], [0.9, 0.1], [0.5, 0.5]]
    probe = lo.fem.DerivedOutput(_von_mises(u), u, points=pts)
    got = probe.from_states(snaps.Q)
    want = np.array([_affine(c)[1] for c in coeffs])
    assert got.shape == (3, 3)
    np.testing.assert_allclose(got, np.tile(want, (3, 1)), rtol=1e-10)
    basis = lo.pod(snaps.Q, 3)
    np.testing.assert_allclose(probe.from_reduced(basis, basis.project(snaps.Q)), got, rtol=1e-9)
    # the stress tensor itself: (p, 2, 2, K)
    sig = lo.fem.DerivedOutput(_sigma(u), u, points=pts[:1]).from_states(snaps.Q)
    assert sig.shape == (1, 2, 2, 3)
    np.testing.assert_allclose(sig[0, :, :, 2], _affine(coeffs[2])[2], rtol=1e-10)
    # only the rows of the points' cells are reconstructed
    assert len(probe.rows()) < snaps.Q.shape[0] // 3


def test_von_mises_as_a_field(recorded):
    u, rec, snaps, coeffs = recorded
    W = dolfinx.fem.functionspace(u.function_space.mesh, ("DG", 0))
    field = lo.fem.DerivedOutput(_von_mises(u), u, space=W).from_states(snaps.Q)
    if MPI.COMM_WORLD.rank == 0:
        assert field.shape == (W.dofmap.index_map.size_global, 3)
        np.testing.assert_allclose(field[:, 1], _affine(coeffs[1])[1], rtol=1e-10)


def test_bad_arguments_are_named(recorded):
    u, rec, snaps, _ = recorded
    with pytest.raises(InputError, match="exactly one of points"):
        lo.fem.DerivedOutput(_von_mises(u), u)
    with pytest.raises(InputError, match="all of one length"):
        lo.fem.DerivedOutput(_von_mises(u), u, points=[[0.5, 0.5], [0.1, 0.2, 0.0]])
    with pytest.raises(InputError, match="outside the mesh"):
        lo.fem.DerivedOutput(_von_mises(u), u, points=[[2.0, 0.5]])
    with pytest.raises(InputError, match="must be the dolfinx Function"):
        lo.fem.DerivedOutput(_von_mises(u), snaps.Q, points=[[0.5, 0.5]])
    probe = lo.fem.DerivedOutput(_von_mises(u), u, points=[[0.5, 0.5]])
    with pytest.raises(InputError, match="rows"):
        probe.from_states(snaps.Q[:-1])
