"""Euler-Bernoulli beam: a Lagrangian ROM learned from a FEniCSx simulation.

    python demos/beam.py [--quick] [--out DIR]

1. The physics is one line of UFL - the Lagrangian density 1/2 mu w_t^2 - 1/2 EI w_xx^2 -
   on cubic Hermite elements (200 nodes, state [w; theta] in R^400, simply supported).
2. The FOM is the midpoint variational integrator derived from it (dt = 1e-5 s). We record
   full states to t = 0.18 s and only the midpoint deflection to t = 3 s.
3. The inference sees only the snapshot arrays of the training window [0, 0.03] s:
   block-diagonal POD (w and theta), 8th-order finite differences, and a symmetric positive
   definite Kh (L-OpInf). ``lopinf_del`` fits the same SPD Kh to the midpoint scheme's own
   discrete Euler-Lagrange relation (``ddt.variational_data``) instead of 8th-order
   differences. Beside them: standard OpInf (unconstrained Kh) and the intrusive Galerkin ROM
   (V^T M V, V^T K V from our FOM), in the same basis.
4. Every ROM is integrated with the same midpoint scheme and scored: state error on the
   training and test windows, FOM energy error to t = 2 s, midpoint deflection to t = 3 s.
5. The peer, when ``opinf`` is installed (``pip install 'dolfinx_lopinf[peers]'``): opinf's
   first-order model dx/dt = A x on x = [q; q_t] (2r states), fitted the way its tutorials
   fit it (``dolfinx_lopinf.studies.peers``): its own POD of the scaled [q; q_t] (its randomized
   SVD, seeded) in the Euclidean rows, the row's mass-orthonormal basis for q and q_t in the
   others; its 6th-order differences; its regulariser search. Integrated exactly (matrix
   exponential) and scored with the same metrics: rows ``opinf_peer`` under ``peer_roms`` in
   metrics.json, peer_error_vs_r.png, peer_energy_error.png.

Writes DIR/metrics.json and DIR/*.png. ``--quick`` shortens windows and the r sweep.
"""

from __future__ import annotations

import time

import numpy as np
from tqdm.auto import tqdm

import dolfinx_lopinf as lo
from dolfinx_lopinf.studies import peers
from dolfinx_lopinf.viz import render
from dolfinx_lopinf.fem._dolfinx import MPI
from dolfinx_lopinf.fem.state import output_matrix_in_state
from dolfinx_lopinf.fem.intrusive import dense_state_matrix
from dolfinx_lopinf.scenes import beam as scene
from dolfinx_lopinf.studies import harness

FULL = dict(t_train=scene.T_TRAIN, t_end=scene.T_END, t_energy=2.0, t_long=3.0,
            r_values=list(range(2, 21, 2)), r_plot=20, every_long=10)
QUICK = dict(t_train=0.01, t_end=0.04, t_energy=0.2, t_long=0.3,
             r_values=[4, 8], r_plot=8, every_long=10)


