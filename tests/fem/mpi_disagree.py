"""Ranks that disagree (issue 27), run under mpiexec -n 2 by test_agreement.py.

``python mpi_disagree.py agree [LOGDIR]`` (``agree=<case>``: that case alone): every case below
gives one rank another (or a bad) argument of a collective entry point; each rank catches what
it raises and logs one line ``RESULT <case> rank=<r> <ErrorClass>: <message>`` (to stdout, and
to LOGDIR/rank<r>.txt, free of the interleaving of the two ranks' output) - the test asserts
both ranks raised the same error, and that nothing hung (the run is under a timeout; ``START
<case>`` lines show where it stopped). ``fit``: rank 1's lo.fit refuses its data, uncaught,
while rank 0 waits in a barrier (the job must abort, not hang). ``sink_one``: a sink raises
on rank 1 only inside the time loop (the job must abort). ``sink_all``: a sink raises on both
ranks (both must raise it and exit normally).
"""
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from dolfinx_lopinf.fem._dolfinx import MPI, PETSc, dolfinx  # the wheel's MPI before dolfinx
import ufl

import dolfinx_lopinf as lo
from dolfinx_lopinf.fem import galerkin_nonlinear as gn
from dolfinx_lopinf.fem import probes
from dolfinx_lopinf.fem.loop import OutputProbe
from dolfinx_lopinf.fem.state import point_output_matrix
from dolfinx_lopinf.fem.newmark import NewmarkIntegrator
from dolfinx_lopinf.fem.intrusive import reduced_matrix
from dolfinx_lopinf.fem.streaming import StreamingPOD

comm = MPI.COMM_WORLD
rank = comm.rank
other = rank == 1  # the rank that disagrees
DT = 1e-3


def string(n=16):
    msh = dolfinx.mesh.create_interval(comm, n, [0.0, 1.0])
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
    q, qt = dolfinx.fem.Function(V), dolfinx.fem.Function(V)
    ends = dolfinx.fem.locate_dofs_geometrical(V, lambda x: np.isclose(x[0], 0) | np.isclose(x[0], 1))
    bc = dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), ends, V)
    system = lo.LagrangianSystem((0.5 * qt**2 - 0.5 * q.dx(0) ** 2) * ufl.dx, q, qt, bcs=[bc])
    x = V.tabulate_dof_coordinates()[:, 0]
    return system, V, x * (1 - x), np.zeros_like(x)


ONLY = None  # "agree=<case>" runs that case alone
LOG = None  # a folder: each rank also writes its lines to rank<r>.txt there (no interleaving)


def log(line):
    print(line, flush=True)
    if LOG is not None:
        with open(Path(LOG) / f"rank{rank}.txt", "a") as f:
            f.write(line + "\n")


def case(name, fn):
    if ONLY is not None and name != ONLY:
        return
    log(f"START {name} rank={rank}")
    try:
        fn()
        line = "no error"
    except Exception as exc:  # noqa: BLE001
        line = f"{type(exc).__name__}: {exc}".replace("\n", " ")
    log(f"RESULT {name} rank={rank} {line}")
    comm.Barrier()  # both ranks are back in step: the next case starts together


