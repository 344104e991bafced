"""The linear step solvers (fem/linsolve.py): every iterative path gives the direct answer to
its tolerance (Newmark and the linear midpoint rule, 1 and 2 ranks), and bad solver names or
PETSc types are refused with a clear InputError."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

from dolfinx_lopinf.errors import InputError  # noqa: E402
from dolfinx_lopinf.fem import linsolve  # noqa: E402
from dolfinx_lopinf.fem._dolfinx import ufl  # noqa: E402
from dolfinx_lopinf.fem.integrators import MidpointIntegrator  # noqa: E402
from dolfinx_lopinf.fem.newmark import NewmarkIntegrator  # noqa: E402
from dolfinx_lopinf.fem.fom import run as run_loop  # noqa: E402
from dolfinx_lopinf.fem.lagrangian import LagrangianSystem  # noqa: E402

SCRIPT = Path(__file__).with_name("mpi_linsolve.py")
_spec = importlib.util.spec_from_file_location("mpi_linsolve", SCRIPT)
bar = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bar)


@pytest.fixture(scope="module")
def system():
    return bar.build()


@pytest.fixture(scope="module")
def direct(system):
    """MUMPS at dt, and how far the scheme's answer moves from dt to dt/2 (the size of its
    truncation error, which the iterative tolerance is tied to)."""
    Y, q, stats = bar.newmark(*system, "direct")
    Y_half, _, _ = bar.newmark(*system, "direct", steps=80, dt=bar.DT / 2)
    return Y, q, stats, _rel(Y, Y_half[::2])


def _rel(a, b):
    return np.abs(a - b).max() / np.abs(b).max()


@pytest.mark.parametrize("solver", bar.ITERATIVE)
def test_newmark_iterative_gives_the_direct_answer(system, direct, solver):
    """Default tolerance (1e-3 of the extrapolated warm start's residual, ~1 % of the local
    truncation error): the tip history and the state move from MUMPS's by less than 5 % of
    what halving dt moves them (measured 0.1-3 %); at ksp_rtol = 1e-10 the CG paths give
    MUMPS's answer to 1e-8 (Chebyshev would take ~10^4 iterations a step there)."""
    Y_ref, q_ref, stats_ref, time_error = direct
    assert stats_ref["solver"] == "direct" and np.abs(Y_ref).max() > 0 and time_error > 1e-4
    Y, q, stats = bar.newmark(*system, solver)
    assert stats["solver"] == solver and stats["iterations_per_solve"] >= 1
    assert _rel(Y, Y_ref) < 0.05 * time_error, (_rel(Y, Y_ref), time_error)
    assert _rel(q, q_ref) < 0.05 * time_error, (_rel(q, q_ref), time_error)
    if solver == "chebyshev":
        return
    Y, q, _ = bar.newmark(*system, solver, options={"ksp_rtol": 1e-10})
    assert _rel(Y, Y_ref) < 1e-8 and _rel(q, q_ref) < 1e-8, (_rel(Y, Y_ref), _rel(q, q_ref))


def test_midpoint_iterative_gives_the_direct_answer(system):
    """The linear midpoint rule (no damping) through -A1 = M/dt + dt/4 K: the trajectory within
    5 % of what halving dt moves it, and MUMPS's to 1e-8 at ksp_rtol = 1e-10."""
    q_ref = bar.midpoint(system[0], "direct")
    time_error = _rel(q_ref, bar.midpoint(system[0], "direct", steps=60, dt=bar.DT / 2)[:, 1::2])
    assert time_error > 1e-4
    q = bar.midpoint(system[0], "cg+pmg")
    assert _rel(q, q_ref) < 0.05 * time_error, (_rel(q, q_ref), time_error)
    q = bar.midpoint(system[0], "cg+pmg", options={"ksp_rtol": 1e-10})
    assert _rel(q, q_ref) < 1e-8


