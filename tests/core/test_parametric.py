"""Parametric L-OpInf (numpy core): the affine structure, the joint certified fit, the
certificate at unseen parameters, the SPD interpolation of non-affine fits, and the named
errors of bad input.

The data are exact: a reduced system M a + C v + K u = B f with known affine operators,
stepped by the ROM's own Newmark scheme at each training parameter, so its three-point
relation holds to rounding and the fit must give the operators back."""

import json
import subprocess
import sys
import warnings

from dataclasses import replace

import numpy as np
import pytest

import dolfinx_lopinf as lo
from dolfinx_lopinf.core import interpolated as ip
from dolfinx_lopinf.core import parametric as par
from dolfinx_lopinf.core.basis import Basis
from dolfinx_lopinf.errors import InputError, ParameterRangeWarning

N = 5
DT = 0.01


def _spd(rng, n, lo_, hi):
    Q = np.linalg.qr(rng.standard_normal((n, n)))[0]
    return Q @ np.diag(rng.uniform(lo_, hi, n)) @ Q.T


@pytest.fixture(scope="module")
def truth():
    rng = np.random.default_rng(3)
    return {"K[1]": _spd(rng, N, 5, 40), "K[mu]": _spd(rng, N, 1, 20),
            "C[z]": _spd(rng, N, 0.02, 0.2), "C[mu*z]": _spd(rng, N, 0.01, 0.1),
            "B[1]": rng.standard_normal((N, 1)), "B[mu]": 0.5 * rng.standard_normal((N, 1))}


STRUCTURE = par.AffineStructure(("mu", "z"), mass=["1"], stiffness=["1", "mu"],
                                damping=["z", "mu*z"], inputs=["1", "mu"])


def _operators(truth, mu, z):
    K = truth["K[1]"] + mu * truth["K[mu]"]
    C = z * truth["C[z]"] + mu * z * truth["C[mu*z]"]
    B = truth["B[1]"] + mu * truth["B[mu]"]
    return K, C, B


def _load(k):
    return lambda t: np.array([np.sin((1.7 + 0.9 * k) * t) + 0.4 * np.cos(5.3 * t + k)])


def _trajectory(K, C, B, load, n=300, dt=DT, q0=None):
    rom = lo.core.LagrangianROM(K=K, C=C, B=B, scheme="newmark")
    q0 = np.zeros(K.shape[0]) if q0 is None else q0
    tr = rom.simulate(q0, np.zeros(K.shape[0]), dt, n, inputs=load)
    U = np.column_stack([load(t) for t in tr.times])
    return lo.Snapshots(tr.times, tr.Qh, U=U, scheme="newmark")


TRAIN = [(0.5, 1.0), (1.0, 0.5), (2.0, 1.5), (3.0, 1.0), (1.5, 2.0), (2.5, 0.7)]


@pytest.fixture(scope="module")
def data(truth):
    out = []
    for mu in TRAIN:
        for k in range(2):  # two trajectories per parameter, each with its own input
            out.append((mu, _trajectory(*_operators(truth, *mu), _load(k))))
    return out


def _identity_basis(n=N):
    return Basis(np.eye(n), {}, {"all": (np.arange(n), np.arange(n))})


@pytest.fixture(scope="module")
def model(data):
    return par.fit_affine(data, STRUCTURE, basis=_identity_basis(), damping="structure")


# -- the structure ---------------------------------------------------------------------------
def test_structure_thetas_cone_and_text():
    s = STRUCTURE
    assert s.theta("damping", [2.0, 3.0]).tolist() == [3.0, 6.0]
    assert s.theta("stiffness", {"mu": 2.0, "z": 3.0}).tolist() == [1.0, 2.0]
    assert s.cone == "mu >= 0 and z >= 0"  # mu*z >= 0 follows
    assert "K(mu) = 1 * K[1] + mu * K[mu]" in s.describe()
    assert s.cone_violations([-1.0, 2.0]) == [("damping", "mu*z", -2.0), ("stiffness", "mu", -1.0)]
    assert par.AffineStructure.from_dict(s.as_dict()) == s


@pytest.mark.parametrize("kwargs, words", [
    ({"mass": ["mu"]}, "no parameter-free term"),
    ({"stiffness": ["1", "nu"]}, "'nu'"),
    ({"stiffness": ["1", "1"]}, "twice"),
    ({"stiffness": []}, "no stiffness"),
])
def test_bad_structures_are_named(kwargs, words):
    with pytest.raises(InputError, match=words):
        par.AffineStructure(("mu",), **kwargs)