def agree_cases():
    system, V, q0, v0 = string()
    sm = lo.fem.StateMap.from_coordinates(V)
    n = len(sm.order)
    run = lambda **kw: lo.run(system, q0, v0, kw.pop("dt", DT), kw.pop("t_end", 0.02),  # noqa: E731
                              progress=False, **kw)
    case("run_dt", lambda: run(dt=2e-3 if other else 1e-3))
    case("run_t_end", lambda: run(t_end=0.04 if other else 0.02))
    case("run_record_every", lambda: run(record_every=2 if other else 1))
    case("run_t_end_not_whole_on_one_rank", lambda: run(t_end=0.0205 if other else 0.02))
    case("run_state_map", lambda: run(state_map=lo.fem.StateMap(sm.order, sm.scale * (2.0 if other else 1.0))))

    it = lo.fem.MidpointIntegrator(system, DT)
    it.initialize(q0, v0)
    case("loop_steps", lambda: lo.run(it, 10 if other else 7))
    E = point_output_matrix(V, [[0.5, 0, 0]])
    case("loop_sinks", lambda: lo.run(it, 3, sinks=[OutputProbe(E)] if other else []))
    case("loop_bad_sink_one_rank", lambda: lo.run(it, 3, sinks=[5] if other else []))
    case("step_input_one_rank", lambda: it.step(1.0 if other else None))
    case("initialize_nan_one_rank", lambda: it.initialize(np.where(other, np.nan, q0), v0))
    case("integrator_dt", lambda: lo.fem.MidpointIntegrator(system, 2e-3 if other else 1e-3))
    it.close()
    case("loop_closed", lambda: lo.run(it, 3))

    nm = NewmarkIntegrator(system, DT, input_forms=[ufl.TestFunction(V) * ufl.dx])
    nm.initialize([0.0])
    case("newmark_inputs_differ", lambda: lo.run(nm, 3, inputs=lambda t: [2.0 if other else 1.0]))
    case("newmark_step_length", lambda: nm.step([1.0, 2.0] if other else [1.0]))
    nm.close()

    x = np.linspace(0.0, 1.0, n)
    B = np.column_stack([np.sin(np.pi * x), np.sin(2 * np.pi * x)])
    with lo.fem.MidpointIntegrator(system, 1e-4) as m:
        G = probes.mass_gram(m, B, sm)
    B = B @ np.linalg.inv(np.linalg.cholesky(G)).T
    Bnan = B.copy()
    Bnan[3, 0] = np.nan
    Q, Vel = np.ones((2, 3)), np.zeros((2, 3))
    case("probe_nan_V_one_rank", lambda: lo.fem.probe(system, Bnan if other else B, sm, Q, Vel,
                                                  step_size=1e-4, levels=2, step_tol=None))
    case("probe_Q_differs", lambda: lo.fem.probe(system, B, sm, Q * (2.0 if other else 1.0), Vel,
                                             step_size=1e-4, levels=2, step_tol=None))
    case("points_differ", lambda: point_output_matrix(V, [[0.7 if other else 0.5, 0, 0]]))
    case("points_nan_one_rank", lambda: point_output_matrix(V, [[np.nan if other else 0.5, 0, 0]]))
    mass = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(
        ufl.TrialFunction(V) * ufl.TestFunction(V) * ufl.dx))
    mass.assemble()
    case("reduced_matrix_basis_differs", lambda: reduced_matrix(mass, V, B * (2.0 if other else 1.0), sm))
    mass.destroy()

    pod = StreamingPOD(V, 4)
    for k in range(3):
        pod.append(np.full(V.dofmap.index_map.size_local, k + 1.0) * np.arange(V.dofmap.index_map.size_local))
    case("pod_append_nan_one_rank", lambda: pod.append(np.full(V.dofmap.index_map.size_local,
                                                               np.nan if other else 1.0)))
    case("pod_r_differs", lambda: pod.compute(2 if other else 1))
    pod.close()

    u = dolfinx.fem.Function(V)
    energy = 0.5 * ufl.inner(ufl.grad(u), ufl.grad(u)) * ufl.dx + 0.25 * u**4 * ufl.dx
    case("galerkin_basis_nan_one_rank", lambda: gn.GalerkinForce(energy, u, Bnan if other else B, sm))
    gf = gn.GalerkinForce(energy, u, B, sm)
    case("galerkin_q_differs", lambda: gf.force(np.array([0.1, 0.3 if other else 0.2])))

    # SnapshotRecorder: a scheme named on one rank only; another recorded time on one rank
    u_rec = dolfinx.fem.Function(V)
    case("recorder_scheme_one_rank",
         lambda: lo.SnapshotRecorder(u_rec, scheme="newmark" if other else None))
    rec = lo.SnapshotRecorder(u_rec)
    rec.record(0.0, u_rec)
    case("recorder_time_differs", lambda: rec.record(2 * DT if other else DT, u_rec))

    # write_vtx: rank 0's path and states; the settings must agree; an unrelated folder stays
    d = Path(comm.bcast(tempfile.mkdtemp() if rank == 0 else None, root=0))
    S = np.ones((n, 2))
    case("vtx_engine_differs", lambda: lo.write_vtx(d / "a.bp", V, S, [0.0, 1.0],
                                                    engine="BP5" if other else "BP4"))
    if rank == 0:
        (d / "photos.bp").mkdir()
        (d / "photos.bp" / "IMG_001.jpg").write_text("precious")
    comm.Barrier()
    case("vtx_unrelated_folder", lambda: lo.write_vtx(d / "photos.bp", V, S, [0.0, 1.0]))
    if rank == 0:
        log(f"PHOTOS {sorted(os.listdir(d / 'photos.bp'))}")


def fit_case():
    t = np.arange(0, 400) * 0.01
    Q = np.vstack([np.cos(t), np.sin(t), np.cos(2 * t)])
    if other:
        Q[0, 5] = np.nan
    lo.fit(lo.Snapshots(times=t, Q=Q), 2)  # raises on rank 1 only, uncaught
    comm.Barrier()  # rank 0 waits here
    log(f"PASSED THE BARRIER rank={rank}")


def late_case():
    """snapshots() reached by rank 1 only seconds after rank 0 (as when a user calls it inside
    ``if comm.rank == 0:``): rank 0 names the problem after LOPINF_MPI_TIMEOUT s, then both
    finish once rank 1 arrives."""
    import time

    system, V, q0, v0 = string()
    u_rec = dolfinx.fem.Function(V)
    rec = lo.SnapshotRecorder(u_rec)
    for k in range(3):
        rec.record(k * DT, u_rec)
    if other:
        time.sleep(4.0)
    snaps = rec.snapshots()
    log(f"LATE DONE rank={rank} {None if snaps is None else snaps.Q.shape}")


def sink_case(on_every_rank: bool):
    system, V, q0, v0 = string()
    it = lo.fem.MidpointIntegrator(system, DT)
    it.initialize(q0, v0)

    def sink(state):
        if state.k == 3 and (on_every_rank or other):
            raise RuntimeError(f"sink failed at step 3 on rank {rank}")

    try:
        lo.run(it, 10, sinks=[sink])
    except RuntimeError as exc:
        log(f"RESULT sink rank={rank} RuntimeError: {exc}")
    comm.Barrier()
    log(f"DONE rank={rank}")


if __name__ == "__main__":
    which, _, ONLY = sys.argv[1].partition("=")
    ONLY = ONLY or None
    LOG = sys.argv[2] if len(sys.argv) > 2 else None
    if which == "agree":
        agree_cases()
        log(f"ALL DONE rank={rank}")
    elif which == "fit":
        fit_case()
    elif which == "late":
        late_case()
    elif which == "sink_one":
        sink_case(False)
    elif which == "sink_all":
        sink_case(True)
