"""The affine structure read from UFL, the parametric FOM, and their bad inputs.

* the split of each scene reproduces its assembled forms at random parameters to rounding,
  and names the terms expected (K = 1 K[1] + mu K[mu]; K = E K[E], C = zeta C[zeta] +
  E zeta C[E*zeta]);
* a parameter inside a tanh is named non-affine (or leaves the system without a structure);
* with the complete mass-orthonormal basis (r = n) the intrusive parametric ROM steps the
  FOM's Newmark scheme to rounding at an unseen mu, and parametric L-OpInf fitted on FOM
  data gives the projected terms back: the FOM, the split, the projection and the fit agree.
"""

import warnings

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

import dolfinx_lopinf as lo  # noqa: E402
from dolfinx_lopinf.core.basis import Basis  # noqa: E402
from dolfinx_lopinf.errors import InputError, InputTypeError, NonAffineParameterError  # noqa: E402
from dolfinx_lopinf.fem import param_fom  # noqa: E402
from dolfinx_lopinf.fem._dolfinx import MPI, PETSc, dolfinx, ufl  # noqa: E402
from dolfinx_lopinf.fem.affine import ParametricSystem, split_form  # noqa: E402
from dolfinx_lopinf.scenes import membrane2d, param_cantilever  # noqa: E402


@pytest.fixture(scope="module")
def membrane():
    return membrane2d.build(6)


@pytest.fixture(scope="module")
def cantilever():
    return param_cantilever.build((4, 1, 1))


def test_membrane_split_reproduces_the_forms(membrane):
    s = membrane.psys.structure
    assert s.stiffness == ((), ("mu",)) and s.mass == ((),) and s.damping == () and s.inputs == ((),)
    worst = membrane.psys.check_split(mus=[[0.3], [2.7], [11.0]])
    assert set(worst) == {"mass", "stiffness", "inputs"}
    assert max(worst.values()) < 1e-13, worst


def test_cantilever_split_reproduces_the_forms(cantilever):
    s = cantilever.psys.structure
    assert s.stiffness == (("E",),) and s.damping == (("zeta",), ("E", "zeta"))
    assert s.cone == "E >= 0 and zeta >= 0"
    worst = cantilever.psys.check_split(mus=[[0.7e4, 1.3], [2.1e4, 0.4]])
    assert max(worst.values()) < 1e-13, worst
    assert "C(mu) = zeta * C[zeta] + E*zeta * C[E*zeta]" in cantilever.psys.describe()


def test_a_wrong_split_would_be_caught(membrane):
    """check_split measures: scale one term and the check reports it (the test can fail)."""
    psys = membrane.psys
    saved = psys.term_forms["stiffness"][1]
    try:
        psys.term_forms["stiffness"][1] = 1.01 * saved
        assert psys.check_split(mus=[[2.0]])["stiffness"] > 1e-4
    finally:
        psys.term_forms["stiffness"][1] = saved


def test_non_affine_parameter_is_named():
    scene = membrane2d.build(4, study="radius")
    assert scene.psys.structure is None
    assert scene.psys.nonaffine["parameter"] == "R"
    assert "non-affinely" in scene.psys.describe()
    with pytest.raises(NonAffineParameterError, match="'R' enters the stiffness non-affinely"):
        membrane2d.build(4, study="radius", affine=True)
    # the FOM still runs at any R
    snap, _ = param_fom.simulate(scene.psys, 0.15, 0.01, 5, inputs=membrane2d.test_load)
    assert snap.Q.shape[1] == 6


def _tiny():
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 3, 3)
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
    q, q_t = dolfinx.fem.Function(V), dolfinx.fem.Function(V)
    c = dolfinx.fem.Constant(msh, PETSc.ScalarType(1.0))
    return msh, V, q, q_t, c


def test_bad_parameters_are_named():
    msh, V, q, q_t, c = _tiny()
    L = (0.5 * q_t**2 - 0.5 * c * ufl.inner(ufl.grad(q), ufl.grad(q))) * ufl.dx
    f = dolfinx.fem.Function(V)
    with pytest.raises(InputTypeError, match="parameter 'k' is a Function, not a dolfinx.fem.Constant"):
        ParametricSystem(L, q, q_t, {"k": f})
    other = dolfinx.fem.Constant(msh, PETSc.ScalarType(2.0))
    with pytest.raises(InputError, match=r"\['nu'\] are not Constants of the forms"):
        ParametricSystem(L, q, q_t, {"c": c, "nu": other})
    vec = dolfinx.fem.Constant(msh, np.array([1.0, 2.0]))
    with pytest.raises(InputError, match="scalar Constant"):
        ParametricSystem(L, q, q_t, {"v": vec})
    psys = ParametricSystem(L, q, q_t, {"c": c})
    with pytest.raises(InputError, match="has 2 value"):
        psys.set([1.0, 2.0])
    sq = (0.5 * q_t**2 - 0.5 * c * c * ufl.inner(ufl.grad(q), ufl.grad(q))) * ufl.dx
    with pytest.raises(NonAffineParameterError, match="'c'"):
        ParametricSystem(sq, q, q_t, {"c": c}, affine=True)


