"""Sine-Gordon: a gray-box Lagrangian ROM of a nonlinear wave, learned from its UFL Lagrangian.

    python demos/sine_gordon.py [--quick] [--out DIR]

1. The user writes the density 1/2 q_t^2 - 1/2 q_x^2 - (1 - cos q) in UFL (P1, lumped mass,
   a closed periodic mesh of 2,000 points on [-20, 20)); the FOM is the midpoint
   variational integrator with PETSc SNES Newton at every step, dt = 0.005, to T = 25.
   It is checked against the exact kink-antikink solution 4 arctan(t / cosh x).
2. The nonlinear potential U(q) = 1 - cos q is found in the form itself
   (:mod:`dolfinx_lopinf.fem.nonlinear`) and f_nl = U' = sin is evaluated pointwise on the
   snapshots - nothing else about the discretisation reaches the inference.
3. POD of [Q, F_nl] on the training window [0, 5]; L-OpInf fits a symmetric Kh in
   qh_tt = Kh qh - V^T f_nl(V qh) (Lyapunov solve); beside it standard OpInf (unconstrained
   Kh) and the intrusive Galerkin ROM (V^T K V from our FOM). ``lopinf_nsd`` adds Kh <= 0
   (the reduced Laplacian is negative semidefinite) to the paper's symmetry constraint.
4. Every ROM runs the midpoint VI with a reduced Newton solve; we score state errors on
   [0, 5] and [5, 25], the FOM energy of the reconstruction to T = 105 for r = 12, 14.
"""

from __future__ import annotations

import time

import numpy as np
from tqdm.auto import tqdm

import dolfinx_lopinf as lo
from dolfinx_lopinf.fem import nonlinear
from dolfinx_lopinf.viz import render
from dolfinx_lopinf.fem._dolfinx import MPI
from dolfinx_lopinf.fem.intrusive import dense_state_matrix
from dolfinx_lopinf.scenes import sine_gordon as scene
from dolfinx_lopinf.studies import harness

FULL = dict(n=scene.N_POINTS, t_train=scene.T_TRAIN, t_end=scene.T_END, t_long=scene.T_LONG,
            r_values=list(range(1, 15)), r_long=[12, 14], shapes_at=[5.0, 15.0, 25.0], every=10)
QUICK = dict(n=400, t_train=2.0, t_end=6.0, t_long=12.0, r_values=[4, 8], r_long=[8],
             shapes_at=[2.0, 4.0, 6.0], every=10)