@pytest.mark.parametrize("mu, words", [
    ([1.0], "has 1 value"), ([1.0, 2.0, 3.0], "has 3 value"), ({"mu": 1.0}, "missing"),
    ({"mu": 1.0, "z": 1.0, "E": 2.0}, "unknown"), ([np.nan, 1.0], "not finite"),
])
def test_mu_of_the_wrong_length_or_kind_is_named(mu, words):
    with pytest.raises(InputError, match=words):
        STRUCTURE.check_mu(mu)


# -- the fit ---------------------------------------------------------------------------------
def test_fit_recovers_known_affine_operators(model, truth):
    for op, names in (("stiffness", ["K[1]", "K[mu]"]), ("damping", ["C[z]", "C[mu*z]"]),
                      ("inputs", ["B[1]", "B[mu]"])):
        for A, name in zip(model.terms[op], names):
            T = truth[name]
            assert np.abs(A - T).max() <= 1e-8 * np.abs(T).max(), name
    c = model.report["certificate"]
    assert c["converged"] and c["relative_residual"] < 1e-10
    assert c["duality_gap"] <= 1e-8
    assert model.report["basis"] == "given" and "this Euclidean POD" not in model.report["mass"]
    assert "mu >= 0 and z >= 0" in c["stable_for"] and "not only the 6" in c["stable_for"]


def test_every_term_is_symmetric_psd_so_every_mu_of_the_cone_is_stable(model):
    for op in ("stiffness", "damping"):
        for A in model.terms[op]:
            assert np.array_equal(A, A.T)
            assert np.linalg.eigvalsh(A)[0] > 0
    rng = np.random.default_rng(0)
    for mu in rng.uniform(0, 50, (20, 2)):   # far outside the training box, inside the cone
        M, C, K, B = model.operators(mu)
        assert np.linalg.eigvalsh(K)[0] > 0 and np.linalg.eigvalsh(C)[0] > 0


def test_unseen_parameter_prediction_matches_the_truth(model, truth):
    mu = (1.7, 1.2)   # inside the training box, not a training point
    ref = _trajectory(*_operators(truth, *mu), _load(5))
    pred = model.predict(mu, n_steps=300, inputs=ref.U)
    assert np.abs(pred.Qh - ref.Q).max() <= 1e-7 * np.abs(ref.Q).max()


def test_save_load_gives_the_same_model(model, data, tmp_path):
    """A parametric model in one file, read back with numpy alone: the same operators at any
    mu, the same predictions, the same projection (a weighted basis keeps its W V)."""
    back = par.ParametricModel.load(model.save(tmp_path / "pm"))
    assert back.structure == model.structure and back.scheme == model.scheme
    assert back.dt == model.dt and np.array_equal(back.mu_train, model.mu_train)
    mu = (1.7, 1.2)
    for A, B in zip(back.operators(mu), model.operators(mu)):
        assert (A is None and B is None) or np.array_equal(A, B)
    u = _load(5)
    assert np.array_equal(back.predict(mu, n_steps=50, inputs=u).Qh,
                          model.predict(mu, n_steps=50, inputs=u).Qh)
    assert back.report["certificate"]["duality_gap"] == model.report["certificate"]["duality_gap"]
    W = np.diag(np.linspace(1.0, 2.0, N))  # a weighted basis projects with W V after loading
    weighted = replace(model, basis=Basis(np.diag(1 / np.sqrt(np.diag(W))), {},
                                          {"all": (np.arange(N), np.arange(N))}, W))
    again = par.ParametricModel.load(weighted.save(tmp_path / "pmw"))
    q = np.arange(1.0, N + 1)
    assert np.allclose(again.basis.project(q), weighted.basis.project(q), rtol=0, atol=1e-14)
    (tmp_path / "junk.npz").write_bytes(b"not a model")
    with pytest.raises(lo.errors.FileFormatError, match="junk"):
        par.ParametricModel.load(tmp_path / "junk.npz")
    np.savez(tmp_path / "other.npz", K=np.eye(2))
    with pytest.raises(lo.errors.FileFormatError, match="not a file written by ParametricModel"):
        par.ParametricModel.load(tmp_path / "other.npz")


