"""The snapshots' inner product (``Snapshots.weight``): the weighted POD without an n x n
factorisation, its leading-mode variant, storage, and ``lo.fit`` building its basis in it -
the Galerkin projection that takes a fit to the projection floor where the Euclidean POD
stays above it (numpy only)."""

import dataclasses

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp

import dolfinx_lopinf as lo
from dolfinx_lopinf.core import synthetic
from dolfinx_lopinf.core.basis import leading_svd, weighted_svd
from dolfinx_lopinf.core._checks import check_weight
from dolfinx_lopinf.errors import InputError


def _graded_bar(N=60, grade=20.0):
    """A clamped-free bar of N linear elements whose sizes grow geometrically by ``grade``
    (consistent mass, unit stiffness and density, Rayleigh damping), loaded by x^2: on such
    a mesh the Euclidean norm of the nodal values weighs the short elements as much as the
    long ones, unlike the mass (L2) norm of the field."""
    x = (np.geomspace(1.0, grade, N + 1) - 1.0) / (grade - 1.0)
    h = np.diff(x)
    K, M = np.zeros((N + 1, N + 1)), np.zeros((N + 1, N + 1))
    for e in range(N):
        K[e:e + 2, e:e + 2] += np.array([[1.0, -1.0], [-1.0, 1.0]]) / h[e]
        M[e:e + 2, e:e + 2] += h[e] / 6.0 * np.array([[2.0, 1.0], [1.0, 2.0]])
    K, M = K[1:, 1:], M[1:, 1:]
    return M, K, 0.05 * M + 2e-4 * K, (M @ x[1:] ** 2)[:, None]


@pytest.fixture(scope="module")
def graded():
    M, K, C, B = _graded_bar()
    fom = lo.core.LagrangianROM(K=K, M=M, C=C, B=B, scheme="newmark", lagrangian=False)
    n, dt, steps = len(K), 0.02, 400
    runs = {name: fom.simulate(np.zeros(n), np.zeros(n), dt, steps, inputs=load)
            for name, load in (("train", synthetic._bar_train), ("test", synthetic._bar_test))}
    t = dt * np.arange(steps + 1)
    U = np.array([synthetic._bar_train(s) for s in t]).T
    return {"M": M, "train": lo.Snapshots(t, runs["train"].Qh, U=U, scheme="newmark",
                                          weight=sp.csr_array(M)),
            "test": runs["test"].Qh, "steps": steps}


def _decaying(n=120, K=60, seed=3):
    rng = np.random.default_rng(seed)
    return (rng.standard_normal((n, 10)) @ np.diag(10.0 ** -np.arange(10.0))
            @ rng.standard_normal((10, K)))


def _spd_sparse(n, seed=4):
    rng = np.random.default_rng(seed)
    return sp.diags([np.full(n - 1, 0.2), 1.0 + rng.random(n), np.full(n - 1, 0.2)], [-1, 0, 1])


def test_weighted_pod_is_the_svd_of_R_Q_without_factorising_W():
    Q, W = _decaying(), _spd_sparse(120)
    R = scipy.linalg.cholesky(W.toarray())
    U, s, _ = np.linalg.svd(R @ Q, full_matrices=False)
    for weight in (W, W.toarray()):
        basis = lo.pod(Q, 6, weight=weight)
        assert np.allclose(basis.singular_values["all"][:10], s[:10], rtol=0, atol=1e-14 * s[0])
        assert np.abs(basis.V.T @ (W @ basis.V) - np.eye(6)).max() < 1e-13
        ref = scipy.linalg.solve_triangular(R, U[:, :6])
        for j in range(6):  # same vectors up to sign, to the accuracy the gap allows
            assert min(np.linalg.norm(basis.V[:, j] - ref[:, j]),
                       np.linalg.norm(basis.V[:, j] + ref[:, j])) < 1e-8
    assert np.allclose(lo.pod(Q, 6, weight=W).V, lo.pod(Q, 6, weight=W.toarray()).V, atol=1e-13)


def test_leading_modes_in_the_weight_match_the_full_weighted_svd():
    Q, W = _decaying(400, 200), check_weight(_spd_sparse(400), 400)
    U, s = weighted_svd(Q, W)
    Ul, sl = leading_svd(Q, 8, weight=W)
    assert np.allclose(sl[:8], s[:8], rtol=0, atol=1e-13 * s[0])
    assert np.abs(Ul.T @ (W @ Ul) - np.eye(8)).max() < 1e-13
    assert np.abs(np.abs(np.sum(Ul[:, :4] * (W @ U[:, :4]), axis=0)) - 1).max() < 1e-10