def test_split_form_multi_affine_terms():
    msh, V, q, q_t, c = _tiny()
    d = dolfinx.fem.Constant(msh, PETSc.ScalarType(3.0))
    v = ufl.TestFunction(V)
    form = (2.0 + c + c * d) * v * ufl.dx
    terms = dict(split_form(form, {"c": c, "d": d}))
    assert set(terms) == {(), ("c",), ("c", "d")}
    with pytest.raises(NonAffineParameterError):
        split_form(ufl.exp(c) * v * ufl.dx, {"c": c}, "inputs")


def test_fom_rejects_schemes_outside_the_newmark_family(membrane):
    with pytest.raises(InputError, match="generalised-alpha family"):
        param_fom.simulate(membrane.psys, 1.0, 0.01, 3, scheme="midpoint")
    with pytest.raises(InputError, match="1 finite value"):
        param_fom.simulate(membrane.psys, 1.0, 0.01, 3, inputs=lambda t: [1.0, 2.0])


def test_fom_warns_at_a_parameter_outside_the_cone(membrane):
    """The reduced model refuses a mu outside its certified cone; the full model ran there (a
    negative Young's modulus) with no word. It now runs with a ParameterRangeWarning naming
    the term and its coefficient."""
    import warnings

    from dolfinx_lopinf.errors import ParameterRangeWarning

    with pytest.warns(ParameterRangeWarning, match=r"outside the cone.*stiffness term mu has coefficient -0.5"):
        param_fom.simulate(membrane.psys, -0.5, 0.01, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ParameterRangeWarning)
        param_fom.simulate(membrane.psys, 1.0, 0.01, 2)


def _complete_basis(psys):
    """Every free dof, orthonormal in the mass: V^T M V = I, r = n - (boundary dofs)."""
    W = psys.mass_matrix()
    n = W.shape[0]
    free = np.ones(n, dtype=bool)
    bdofs = psys.bcs[0].dof_indices()[0]
    dofs = psys.state_map.order
    free[np.isin(dofs, bdofs)] = False
    E = np.eye(n)[:, free]
    L = np.linalg.cholesky(E.T @ W @ E)
    V = E @ np.linalg.inv(L).T
    return Basis(V, {}, {"all": (np.arange(n), np.arange(V.shape[1]))}, W)


@pytest.mark.parametrize("scheme", ["newmark", lo.schemes.GeneralizedAlpha(rho_inf=0.8)])
def test_intrusive_at_r_n_steps_the_fom(membrane, scheme):
    psys = membrane.psys
    basis = _complete_basis(psys)
    mu, dt, n = 2.3, 0.02, 60
    snap, _ = param_fom.simulate(psys, mu, dt, n, inputs=membrane2d.test_load, scheme=scheme)
    model = psys.intrusive(basis, scheme, dt, mu_train=[[1.0], [3.0]])
    traj = model.predict(mu, n, inputs=membrane2d.test_load)  # loads where the scheme applies them
    err = np.abs(basis.V @ traj.Qh - snap.Q).max() / np.abs(snap.Q).max()
    assert err < 1e-10, err
    # the recorded energy is the mechanical energy of the states (Galerkin = exact at r = n)
    rom = model.rom(mu)
    assert np.allclose(rom.energy(traj.Qh, traj.Vh), snap.energy, rtol=1e-9,
                       atol=1e-12 * snap.energy.max())


@pytest.mark.parametrize("scheme", ["newmark", lo.schemes.GeneralizedAlpha(rho_inf=0.8)])
def test_lopinf_at_r_n_gives_the_projected_terms_back(membrane, scheme):
    """The data relation of the FOM's own scheme (Newmark's three-point, generalised-alpha's
    four-point with its loads at t_{n+1-alpha_f}) holds exactly: the fit is the projection."""
    psys = membrane.psys
    basis = _complete_basis(psys)
    dt, n = 0.02, 120
    data = [(mu, param_fom.simulate(psys, mu, dt, n, inputs=u, scheme=scheme)[0])
            for mu in (0.5, 2.0, 3.5) for u in membrane2d.train_loads()]
    assert data[0][1].scheme == scheme
    M0 = psys.mass_matrix()  # the snapshots carry the parameter-free mass as inner product
    assert np.abs(data[0][1].weight.toarray() - M0).max() <= 1e-13 * np.abs(M0).max()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", lo.errors.IllConditionedDataWarning)
        model = lo.parametric.fit_affine(data, psys.structure, basis=basis, damping="structure")
    assert model.scheme == scheme
    ref = psys.intrusive(basis, scheme, dt)
    for op in ("stiffness", "inputs"):
        for A, B in zip(model.terms[op], ref.terms[op]):
            assert np.abs(A - B).max() <= 1e-5 * np.abs(B).max(), op
    assert model.report["certificate"]["converged"]


@pytest.mark.mpi
def test_parametric_fom_two_ranks_equals_serial(serial_and_parallel):
    from pathlib import Path

    a, b = serial_and_parallel(Path(__file__).with_name("mpi_param_fom.py"))
    for key in ("Q", "E", "U", "K", "B"):
        assert np.abs(a[key] - b[key]).max() <= 1e-10 * np.abs(a[key]).max(), key
    assert a["split"] < 1e-13 and b["split"] < 1e-13
