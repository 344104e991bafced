"""Soft-robotic fishtail: a forced, damped Lagrangian ROM of 3D elasticity.

    python demos/fishtail.py [--quick] [--size small|default|large] [--out DIR] [--train sine|sigmoid]

1. Geometry from meshes/fishtail.py (gmsh): a silicone hull lofted through three ellipses, a
   carbon centre beam ending at the point of interest (0, 0, 0.21) m, two pressure chambers.
2. FOM from the UFL Lagrangian 1/2 rho |q_t|^2 - 1/2 sigma(q) : eps(q) on P2 tetrahedra, two
   materials, Rayleigh damping C = 1e-4 M + 2e-4 K, chamber pressures +u(t) / -u(t) (pre-
   pressure u_pre = 0: the paper gives no value), Newmark dt = 1e-3 s to T = 2 s, for the four
   inputs (step, sine, ramp, sigmoid). Only the training window's states are kept; the POI
   output and the FOM energy are recorded for every step.
3. L-OpInf from the training arrays (sine on [0, 0.4] s by default): POD, 8th-order
   differences, Kh, Ch >= eps I and free Bh (one input channel), Eh by least squares; the
   intrusive Galerkin ROM beside it. ROMs run Newmark like the FOM.
4. Output error for every input (unseen ones included), energy tracking, 3D renders.
"""

from __future__ import annotations

import resource
import sys
import time

import numpy as np

import dolfinx_lopinf as lo
from dolfinx_lopinf.viz import render
from dolfinx_lopinf.fem._dolfinx import MPI
from dolfinx_lopinf.fem.loop import FieldSnapshots
from dolfinx_lopinf.fem.state import StateMap, gather_states, output_matrix_in_state
from dolfinx_lopinf.fem.streaming import StreamingPOD
from dolfinx_lopinf.fem.intrusive import reduced_matrix
from dolfinx_lopinf.fem.linsolve import SOLVERS
from dolfinx_lopinf.scenes import fishtail as scene
from dolfinx_lopinf.studies import harness

TRAIN_WINDOW = {"sine": 0.4, "sigmoid": 1.0}
#: from this many dofs the energy is recorded every ENERGY_EVERY_LARGE steps (5 ms: 400 points
#: over the 2 s, the sine's 0.2 s period drawn by 40)
ENERGY_STRIDE_FROM, ENERGY_EVERY_LARGE = 300_000, 5


def run_fom(tail, nm, u_fn, t_end, comm, *, spod=None, t_keep=0.0, snap_steps=(), energy_every=1):
    """Newmark to t_end (the scene's :func:`simulate`, the one time loop). States up to t_keep
    go to ``spod`` (an on-disk StreamingPOD, so memory does not grow with n x K); the POI
    output is kept every step, the energy every ``energy_every`` steps, full fields only at
    ``snap_steps`` (for the renders)."""
    fields = FieldSnapshots(snap_steps)
    sinks = [fields] if spod is None else [spod.sink(until_step=int(round(t_keep / scene.DT))), fields]
    Y, E, seconds = scene.simulate(tail, nm, u_fn, t_end, sinks=sinks, energy_every=energy_every,
                                   progress=harness.is_root(comm) and sys.stderr.isatty())
    return Y, E, seconds, fields.fields


def _options(parser):
    """The fishtail's own command-line options (beside the harness's --quick and --out)."""
    parser.add_argument("--size", choices=sorted(scene.SIZES), default="default")
    parser.add_argument("--train", choices=sorted(TRAIN_WINDOW), default="sine")
    parser.add_argument("--basis", choices=["mass", "euclidean"], default="mass")
    parser.add_argument("--inputs", default=None,
                        help="comma-separated inputs to simulate (default: all four; the training "
                             "input is always included)")
    parser.add_argument("--solver", choices=list(SOLVERS), default="auto",
                        help="Newmark solve (dolfinx_lopinf.fem.linsolve): auto = the MUMPS "
                             "Cholesky, with the recycled subspace from 100k unknowns and block "
                             "low rank from 300k (the fastest measured), or an iterative one")
    parser.add_argument("--data", choices=["newmark", "fd"], default="newmark",
                        help="newmark: fit the three-point relation of Newmark snapshots (default); "
                             "fd: 8th-order finite-difference derivatives")
    parser.add_argument("--energy-every", type=int, default=None,
                        help="record the FOM energy every N steps (default: every step, and every "
                             f"{ENERGY_EVERY_LARGE}th from {ENERGY_STRIDE_FROM:,} dofs, where its two "
                             "products with the matrices per step cost as much as the step)")
    parser.add_argument("--scratch", default=None, help="directory for the on-disk training snapshots")
    parser.add_argument("--hull-density", choices=sorted(scene.HULL_DENSITIES), default="paper",
                        help="silicone: 1.07e3 kg/m^3; paper: 1.07e-3 kg/m^3 as the paper prints it")