def test_auto_is_direct_and_cg_is_gamg():
    """``auto``: the exact factorisation below SUBSPACE_FROM global unknowns (or when the size
    is not known), with the recycled subspace from there on, and the block low-rank factor
    from BLR_FROM."""
    assert linsolve.SUBSPACE_FROM < linsolve.BLR_FROM
    assert linsolve.resolve("auto") == "direct"
    assert linsolve.resolve("auto", linsolve.SUBSPACE_FROM - 1) == "direct"
    assert linsolve.resolve("auto", linsolve.SUBSPACE_FROM) == "direct+subspace"
    assert linsolve.resolve("auto", linsolve.BLR_FROM - 1) == "direct+subspace"
    assert linsolve.resolve("auto", linsolve.BLR_FROM) == "direct+blr+subspace"
    assert linsolve.resolve(" Direct+BLR ", 10) == "direct+blr"
    assert linsolve.resolve(" CG ") == "cg+gamg"
    assert linsolve.resolve("cg+pmg") == "cg+pmg"


def test_block_low_rank_factorisation_is_mumps_blr_and_gives_the_direct_answer(system, direct):
    """``direct+blr`` sets MUMPS's BLR switch and threshold on the factor (a user's
    petsc_options still win) and steps like a factorisation (no warm start, no iterations).
    On this small bar its answer is the exact factor's (measured: identical, 1 and 2 ranks -
    no front reaches MUMPS's BLR block size, so nothing is compressed; the approximation
    itself was measured on the fishtail: 8.6e-8 at 392k and 4.0e-6 at 795k dofs over 30
    steps), so what this checks is the solver's set-up: the switch and threshold on the
    factor."""
    Y_ref, q_ref, _, _ = direct
    Y, q, stats = bar.newmark(*system, "direct+blr")
    assert stats["solver"] == "direct+blr"
    assert _rel(Y, Y_ref) < 1e-9 and _rel(q, q_ref) < 1e-9, (_rel(Y, Y_ref), _rel(q, q_ref))
    from dolfinx_lopinf.fem._dolfinx import dolfinx

    V = system[0].V  # a small SPD matrix: the bar's mass matrix
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    M = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(ufl.inner(u, v) * ufl.dx))
    M.assemble()
    for options, eps in ((None, linsolve.BLR_EPSILON), ({"mat_mumps_cntl_7": 1e-12}, 1e-12)):
        solver = linsolve.StepSolver(M, V.mesh.comm, "direct+blr", "test_blr_", options)
        try:
            F = solver.ksp.getPC().getFactorMatrix()
            assert not solver.iterative and F.getMumpsIcntl(35) == 2
            assert F.getMumpsCntl(7) == pytest.approx(eps)
        finally:
            solver.close()
    M.destroy()


def test_midpoint_auto_resolves_from_the_size_like_newmark(system, monkeypatch):
    """The midpoint rule's ``auto`` resolves from the problem's size like Newmark's: with the
    thresholds below this bar's size, the linear step is the block low-rank Cholesky of -A1
    with the recycled subspace (the exact factor's trajectory to 5 % of what halving dt moves
    it), with SUBSPACE_FROM above it the exact factor (to 1e-9), and a Newton step stays
    direct."""
    q_ref = bar.midpoint(system[0], "direct")
    time_error = _rel(q_ref, bar.midpoint(system[0], "direct", steps=60, dt=bar.DT / 2)[:, 1::2])
    sysm = system[0]
    monkeypatch.setattr(linsolve, "BLR_FROM", 1)
    for subspace_from, name, tol in ((10**9, "direct", 1e-9),
                                     (1, "direct+blr+subspace", 0.05 * time_error)):
        monkeypatch.setattr(linsolve, "SUBSPACE_FROM", subspace_from)
        integ = MidpointIntegrator(sysm, bar.DT)
        try:
            resolved = integ.solver.name if integ.solver is not None else "direct"
        finally:
            integ.close()
        assert resolved == name
        q = bar.midpoint(sysm, "auto")
        assert _rel(q, q_ref) < tol, (name, _rel(q, q_ref))
    integ = MidpointIntegrator(_nonlinear_bar(), bar.DT)
    try:
        assert integ.solver is None  # SNES with its own direct solve
    finally:
        integ.close()