def main(argv=None):
    args = harness.parse(__doc__, argv, out="results/sine_gordon", quick="n = 400, short windows, r in {4, 8}")
    cfg = QUICK if args.quick else FULL
    comm = MPI.COMM_WORLD
    out = args.out
    dt = scene.DT

    # --- FOM from the UFL Lagrangian -------------------------------------------------------
    sg = scene.build(cfg["n"], comm)
    nl = nonlinear.identify(sg.system)  # U(q) found in the form, g = U' compiled to numpy
    q0 = np.zeros_like(sg.x_local)
    v0 = 4.0 / np.cosh(sg.x_local)
    # states are recorded to t_end; the FOM itself runs on to t_long for its energy bound
    snaps, info = lo.run(sg.system, q0, v0, dt, cfg["t_long"], state_until=cfg["t_end"],
                         state_map=sg.state_map, record_velocity=False, energy_every=cfg["every"],
                         energy_until=cfg["t_long"])
    # the FOM's linear operator, only to build the intrusive ROM and to score energies:
    # -d2L/dq2 at q = 0 is S + M g'(0); K_fom = -M^-1 S  (q_tt = K_fom q - f_nl(q))
    sg.system.q.x.array[:] = 0.0  # linearise about q = 0
    stiff = dense_state_matrix(sg.system.stiffness_form, sg.system.V, sg.state_map)
    mass = dense_state_matrix(sg.system.mass_form, sg.system.V, sg.state_map)
    v0s = v0_state(sg, v0)  # collective gather: every rank, before the ROM work on rank 0
    if not harness.is_root(comm):
        return None
    out.mkdir(parents=True, exist_ok=True)
    h = float(np.mean(np.diag(mass)))
    K_fom = -(stiff - mass * nl.dg(np.zeros(1))[0]) / h
    exact_err = float(np.abs(snaps.Q[:, -1] - scene.exact_kink_antikink(sg.x, cfg["t_end"])).max())
    print(f"FOM: n = {snaps.n_states}, {info['steps']} Newton steps to t = {cfg['t_long']} in "
          f"{info['seconds']:.1f} s, max relative energy error {info['energy_drift']:.1e}, "
          f"max error vs exact solution at "
          f"t = {cfg['t_end']}: {exact_err:.2e}")

    # --- gray-box data: states and f_nl(states) only ---------------------------------------
    train = snaps.window(0.0, cfg["t_train"])
    F_train = nl(train.Q)
    every = cfg["every"]
    n_steps = int(round(cfg["t_end"] / dt))
    k_train = int(round(cfg["t_train"] / dt)) // every  # index of t_train in subsampled arrays
    Q_sub = snaps.Q[:, ::every]
    r_max = max(cfg["r_values"])
    t_pod = time.perf_counter()
    full_basis = lo.pod(np.hstack([train.Q, F_train]), r_max)
    pod_s = time.perf_counter() - t_pod
    rows, keep = [], {}
    for r in tqdm(cfg["r_values"], desc="ROMs", unit="r"):
        basis = full_basis.truncate(r)
        V = basis.V
        for method, (K, t_fit) in _fit_operators(V, train, F_train, K_fom).items():
            rom = lo.core.WaveROM(K=K, V=V, g=nl.g, dg=nl.dg, U=nl.U, meta={"method": method})
            row = {"method": method, "r": r, "infer_seconds": t_fit + pod_s,
                   "projection_error_train": basis.projection_error(train.Q),
                   "projection_error_test": basis.projection_error(Q_sub[:, k_train:])}
            try:
                tr = rom.simulate(V.T @ snaps.Q[:, 0], V.T @ v0s, dt, n_steps, every=every)
                Q_rom = V @ tr.Qh
                row.update(train_error=lo.relative_error(Q_sub[:, :k_train + 1], Q_rom[:, :k_train + 1]),
                           test_error=lo.relative_error(Q_sub[:, k_train:], Q_rom[:, k_train:]),
                           rom_seconds=tr.seconds, rom_backend=tr.backend,
                           rom_seconds_numpy=rom.simulate(V.T @ snaps.Q[:, 0], V.T @ v0s, dt, n_steps,
                                                          every=every, backend="numpy").seconds,
                           stable=harness.stable(tr.Qh))
                keep[(method, r)] = (rom, tr)
            except (RuntimeError, FloatingPointError, np.linalg.LinAlgError) as exc:
                row.update(train_error=float("inf"), test_error=float("inf"), rom_seconds=None,
                           stable=False, failure=str(exc)[:200])
            rows.append(row)

    # --- long runs: FOM energy of the reconstructed state to t_long -------------------------
    energy_curves = _long_runs(rows, keep, snaps.Q[:, 0], v0s, K_fom, nl, h, cfg)
    for row in rows:
        row.setdefault("max_energy_error", None)

    # --- hyper-reduction (ECSW): the reduced force from a few weighted points ----------------
    r_h = max(cfg["r_long"])
    rom_full, tr_full = keep[("lopinf", r_h)]
    hr = hyper_reduce(rom_full, train, dt, cfg)
    # the simplified Newton (Jacobian kept until convergence slows; same tolerance): the ECSW
    # ROM's fast path (issue 16); the full-nonlinearity rows above use a fresh Jacobian
    tr_h = hr.simulate(rom_full.V.T @ snaps.Q[:, 0], rom_full.V.T @ v0s, dt, n_steps, every=every,
                       jacobian="lazy")
    Q_h = rom_full.V @ tr_h.Qh
    hyper_row = harness.rom_row(
        "lopinf_ecsw", r_h, points=int(hr.V.shape[0]),
        train_error=lo.relative_error(Q_sub[:, :k_train + 1], Q_h[:, :k_train + 1]),
        test_error=lo.relative_error(Q_sub[:, k_train:], Q_h[:, k_train:]),
        rom_seconds=tr_h.seconds, rom_backend=tr_h.backend,
        rom_seconds_numpy=hr.simulate(rom_full.V.T @ snaps.Q[:, 0], rom_full.V.T @ v0s, dt, n_steps,
                                      every=every, backend="numpy", jacobian="lazy").seconds,
        jacobian="lazy",
        rom_seconds_full_nonlinearity=tr_full.seconds,
        infer_seconds=hr.meta["ecsw_seconds"], stable=harness.stable(tr_h.Qh),
        projection_error_test=rows[-1]["projection_error_test"], max_energy_error=None)
    rows.append(hyper_row)
    scaling = step_time_vs_n(cfg, r_h) if not args.quick else []

    metrics = harness.metrics(
        "sine_gordon", error="state", quick=args.quick, roms=rows,
        n_dofs=int(snaps.n_states), dt=dt, t_train=cfg["t_train"], t_end=cfg["t_end"],
        t_long=cfg["t_long"], fom_seconds=info["seconds"], fom_steps=info["steps"],
        fom_energy_drift_definition="max |E - E0| / E0 to t_long",
        fom_seconds_to_t_end=info["seconds_to_state_until"],
        fom_energy_drift=info["energy_drift"], fom_error_vs_exact=exact_err,
        energy_error_definition="max over t <= t_long of |E(V qh, V vh) - E(0)| / E(0), FOM energy",
        hyper_reduction_step_time_vs_n=scaling)
    harness.write_metrics(out, metrics)
    _figures(out, cfg, sg, snaps, keep, rows, energy_curves, dt, info["seconds_to_state_until"])
    harness.summary(rows, [("method", "method"), ("r", "r"), ("train_error", "train"),
                           ("test_error", "test"), ("projection_error_test", "proj test"),
                           ("max_energy_error", "energy"), ("rom_seconds", "rom s"),
                           ("stable", "stable")], widths=[11, 3, 9, 9, 9, 9, 9, 6])
    return metrics