def main(argv=None):
    args = harness.parse(__doc__, argv, out="results/beam", quick="short windows, r in {4, 8}")
    cfg = QUICK if args.quick else FULL
    out = args.out
    comm = MPI.COMM_WORLD
    root = harness.is_root(comm)
    if root:
        out.mkdir(parents=True, exist_ok=True)
    dt = scene.DT

    # --- FOM -------------------------------------------------------------------------------
    beam = scene.build(200, comm)
    q0, v0 = beam.initial_state()
    snaps, info = lo.run(beam.system, q0, v0, dt, cfg["t_long"], state_until=cfg["t_end"],
                         state_map=beam.state_map, output_matrix=beam.output_matrix)
    E_mid = output_matrix_in_state(beam.system.V, beam.output_matrix, beam.state_map)
    if root:
        print(f"FOM: {info['steps']} steps to t = {cfg['t_long']} s in {info['seconds']:.1f} s, "
              f"energy drift {info['energy_drift']:.2e} (relative, to t = {cfg['t_end']} s)")
        train = snaps.window(0.0, cfg["t_train"])
        test = snaps.window(cfg["t_train"], cfg["t_end"])

    # --- basis and reduced data: only the training snapshots -------------------------------
    # Two bases, both from the training snapshots: the paper's block-diagonal Euclidean POD
    # (strictly black box) and a mass-orthonormal POD (V^T M V = I, so the reduced mass that
    # L-OpInf fixes to I is exact; it uses the FOM's mass matrix, which a black box lacks).
    # ROM work is small and runs on rank 0; every rank takes part in the Galerkin sums.
    mass = dense_state_matrix(beam.system.mass_form, beam.system.V, beam.state_map)
    r_max = max(cfg["r_values"])
    bases = comm.bcast({"euclidean-block": lo.pod(train.Q, r_max, blocks=train.blocks),
                        "mass-orthonormal": lo.pod(train.Q, r_max, weight=mass)} if root else None)
    # the opinf peer (optional): its FOM energy needs the stiffness matrix too
    with_peer = peers.have_opinf()
    stiffness = dense_state_matrix(beam.system.stiffness_form, beam.system.V, beam.state_map) \
        if with_peer else None
    peer_seconds, peer_pod = 0.0, {}
    if root and not with_peer:
        print(f"opinf not installed: {peers.INSTALL_HINT} (the opinf_peer rows are skipped)")
    elif root:  # opinf's own POD of the scaled [q; q_t], one (randomized, seeded) SVD for all r
        t0 = time.perf_counter()
        peer_pod = dict(zip(cfg["r_values"], peers.opinf_first_order(
            train.Q, train.times, cfg["r_values"], velocities=train.V, basis="stacked",
            svdsolver="randomized")))
        peer_seconds += time.perf_counter() - t0
    rows, peer_rows, traj_plot = [], [], {}
    for r in tqdm(cfg["r_values"], desc="ROMs", unit="r", disable=not root):
        for basis_name, full_basis in bases.items():
            basis = full_basis.truncate(r)
            galerkin = lo.fem.galerkin_rom(beam.system, basis.V, beam.state_map)
            if root:
                new_rows, trajs = _fit_and_score(basis, galerkin, train, test, snaps, cfg, dt)
                rows += [dict(row, basis=basis_name) for row in new_rows]
                if with_peer:
                    t0 = time.perf_counter()
                    peer = peer_pod[r] if basis_name == "euclidean-block" else peers.opinf_first_order(
                        train.Q, train.times, r, velocities=train.V, basis=basis)
                    row, trajs["opinf_peer"] = _score_peer(peer, train, test, snaps, cfg, dt, mass,
                                                           stiffness)
                    peer_rows.append(dict(row, basis=basis_name))
                    peer_seconds += time.perf_counter() - t0
                if r == cfg["r_plot"]:
                    traj_plot[basis_name] = trajs
    if not root:
        return None
    metrics = harness.metrics(
        "beam", error="state", quick=args.quick, roms=rows,
        n_dofs=int(snaps.n_states), dt=dt, t_train=cfg["t_train"],
        t_end=cfg["t_end"], t_energy=cfg["t_energy"], t_long=cfg["t_long"],
        fom_seconds=info["seconds"], fom_steps=info["steps"],
        fom_seconds_to_t_end=info["seconds_to_state_until"],
        fom_energy_drift=info["energy_drift"],
        energy_error_definition="max over t <= t_energy of |E(V qh, V vh) - E(V qh0, V vh0)| / E(V qh0, V vh0), FOM energy",
        # opinf's first-order model (dolfinx_lopinf.studies.peers), scored as the rows above; empty
        # without opinf. peer_seconds: everything the peer rows cost (fits, POD, runs, scores)
        peer_roms=peer_rows,
        peer={"package": "opinf", "installed": with_peer, "seconds": peer_seconds,
                 "install": peers.INSTALL_HINT,
                 "model": "ContinuousModel('A') on x = [q; q_t] (2r states), L2Solver, "
                          "regulariser by ROM.fit_regselect_continuous over logspace(-12, 2, 15); "
                          "ord6 finite differences; each variable scaled to max |.| = 1; "
                          "integrated exactly (expm)",
                 "basis": {"euclidean-block": "opinf PODBasis(2r, svdsolver='randomized') of "
                                              "the scaled [q; q_t]",
                           "mass-orthonormal": "the row's mass-orthonormal basis for q and q_t"}})
    harness.write_metrics(out, metrics)
    _figures(out, cfg, snaps, beam, traj_plot, rows, E_mid, dt)
    if peer_rows:
        _peer_figures(out, cfg, traj_plot, rows, peer_rows)
    order = list(bases)
    _summary(sorted(rows + peer_rows, key=lambda x: (x["r"], order.index(x["basis"]))), cfg)
    if with_peer:
        print(f"opinf peer rows: {peer_seconds:.1f} s in all")
    return metrics


