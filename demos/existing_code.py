"""A ROM from an existing dolfinx code: a 3D cantilever under a time-dependent tip load.

    python demos/existing_code.py [--quick] [--out DIR] [--r 2,4,8]

The first half of this file is an ordinary dolfinx elastodynamics program - linear
elasticity, Rayleigh damping C = alpha M + beta K, Newmark average acceleration, a vertical
traction p(t) on the free end - written without any of our FOM machinery. Three lines
connect it to dolfinx_lopinf: create a ``SnapshotRecorder``, call ``record`` once per step,
ask for ``snapshots()``. The second half is one call, ``lo.fit(snapshots, r)``: it fits a
forced, damped L-OpInf ROM from those arrays alone,

    qh_tt + Ch qh_t + Kh qh = Bh p(t),  y = Eh qh   (Kh, Ch symmetric >= eps I),

to the data relation of the loop's integrator, which it finds itself (``scheme="auto"``:
here the Newmark three-point relation), and predicts the tip displacement for a load history
it has never seen. Beside it, the same fit from 8th-order finite differences
(``scheme="continuous"``, the path the README showed before) for comparison, and - when
``opinf`` is installed (``pip install 'dolfinx_lopinf[peers]'``) - the established peer:
opinf's first-order model dx/dt = A x + B p(t) on x = [q; q_t] (2r states, q_t from opinf's
own differences), fitted the way its tutorials fit it (``dolfinx_lopinf.studies.peers``), scored on
the same tip error (rows ``opinf_peer`` under ``peer_roms`` in metrics.json).
"""

from __future__ import annotations

import time
import warnings

import numpy as np

import dolfinx_lopinf as lo  # imports dolfinx_solver first when the PyPI wheel is used
from dolfinx_lopinf.studies import peers
from dolfinx_lopinf.viz import render
from dolfinx_lopinf.fem.state import output_matrix_in_state
from dolfinx_lopinf.studies import harness

import dolfinx  # noqa: E402  (after dolfinx_lopinf, for the PyPI wheel)
import dolfinx.fem.petsc  # noqa: E402
import ufl  # noqa: E402
from mpi4py import MPI  # noqa: E402
from petsc4py import PETSc  # noqa: E402

LENGTH, WIDTH, HEIGHT = 1.0, 0.1, 0.1
E_MOD, NU, RHO = 1.0e5, 0.3, 1.0
ALPHA, BETA = 0.5, 2e-4  # Rayleigh damping
DT = 1e-3


def train_load(t):
    """A multi-frequency load that excites the first bending modes (0.5 - 9 Hz)."""
    return (np.sin(2 * np.pi * 0.5 * t) + 0.6 * np.sin(2 * np.pi * 3.1 * t + 0.3)
            + 0.4 * np.sin(2 * np.pi * 5.3 * t) + 0.3 * np.sin(2 * np.pi * 8.9 * t + 1.0))


def test_load(t):
    """Unseen: a smoothed step to 1 at t = 0.2 s plus a 2 Hz oscillation that switches on late."""
    step = 0.5 * (1 + np.tanh((t - 0.2) / 0.02))
    return step + 0.5 * np.sin(2 * np.pi * 2.0 * t) * (t > 0.8)