def test_weighted_pod_refuses_a_weight_that_is_not_an_inner_product():
    Q = _decaying(6, 20)
    indefinite = np.kron(np.eye(3), np.array([[1.0, 2.0], [2.0, 1.0]]))  # diagonal > 0
    with pytest.raises(InputError, match="not positive definite on the snapshots' span"):
        lo.pod(Q, 2, weight=indefinite)
    with pytest.raises(InputError, match="not symmetric"):
        lo.pod(Q, 2, weight=np.triu(np.ones((6, 6))))
    with pytest.raises(InputError, match="diagonal entry <= 0"):
        lo.pod(Q, 2, weight=-np.eye(6))
    with pytest.raises(InputError, match=r"must be \(6, 6\)"):
        lo.pod(Q, 2, weight=np.eye(5))
    with pytest.raises(InputError, match="numerical rank 10 in the weighted"):
        lo.pod(_decaying(), 12, weight=_spd_sparse(120))


def test_snapshots_keep_their_weight_through_save_load_and_window(tmp_path):
    Q, W = _decaying(), _spd_sparse(120)
    t = 0.1 * np.arange(Q.shape[1])
    for weight in (W, W.toarray()):
        s = lo.Snapshots(t, Q, weight=weight)
        back = lo.Snapshots.load(s.save(tmp_path / "s"))
        assert type(back.weight) is type(s.weight)
        assert abs(back.weight - s.weight).max() == 0
        assert abs(s.window(0.0, 1.0).weight - s.weight).max() == 0
    with pytest.raises(InputError, match="non-finite"):
        lo.Snapshots(t, Q, weight=sp.csr_array(np.diag(np.r_[np.nan, np.ones(119)])))


def test_fit_builds_its_basis_in_the_snapshots_inner_product(graded):
    train, test = graded["train"], graded["test"]
    weighted = lo.fit(train, 8)
    plain = lo.fit(dataclasses.replace(train, weight=None), 8)
    assert weighted.report["basis"] == "POD in the snapshots' inner product"
    assert plain.report["basis"] == "POD"
    assert np.abs(weighted.basis.V.T @ graded["M"] @ weighted.basis.V - np.eye(8)).max() < 1e-12
    errors = {}
    for name, model in (("weighted", weighted), ("plain", plain)):
        pred = model.predict(graded["steps"], inputs=synthetic._bar_test)
        errors[name] = (lo.relative_error(test, model.reconstruct(pred.Qh)),
                        model.basis.projection_error(test))
    # the Galerkin (mass) projection: at the floor (measured 1.06x); the Euclidean POD of the
    # same data 2.0x above its floor, 1.7x the weighted error
    assert errors["weighted"][0] <= 1.3 * errors["weighted"][1]
    assert errors["weighted"][0] <= 0.8 * errors["plain"][0]
    q0 = test[:, 5]  # and projects full states with the same inner product
    assert np.allclose(weighted.basis.project(q0), weighted.basis.V.T @ graded["M"] @ q0)


def test_saved_weighted_model_projects_as_before(graded, tmp_path):
    model = lo.fit(graded["train"], 6)
    back = lo.ReducedModel.load(model.save(tmp_path / "m"))
    q0 = graded["test"][:, 40]
    assert np.allclose(back.basis.project(q0), model.basis.project(q0), rtol=0, atol=1e-14)


def test_trajectories_with_different_inner_products_are_refused(graded):
    train = graded["train"]
    other = dataclasses.replace(train, weight=2.0 * train.weight)
    with pytest.raises(InputError, match="different inner products"):
        lo.fit([train, other], 4)
    with pytest.raises(InputError, match="trajectory 0 is set, of trajectory 1 None"):
        lo.fit([train, dataclasses.replace(train, weight=None)], 4)
    with pytest.raises(InputError, match="trajectory 0 is None, of trajectory 1 set"):
        lo.fit([dataclasses.replace(train, weight=None), train], 4)
    # as the message says, a basis of one's own settles it
    basis = lo.pod(train.Q, 4, weight=train.weight)
    assert lo.fit([train, other], 4, basis=basis).report["basis"] == "given"
    # the same weight, sparse and dense or one rounding apart, is one inner product
    dense = dataclasses.replace(train, weight=train.weight.toarray() * (1 + 1e-15))
    assert lo.fit([train, dense], 4).report["basis"] == "POD in the snapshots' inner product"


def test_a_loaded_models_basis_fits_as_the_original(graded, tmp_path):
    """A weighted basis read back from a model file keeps W V, not W: lo.fit must project
    with it (it projected with V^T, a different and silently worse model)."""
    model = lo.fit(graded["train"], 6)
    loaded = lo.ReducedModel.load(model.save(tmp_path / "m")).basis
    assert loaded.weight is None and loaded.dual is not None
    refit = lo.fit(graded["train"], 6, basis=loaded)
    again = lo.fit(graded["train"], 6, basis=model.basis)
    assert np.allclose(refit.rom.K, again.rom.K, rtol=1e-9, atol=1e-12 * np.abs(again.rom.K).max())
    assert np.allclose(loaded.projector(), model.basis.projector(), rtol=0, atol=1e-14)


def test_blocks_keep_their_euclidean_block_pod(graded):
    train = graded["train"]
    n = train.n_states
    blocked = dataclasses.replace(train, blocks={"a": np.arange(n // 2), "b": np.arange(n // 2, n)})
    model = lo.fit(blocked, 4, mass="identity")
    assert model.report["basis"] == "block POD" and model.basis.weight is None