def test_free_response_outside_the_range_keeps_its_energy_bounded(model):
    q0 = np.ones(N)
    with pytest.warns(ParameterRangeWarning, match="outside the training range"):
        rom = model.rom((40.0, 0.05))
    tr = rom.simulate(q0, np.zeros(N), DT, 3000)
    e = rom.energy(tr.Qh, tr.Vh)
    assert np.all(np.diff(e) <= 1e-12 * e[0])  # damped: the energy never grows


def test_outside_the_cone_is_refused_or_checked(model):
    with pytest.raises(InputError, match=r"outside the cone mu >= 0 and z >= 0.*theta_C\[mu\*z\]"):
        model.predict((1.0, -0.5), n_steps=5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ParameterRangeWarning)
        with pytest.raises(InputError, match="not stable at this mu"):
            model.predict((1.0, -0.5), n_steps=5, outside_cone="check")  # C(mu) < 0 there
        # mu = -0.05: K = K[1] - 0.05 K[mu] is still positive definite: checked, allowed
        tr = model.predict((-0.05, 1.0), n_steps=5, outside_cone="check",
                           inputs=np.zeros((1, 6)))
    assert np.all(np.isfinite(tr.Qh))


def test_mu_of_the_wrong_length_at_predict(model):
    with pytest.raises(InputError, match="has 1 value.*2 parameter"):
        model.predict(1.0, n_steps=5)


def test_trajectories_with_different_dt_are_named(truth, data):
    other = _trajectory(*_operators(truth, 1.0, 1.0), _load(0), dt=0.02)
    with pytest.raises(InputError, match=r"dt = 0.02.*dt = 0.01"):
        par.fit_affine(data[:4] + [((1.0, 1.0), other)], STRUCTURE, basis=_identity_basis())


def test_other_bad_training_data_is_named(truth, data):
    with pytest.raises(InputError, match="has 1 value"):
        par.fit_affine([(1.0, data[0][1])], STRUCTURE, basis=_identity_basis())
    bare = lo.Snapshots(data[0][1].times, data[0][1].Q, scheme="newmark")
    with pytest.raises(InputError, match="differ in their inputs"):
        par.fit_affine(data[:2] + [((1.0, 1.0), bare)], STRUCTURE, basis=_identity_basis())
    # every training parameter has z = 0: the damping terms do not act, nothing determines them
    flat = [((mu, 0.0), s) for (mu, _), s in data]
    with pytest.raises(InputError, match=r"term z of C is zero at every training parameter"):
        par.fit_affine(flat, STRUCTURE, basis=_identity_basis(), damping="structure")
    with pytest.raises(InputError, match="damping must be one of"):
        par.fit_affine(data, STRUCTURE, basis=_identity_basis(), damping="yes")
    with pytest.raises(InputError, match="pairs"):
        par.fit_affine([data[0][1]], STRUCTURE, basis=_identity_basis())


def test_active_constraints_are_certified_by_the_interior_point(truth):
    """K[mu] with a zero eigenvalue and noisy data: the unconstrained symmetric fit of that
    block is indefinite, the PSD constraint is active and the interior point certifies."""
    rng = np.random.default_rng(7)
    Kmu = truth["K[mu]"].copy()
    w, Q = np.linalg.eigh(Kmu)
    w[0] = 0.0
    Kmu = (Q * w) @ Q.T
    st = par.AffineStructure(("mu",), mass=["1"], stiffness=["1", "mu"], inputs=["1"])
    data = []
    for mu in (0.5, 1.5, 2.5, 3.5):
        for k in range(2):
            s = _trajectory(truth["K[1]"] + mu * Kmu, None, truth["B[1]"], _load(k))
            noisy = s.Q + 1e-4 * np.abs(s.Q).max() * rng.standard_normal(s.Q.shape)
            data.append((mu, lo.Snapshots(s.times, noisy, U=s.U, scheme="newmark")))
    m = par.fit_affine(data, st, basis=_identity_basis(), damping="structure")
    c = m.report["certificate"]
    assert c["solver"] == "ipm" and c["converged"] and c["duality_gap"] <= 1e-8
    assert min(np.linalg.eigvalsh(A)[0] for A in m.terms["stiffness"]) >= 0.99e-8 / 3.5