def simulate_cantilever(load, t_end, n_cells=(30, 4, 4), recorder_factory=None):
    """The user's own elastodynamics code (Newmark, gamma = 1/2, beta = 1/4)."""
    comm = MPI.COMM_WORLD
    msh = dolfinx.mesh.create_box(comm, [[0, 0, 0], [LENGTH, WIDTH, HEIGHT]], list(n_cells),
                                  dolfinx.mesh.CellType.hexahedron)
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1, (3,)))
    lmbda = E_MOD * NU / ((1 + NU) * (1 - 2 * NU))
    mu = E_MOD / (2 * (1 + NU))

    def sigma(w):
        eps = ufl.sym(ufl.grad(w))
        return lmbda * ufl.tr(eps) * ufl.Identity(3) + 2 * mu * eps

    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    fdim = msh.topology.dim - 1
    clamped = dolfinx.mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[0], 0.0))
    bc = dolfinx.fem.dirichletbc(np.zeros(3), dolfinx.fem.locate_dofs_topological(V, fdim, clamped), V)
    tip = dolfinx.mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[0], LENGTH))
    tags = dolfinx.mesh.meshtags(msh, fdim, tip, np.full(len(tip), 1, dtype=np.int32))
    ds = ufl.Measure("ds", domain=msh, subdomain_data=tags)
    p = dolfinx.fem.Constant(msh, 0.0)
    traction = ufl.as_vector((0.0, 0.0, -p))

    m_form = dolfinx.fem.form(RHO * ufl.inner(u, v) * ufl.dx)
    k_form = dolfinx.fem.form(ufl.inner(sigma(u), ufl.sym(ufl.grad(v))) * ufl.dx)
    f_form = dolfinx.fem.form(ufl.inner(traction, v) * ds(1))
    M = dolfinx.fem.petsc.assemble_matrix(m_form, bcs=[bc]); M.assemble()
    K = dolfinx.fem.petsc.assemble_matrix(k_form, bcs=[bc]); K.assemble()
    C = M.copy(); C.scale(ALPHA); C.axpy(BETA, K)
    A = M.copy(); A.axpy(0.5 * DT, C); A.axpy(0.25 * DT**2, K)
    solver = PETSc.KSP().create(comm)
    solver.setOperators(A)
    solver.setType("preonly")
    solver.getPC().setType("lu")
    solver.getPC().setFactorSolverType("mumps")

    q, vel, acc = (dolfinx.fem.Function(V) for _ in range(3))
    q_star, v_star = q.x.petsc_vec.duplicate(), q.x.petsc_vec.duplicate()
    rhs, tmp = q.x.petsc_vec.duplicate(), q.x.petsc_vec.duplicate()
    recorder = recorder_factory(q) if recorder_factory else None

    n_steps = int(round(t_end / DT))
    t0 = time.perf_counter()
    if recorder is not None:
        recorder.record(0.0, q, inputs=[load(0.0)])
    for n in range(1, n_steps + 1):
        t = n * DT
        q.x.petsc_vec.copy(q_star); q_star.axpy(DT, vel.x.petsc_vec); q_star.axpy(0.25 * DT**2, acc.x.petsc_vec)
        vel.x.petsc_vec.copy(v_star); v_star.axpy(0.5 * DT, acc.x.petsc_vec)
        p.value = load(t)
        with rhs.localForm() as loc:
            loc.set(0.0)
        dolfinx.fem.petsc.assemble_vector(rhs, f_form)
        rhs.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        C.mult(v_star, tmp); rhs.axpy(-1.0, tmp)
        K.mult(q_star, tmp); rhs.axpy(-1.0, tmp)
        dolfinx.fem.petsc.set_bc(rhs, [bc])
        solver.solve(rhs, acc.x.petsc_vec)
        q_star.copy(q.x.petsc_vec); q.x.petsc_vec.axpy(0.25 * DT**2, acc.x.petsc_vec)
        v_star.copy(vel.x.petsc_vec); vel.x.petsc_vec.axpy(0.5 * DT, acc.x.petsc_vec)
        for f in (q, vel, acc):
            f.x.scatter_forward()
        if recorder is not None:
            recorder.record(t, q, inputs=[load(t)])  # <- the one line inside the loop
    seconds = comm.allreduce(time.perf_counter() - t0, op=MPI.MAX)
    return V, recorder, seconds


