"""The inner product a SnapshotRecorder records (Snapshots.weight): by default the L2 Gram
matrix of the recorded space in state coordinates (fem.state.state_gram), else a user's
bilinear form or assembled PETSc Mat, or none; checked at construction, built once at the
first snapshots() call. The 2-rank case is in test_mpi.py (mpi_recorder.py)."""

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

import scipy.sparse as sp  # noqa: E402

import dolfinx_lopinf as lo  # noqa: E402
from dolfinx_lopinf.errors import InputError  # noqa: E402
from dolfinx_lopinf.fem import state as state_module  # noqa: E402
from dolfinx_lopinf.fem._dolfinx import MPI, PETSc, dolfinx, ufl  # noqa: E402
from dolfinx_lopinf.fem.intrusive import dense_state_matrix  # noqa: E402
from dolfinx_lopinf.fem.state import StateMap, state_gram  # noqa: E402


def _space(kind):
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 4, 3)
    if kind == "vector P2":
        return dolfinx.fem.functionspace(msh, ("Lagrange", 2, (2,)))
    if kind == "scalar P1":
        return dolfinx.fem.functionspace(msh, ("Lagrange", 1))
    import basix.ufl

    cell = msh.basix_cell()
    return dolfinx.fem.functionspace(msh, basix.ufl.mixed_element(
        [basix.ufl.element("Lagrange", cell, 2, shape=(2,)), basix.ufl.element("Lagrange", cell, 1)]))


def _mass(V, rho=1.0):
    return rho * ufl.inner(ufl.TrialFunction(V), ufl.TestFunction(V)) * ufl.dx


def _recorded(u, steps=3, **kw):
    """Snapshots of ``steps`` random states of u (and the recorder)."""
    rec = lo.SnapshotRecorder(u, **kw)
    for k in range(steps):
        u.x.array[:] = np.random.default_rng(k).standard_normal(u.x.array.size)
        rec.record(0.1 * k, u)
    return rec.snapshots(), rec


def _close(W, D, rtol=1e-13):
    W = W.toarray() if sp.issparse(W) else W
    assert np.abs(W - D).max() <= rtol * np.abs(D).max(), np.abs(W - D).max() / np.abs(D).max()


@pytest.mark.parametrize("order", ["dofs", "coordinates"])
@pytest.mark.parametrize("kind", ["vector P2", "scalar P1"])
def test_default_weight_is_the_l2_gram_matrix_in_state_coordinates(kind, order):
    V = _space(kind)
    snaps, rec = _recorded(dolfinx.fem.Function(V), order=order)
    W = snaps.weight
    assert isinstance(W, sp.csr_array) and W.shape == (snaps.Q.shape[0],) * 2
    _close(W, dense_state_matrix(_mass(V), V, rec.state_map))
    assert (W != W.T).nnz == 0
    if kind == "vector P2":  # the components do not couple in inner(u, v): no stored zeros
        assert W.nnz < 0.6 * dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(_mass(V))).getInfo()["nz_used"]


def test_state_gram_applies_the_state_maps_scales():
    V = _space("scalar P1")
    base = StateMap.from_coordinates(V)
    sm = StateMap(base.order, np.linspace(0.5, 3.0, len(base.order)))
    _close(state_gram(V, sm), dense_state_matrix(_mass(V), V, sm))


def test_a_user_form_is_assembled_as_given():
    V = _space("vector P2")
    u = dolfinx.fem.Function(V)
    plain = _recorded(u)[0].weight
    snaps, rec = _recorded(u, weight=_mass(V, 2.5))
    _close(snaps.weight, 2.5 * plain.toarray())
    compiled = _recorded(u, weight=dolfinx.fem.form(_mass(V, 2.5)))[0].weight  # a dolfinx Form
    _close(compiled, 2.5 * plain.toarray())


def test_an_assembled_mat_with_dirichlet_rows_is_taken_as_it_is():
    V = _space("scalar P1")
    boundary = dolfinx.fem.locate_dofs_geometrical(V, lambda x: np.isclose(x[0], 0.0))
    bc = dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), boundary, V)
    M = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(_mass(V)), bcs=[bc])
    M.assemble()
    snaps, rec = _recorded(dolfinx.fem.Function(V), order="coordinates", weight=M)
    W = snaps.weight.toarray()
    D = dense_state_matrix(_mass(V), V, rec.state_map)
    rows = np.isin(rec.state_map.order, boundary)
    assert rows.sum() == 4
    np.testing.assert_array_equal(np.diag(W)[rows], 1.0)
    assert not W[rows][:, ~rows].any() and not W[~rows][:, rows].any()
    _close(W[~rows][:, ~rows], D[~rows][:, ~rows])
    # a matrix PETSc cannot hand out by rows (nest) is converted first
    N = dolfinx.fem.petsc.assemble_matrix([[dolfinx.fem.form(_mass(V))]], kind="nest")
    N.assemble()
    _close(state_gram(V, rec.state_map, N), D)
    for A in (M, N):
        A.destroy()