def _fit_operators(V, train, F_train, K_fom):
    """Kh of each method in basis V from the training states and forces (8th-order
    differences): L-OpInf (Kh symmetric), L-OpInf with Kh <= 0, standard OpInf (least
    squares), intrusive (V^T K V). Returns {method: (Kh, fit seconds)}."""
    Qh, _, ddQh = lo.core.derivatives(V.T @ train.Q, train.times)
    Fh = (V.T @ F_train)[:, 4:-4]
    fits = {}
    for method, fit in (("lopinf", lambda: lo.core.infer_wave(Qh, ddQh, Fh).K),
                        ("lopinf_nsd", lambda: lo.core.infer_wave(Qh, ddQh, Fh, negative_semidefinite=True).K),
                        ("opinf", lambda: np.linalg.lstsq(Qh.T, (ddQh + Fh).T, rcond=None)[0].T)):
        t0 = time.perf_counter()
        K = fit()
        fits[method] = (K, time.perf_counter() - t0)
    fits["intrusive"] = (V.T @ K_fom @ V, 0.0)
    return fits


def _long_runs(rows, keep, q0, v0s, K_fom, nl, h, cfg):
    """Each kept ROM at r in r_long run to t_long: its rows get max_energy_error (the FOM
    energy of the reconstructed state) and stable updated. Returns the energy curves."""
    dt, every = scene.DT, cfg["every"]
    n_long = int(round(cfg["t_long"] / dt))
    energy_curves = {}
    for r in cfg["r_long"]:
        for method in ("lopinf", "lopinf_nsd", "opinf", "intrusive"):
            if (method, r) not in keep:
                continue
            rom = keep[(method, r)][0]
            V = rom.V
            try:
                tr = rom.simulate(V.T @ q0, V.T @ v0s, dt, n_long, every=4 * every)
                E = fom_energy(tr.Qh, tr.Vh, V, K_fom, nl, h)
                err = np.abs(E - E[0]) / abs(E[0])
            except RuntimeError as exc:
                err, tr = np.array([np.inf]), None
                print(f"{method} r={r}: {exc}")
            energy_curves[(method, r)] = (tr.times if tr is not None else np.zeros(1), err)
            for row in rows:
                if row["method"] == method and row["r"] == r:
                    row["max_energy_error"] = float(np.max(err))
                    row["stable"] = row["stable"] and harness.stable(np.zeros(0), err)
    return energy_curves


