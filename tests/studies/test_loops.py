"""The user-loop study (dolfinx_lopinf.studies.loops): five dolfinx time loops written in
community styles, an independent numpy reference of their schemes, and the study script.

* r = n: the reference integrator with the full basis I[:, free] and the loop's own forms
  reproduces each loop's (u, v, a) (quick size; measured 5e-16 .. 8e-11 relative, asserted
  at 1e-9) - this checks the loop's scheme (as documented) and the reference together.
* the recorded Snapshots have the shapes, times and inputs the loop's scheme implies (load
  values at the scheme's own load times; every 5th step for newmark_every_k).
* the reference's generalised-alpha has the Chung-Hulbert high-frequency limit (the tour's
  alpha_m = 0.2, alpha_f = 0.4: rho_inf = 2/3); its average-acceleration Newmark conserves
  energy.
* one end-to-end run of ``python -m dolfinx_lopinf.studies.loops`` at the quick size, with a
  rounding copy of each recording (1e-15 apart: the same choice, errors within 1.5x).
"""

import json

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

from dolfinx_lopinf.studies.loops import reference, study  # noqa: E402

LOOPS = study.LOOPS


@pytest.fixture(scope="module", params=LOOPS)
def verified(request):
    loop = study.load_loop(request.param)
    return loop, study.verify(loop, "quick", keep=True)


def test_reference_reproduces_loop(verified):
    loop, v = verified
    assert v["n_free"] < v["n"] and v["fixed_max"] == 0.0  # Dirichlet rows exist and stay zero
    assert v["Q"] < 1e-9, v["Q"]
    for key in ("V", "A"):
        assert v[key] is None or v[key] < 1e-9, (key, v[key])
    has_va = v["collected"]["V"] is not None
    assert has_va == (loop.NAME != "membrane_central_difference")  # the membrane keeps u only
    assert v["times_error"] < 1e-12 and v["recorded_equals_collected"]


def test_reference_detects_a_wrong_scheme(verified):
    """The r = n check can fail: the same loop integrated with beta 5 % off (or, for the
    explicit loop, its load one step late) is >= 1e4 times farther from the loop's trajectory
    than the right scheme (measured: 3e-5 .. 1e-1 against <= 8e-11)."""
    loop, v = verified
    info, ops = v["info"], v["ops"]
    sch = dict(info["scheme"])
    load = loop.train_load
    if sch["beta"] == 0.0:
        load = (lambda t: loop.train_load(t - info["dt"]))
    else:
        sch["beta"] *= 1.05
    free = ops["free"]
    W = np.eye(len(free) + int(ops["fixed"].sum()))[:, free]
    ref = reference.integrate(reference.galerkin(ops, W), sch, info["dt"], info["n_steps"],
                              inputs=load, every=sch["record_every"])
    assert reference.rel_error(v["collected"]["Q"][free], ref["Q"]) > 1e4 * max(v["Q"], 1e-13)


def test_recorded_snapshots(verified):
    loop, v = verified
    snaps, X, info = v["snapshots"], v["collected"], v["info"]
    sch, dt = info["scheme"], info["dt"]
    k = sch["record_every"]
    assert k == (5 if loop.NAME == "newmark_every_k" else 1)
    n_samples = info["n_steps"] // k + 1
    assert snaps.Q.shape == (v["n"], n_samples)
    # one input per distinct load time (central differences evaluate f(t_0) for the state at
    # t_0 and again in the first step: recorded once)
    n_loads = len(np.unique(X["load_times"]))
    assert snaps.U.shape == (1, n_loads) and snaps.Y.shape == (1, n_samples)
    np.testing.assert_allclose(snaps.times, k * dt * np.arange(n_samples), rtol=0, atol=1e-12)
    # the inputs are the load values at the times the loop evaluated them
    t = snaps.times[1:]
    expected = t - (dt if sch["beta"] == 0.0 else sch["alpha_f"] * dt)  # explicit: the load at t_n
    np.testing.assert_allclose(X["load_times"][1:], expected, rtol=0, atol=1e-12)
    times_u = snaps.times if snaps.input_times is None else snaps.input_times
    np.testing.assert_allclose(times_u, np.unique(X["load_times"]), rtol=0, atol=1e-12)
    np.testing.assert_allclose(snaps.U[0], [loop.train_load(s) for s in times_u], rtol=0, atol=1e-14)
    assert np.abs(snaps.Q).max() > 0 and np.all(np.isfinite(snaps.Y))


def test_membrane_time_step_below_cfl():
    loop = study.load_loop("membrane_central_difference")
    import dolfinx
    import dolfinx_lopinf as lo
    from mpi4py import MPI
    from dolfinx_lopinf.studies.loops import operators

    for size in ("quick", "default"):
        n = loop.SIZES[size]["cells"]
        domain = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, n, n, dolfinx.mesh.CellType.triangle)
        V = dolfinx.fem.functionspace(domain, ("Lagrange", 1))
        ops = operators.fe_operators(loop, V, lo.fem.StateMap.from_coordinates(V))
        f = ops["free"]
        m = np.diag(ops["M"])[f]
        assert np.allclose(ops["M"][np.ix_(f, f)], np.diag(m))  # lumped
        lam = np.linalg.eigvalsh(ops["K"][np.ix_(f, f)] / np.sqrt(np.outer(m, m)))[-1]
        assert loop.SIZES[size]["dt"] < 0.9 * 2 / np.sqrt(lam)