def test_no_weight():
    snaps, rec = _recorded(dolfinx.fem.Function(_space("scalar P1")), weight=None)
    assert snaps.weight is None and rec.weight is None


def test_the_weight_is_built_once_and_kept_with_blocks(monkeypatch, tmp_path):
    V = _space("scalar P1")
    calls = []
    original = state_module.state_gram

    def counting(*args):
        calls.append(1)
        return original(*args)

    monkeypatch.setattr("dolfinx_lopinf.fem.recorder.state_gram", counting)
    n = V.dofmap.index_map.size_global
    sm = StateMap(np.arange(n)[::-1].copy(), np.ones(n), {"a": np.arange(n // 2),
                                                           "b": np.arange(n // 2, n)})
    snaps, rec = _recorded(dolfinx.fem.Function(V), state_map=sm)
    again = rec.snapshots()
    assert len(calls) == 1 and sorted(snaps.blocks) == ["a", "b"]
    _close(again.weight, dense_state_matrix(_mass(V), V, sm))
    back = lo.Snapshots.load(snaps.save(tmp_path / "weighted"))
    assert abs(back.weight - snaps.weight).max() == 0


def test_a_mixed_space_gives_a_positive_definite_weight():
    V = _space("mixed (P2)^2 x P1")
    snaps, rec = _recorded(dolfinx.fem.Function(V))
    W = snaps.weight
    assert W.shape == (V.dofmap.index_map.size_global * V.dofmap.index_map_bs,) * 2
    assert np.linalg.eigvalsh(W.toarray()).min() > 0
    _close(W, dense_state_matrix(_mass(V), V, rec.state_map))


def _bad_weights():
    V = _space("scalar P1")
    other = dolfinx.fem.functionspace(V.mesh, ("Lagrange", 2))
    small = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(_mass(other)))
    small.assemble()
    unassembled = dolfinx.fem.petsc.create_matrix(dolfinx.fem.form(_mass(V)))
    return V, [
        ("h1", "got the string 'h1'"),
        (np.eye(20), "got ndarray"),
        (small, r"PETSc Mat of global size \(63, 63\); the space has 20 dofs"),
        (unassembled, "not assembled"),
        (PETSc.Mat(), "empty or destroyed PETSc Mat"),
        (ufl.TestFunction(V) * ufl.dx, "weight is a linear form"),
        (_mass(other), "bilinear form on another function space"),
        (ufl.inner(ufl.TrialFunction(other), ufl.TestFunction(V)) * ufl.dx, "another function space"),
    ], (small, unassembled)


def test_bad_weights_are_refused_at_construction():
    V, cases, mats = _bad_weights()
    u = dolfinx.fem.Function(V)
    for weight, match in cases:
        with pytest.raises(InputError, match=match) as info:
            lo.SnapshotRecorder(u, weight=weight)
        assert "weight" in str(info.value)
        if isinstance(weight, str) or isinstance(weight, np.ndarray):
            assert '"l2"' in str(info.value) and "UFL bilinear form" in str(info.value)
    with pytest.raises(InputError, match="weight"):
        state_gram(V, StateMap.identity(V), "h1")
    for A in mats:
        A.destroy()


def test_a_weight_that_is_no_inner_product_is_refused_when_assembled():
    """A form that passes the construction checks but assembles to no inner product - not
    symmetric, or a diagonal entry <= 0 - is an InputError at snapshots() (on every rank:
    the verdict is broadcast from the rank that gathered it), not silently symmetrised."""
    V = _space("vector P2")
    du, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    skew = (ufl.inner(du, v) + 0.3 * du[0] * v[1]) * ufl.dx
    with pytest.raises(InputError, match="weight is not symmetric"):
        _recorded(dolfinx.fem.Function(V), weight=skew)
    with pytest.raises(InputError, match="diagonal entry <= 0"):
        _recorded(dolfinx.fem.Function(V), weight=-_mass(V))
    # the package's own runs do not fail at their end over the optional weight
    with pytest.warns(lo.errors.LOpInfWarning, match="carry no inner product"):
        assert state_gram(V, StateMap.identity(V), -_mass(V), strict=False) is None