@pytest.mark.parametrize("solver", bar.SUBSPACE)
def test_subspace_solvers_give_the_direct_answer_and_project_most_steps(system, direct, solver):
    """The factor with the recycled subspace: most steps are answered by the projection
    (measured 32 of 40 on this bar), and the answer moves from MUMPS's by less than 5 % of what
    halving dt moves it (measured 4e-6 of it); at ksp_rtol = 1e-10 no projection is good
    enough and every step is the factor's, exactly; a subspace of 4 directions compresses
    (and still gives the factor's answer)."""
    Y_ref, q_ref, _, time_error = direct
    Y, q, stats = bar.newmark(*system, solver)
    assert stats["solver"] == solver and stats["projected_solves"] >= stats["solves"] // 2
    assert 0 < stats["subspace_directions"] < stats["solves"] - stats["projected_solves"] + 1
    assert _rel(Y, Y_ref) < 0.05 * time_error and _rel(q, q_ref) < 0.05 * time_error
    for options in ({"ksp_rtol": 1e-10}, {"subspace_size": 4}):
        Y, q, stats = bar.newmark(*system, solver, options=options)
        assert stats["subspace_directions"] <= options.get("subspace_size", 64)
        if stats["projected_solves"] == 0:
            assert _rel(Y, Y_ref) < 1e-12 and _rel(q, q_ref) < 1e-12
        else:
            assert _rel(Y, Y_ref) < 0.05 * time_error


def test_midpoint_subspace_gives_the_direct_answer(system):
    q_ref = bar.midpoint(system[0], "direct")
    time_error = _rel(q_ref, bar.midpoint(system[0], "direct", steps=60, dt=bar.DT / 2)[:, 1::2])
    q = bar.midpoint(system[0], "direct+subspace")
    assert _rel(q, q_ref) < 0.05 * time_error, (_rel(q, q_ref), time_error)


def _spd_matrix(n, seed=0):
    """A small SPD PETSc matrix (dense pattern) and its numpy copy, condition ~1e4."""
    from dolfinx_lopinf.fem._dolfinx import MPI, PETSc

    rng = np.random.default_rng(seed)
    Q = np.linalg.qr(rng.standard_normal((n, n)))[0]
    dense = (Q * np.logspace(0, 4, n)) @ Q.T
    A = PETSc.Mat().createDense((n, n), comm=MPI.COMM_SELF)
    A.setUp()
    A.setValues(range(n), range(n), dense)
    A.assemble()
    return A, dense


def _vec(A, values):
    v = A.createVecLeft()
    v.array_w[:] = values
    return v


def test_recycled_subspace_projects_onto_its_span_and_compresses_to_the_recent_half():
    """A-orthonormal directions; a right-hand side whose solution lies in the span is answered
    to rounding, one outside it is refused (x untouched); a solution already in the span adds
    nothing; when full, the kept half is the one the recent projections used."""
    n = 30
    A, dense = _spd_matrix(n)
    sub = linsolve.RecycledSubspace(A, capacity=6)
    rng = np.random.default_rng(1)
    X = rng.standard_normal((n, 6))
    for j in range(6):
        x, b = _vec(A, X[:, j]), _vec(A, dense @ X[:, j])
        assert sub.extend(x, b)
    V = sub.V[:sub.k]
    assert np.allclose(V @ dense @ V.T, np.eye(6), atol=1e-10)
    assert np.allclose(sub.W[:6], V @ dense, atol=1e-9)
    x_in = X[:, :2] @ np.array([0.3, -1.2])  # in the span
    b, x = _vec(A, dense @ x_in), _vec(A, np.zeros(n))
    ok, rho = sub.project(b, x, 1e-8 * np.linalg.norm(dense @ x_in))
    assert ok and np.allclose(x.array_r, x_in, rtol=1e-8, atol=1e-10)
    assert not sub.extend(_vec(A, x_in), b)  # nothing new
    assert sub.k == 6
    x_out = rng.standard_normal(n)
    b, x = _vec(A, dense @ x_out), _vec(A, np.full(n, 7.0))
    ok, rho = sub.project(b, x, 1e-8 * b.norm())
    assert not ok and rho > 1e-3 * b.norm() and np.all(x.array_r == 7.0)
    # full: the next direction compresses to 3, keeping the span of the recent projections
    for _ in range(3):
        sub.project(_vec(A, dense @ x_in), x, 0.0)
    assert sub.extend(_vec(A, x_out), _vec(A, dense @ x_out))
    assert sub.k == 4
    ok, _ = sub.project(_vec(A, dense @ x_in), x, 1e-8 * np.linalg.norm(dense @ x_in))
    assert ok and np.allclose(x.array_r, x_in, rtol=1e-7, atol=1e-9)
    ok, _ = sub.project(_vec(A, dense @ x_out), x, 1e-8 * np.linalg.norm(dense @ x_out))
    assert ok and np.allclose(x.array_r, x_out, rtol=1e-7, atol=1e-9)
    V = sub.V[:sub.k]
    assert np.allclose(V @ dense @ V.T, np.eye(4), atol=1e-10)
    sub.close()
    A.destroy()