def test_reference_generalised_alpha_limits():
    """Numpy only. The tour's scheme (alpha_m = 0.2, alpha_f = 0.4) is Chung-Hulbert with
    rho_inf = 2/3 (alpha_f = rho/(1+rho), alpha_m = (2 rho - 1)/(rho + 1)): on a 1-dof
    oscillator with omega dt -> inf its one-step amplification matrix of (u, v, a) has the
    triple eigenvalue -rho_inf, so trace -> -2 and det -> -8/27. Average-acceleration Newmark
    conserves the energy of an undamped oscillator."""
    ga = {"alpha_m": 0.2, "alpha_f": 0.4, "gamma": 0.7, "beta": 0.36}
    ops = {"M": np.eye(1), "K": np.array([[1e12]])}
    A = np.empty((3, 3))
    for j, (q0, v0, a0) in enumerate(np.eye(3)):
        traj = reference.integrate(ops, ga, 1.0, 1, q0=[q0], v0=[v0], a0=[a0])
        A[:, j] = [traj["Q"][0, 1], traj["V"][0, 1], traj["A"][0, 1]]
    assert abs(np.trace(A) + 2.0) < 1e-6 and abs(np.linalg.det(A) + 8 / 27) < 1e-6
    nm = {"gamma": 0.5, "beta": 0.25}
    ops = {"M": np.eye(1), "K": np.array([[4.0]])}
    traj = reference.integrate(ops, nm, 0.3, 500, q0=[1.0], v0=[0.5])
    energy = 0.5 * traj["V"][0] ** 2 + 2.0 * traj["Q"][0] ** 2
    assert np.ptp(energy) < 1e-12 * energy[0]


def test_study_end_to_end(tmp_path):
    from dolfinx_lopinf import Snapshots
    from dolfinx_lopinf.studies.loops.__main__ import main

    names = ["newmark_nonlinear_problem", "membrane_central_difference"]
    metrics = main(["--size", "quick", "--r", "2,4", "--loops", ",".join(names), "--copies", "2",
                    "--out", str(tmp_path)])
    on_disk = json.loads((tmp_path / "metrics.json").read_text())
    assert set(on_disk["loops"]) == set(names) == set(metrics["loops"])
    saved = Snapshots.load(tmp_path / "membrane_central_difference_free.npz")  # re-fit without the loop
    assert saved.Q.shape[1] == on_disk["loops"]["membrane_central_difference"]["free_run"]["steps"] + 1
    for name in names:
        res = on_disk["loops"][name]
        assert res["output_check"] < 1e-12  # the recorder's outputs = the study's E_state @ Q
        assert [x["r"] for x in res["rows"]] == [2, 4]
        for x in res["rows"]:
            for key in ("intrusive_output", "floor_state", "intrusive_state"):
                assert np.isfinite(x[key]) and x[key] >= 0, (name, key)
            for style in res["styles"] + ["named"]:
                fit = x["fits"][style]
                assert "failure" not in fit and np.isfinite(fit["output"]), (name, style, fit)
                if style != "named":  # a copy 1e-15 away chooses the same model, near the same error
                    c = fit["copies"]
                    assert c["agree"] and len(c["choices"]) == 2 and c["spread"] < 1.5, (name, style, c)
            # the intrusive ROM cannot beat the projection floor of its own basis
            assert x["intrusive_state"] >= x["floor_state"] * (1 - 1e-9)
    free = on_disk["loops"]["membrane_central_difference"]
    assert free["free_run"]["fom_energy_drift"] < 1e-10  # central differences conserve it
    assert all(x["intrusive_free_energy_drift"] < 1e-10 for x in free["rows"])


@pytest.mark.parametrize("name", LOOPS)
def test_loops_are_user_code(name):
    """The loops are the users' programs: no import of dolfinx_lopinf, dolfinx_solver first,
    and the interface the study relies on."""
    import ast
    import inspect

    loop = study.load_loop(name)
    tree = ast.parse(inspect.getsource(loop))
    imported = [a.name for node in tree.body if isinstance(node, ast.Import) for a in node.names] + \
        [node.module for node in tree.body if isinstance(node, ast.ImportFrom)]
    assert not any(m.startswith("dolfinx_lopinf") for m in imported), imported
    first_fenics = next(m for m in imported if m.split(".")[0] in ("dolfinx", "ufl", "mpi4py", "petsc4py",
                                                                     "dolfinx_solver"))
    assert first_fenics == "dolfinx_solver"
    for attr in ("simulate", "train_load", "test_load", "SIZES", "OUTPUT", "scheme", "fe_forms"):
        assert hasattr(loop, attr), attr
    assert set(loop.SIZES) == {"quick", "default"}
    assert loop.train_load(0.0) == 0.0 and loop.test_load(0.0) == 0.0  # from rest, consistent a_0
    assert {"name", "alpha_m", "alpha_f", "beta", "gamma", "record_every"} <= set(loop.scheme())