def test_a_parameter_dependent_mass_is_learned_as_a_psd_block(truth):
    rng = np.random.default_rng(11)
    M1 = 0.3 * _spd(rng, N, 0.1, 1.0)
    st = par.AffineStructure(("mu",), mass=["1", "mu"], stiffness=["1"], inputs=["1"])
    data = [(mu, _trajectory(truth["K[1]"], None, truth["B[1]"], _load(k)))
            for mu in (0.5, 1.0, 2.0, 3.0) for k in range(2)]
    data = []
    for mu in (0.5, 1.0, 2.0, 3.0):
        for k in range(2):
            rom = lo.core.LagrangianROM(K=truth["K[1]"], M=np.eye(N) + mu * M1, B=truth["B[1]"],
                                   scheme="newmark")
            tr = rom.simulate(np.zeros(N), np.zeros(N), DT, 300, inputs=_load(k))
            U = np.column_stack([_load(k)(t) for t in tr.times])
            data.append((mu, lo.Snapshots(tr.times, tr.Qh, U=U, scheme="newmark")))
    m = par.fit_affine(data, st, basis=_identity_basis(), damping="structure")
    assert np.abs(m.terms["mass"][0] - M1).max() <= 1e-7 * np.abs(M1).max()
    M, _, K, _ = m.operators(2.5)
    assert np.allclose(M, np.eye(N) + 2.5 * M1, atol=1e-7)
    assert "learned" in m.report["mass"]


def test_closure_damping_choice_is_reported(data):
    conservative = par.AffineStructure(("mu", "z"), mass=["1"], stiffness=["1", "mu"],
                                       inputs=["1", "mu"])
    closure = par.with_closure(conservative)
    assert closure.damping == ((), ("mu",))
    m = par.fit_affine(data, conservative, basis=_identity_basis(), damping="auto")
    assert m.report["damping"] in ("structure", "closure")
    errs = m.report["held_back_errors"]
    assert set(errs) == {"structure", "closure"}
    # the data are damped: a conservative model cannot predict the held-back end; the closure can
    assert m.report["damping"] == "closure" and errs["closure"] < 0.5 * errs["structure"]


def test_intrusive_projection_of_given_terms(truth):
    full = {"mass": [np.eye(N)], "stiffness": [truth["K[1]"], truth["K[mu]"]],
            "damping": [truth["C[z]"], truth["C[mu*z]"]], "inputs": [truth["B[1]"], truth["B[mu]"]]}
    m = par.intrusive(STRUCTURE, full, _identity_basis(), "newmark", DT)
    _, C, K, B = m.operators((2.0, 0.5))
    K2, C2, B2 = _operators(truth, 2.0, 0.5)
    assert np.allclose(K, K2) and np.allclose(C, C2) and np.allclose(B, B2)
    with pytest.raises(InputError, match="not orthonormal in the parameter-free mass"):
        par.intrusive(STRUCTURE, dict(full, mass=[2 * np.eye(N)]), _identity_basis(), "newmark", DT)


def test_sample_design_corners_then_interior():
    pts = par.sample_design([(0, 1), (10, 20)], 6)
    assert pts.shape == (6, 2)
    assert {tuple(p) for p in pts[:4]} == {(0, 10), (0, 20), (1, 10), (1, 20)}
    assert np.all((pts[4:] > [0, 10]) & (pts[4:] < [1, 20]))


# -- non-affine: interpolation on the SPD manifold -------------------------------------------
def test_spd_interpolation_is_spd_and_exact_at_the_nodes():
    rng = np.random.default_rng(2)
    A, B = _spd(rng, 4, 0.1, 5), _spd(rng, 4, 0.1, 5)
    assert np.allclose(ip.geodesic(A, B, 0.0), A) and np.allclose(ip.geodesic(A, B, 1.0), B)
    for t in (-1.5, 0.3, 2.5):   # inside and far outside: SPD
        assert np.linalg.eigvalsh(ip.geodesic(A, B, t))[0] > 0
    assert np.allclose(ip.expm_sym(ip.logm_spd(A)), A)
    with pytest.raises(InputError, match="not positive definite"):
        ip.logm_spd(-A)


