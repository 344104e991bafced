"""Soft-robotic fishtail: a forced, damped Lagrangian ROM of 3D elasticity.

    python demos/fishtail.py [--quick] [--size small|default|large] [--out DIR] [--train sine|sigmoid]

1. Geometry from meshes/fishtail.py (gmsh): a silicone hull lofted through three ellipses, a
   carbon centre beam ending at the point of interest (0, 0, 0.21) m, two pressure chambers.
2. FOM from the UFL Lagrangian 1/2 rho |q_t|^2 - 1/2 sigma(q) : eps(q) on P2 tetrahedra, two
   materials, Rayleigh damping C = 1e-4 M + 2e-4 K, chamber pressures +u(t) / -u(t) (pre-
   pressure u_pre = 0: METHOD.md gives no value), Newmark dt = 1e-3 s to T = 2 s, for the four
   inputs (step, sine, ramp, sigmoid). Only the training window's states are kept; the POI
   output and the FOM energy are recorded for every step.
3. L-OpInf from the training arrays (sine on [0, 0.4] s by default): POD, 8th-order
   differences, Kh, Ch >= eps I and free Bh (one input channel), Eh by least squares; the
   intrusive Galerkin ROM beside it. ROMs run Newmark like the FOM.
4. Output error for every input (unseen ones included), energy tracking, 3D renders.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import dolfinx_lopinf as lo
from dolfinx_lopinf import render
from dolfinx_lopinf._dolfinx import MPI
from dolfinx_lopinf.fom import StateMap, gather_states, output_matrix_in_state
from dolfinx_lopinf.integrators import NewmarkIntegrator
from dolfinx_lopinf.intrusive import reduced_matrix
from dolfinx_lopinf.scenes import fishtail as scene

SIZES = {"small": 0.012, "default": 0.007, "large": 0.0028}
TRAIN_WINDOW = {"sine": 0.4, "sigmoid": 1.0}


def run_fom(tail, nm, u_fn, t_end, t_keep, comm, snap_steps=()):
    """Newmark to t_end; keep owned states to t_keep (and at ``snap_steps``, for renders),
    outputs and energy every step."""
    dt = scene.DT
    n_steps = int(round(t_end / dt))
    n_keep = int(round(t_keep / dt))
    n_owned = tail.system.V.dofmap.index_map.size_local * 3
    Q = np.empty((n_owned, n_keep + 1))
    Y, E = np.empty(n_steps + 1), np.empty(n_steps + 1)
    snaps = {}
    nm.initialize(tail.chamber_pressures(float(u_fn(0.0))))
    Q[:, 0] = 0.0
    Y[0], E[0] = 0.0, 0.0
    t0 = time.perf_counter()
    for k in range(1, n_steps + 1):
        nm.step(tail.chamber_pressures(float(u_fn(k * dt))))
        if k <= n_keep:
            Q[:, k] = nm.q.x.array[:n_owned]
        if k in snap_steps:
            snaps[k] = nm.q.x.array.copy()
        Y[k] = comm.allreduce(float((tail.output_matrix @ nm.q.x.array)[0]))
        E[k] = nm.energy()
    seconds = comm.allreduce(time.perf_counter() - t0, op=MPI.MAX)
    run_fom.snapshots = snaps
    return Q, Y, E, seconds


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small mesh, T = 0.6 s, r in {2, 4}")
    parser.add_argument("--size", choices=sorted(SIZES), default="default")
    parser.add_argument("--out", default="results/fishtail")
    parser.add_argument("--train", choices=sorted(TRAIN_WINDOW), default="sine")
    parser.add_argument("--basis", choices=["mass", "euclidean"], default="mass")
    args = parser.parse_args(argv)
    comm = MPI.COMM_WORLD
    out = Path(args.out)
    size = "small" if args.quick else args.size
    t_end = 0.6 if args.quick else scene.T_END
    t_train = TRAIN_WINDOW[args.train]
    inputs = ["sine", "step"] if args.quick else ["sine", "sigmoid", "ramp", "step"]
    r_values = [2, 4] if args.quick else [2, 4, 6, 8, 10]
    dt = scene.DT

    t0 = time.perf_counter()
    tail = scene.build(SIZES[size], comm)
    V = tail.system.V
    nm = NewmarkIntegrator(tail.system, dt, rayleigh=scene.RAYLEIGH, input_forms=tail.input_forms)
    setup_s = time.perf_counter() - t0
    n_dofs = V.dofmap.index_map.size_global * 3
    if comm.rank == 0:
        print(f"fishtail ({size}): {n_dofs} dofs, set-up {setup_s:.1f} s")
    state_map = StateMap.from_coordinates(V)
    fom = {}
    render_input = inputs[-1]  # an unseen input
    render_times = [0.15, 0.3, t_end] if args.quick else [0.15, 0.5, 1.0, 2.0]
    render_steps = [int(round(t / dt)) for t in render_times]
    gif_steps = list(range(int(round(t_end / dt)) // 40, int(round(t_end / dt)) + 1, int(round(t_end / dt)) // 40))
    for name in inputs:
        keep = t_train if name == args.train else 0.0
        steps = set(render_steps + gif_steps) if name == render_input else ()
        Q, Y, E, seconds = run_fom(tail, nm, scene.INPUTS[name], t_end, keep, comm, snap_steps=steps)
        fom[name] = dict(Q=gather_states(V, Q, state_map) if keep else None, Y=Y, E=E, seconds=seconds,
                         fields=run_fom.snapshots)
        if comm.rank == 0:
            print(f"FOM {name}: {int(round(t_end / dt))} steps in {seconds:.1f} s, "
                  f"max |y| = {np.abs(Y).max():.3e} m")

    # --- basis and operators from the training arrays only ---------------------------------
    # Mass-orthonormal POD by the method of snapshots (V^T M V = I, so the reduced mass that
    # L-OpInf fixes to I is exact): C = Q^T M Q, V = Q Psi diag(lambda)^-1/2. It uses the
    # FOM mass matrix (a black box would not give it); --basis euclidean is the paper's POD.
    train = fom[args.train]
    Q_train = comm.bcast(train["Q"] if comm.rank == 0 else None)
    if args.basis == "mass":
        MQ = apply_matrix(nm.M, V, Q_train, state_map)
        lam, Psi = np.linalg.eigh(Q_train.T @ MQ)
        order = np.argsort(lam)[::-1][: max(r_values)]
        V_all = Q_train @ Psi[:, order] / np.sqrt(lam[order])
        Qh_full = V_all.T @ MQ
    else:
        V_all = lo.pod(Q_train, max(r_values)).V
        Qh_full = V_all.T @ Q_train
    rows = []
    rom_plot = {}
    for r in r_values:
        Vr = V_all[:, :r]
        # intrusive Galerkin operators (collective), for comparison only
        Mg = reduced_matrix(nm.M, V, Vr, state_map)
        Kg = reduced_matrix(nm.K, V, Vr, state_map)
        Cg = reduced_matrix(nm.C, V, Vr, state_map)
        Bg = _reduced_input(nm, V, Vr, state_map, comm)
        Eg = output_matrix_in_state(V, tail.output_matrix, state_map) @ Vr  # true POI functional
        if comm.rank != 0:
            continue
        times = dt * np.arange(Q_train.shape[1])
        u_train = scene.INPUTS[args.train](times)
        Qh_all = Qh_full[:r]
        Qh, dQh, ddQh = lo.derivatives(Qh_all, times)
        t_fit = time.perf_counter()
        ops = lo.infer_mechanical(Qh, dQh, ddQh, u_train[None, 4:-4])
        Eh = lo.infer_output(Qh_all, train["Y"][None, : len(times)])
        infer_s = time.perf_counter() - t_fit
        lopinf = lo.LagrangianROM(K=ops.K, C=ops.C, B=ops.B, E=Eh, scheme="newmark")
        intrusive = lo.LagrangianROM(K=Kg, M=Mg, C=Cg, B=Bg, E=Eg, scheme="newmark")
        for method, rom in (("lopinf", lopinf), ("intrusive", intrusive)):
            row = {"method": method, "r": r, "infer_seconds": infer_s if method == "lopinf" else 0.0,
                   "output_errors": {}, "rom_seconds": {}}
            for name in inputs:
                n = int(round(t_end / dt))
                tr = rom.simulate(np.zeros(r), np.zeros(r), dt, n, inputs=lambda t: np.array([scene.INPUTS[name](t)]))
                y_fom = fom[name]["Y"]
                row["output_errors"][name] = lo.relative_error(y_fom, tr.Y[0])
                row["rom_seconds"][name] = tr.seconds
                e_rom = 0.5 * np.einsum("ik,ij,jk->k", tr.Vh, Mg, tr.Vh) + 0.5 * np.einsum("ik,ij,jk->k", tr.Qh, Kg, tr.Qh)
                row.setdefault("energy_errors", {})[name] = float(
                    np.abs(e_rom - fom[name]["E"]).max() / np.abs(fom[name]["E"]).max())
                if r == r_values[-1] or r == 2:
                    rom_plot[(method, r, name)] = (tr, Vr)
            row["train_error"] = row["output_errors"][args.train]
            row["test_error"] = max(v for k, v in row["output_errors"].items() if k != args.train)
            row["stable"] = bool(all(np.isfinite(v) for v in row["output_errors"].values()))
            if method == "lopinf":
                row.update(min_eig_K=ops.certificate["min_eig_K"], min_eig_C=ops.certificate["min_eig_C"],
                           solver=ops.certificate["solver"])
            rows.append(row)
    if comm.rank != 0:
        return None
    out.mkdir(parents=True, exist_ok=True)
    metrics = {"scene": "fishtail", "size": size, "n_dofs": int(n_dofs), "dt": dt,
               "t_train": t_train, "train_input": args.train, "t_end": t_end,
               "fom_seconds": {k: v["seconds"] for k, v in fom.items()},
               "fom_setup_seconds": setup_s, "u_pre": 0.0, "basis": args.basis,
               "roms": rows}
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    t = dt * np.arange(int(round(t_end / dt)) + 1)
    for name in inputs:
        series = {"FOM": fom[name]["Y"]}
        for (method, r, nm_), tr in rom_plot.items():
            if nm_ == name and method == "lopinf":
                series[f"L-OpInf r={r}"] = tr[0].Y[0]
        render.curves(out / f"poi_{name}.png", t, series, ylabel="tip displacement x [m]",
                      vline=t_train if name == args.train else None,
                      title=f"{name} input" + (" (training input)" if name == args.train else " (unseen)"),
                      colors=["C7", "C0", "C1", "C2"])
    if comm.size == 1:
        n_boundary, n_points = _renders(out, V, state_map, fom[render_input]["fields"], rom_plot,
                                        render_input, render_steps, gif_steps, r_values[-1], dt)
        metrics["render_reconstructed_points"] = {"boundary": int(n_boundary), "all": int(n_points)}
        (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    print(f"{'method':>10} {'r':>3} " + " ".join(f"{n:>9}" for n in inputs))
    for row in rows:
        print(f"{row['method']:>10} {row['r']:>3} " + " ".join(f"{row['output_errors'][n]:9.2e}" for n in inputs))
    return metrics


def _renders(out, V, state_map, fields, rom_plot, name, render_steps, gif_steps, r, dt):
    """FOM vs L-OpInf deformed fishtail (serial): stills at a few times and a GIF.

    Only the boundary is visible, so only the basis rows of the dofs on boundary facets are
    used: the ROM field is V[boundary rows] qh (partial reconstruction), never the full
    n-vector; interior points of the drawn grid stay at zero and are never seen.
    """
    import pyvista
    from dolfinx import plot

    from dolfinx_lopinf._dolfinx import dolfinx

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
    tr, Vr = rom_plot[("lopinf", r, name)]
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
                                 titles=[f"t = {k * dt:.2f} s (x{magnify:.0f})" for k in render_steps])
    render.animation(out / f"deformed_{name}.gif", volume,
                     {"FOM": [fom_field(k) for k in gif_steps],
                      f"L-OpInf r={r}": [rom_field(k) for k in gif_steps]},
                     magnify=magnify, titles=[f"t = {k * dt:.2f} s" for k in gif_steps])
    return len(pts), volume.n_points


def apply_matrix(A, V, X, state_map):
    """A X for a PETSc matrix and state-coordinate columns X (n, K) available on every rank;
    the result (n, K) in state coordinates on every rank."""
    from dolfinx_lopinf.fom import owned_global_dofs

    comm = V.mesh.comm
    W = state_map.to_dofs(X)
    owned = owned_global_dofs(V)
    x, y = A.createVecRight(), A.createVecLeft()
    out = np.zeros_like(W)
    for j in range(W.shape[1]):
        x.array[:] = W[owned, j]
        A.mult(x, y)
        out[owned, j] = y.array
    out = comm.allreduce(out)
    return out[state_map.order] / state_map.scale[:, None]


def _reduced_input(nm, V, basis, state_map, comm):
    """V^T (b_left - b_right): the Galerkin input vector of u (pressures +u / -u)."""
    from dolfinx_lopinf.fom import owned_global_dofs

    W = state_map.to_dofs(basis)
    owned = owned_global_dofs(V)
    b = nm.inputs[0].array[: len(owned)] - nm.inputs[1].array[: len(owned)]
    return comm.allreduce(W[owned].T @ b)[:, None]


if __name__ == "__main__":
    main()