def _fit_and_score(basis, galerkin, train, test, snaps, cfg, dt):
    """Fit L-OpInf and standard OpInf in ``basis``, add the Galerkin ROM, simulate all three
    with the midpoint VI and score them (relative state errors on the training and test
    windows, the energy error, the midpoint deflection)."""
    Qh_all = basis.project(train.Q)
    Qh, _, ddQh = lo.core.derivatives(Qh_all, train.times)
    Qbar, D2 = lo.core.ddt.variational_data(Qh_all, train.times)  # midpoint-DEL-consistent data
    fits, roms = {}, {"intrusive": galerkin}
    for method, infer, data in (("lopinf", lo.core.infer_mechanical, (Qh, ddQh)),
                                ("lopinf_del", lo.core.infer_mechanical, (Qbar, D2)),
                                ("opinf", lo.core.infer_opinf, (Qh, ddQh))):
        t0 = time.perf_counter()
        fits[method] = infer(data[0], None, data[1], damping=False)
        # standard OpInf's Kh is neither symmetric nor definite by design: no structure check
        roms[method] = lo.core.LagrangianROM(K=fits[method].K, lagrangian=None if method != "opinf" else False,
                                        meta={"infer_seconds": time.perf_counter() - t0})
    qh0, vh0 = basis.project(snaps.Q[:, 0]), basis.project(snaps.V[:, 0])
    E_ref = _fom_energy(galerkin, qh0[:, None], vh0[:, None])[0]
    n_steps, n_long = int(round(cfg["t_end"] / dt)), int(round(cfg["t_long"] / dt))
    k_train = len(train.times)
    rows, trajs = [], {}
    for method in ("lopinf", "lopinf_del", "opinf", "intrusive"):
        rom = roms[method]
        short = rom.simulate(qh0, vh0, dt, n_steps)
        long = rom.simulate(qh0, vh0, dt, n_long, every=cfg["every_long"])
        Q_rom = basis.reconstruct(short.Qh)
        energy_err = np.abs(_fom_energy(galerkin, long.Qh, long.Vh) - E_ref) / abs(E_ref)
        window = long.times <= cfg["t_energy"] + 1e-12
        row = harness.rom_row(
            method, basis.r,
            train_error=lo.relative_error(train.Q, Q_rom[:, :k_train]),
            test_error=lo.relative_error(test.Q, Q_rom[:, k_train - 1:]),
            stable=harness.stable(long.Qh, energy_err[window]),
            projection_error_train=basis.projection_error(train.Q),
            projection_error_test=basis.projection_error(test.Q),
            max_energy_error=float(np.nanmax(energy_err[window])),
            max_energy_error_t_long=float(np.nanmax(energy_err)),
            infer_seconds=float(rom.meta.get("infer_seconds", 0.0)),
            rom_seconds=short.seconds, rom_backend=short.backend,
            rom_seconds_numpy=rom.simulate(qh0, vh0, dt, n_steps, backend="numpy").seconds,
            rom_seconds_long=long.seconds)
        if method in fits:
            cert = fits[method].certificate
            row.update(solver=cert["solver"], min_eig_K=cert["min_eig_K"],
                       symmetry_error=cert["symmetry_error"],
                       fit_relative_residual=cert["relative_residual"])
        rows.append(row)
        trajs[method] = (short, long, energy_err, basis)
    return rows, trajs