@pytest.mark.parametrize("options, match", [
    ({"subspace_size": 1}, "subspace_size"), ({"subspace_size": 2.5}, "subspace_size"),
    ({"ksp_rtol": 2.0}, "ksp_rtol"), ({"ksp_rtol": "tight"}, "ksp_rtol"),
])
def test_bad_subspace_options_are_refused(system, options, match):
    sysm, load, _ = system
    with pytest.raises(InputError, match=match):
        NewmarkIntegrator(sysm, bar.DT, input_forms=load, solver="direct+subspace",
                          petsc_options=options)


@pytest.mark.parametrize("bad", ["mumps", "gmres", "cg+hypre", "", None, 3])
def test_bad_solver_names_are_refused(system, bad):
    sysm, load, _ = system
    with pytest.raises(InputError, match="solver must be one of 'auto', 'direct'"):
        NewmarkIntegrator(sysm, bar.DT, input_forms=load, solver=bad)
    with pytest.raises(InputError, match="solver must be one of"):
        MidpointIntegrator(sysm, bar.DT, solver=bad)


@pytest.mark.parametrize("options, match", [
    ({"pc_type": "hpyre"}, "'hpyre' is not a PETSc type"),
    ({"ksp_type": "cgg"}, "'cgg' is not a PETSc type"),
    ({"-ksp_rtol": 1e-6}, "without the prefix and without '-'"),
    (["ksp_rtol", 1e-6], "must be a dict"),
])
def test_bad_petsc_options_are_refused(system, options, match):
    sysm, load, _ = system
    with pytest.raises(InputError, match=match):
        NewmarkIntegrator(sysm, bar.DT, input_forms=load, solver="cg+jacobi", petsc_options=options)


def test_pmg_needs_a_higher_degree_space():
    sysm, load, _ = bar.build(degree=1, n=(4, 1, 1))
    with pytest.raises(InputError, match="degree >= 2"):
        NewmarkIntegrator(sysm, bar.DT, input_forms=load, solver="cg+pmg")


def _nonlinear_bar():
    """A small bar with a quartic potential added: a Lagrangian the midpoint rule steps by
    Newton (SNES)."""
    sysm, _, _ = bar.build(n=(2, 1, 1))
    q, q_t = sysm.q, sysm.q_t
    return LagrangianSystem(sysm.lagrangian - 0.25 * ufl.inner(q, q) ** 2 * ufl.dx, q, q_t,
                            bcs=sysm.bcs)


def test_newton_steps_keep_the_direct_solve():
    nonlinear = _nonlinear_bar()
    assert not nonlinear.is_quadratic
    with pytest.raises(InputError, match="keeps its direct solve"):
        MidpointIntegrator(nonlinear, bar.DT, solver="cg+pmg")
    MidpointIntegrator(nonlinear, bar.DT, solver="direct").close()


@pytest.mark.mpi
def test_iterative_paths_two_ranks_equal_serial_and_direct(serial_and_parallel):
    """On 1 and on 2 ranks every iterative path gives the direct answer to its tolerance, and
    the 2-rank answers are the serial ones to that tolerance too; the block low-rank factor
    gives the exact factor's answer to 1e-9 on both."""
    a, b = serial_and_parallel(SCRIPT)
    for run in (a, b):
        tn, tm = float(run["newmark_time_error"]), float(run["midpoint_time_error"])
        assert tn > 1e-4 and tm > 1e-4
        for part in ("Y", "q"):
            assert _rel(run[f"newmark_{part}_direct+blr"], run[f"newmark_{part}_direct"]) < 1e-9
        for solver in bar.ITERATIVE + bar.SUBSPACE:
            assert _rel(run[f"newmark_Y_{solver}"], run["newmark_Y_direct"]) < 0.05 * tn, solver
            assert _rel(run[f"newmark_q_{solver}"], run["newmark_q_direct"]) < 0.05 * tn, solver
        for solver in ("cg+pmg", "direct+subspace"):
            assert _rel(run[f"midpoint_q_{solver}"], run["midpoint_q_direct"]) < 0.05 * tm, solver
    for key in a.files:
        scheme = "midpoint" if key.startswith("midpoint") else "newmark"
        assert _rel(b[key], a[key]) < 0.05 * float(a[f"{scheme}_time_error"]), key
    assert _rel(b["newmark_q_direct"], a["newmark_q_direct"]) < 1e-10