def main(argv=None):
    args = harness.parse(__doc__, argv, out="results/existing_code", quick="coarser mesh, shorter runs",
                         extra=lambda p: p.add_argument(
                             "--r", default=None, help="reduced dimensions, comma-separated (default 2,4,8)"))
    comm = MPI.COMM_WORLD
    out = args.out
    cells = (12, 2, 2) if args.quick else (30, 4, 4)
    t_train, t_test = (1.0, 1.0) if args.quick else (2.0, 2.0)
    tip_point = np.array([[LENGTH, 0.5 * WIDTH, 0.5 * HEIGHT]])

    def factory(q):
        E = lo.point_output_matrix(q.function_space, tip_point, component=2)
        return lo.SnapshotRecorder(q, output_matrix=E)

    # 1. the user's code, run twice: the training load and the unseen test load
    V, rec_train, fom_train_s = simulate_cantilever(train_load, t_train, cells, factory)
    _, rec_test, fom_test_s = simulate_cantilever(test_load, t_test, cells, factory)
    train, test = rec_train.snapshots(), rec_test.snapshots()
    # the peer (optional) needs the tip output as a matrix on the state (collective)
    with_peer = peers.have_opinf()
    E_state = output_matrix_in_state(V, rec_train.output_matrix, rec_train.state_map) \
        if with_peer else None
    if not harness.is_root(comm):
        return None

    # 2. non-intrusive fit from the arrays alone: one call per r; scheme="auto" finds the
    #    relation the loop's integrator obeys. The finite-difference fit beside it, to compare.
    r_values = [int(x) for x in (args.r or ("2,4" if args.quick else "2,4,8")).split(",")]
    n_test, n_train = int(round(t_test / DT)), int(round(t_train / DT))
    out.mkdir(parents=True, exist_ok=True)
    rows, preds = [], {}
    for r in r_values:
        for method, scheme in (("lopinf", "auto"), ("lopinf_fd", "continuous")):
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", lo.errors.LOpInfWarning)  # reported below
                model = lo.fit(train, r, scheme=scheme)
            infer_s = time.perf_counter() - t0
            pred = model.predict(n_test, inputs=test_load)    # 3. the unseen load history
            numpy_s = model.predict(n_test, inputs=test_load, backend="numpy").seconds
            refit = model.predict(n_train, inputs=train_load)
            cert = model.report["certificate"]
            rows.append(harness.rom_row(
                method, r, scheme=model.scheme.spec, mass=model.report["mass"],
                damping=model.report["damping"], why=model.report["why"],
                identification=model.report["identification"].get("why", ""),
                candidate_errors=model.report.get("candidate_errors", {}),
                train_error=lo.relative_error(train.Y, refit.Y),
                test_error=lo.relative_error(test.Y, pred.Y),
                infer_seconds=infer_s, solve_seconds=cert["seconds"],
                solver=cert["solver"], rom_seconds=pred.seconds, rom_backend=pred.backend,
                rom_seconds_numpy=numpy_s,
                speedup=fom_test_s / pred.seconds, min_eig_K=cert["min_eig_K"],
                min_eig_C=cert.get("min_eig_C"),
                projection_error_test=model.basis.projection_error(test.Q),
                stable=harness.stable(pred.Qh)))
            preds[(method, r)] = pred
            if method == "lopinf" and r == r_values[-1]:
                model.save(out / "cantilever_rom.npz")
    # 4. the peer: opinf's first-order model from the same arrays (one POD for every r)
    peer_rows, peer_seconds = _peer_rows(train, test, r_values, E_state, fom_test_s, preds) \
        if with_peer else ([], 0.0)
    if not with_peer:
        print(f"opinf not installed: {peers.INSTALL_HINT} (the opinf_peer rows are skipped)")
    r_top = r_values[-1]
    best = next(x for x in rows if x["method"] == "lopinf" and x["r"] == r_top)
    metrics = harness.metrics(
        "existing_code_cantilever", error="output", quick=args.quick, roms=rows,
        n_dofs=int(train.n_states), dt=DT,
        t_train=t_train, t_end=t_test, fom_seconds=fom_test_s,
        fom_train_seconds=fom_train_s, saved_rom_r=r_top,
        # opinf's first-order model (dolfinx_lopinf.studies.peers), scored as the rows above; empty
        # without opinf. peer: what it is and everything it cost (POD, fits, runs, scores)
        peer_roms=peer_rows,
        peer={"package": "opinf", "installed": with_peer, "seconds": peer_seconds,
                 "install": peers.INSTALL_HINT,
                 "model": "ContinuousModel('AB') on x = [q; q_t] (2r states), q_t = opinf ord6 "
                          "differences of q; opinf PODBasis(2r, svdsolver='randomized') of the "
                          "scaled [q; q_t]; L2Solver, "
                          "regulariser by ROM.fit_regselect_continuous over logspace(-12, 2, 15); "
                          "integrated exactly (expm, load linear between steps)"})
    harness.write_metrics(out, metrics)
    series = {"FOM (unseen load)": test.Y[0],
              f"L-OpInf r={r_top}, scheme {best['scheme']}": preds[("lopinf", r_top)].Y[0],
              f"L-OpInf r={r_top}, finite differences": preds[("lopinf_fd", r_top)].Y[0]}
    if peer_rows:
        series[f"opinf peer r={r_top} (first order, {2 * r_top} states)"] = preds[("opinf_peer", r_top)].Y[0]
    render.curves(out / "tip_displacement.png", test.times, series,
                  ylabel="tip displacement u_z [m]",
                  title=f"cantilever: tip displacement under the unseen load (L-OpInf r={r_top}: "
                        f"relative error {best['test_error']:.1e}, {best['speedup']:.0f}x faster "
                        f"than the FOM)")
    print(f"n = {train.n_states} dofs; FOM {fom_test_s:.2f} s for {n_test} steps")
    harness.summary(sorted(rows + peer_rows, key=lambda x: x["r"]),
                    [("method", "method"), ("r", "r"), ("scheme", "scheme"), ("mass", "Mh"),
                     ("train_error", "tip err train"), ("test_error", "unseen load"),
                     ("infer_seconds", "fit s"), ("rom_seconds", "ROM s")],
                    widths=[10, 3, 10, 8, 13, 11, 9, 9])
    if with_peer:
        print(f"opinf peer rows: {peer_seconds:.1f} s in all")
    return metrics