def main(argv=None):
    args = harness.parse(__doc__, argv, out="results/fishtail",
                         quick="small mesh, T = 0.6 s, r in {2, 4}", extra=_options)
    parser = args.parser
    comm = MPI.COMM_WORLD
    out = args.out
    size = "small" if args.quick else args.size
    t_end = 0.6 if args.quick else scene.T_END
    t_train = TRAIN_WINDOW[args.train]
    inputs = ["sine", "step"] if args.quick else ["sine", "sigmoid", "ramp", "step"]
    if args.inputs:
        inputs = args.inputs.split(",")
        unknown = sorted(set(inputs) - set(scene.INPUTS))
        if unknown:
            parser.error(f"unknown inputs {unknown}; choose from {sorted(scene.INPUTS)}")
    inputs = [args.train] + [name for name in inputs if name != args.train]  # training run first
    r_values = [2, 4] if args.quick else [2, 4, 6, 8, 10]
    dt = scene.DT
    n_steps = int(round(t_end / dt))
    if args.energy_every is not None and not 1 <= args.energy_every <= n_steps:
        parser.error(f"--energy-every must be in 1..{n_steps}, got {args.energy_every}")

    t0 = time.perf_counter()
    tail = scene.build(scene.SIZES[size], comm, hull_density=args.hull_density)
    V = tail.system.V
    nm = scene.integrator(tail, dt, solver=args.solver)
    setup_s = time.perf_counter() - t0
    n_dofs = V.dofmap.index_map.size_global * 3
    energy_every = args.energy_every
    if energy_every is None:
        energy_every = ENERGY_EVERY_LARGE if n_dofs >= ENERGY_STRIDE_FROM else 1
    if comm.rank == 0:
        print(f"fishtail ({size}): {n_dofs} dofs, set-up {setup_s:.1f} s")
    state_map = StateMap.from_coordinates(V)
    fom = {}
    render_input = inputs[-1]  # an unseen input
    # fields kept for the renders: the first 50 ms after the input starts (where the tip's
    # extremes are picked from the output) and the GIF frames
    early = list(range(int(round(0.1 / dt)), int(round(0.15 / dt)) + 1))
    gif_steps = list(range(n_steps // 40, n_steps + 1, n_steps // 40))
    # only the training run's states are stored, on disk, in the POD inner product:
    # W = M gives V^T M V = I, so the reduced mass that L-OpInf fixes to I is exact (it uses
    # the FOM mass matrix; --basis euclidean is the paper's black-box POD).
    n_train = int(round(t_train / dt)) + 1
    spod = StreamingPOD(V, n_train, weight=nm.M if args.basis == "mass" else None,
                        directory=args.scratch)
    for name in inputs:
        # the fields of the renders (one rank only draws them: on N ranks none are kept)
        steps = set(early + gif_steps) if name == render_input and comm.size == 1 else ()
        Y, E, seconds, fields = run_fom(tail, nm, scene.INPUTS[name], t_end, comm,
                                        spod=spod if name == args.train else None,
                                        t_keep=t_train, snap_steps=steps, energy_every=energy_every)
        if name == render_input:  # tip extremes, mid-run and the end; drop the other fields
            render_steps = [max(early, key=lambda k: Y[k]), min(early, key=lambda k: Y[k]),
                            n_steps // 2, n_steps]
            fields = {k: v for k, v in fields.items() if k in set(render_steps + gif_steps)}
        fom[name] = dict(Y=Y, E=E, seconds=seconds, fields=fields)
        if harness.is_root(comm):  # keep the FOM's outputs whatever happens later
            out.mkdir(parents=True, exist_ok=True)
            np.savez(out / f"fom_{name}.npz", t=dt * np.arange(len(Y)), Y=Y, E=E,
                     t_energy=dt * energy_every * np.arange(len(E)), seconds=seconds)
            print(f"FOM {name}: {n_steps} steps in {seconds:.1f} s, "
                  f"max |y| = {np.abs(Y).max():.3e} m", flush=True)
        if name == args.train:  # basis right away: a training run too poor for r fails fast
            r_values, V_all, Qh_full, pod_lam, snapshot_disk, pod_s = _training_basis(
                spod, r_values, V, state_map, comm)

    # --- operators from the training run only ------------------------------------------------
    train = fom[args.train]
    rows = []
    rom_plot = {}
    for r in r_values:
        Vr = V_all[:, :r]
        # intrusive Galerkin operators (collective), for comparison only
        Mg = reduced_matrix(nm.M, V, Vr, state_map)
        Kg = reduced_matrix(nm.K, V, Vr, state_map)
        Cg = scene.RAYLEIGH[0] * Mg + scene.RAYLEIGH[1] * Kg  # V^T C V (C is not stored)
        Bg = _reduced_input(nm, V, Vr, state_map, comm)
        Eg = output_matrix_in_state(V, tail.output_matrix, state_map) @ Vr  # true POI functional
        if comm.rank != 0:
            continue
        times = dt * np.arange(Qh_full.shape[1])
        u_train = scene.INPUTS[args.train](times)
        Qh_all = Qh_full[:r]
        t_fit = time.perf_counter()
        if args.data == "newmark":  # the three-point relation Newmark snapshots obey exactly
            Qbar, D1, D2, Ubar = lo.core.ddt.newmark_data(Qh_all, times, u_train[None])
            ops = lo.core.infer_mechanical(Qbar, D1, D2, Ubar)
        else:  # 8th-order finite differences (continuous-time operators)
            Qh, dQh, ddQh = lo.core.derivatives(Qh_all, times)
            ops = lo.core.infer_mechanical(Qh, dQh, ddQh, u_train[None, 4:-4])
        Eh = lo.core.infer_output(Qh_all, train["Y"][None, : len(times)])
        infer_s = time.perf_counter() - t_fit
        lopinf = lo.core.LagrangianROM(K=ops.K, C=ops.C, B=ops.B, E=Eh, scheme="newmark")
        intrusive = lo.core.LagrangianROM(K=Kg, M=Mg, C=Cg, B=Bg, E=Eg, scheme="newmark")
        for method, rom in (("lopinf", lopinf), ("intrusive", intrusive)):
            row, plots = _score(method, rom, r, Mg, Kg, fom, inputs, args.train, t_train, t_end,
                                energy_every)
            row["infer_seconds"] = infer_s if method == "lopinf" else 0.0
            if method == "lopinf":
                row.update(min_eig_K=ops.certificate["min_eig_K"], min_eig_C=ops.certificate["min_eig_C"],
                           solver=ops.certificate["solver"])
            if r == r_values[-1] or r == 2:
                rom_plot.update({(method, r, name): (tr, Vr, e_rom) for name, (tr, e_rom) in plots.items()})
            rows.append(row)
    # peak resident memory of each rank (ru_maxrss is in KiB on Linux)
    peak_rss = comm.gather(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
    if not harness.is_root(comm):
        nm.close()
        return None
    out.mkdir(parents=True, exist_ok=True)
    fom_seconds = {k: v["seconds"] for k, v in fom.items()}
    metrics = harness.metrics(
        "fishtail", error="output", quick=args.quick, roms=rows,
        size=size, n_dofs=int(n_dofs), dt=dt,
        t_train=t_train, train_input=args.train, t_end=t_end,
        fom_seconds=max(fom_seconds.values()), fom_seconds_by_input=fom_seconds,
        fom_setup_seconds=setup_s, pod_seconds=pod_s, fom_solver=nm.solver.stats(),
        snapshot_disk_bytes=int(snapshot_disk), n_ranks=comm.size, energy_every=energy_every,
        peak_rss_bytes_per_rank=peak_rss, u_pre=0.0, basis=args.basis, data=args.data,
        hull_density=scene.HULL_DENSITIES[args.hull_density],
        pod_singular_values=np.sqrt(np.maximum(pod_lam[:20], 0)).tolist())
    harness.write_metrics(out, metrics)
    t = dt * np.arange(n_steps + 1)
    for name in inputs:
        outputs, energies = {"FOM": fom[name]["Y"]}, {"FOM": fom[name]["E"]}
        for (method, r, nm_), (tr, _, e_rom) in sorted(rom_plot.items(), key=lambda kv: (kv[0][0] != "lopinf", kv[0][1])):
            if nm_ == name:
                label = f"{'L-OpInf' if method == 'lopinf' else 'intrusive'} r={r}"
                outputs[label], energies[label] = tr.Y[0], e_rom[::energy_every]
        render.output_error_energy(out / f"poi_{name}.png", t, outputs, energies,
                                   ylabel="tip displacement x [m]",
                                   vline=t_train if name == args.train else None,
                                   t_energy=t[::energy_every],
                                   title=f"{name} input" + (" (training input)" if name == args.train else " (unseen)"))
    if comm.size == 1:
        n_boundary, n_points = _renders(out, V, state_map, fom[render_input]["fields"], rom_plot,
                                        render_input, render_steps, gif_steps, r_values[-1], dt)
        metrics["render_reconstructed_points"] = {"boundary": int(n_boundary), "all": int(n_points)}
        harness.write_metrics(out, metrics)
    nm.close()
    harness.summary([dict(row, **row["output_errors"]) for row in rows],
                    ["method", "r"] + inputs + ["stable"], widths=[10, 3] + [9] * len(inputs) + [6])
    return metrics


def _training_basis(spod, r_values, V, state_map, comm):
    """The POD of the training run's on-disk snapshots (r capped by their numerical rank):
    r values kept, the gathered basis (n x r_max, not n x K) on every rank, Qh, the Gram
    eigenvalues, the disk bytes used and the seconds taken. Closes ``spod``."""
    t0 = time.perf_counter()
    rank = spod.numerical_rank()
    if rank < max(r_values) and harness.is_root(comm):
        print(f"the training snapshots have numerical rank {rank}: r <= {rank} only")
    r_values = [r for r in r_values if r <= rank]
    basis_local, Qh_full, pod_lam = spod.compute(max(r_values))
    snapshot_disk = comm.allreduce(spod.disk_bytes)
    spod.close()
    V_all = comm.bcast(gather_states(V, basis_local, state_map))
    return r_values, V_all, Qh_full, pod_lam, snapshot_disk, time.perf_counter() - t0


def _score(method, rom, r, Mg, Kg, fom, inputs, train_input, t_train, t_end, energy_every=1):
    """Run ``rom`` from rest under every input and score its output against the FOM's:
    output error per input, train error (the training input), test error (the worst unseen
    input, or the training input after its window when there is no other), the energy error
    per input (at the FOM energy's steps, every ``energy_every``-th), times, stable. Returns
    the row and {input: (trajectory, ROM energy at every step)}."""
    dt = scene.DT
    row = {"method": method, "r": r, "infer_seconds": 0.0, "output_errors": {},
           "rom_seconds_by_input": {}}
    outputs, plots = [], {}
    for name in inputs:
        n = int(round(t_end / dt))
        tr = rom.simulate(np.zeros(r), np.zeros(r), dt, n,
                          inputs=lambda t, name=name: np.array([scene.INPUTS[name](t)]))
        row["output_errors"][name] = lo.relative_error(fom[name]["Y"], tr.Y[0])
        row["rom_seconds_by_input"][name] = tr.seconds
        row["rom_backend"] = tr.backend
        row.setdefault("rom_seconds_numpy_by_input", {})[name] = rom.simulate(
            np.zeros(r), np.zeros(r), dt, n, backend="numpy",
            inputs=lambda t, name=name: np.array([scene.INPUTS[name](t)])).seconds
        outputs.append(tr.Y[0])
        e_rom = 0.5 * np.einsum("ik,ij,jk->k", tr.Vh, Mg, tr.Vh) + 0.5 * np.einsum("ik,ij,jk->k", tr.Qh, Kg, tr.Qh)
        row.setdefault("energy_errors", {})[name] = float(
            np.abs(e_rom[::energy_every] - fom[name]["E"]).max() / np.abs(fom[name]["E"]).max())
        plots[name] = (tr, e_rom)
    row["train_error"] = row["output_errors"][train_input]
    unseen = [v for k, v in row["output_errors"].items() if k != train_input]
    if unseen:
        row["test_error"] = max(unseen)
    else:  # one input only: the training input after its training window
        k = int(round(t_train / dt))
        row["test_error"] = lo.relative_error(fom[train_input]["Y"][k:], plots[train_input][0].Y[0][k:])
    row["rom_seconds"] = max(row["rom_seconds_by_input"].values())  # the slowest input
    row["rom_seconds_numpy"] = max(row["rom_seconds_numpy_by_input"].values())
    row["stable"] = harness.stable(np.concatenate(outputs))
    return row, plots


def _renders(out, V, state_map, fields, rom_plot, name, render_steps, gif_steps, r, dt):
    """FOM vs L-OpInf deformed fishtail (serial): stills at a few times and a GIF.

    Only the boundary is visible, so only the basis rows of the dofs on boundary facets are
    used: the ROM field is V[boundary rows] qh (partial reconstruction), never the full
    n-vector; interior points of the drawn grid stay at zero and are never seen.
    """
    import pyvista
    from dolfinx import plot

    from dolfinx_lopinf.fem._dolfinx import dolfinx

    msh = V.mesh
    fdim = msh.topology.dim - 1
    msh.topology.create_connectivity(fdim, msh.topology.dim)
    facets = dolfinx.mesh.exterior_facet_indices(msh.topology)
    pts = dolfinx.fem.locate_dofs_topological(V, fdim, facets)  # dof blocks on the boundary
    topology, cell_types, geometry = plot.vtk_mesh(V)
    volume = pyvista.UnstructuredGrid(topology, cell_types, geometry)
    inverse = np.empty_like(state_map.order)
    inverse[state_map.order] = np.arange(len(state_map.order))
    rows = inverse[(3 * pts[:, None] + np.arange(3)).ravel()]  # their state rows
    tr, Vr, _ = rom_plot[("lopinf", r, name)]
    V_boundary = Vr[rows]  # (3 * boundary points, r): all the picture needs

    def rom_field(k):
        u = np.zeros((volume.n_points, 3))
        u[pts] = (V_boundary @ tr.Qh[:, k]).reshape(-1, 3)
        return u

    def fom_field(k):
        u = np.zeros((volume.n_points, 3))
        u[pts] = fields[k].reshape(-1, 3)[pts]
        return u

    peak = max(np.abs(fom_field(k)).max() for k in render_steps)
    magnify = 0.03 / peak  # largest displacement drawn as 3 cm
    frames = [{"FOM": fom_field(k), f"L-OpInf r={r}": rom_field(k)} for k in render_steps]
    render.deformed_side_by_side(out / f"deformed_{name}.png", volume, frames, magnify=magnify,
                                 titles=[f"t = {k * dt:.3f} s (x{magnify:.1f})" for k in render_steps])
    render.animation(out / f"deformed_{name}.gif", volume,
                     {"FOM": [fom_field(k) for k in gif_steps],
                      f"L-OpInf r={r}": [rom_field(k) for k in gif_steps]},
                     magnify=magnify, titles=[f"t = {k * dt:.2f} s" for k in gif_steps])
    return len(pts), volume.n_points


def _reduced_input(nm, V, basis, state_map, comm):
    """V^T (b_left - b_right): the Galerkin input vector of u (pressures +u / -u)."""
    from dolfinx_lopinf.fem.state import owned_global_dofs

    W = state_map.to_dofs(basis)
    owned = owned_global_dofs(V)
    b = nm.inputs[0].array[: len(owned)] - nm.inputs[1].array[: len(owned)]
    return comm.allreduce(W[owned].T @ b)[:, None]


if __name__ == "__main__":
    main()  # one rank failing aborts the job: the package's excepthook (dolfinx_lopinf._mpi_abort)