def test_subspace_solver_answers_a_zero_right_hand_side_without_the_factor(system):
    """A loop whose input starts late (the fishtail's sine is zero for 0.1 s) steps with
    b = 0: the empty span's projection x_p = 0 is exact, so those steps cost no substitution
    (they ran the factor every step, adding no direction)."""
    sysm, load, E = system
    with NewmarkIntegrator(sysm, bar.DT, rayleigh=bar.RAYLEIGH, input_forms=load,
                           solver="direct+subspace") as nm:
        nm.initialize([0.0])
        for _ in range(10):
            nm.step([0.0])
        stats = nm.solver.stats()
        assert stats["solves"] == 10 and stats["projected_solves"] >= 7
        assert stats["subspace_directions"] == 0 and np.all(nm.q.x.array == 0.0)
        nm.step([50.0])  # the input starts: the factor, and the span's first direction
        assert nm.solver.stats()["subspace_directions"] == 1


@pytest.mark.parametrize("solver", bar.SUBSPACE)
def test_newmark_keeps_the_images_of_its_accelerations_without_products(system, solver):
    """The subspace solvers' warm-start residual b - A a_e is formed from the images A a_k of
    the last three answers (a projection's W^T y, a substitution's A d + W^T c, A a_0 once at
    initialize), not by a product with A each step. Those images must be A a_k of the
    accelerations kept (to rounding) after projected and substituted steps and after a
    compression; the guess a_e = a_{k-1} + a_{k-2} - a_k must be Newmark's displacement
    extrapolation 3 q_k - 3 q_{k-1} + q_{k-2}."""
    sysm, load, E = system
    with NewmarkIntegrator(sysm, bar.DT, rayleigh=bar.RAYLEIGH, input_forms=load, solver=solver,
                           petsc_options={"subspace_size": 8}) as nm:
        nm.initialize([0.0])
        qs, Aa = [], nm.A.createVecLeft()
        for k in range(40):
            nm.step([50.0 * np.sin(0.2 * k)])
            qs.append(nm.q.x.petsc_vec.copy())
            for a, image in zip(nm._history, nm._images[:3]):
                nm.A.mult(a, Aa)
                # rounding of the Gram-Schmidt parts and the compressions' rotations:
                # 5.2e-13 measured; a missing part (A d without W^T c) is off by O(1)
                assert (Aa - image).norm() <= 1e-10 * Aa.norm(), k
        stats = nm.solver.stats()
        # both kinds of step were checked, and compressions (more substitutions than room)
        assert 0 < stats["projected_solves"] and stats["solves"] - stats["projected_solves"] > 8
        # the guess of the next step from the accelerations against the displacements'
        a_e = nm._history[0] + nm._history[1] - nm._history[2]
        q, v, a = nm.q.x.petsc_vec, nm.v.x.petsc_vec, nm.a.x.petsc_vec
        q_star = q + bar.DT * v + 0.25 * bar.DT**2 * a
        q_e = 3 * qs[-1] - 3 * qs[-2] + qs[-3]
        from_q = (q_e - q_star) * (4.0 / bar.DT**2)
        assert (from_q - a_e).norm() <= 1e-8 * a_e.norm()
        Aa.destroy()


def test_subspace_accepts_projections_as_close_as_an_inexact_factor(system, direct):
    """With an inexact factor (here MUMPS in single precision: relative residual ~1e-3; a
    block low-rank factor's is its dropping threshold's), a projection whose residual is
    within twice the factor's own is as good as a substitution and is accepted. Without that
    floor a tight tolerance (ksp_rtol = 1e-6) refused every projection (measured 0 of 40
    projected, against 22 with it), paying a substitution per step for no accuracy."""
    Y_ref, _, _, time_error = direct
    Y, q, stats = bar.newmark(*system, "direct+subspace",
                              options={"pc_precision": "single", "ksp_rtol": 1e-6})
    assert 1e-6 < stats["factor_residual"] < 1e-2
    assert stats["projected_solves"] >= 10
    Y_factor, _, _ = bar.newmark(*system, "direct", options={"pc_precision": "single"})
    # no less accurate than the inexact factor's own answers (within 2x), nor the time step's
    assert _rel(Y, Y_ref) <= max(2 * _rel(Y_factor, Y_ref), 0.05 * time_error)