def test_fit_interpolated_on_a_non_affine_family(truth):
    """K(mu) = K[1] + mu^2 K[mu]: not affine in mu; per-parameter fits are exact, the
    log-Euclidean and affine-invariant interpolants SPD everywhere and close between nodes."""
    def ops(mu):
        return truth["K[1]"] + mu**2 * truth["K[mu]"], 0.05 * np.eye(N), truth["B[1]"]

    train = [0.5, 1.0, 1.5, 2.0]
    data = [(mu, _trajectory(*ops(mu), _load(k))) for mu in train for k in range(2)]
    for method in ip.METHODS:
        m = ip.fit_interpolated(data, basis=_identity_basis(), method=method)
        for j, mu in enumerate(train):
            assert np.abs(m.K[j] - ops(mu)[0]).max() <= 1e-6 * np.abs(ops(mu)[0]).max()
            assert np.abs(m.operators([mu])[2] - ops(mu)[0]).max() <= 1e-6 * np.abs(ops(mu)[0]).max()
        _, _, K, _ = m.operators([1.25])
        assert np.linalg.eigvalsh(K)[0] > 0
        assert np.linalg.norm(K - ops(1.25)[0]) < 0.05 * np.linalg.norm(ops(1.25)[0])
        with pytest.warns(ParameterRangeWarning):
            tr = m.predict(3.0, n_steps=50, inputs=np.zeros((1, 51)), q0=np.ones(N))
        assert np.all(np.isfinite(tr.Qh))
        with pytest.raises(InputError, match="1 parameter"):
            m.predict([1.0, 2.0], n_steps=5)


def test_interpolated_needs_two_parameters_and_one_for_geodesics(truth):
    s = _trajectory(truth["K[1]"], None, truth["B[1]"], _load(0))
    with pytest.raises(InputError, match=">= 2 distinct"):
        ip.fit_interpolated([(1.0, s), (1.0, s)], basis=_identity_basis(), damping=False)
    with pytest.raises(InputError, match="one parameter"):
        ip.fit_interpolated([((1.0, 2.0), s), ((2.0, 1.0), s), ((1.5, 1.5), s)],
                            basis=_identity_basis(), damping=False, method="affine-invariant")


def test_front_door_dispatch(data, truth):
    m = lo.parametric.fit(data, structure=STRUCTURE, basis=_identity_basis(), damping="structure")
    assert isinstance(m, par.ParametricModel)
    s = _trajectory(truth["K[1]"], None, truth["B[1]"], _load(0))
    m2 = lo.parametric.fit([(1.0, s), (2.0, s)], basis=_identity_basis(), damping=False)
    assert isinstance(m2, ip.InterpolatedModel)


SCRIPT = r"""
import json, sys
for name in json.loads(sys.argv[1]):
    sys.modules[name] = None
import numpy as np
import dolfinx_lopinf as lo
K0, K1, B = np.diag([1.0, 4.0]), np.diag([0.5, 1.0]), np.array([[1.0], [0.3]])
s = lo.parametric.AffineStructure(("mu",), stiffness=["1", "mu"], inputs=["1"])
data = []
for mu in (0.5, 1.0, 2.0):
    rom = lo.core.LagrangianROM(K=K0 + mu * K1, B=B, scheme="newmark")
    tr = rom.simulate(np.zeros(2), np.zeros(2), 0.05, 200, inputs=lambda t: np.array([np.sin(t)]))
    U = np.sin(tr.times)[None, :]
    data.append((mu, lo.Snapshots(tr.times, tr.Qh, U=U, scheme="newmark")))
m = lo.parametric.fit(data, 2, structure=s, damping="structure")
mi = lo.parametric.fit(data, 2, damping=False)
try:
    lo.parametric.ParametricSystem
    err = "none"
except ImportError as exc:
    err = str(exc)
V = m.basis.V  # the POD basis rotates the coordinates: compare V Kh V^T with the truth
print(json.dumps({"K": (V @ m.operators(1.5)[2] @ V.T).tolist(),
                  "Ki": (V @ mi.operators([1.0])[2] @ V.T).tolist(), "err": err}))
"""


def test_parametric_core_runs_without_dolfinx():
    from tests.core.test_layers import BLOCKED

    proc = subprocess.run([sys.executable, "-c", SCRIPT, json.dumps(BLOCKED)], capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert np.allclose(out["K"], np.diag([1.75, 5.5]), atol=1e-6)
    assert np.allclose(out["Ki"], np.diag([1.5, 5.0]), atol=1e-6)
    assert "dolfinx" in out["err"].lower()