def hyper_reduce(rom, train, dt, cfg, tol=1e-5):
    """ECSW sampling of sum_i U(V_i qh) on training states; returns the hyper-reduced ROM."""
    from dolfinx_lopinf.core import hyper

    t0 = time.perf_counter()
    Qh = rom.V.T @ train.Q[:, :: max(1, train.Q.shape[1] // 200)]
    sample = hyper.ecsw(rom.V, Qh, rom.g, tol=tol)
    seconds = time.perf_counter() - t0
    return lo.core.WaveROM(K=rom.K, V=rom.V[sample.rows], g=rom.g, dg=rom.dg, U=rom.U,
                      weights=sample.weights,
                      meta={"method": "lopinf_ecsw", "ecsw_seconds": seconds,
                            "ecsw_residual": sample.residual})


def step_time_vs_n(cfg, r, sizes=(2000, 20000), n_steps=2000):
    """ROM step time with the full and the hyper-reduced nonlinearity for several n
    (each n: FOM on the training window, POD of [Q, F], L-OpInf, ECSW)."""
    out = []
    for n in sizes:
        sg = scene.build(n, MPI.COMM_SELF)  # a serial ROM timing study, run on one rank
        nl = nonlinear.identify(sg.system)
        v0 = 4.0 / np.cosh(sg.x_local)
        snaps, info = lo.run(sg.system, np.zeros_like(v0), v0, scene.DT, cfg["t_train"],
                             state_map=sg.state_map, record_velocity=False, energy_every=0,
                             progress=False)
        F = nl(snaps.Q)
        V = lo.pod(np.hstack([snaps.Q, F]), r).V
        Qh, _, ddQh = lo.core.derivatives(V.T @ snaps.Q, snaps.times)
        K = lo.core.infer_wave(Qh, ddQh, (V.T @ F)[:, 4:-4], negative_semidefinite=True).K
        rom = lo.core.WaveROM(K=K, V=V, g=nl.g, dg=nl.dg, U=nl.U)
        hr = hyper_reduce(rom, snaps, scene.DT, cfg)
        vh0 = V.T @ v0_state(sg, v0)
        full = rom.simulate(np.zeros(r), vh0, scene.DT, n_steps)
        fast = hr.simulate(np.zeros(r), vh0, scene.DT, n_steps)
        out.append({"n": n, "fom_seconds_train_window": info["seconds"],
                    "step_us_full": 1e6 * full.seconds / n_steps,
                    "step_us_hyper": 1e6 * fast.seconds / n_steps, "points": int(hr.V.shape[0]),
                    "hyper_vs_full_error": lo.relative_error(V @ full.Qh, V @ fast.Qh)})
        print(f"n = {n}: ROM step {out[-1]['step_us_full']:.0f} us (all points) vs "
              f"{out[-1]['step_us_hyper']:.0f} us ({out[-1]['points']} ECSW points), "
              f"difference {out[-1]['hyper_vs_full_error']:.1e}")
    return out


def v0_state(sg, v0_local):
    """The initial velocity in state order (gathered)."""
    from dolfinx_lopinf.fem.state import gather_states

    n_owned = sg.system.V.dofmap.index_map.size_local
    gathered = gather_states(sg.system.V, v0_local[:n_owned, None], sg.state_map)
    return None if gathered is None else gathered[:, 0]  # None on ranks other than 0


def fom_energy(Qh, Vh, V, K_fom, nl, h):
    """FOM energy of V qh, V vh:  h [1/2 |V vh|^2 - 1/2 (V qh)^T K (V qh) + sum U(V qh)]."""
    Kr = V.T @ K_fom @ V
    Z = V @ Qh
    return h * (0.5 * np.sum((V @ Vh) ** 2, axis=0) - 0.5 * np.einsum("ik,ij,jk->k", Qh, Kr, Qh)
                + np.sum(nl.U(Z), axis=0))


def _figures(out, cfg, sg, snaps, keep, rows, energy_curves, dt, fom_seconds):
    render.error_vs_r(out / "error_vs_r.png", [r for r in rows if np.isfinite(r["test_error"])],
                      series=(("train_error", f"train [0, {cfg['t_train']:g}]"),
                              ("test_error", f"test [{cfg['t_train']:g}, {cfg['t_end']:g}]")),
                      title="sine-Gordon: relative state error of each ROM against r")
    r_show = max(cfg["r_long"])
    series = {}
    for t in cfg["shapes_at"]:
        k = int(round(t / dt))
        series[f"FOM t={t:g}"] = snaps.Q[:, k]
        rom, tr = keep[("lopinf", r_show)]
        j = int(round(t / (dt * cfg["every"])))
        series[f"L-OpInf r={r_show} t={t:g}"] = rom.V @ tr.Qh[:, j]
    render.wave_shapes(out / "wave_shapes.png", sg.x, series,
                       title=f"sine-Gordon: the wave q(x, t) of the FOM and of L-OpInf r={r_show} "
                             f"at t = {', '.join(f'{t:g}' for t in cfg['shapes_at'])} "
                             f"(training ends at t = {cfg['t_train']:g})")
    r_max = max(cfg["r_long"])
    shown = [(m, r) for (m, r) in energy_curves if r == r_max] + \
        [(m, r) for (m, r) in energy_curves if r != r_max and m == "lopinf_nsd"]
    names = {"lopinf": "L-OpInf", "lopinf_nsd": "L-OpInf, Kh<=0", "opinf": "standard OpInf",
             "intrusive": "intrusive"}
    render.curves(out / "energy_error.png",
                  {f"{names[m]} r={r}": energy_curves[(m, r)][0] for m, r in shown},
                  {f"{names[m]} r={r}": np.clip(energy_curves[(m, r)][1], 1e-16, 1e3) for m, r in shown},
                  ylabel="relative FOM energy error (clipped at 1e3)", logy=True,
                  vline=cfg["t_train"], colors=["C0", "C1", "C3", "C2", "C5"],
                  title="sine-Gordon: relative error of the FOM energy of the reconstructed ROM "
                        "state")
    fast = [r for r in rows if r["method"] == "lopinf_ecsw"]
    pts = {}
    for method in ("lopinf", "lopinf_nsd", "opinf", "intrusive"):
        sel = [r for r in rows if r["method"] == method and r["test_error"] < 10]
        pts[names[method]] = ([r["rom_seconds"] for r in sel], [r["test_error"] for r in sel])
    pts["L-OpInf + ECSW"] = ([r["rom_seconds"] for r in fast], [r["test_error"] for r in fast])
    # the same ROMs with the numpy reference loop (the points above use the compiled one when
    # numba is installed: rom_backend in metrics.json)
    for label, sel in (("L-OpInf, numpy loop", [r for r in rows if r["method"] == "lopinf"
                                                  and r["test_error"] < 10]),
                       ("L-OpInf + ECSW, numpy loop", fast)):
        pts[label] = ([r["rom_seconds_numpy"] for r in sel], [r["test_error"] for r in sel])
    render.speed_vs_error(out / "speed_vs_error.png", pts, fom_seconds=fom_seconds,
                          title=f"sine-Gordon: ROM wall time to t = {cfg['t_end']:g} against test "
                                f"error (blow-ups omitted)")


if __name__ == "__main__":
    main()