def test_subspace_accepts_projections_as_close_as_the_ones_it_accepts(system):
    """Where the warm start is very good (twice a period of a smooth input), 1e-2 of its
    residual is a test no projection passes, and every such step was a substitution; a
    projection within the median relative residual of the latest accepted projections is
    accepted too, if it improves on the warm start FLOOR_GAIN-fold. Here: the bar's run fills
    the window, then b = A x with x a held direction plus a part outside the span sized to
    half that median (the projection's residual rho), warm starts with residual 20 rho
    (accepted; a substitution once the window is emptied) and 2 rho (a substitution: the
    projection is hardly better than the start)."""
    sysm, load, E = system
    with NewmarkIntegrator(sysm, bar.DT, rayleigh=bar.RAYLEIGH, input_forms=load,
                           solver="direct+subspace") as nm:
        nm.initialize([0.0])
        run_loop(nm, 40, inputs=lambda t: [50.0 * np.sin(2 * np.pi * t) ** 2])
        solver, A = nm.solver, nm.solver.subspace.A
        median = solver.projection_residual
        assert median > 0 and solver.stats()["projection_residual"] == median
        rng = np.random.default_rng(3)
        vecs = x_true, e, b, x, g, Ag, r = [A.createVecRight() for _ in range(7)]
        for start, window, accept in ((20.0, "full", True), (2.0, "full", False),
                                      (20.0, "empty", False)):
            if window == "empty":
                solver._projection_residuals.clear()
            # a fresh b outside the span (each substitution adds its solution to the span)
            x_true.array_w[:] = solver.subspace.V[0]
            e.array_w[:] = rng.standard_normal(e.array_r.shape)
            A.mult(e, b)
            A.mult(x_true, x)
            miss = solver.subspace.project(b, r, 0.0)[1] / x.norm()
            x_true.axpy(0.5 * median / miss, e)
            A.mult(x_true, b)
            rho = solver.subspace.project(b, r, 0.0)[1]
            assert 0.3 * median * b.norm() < rho < 0.7 * median * b.norm()
            g.array_w[:] = rng.standard_normal(g.array_r.shape)
            A.mult(g, Ag)
            c = start * rho / Ag.norm()  # the warm start x_true + c g: residual start x rho
            x_true.copy(x)
            x.axpy(c, g)
            Ag.scale(c)
            Ag.axpy(1.0, b)  # its image A x_true + c A g
            projected = solver.stats()["projected_solves"]
            assert solver.solve(b, x, guess_image=Ag) > 0
            accepted = solver.stats()["projected_solves"] == projected + 1
            assert accepted == accept, (start, window)
            A.mult(x, r)
            r.aypx(-1.0, b)
            assert r.norm() <= (median if accepted else 1e-8) * b.norm()
        for vec in vecs:
            vec.destroy()


def test_factored_newmark_releases_the_assembled_matrix_and_iterative_refuse(system):
    """Once factored, Newmark keeps A only as its action m M + kappa K (a shell: the assembled
    copy, as large as M, is destroyed); an iterative solver, which multiplies by A at every
    iteration, refuses to give it up."""
    sysm, load, E = system
    with NewmarkIntegrator(sysm, bar.DT, rayleigh=bar.RAYLEIGH, input_forms=load,
                           solver="direct+subspace") as nm:
        assert nm.A.getType() == "python"
        x, y, z = nm.M.createVecRight(), nm.M.createVecLeft(), nm.M.createVecLeft()
        x.setRandom()
        nm.A.mult(x, y)
        nm.M.mult(x, z)
        z.scale(1.0 + 0.5 * bar.DT * bar.RAYLEIGH[0])
        w = z.duplicate()
        nm.K.mult(x, w)
        z.axpy(0.5 * bar.DT * bar.RAYLEIGH[1] + 0.25 * bar.DT**2, w)
        assert (y - z).norm() <= 1e-14 * z.norm()
        for vec in (x, y, z, w):
            vec.destroy()
    with NewmarkIntegrator(sysm, bar.DT, rayleigh=bar.RAYLEIGH, input_forms=load,
                           solver="cg+jacobi") as nm:
        assert nm.A.getType() != "python"
        with pytest.raises(InputError, match="iterative"):
            nm.solver.release_matrix(nm.M)