def _peer_rows(train, test, r_values, E_state, fom_test_s, preds):
    """opinf's first-order model (one POD for every r) scored like the L-OpInf rows; adds its
    predictions to ``preds``. Returns (rows, seconds)."""
    peer_rows = []
    t0 = time.perf_counter()
    fitted = peers.opinf_first_order(train.Q, train.times, r_values, velocities=train.V,
                                     inputs=train.U, output_matrix=E_state,
                                     svdsolver="randomized")
    for peer in fitted:
        rest = np.zeros(train.n_states)  # the loop starts at rest, as the ROMs do
        pred = peer.predict(rest, rest, test.times, test_load, full=False)
        refit = peer.predict(rest, rest, train.times, train_load, full=False)
        peer_rows.append(harness.rom_row(
            "opinf_peer", peer.r, scheme="exact",
            train_error=lo.relative_error(train.Y, refit.Y),
            test_error=lo.relative_error(test.Y, pred.Y),
            infer_seconds=peer.fit_seconds, solve_seconds=peer.fit_seconds,
            solver="opinf L2Solver, fit_regselect_continuous", rom_seconds=pred.seconds,
            speedup=fom_test_s / pred.seconds,
            projection_error_test=peer.projection_error(test.Q, times=test.times),
            stable=pred.finite, regularizer=peer.regularizer,
            reduced_states=2 * peer.r, velocity_source=peer.velocity_source,
            peer_basis=peer.basis_kind))
        preds[("opinf_peer", peer.r)] = pred
    peer_seconds = time.perf_counter() - t0
    return peer_rows, peer_seconds


if __name__ == "__main__":
    main()