def _score_peer(peer, train, test, snaps, cfg, dt, mass, stiffness):
    """The opinf peer scored as _fit_and_score scores the ROMs: the same windows and initial
    state, the FOM energy of its reconstructed state (relative to that of its reconstructed
    initial state) to t_energy and t_long, the same stability test."""
    n_steps, n_long, every = int(round(cfg["t_end"] / dt)), int(round(cfg["t_long"] / dt)), cfg["every_long"]
    q0, v0 = snaps.Q[:, 0], snaps.V[:, 0]
    short = peer.predict(q0, v0, np.arange(n_steps + 1) * dt, velocities=False)
    long = peer.predict(q0, v0, np.arange(n_long // every + 1) * (every * dt), full=False)
    energy = peer.energy(long.Xh, mass, stiffness)
    with np.errstate(all="ignore"):
        energy_err = np.abs(energy - energy[0]) / abs(energy[0])
    window = long.times <= cfg["t_energy"] + 1e-12
    k_train = len(train.times)
    row = harness.rom_row(
        "opinf_peer", peer.r,
        train_error=lo.relative_error(train.Q, short.Q[:, :k_train]),
        test_error=lo.relative_error(test.Q, short.Q[:, k_train - 1:]),
        stable=harness.stable(long.Xh, energy_err[window]),
        projection_error_train=peer.projection_error(train.Q, train.V),
        projection_error_test=peer.projection_error(test.Q, test.V),
        max_energy_error=float(np.nanmax(energy_err[window])),
        max_energy_error_t_long=float(np.nanmax(energy_err)),
        infer_seconds=peer.fit_seconds, rom_seconds=short.seconds, rom_seconds_long=long.seconds,
        regularizer=peer.regularizer, reduced_states=2 * peer.r,
        peer_basis=peer.basis_kind, velocity_source=peer.velocity_source)
    return row, (short, long, energy_err, None)


def _fom_energy(galerkin, Qh, Vh):
    """FOM energy of reconstructed states: 1/2 vh^T (V^T M V) vh + 1/2 qh^T (V^T K V) qh."""
    return galerkin.energy(Qh, Vh)


def _figures(out, cfg, snaps, beam, traj_by_basis, rows, E_mid, dt):
    r = cfg["r_plot"]
    traj = traj_by_basis["euclidean-block"]
    short_l, long_l, _, basis = traj["lopinf"]
    short_m, long_m, _, basis_m = traj_by_basis["mass-orthonormal"]["lopinf"]
    # Beam shapes: FOM vs L-OpInf (both bases) at several times up to t_end.
    times = [cfg["t_train"], 0.5 * (cfg["t_train"] + cfg["t_end"]), cfg["t_end"]]
    cols = [int(round(t / dt)) for t in times]
    w = snaps.blocks["w"]
    shapes = {"FOM": snaps.Q[w][:, cols],
              f"L-OpInf r={r} (block POD)": basis.reconstruct(short_l.Qh[:, cols], rows=w),
              f"L-OpInf r={r} (M-orth. POD)": basis_m.reconstruct(short_m.Qh[:, cols], rows=w)}
    render.beam_shapes(out / "beam_shapes.png", beam.x_nodes, shapes, times,
                       title="deflection magnified; training ends at t = %.2f s" % cfg["t_train"])
    windows = (("train_error", f"train [0, {cfg['t_train']:g}] s"),
               ("test_error", f"test [{cfg['t_train']:g}, {cfg['t_end']:g}] s"))
    for name, label in (("euclidean-block", "block-diagonal Euclidean POD (black box)"),
                        ("mass-orthonormal", "mass-orthonormal POD (uses M)")):
        render.error_vs_r(out / f"error_vs_r_{name}.png", [x for x in rows if x["basis"] == name],
                          series=windows, title=f"beam: relative state error of each ROM against r, "
                                                f"{label}")
    tl = long_l.times
    sel = tl <= cfg["t_energy"] + 1e-12
    series = {f"{name} r={r}": traj[key][2][sel] for key, name in
              (("lopinf", "L-OpInf"), ("opinf", "standard OpInf"), ("intrusive", "intrusive"))}
    series[f"L-OpInf r={r}, M-orth. POD"] = traj_by_basis["mass-orthonormal"]["lopinf"][2][sel]
    render.curves(out / "energy_error.png", tl[sel], series, ylabel="relative FOM energy error",
                  logy=True, vline=cfg["t_train"], colors=["C0", "C3", "C2", "C1"],
                  title="beam: relative FOM energy error of the reconstructed ROM state "
                        "(block POD unless noted)")
    y_t = {"FOM": snaps.output_times, f"L-OpInf r={r}": tl, f"standard OpInf r={r}": tl}
    y = {"FOM": snaps.Y[0], f"L-OpInf r={r}": (E_mid @ basis.V @ long_l.Qh)[0],
         f"standard OpInf r={r}": (E_mid @ basis.V @ traj["opinf"][1].Qh)[0]}
    render.curves(out / "midpoint_deflection.png", y_t, y, ylabel="w(l/2, t) [m]",
                  vline=cfg["t_train"], title="beam: midpoint deflection w(l/2, t), FOM and ROMs (block POD)")
    err = {f"{k}": np.abs(np.interp(tl, snaps.output_times, snaps.Y[0]) - v)
           / np.abs(snaps.Y[0]).max() for k, v in list(y.items())[1:]}
    render.curves(out / "midpoint_deflection_error.png", tl, err, logy=True, vline=cfg["t_train"],
                  colors=["C0", "C3"],
                  ylabel="|w_ROM - w_FOM| / max|w_FOM|", title="beam: midpoint deflection error of the ROMs (block POD)")


def _peer_figures(out, cfg, traj_by_basis, rows, peer_rows):
    """The opinf peer beside our ROMs: test error against r, and the energy error at r_plot."""
    def series(method, basis):
        sel = sorted((x for x in rows + peer_rows if x["method"] == method and x["basis"] == basis),
                     key=lambda x: x["r"])
        return [x["r"] for x in sel], [min(x["test_error"], 1e3) for x in sel]

    curves = {"L-OpInf, block POD": ("lopinf", "euclidean-block"),
              "standard OpInf, block POD": ("opinf", "euclidean-block"),
              "opinf peer, its POD of [q; q_t]": ("opinf_peer", "euclidean-block"),
              "intrusive, M-orth. POD": ("intrusive", "mass-orthonormal"),
              "L-OpInf, M-orth. POD": ("lopinf", "mass-orthonormal"),
              "opinf peer, M-orth. POD": ("opinf_peer", "mass-orthonormal")}
    data = {label: series(*key) for label, key in curves.items()}
    render.curves(out / "peer_error_vs_r.png", {k: v[0] for k, v in data.items()},
                  {k: v[1] for k, v in data.items()}, xlabel="reduced dimension r (peer: 2r states)",
                  ylabel="relative state error, test window", logy=True,
                  colors=["C0", "C3", "C6", "C2", "C9", "C8"], markers=True,
                  title="beam: opinf's first-order model (peer) beside our ROMs")
    r = cfg["r_plot"]
    t, e = {}, {}
    for basis, tag in (("euclidean-block", "block POD"), ("mass-orthonormal", "M-orth. POD")):
        for method, name in (("lopinf", "L-OpInf"), ("opinf_peer", "opinf peer")):
            long, energy_err = traj_by_basis[basis][method][1], traj_by_basis[basis][method][2]
            sel = long.times <= cfg["t_energy"] + 1e-12
            label = f"{name} r={r}, {tag}"
            t[label], e[label] = long.times[sel], energy_err[sel]
    render.curves(out / "peer_energy_error.png", t, e, ylabel="relative FOM energy error", logy=True,
                  vline=cfg["t_train"], colors=["C0", "C6", "C9", "C8"],
                  title="FOM energy error of the reconstructed state: L-OpInf and the opinf peer")


def _summary(rows, cfg):
    harness.summary(rows, [("basis", "basis"), ("method", "method"), ("r", "r"),
                           ("train_error", "train"), ("test_error", "test"),
                           ("projection_error_test", "proj test"),
                           ("max_energy_error", "energy err"), ("infer_seconds", "infer s"),
                           ("rom_seconds", "rom s"), ("stable", "stable")],
                    widths=[16, 10, 3, 9, 9, 9, 10, 9, 9, 6])


if __name__ == "__main__":
    main()
