"""Large-deformation 3D cantilever: a polynomial Lagrangian ROM learned as one convex fit.

    python demos/svk_cantilever.py [--quick] [--out DIR]

1. FOM (:mod:`dolfinx_lopinf.scenes.svk_cantilever`): St. Venant-Kirchhoff (and neo-Hookean)
   cantilever, Q2 hexahedra, midpoint VI with PETSc SNES Newton, dt = 2e-3 s, a vertical body
   load a s(t) (ramp, hold, release, free vibration, Rayleigh damping). Runs at the training
   amplitudes (to t_train) and at unseen ones, smaller and larger (to t_end); the linear
   (small-strain) FOM at the largest amplitude shows what the nonlinearity does.
2. Mass-orthonormal POD of the training snapshots (reduced mass exactly I; M is the one FOM
   operator the fit uses, as in the fishtail and beam demos).
3. Four ROMs per r, all integrated by the midpoint VI with a reduced Newton step:
   * ``poly_lopinf``: U(q) = quadratic + cubic + quartic, C >= eps I, B - the gradient of one
     potential, fitted to the midpoint relation with U = m^T G m, G >= eps_g I (bounded below,
     coercive), Clarabel with its duality gap (:mod:`dolfinx_lopinf.core.polynomial`);
   * ``lopinf``: the paper's linear L-OpInf (``lo.infer_mechanical``) on the same relation;
   * ``intrusive``: the Galerkin polynomial ROM, its tensors from V^T F(V q) of the FOM at
     sampled q (exact for SVK, whose reduced force is a cubic polynomial; for neo-Hookean the
     best quartic-potential fit of the Galerkin force over the sampled region), C = alpha I +
     beta K_h, B = V^T b;
   * ``opinf_poly``: unconstrained polynomial OpInf (free force coefficients up to cubic, free
     C and B): no potential.
4. Scores: per unseen amplitude the state and tip errors over [0, t_end]; the energy of an
   undamped, unforced run 5x the training length from the last training state (the ROM's own
   energy and the FOM energy of the reconstruction, U_FOM(V q) = the intrusive potential on
   SVK); fit times, certificates, ROM and FOM times.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np

import dolfinx_lopinf as lo
from dolfinx_lopinf.core import polynomial as pl
from dolfinx_lopinf.core.io_atomic import plain
from dolfinx_lopinf.studies import harness
from dolfinx_lopinf.viz import render
from dolfinx_lopinf.fem._dolfinx import MPI
from dolfinx_lopinf.fem.fom import output_matrix_in_state
from dolfinx_lopinf.fem.intrusive import dense_state_matrix
from dolfinx_lopinf.scenes import svk_cantilever as scene

FULL = dict(cells=(10, 1, 1), t_train=1.0, t_end=1.5, train_amps=[100.0, 250.0],
            test_amps=[50.0, 175.0, 350.0], r_values=[4, 6, 8], long_factor=5,
            materials=["svk", "neo-hookean"])
QUICK = dict(cells=(6, 1, 1), t_train=0.8, t_end=1.0, train_amps=[100.0, 250.0],
             test_amps=[350.0], r_values=[4, 6], long_factor=5, materials=["svk"])
METHODS = ("poly_lopinf", "lopinf", "intrusive", "opinf_poly")
LABELS = {"poly_lopinf": "polynomial L-OpInf", "lopinf": "linear L-OpInf",
          "intrusive": "intrusive Galerkin", "opinf_poly": "polynomial OpInf (no potential)"}


def half_step_inputs(amp, n_steps, dt):
    """u(t_{k+1/2}) = a s(t_{k+1/2}), k = 0 .. n_steps-1, as a (1, n_steps) row."""
    return (amp * scene.profile(dt * (np.arange(n_steps) + 0.5)))[None, :]


def fom_runs(cfg, material):
    """Snapshots of every amplitude (training ones to t_train, test ones to t_end)."""
    cant = scene.build(material, cfg["cells"])
    integ = lo.MidpointIntegrator(cant.system, scene.DT, prefix=f"svk_{material.replace('-', '')}_")
    runs = {}
    for amp in cfg["train_amps"] + cfg["test_amps"]:
        cant.amplitude.value = amp
        t_end = cfg["t_train"] if amp in cfg["train_amps"] else cfg["t_end"]
        snaps, info = lo.run(cant.system, *cant.initial_state(), scene.DT, t_end,
                             output_matrix=cant.output_matrix, state_map=cant.state_map,
                             integrator=integ, progress=False, record_velocity=False,
                             energy_every=0)
        runs[amp] = (snaps, info["seconds"])
        print(f"  FOM {material} a = {amp:g}: {info['steps']} Newton steps in {info['seconds']:.1f} s, "
              f"tip z min {snaps.Y[1].min():+.3f} m, tip x min {snaps.Y[0].min():+.3f} m")
    return cant, runs


def intrusive_potential(cant, Vb, Qh_train, rng):
    """Coefficients of the reduced potential from V^T F(V q) at sampled q (least squares over
    the gradient monomials); exact when F is a cubic polynomial (SVK)."""
    r = Vb.shape[1]
    nu = pl.n_unknowns(r, 0, False)
    p = nu["K"] + nu["cubic"] + nu["quartic"]
    n_s = int(3 * p / r) + 20
    spread = Qh_train.std(axis=1) + 1e-3 * np.abs(Qh_train).max()
    X = spread[:, None] * rng.standard_normal((r, n_s)) * 1.5
    F = Vb.T @ cant.internal_force(Vb @ X)  # (r, n_s)
    scale = float(np.sqrt(np.mean(X**2)))
    Xs = X / scale
    blocks = [pl.monomial_gradients(Xs, pl.monomials(r, d)) for d in (2, 3, 4)]
    A = np.concatenate(blocks, axis=1).transpose(0, 2, 1).reshape(r * n_s, -1)
    norms = np.linalg.norm(A, axis=0)
    theta, *_ = np.linalg.lstsq(A / norms, (F / scale).reshape(-1), rcond=None)
    theta = theta / norms
    p2, p3 = nu["K"], nu["cubic"]
    theta = np.concatenate([theta[:p2], theta[p2:p2 + p3] / scale, theta[p2 + p3:] / scale**2])
    pot = pl.PolynomialPotential.from_coefficients(theta, r)
    misfit = np.linalg.norm(pot.gradient(X) - F) / np.linalg.norm(F)
    return pot, float(misfit)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="6 cells, SVK only, r in {4, 6}, one test amplitude")
    parser.add_argument("--out", default="results/svk_cantilever")
    args = parser.parse_args(argv)
    cfg = QUICK if args.quick else FULL
    if MPI.COMM_WORLD.size > 1:
        raise SystemExit("this demo runs on one rank")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    dt = scene.DT
    t_start = time.perf_counter()
    metrics = {"scene": "svk_cantilever", "dt": dt, "t_train": cfg["t_train"], "t_end": cfg["t_end"],
               "train_amplitudes": cfg["train_amps"], "test_amplitudes": cfg["test_amps"],
               "r_values": cfg["r_values"], "quick": bool(args.quick), "materials": {}}

    # --- the linear FOM at the largest amplitude: what the nonlinearity changes ----------------
    a_max = max(cfg["test_amps"])
    lin = scene.build("linear", cfg["cells"])
    lin.amplitude.value = a_max
    lin_snaps, lin_info = lo.run(lin.system, *lin.initial_state(), dt, cfg["t_end"],
                                 output_matrix=lin.output_matrix, state_map=lin.state_map,
                                 progress=False, record_velocity=False, energy_every=0,
                                 state_until=2 * dt)
    y_linear = lin_snaps.Y

    for material in cfg["materials"]:
        print(f"[{material}]")
        cant, runs = fom_runs(cfg, material)
        M = dense_state_matrix(cant.system.mass_form, cant.V, cant.state_map)
        E_state = output_matrix_in_state(cant.V, cant.output_matrix, cant.state_map)
        b_state = cant.load_vector()
        Q_train = np.hstack([runs[a][0].Q for a in cfg["train_amps"]])
        basis_full = lo.pod(Q_train, max(cfg["r_values"]), weight=M)
        alpha, beta = scene.RAYLEIGH
        n_test_steps = int(round(cfg["t_end"] / dt))
        # the long run: from the last training state of the largest training amplitude
        snaps_long = runs[max(cfg["train_amps"])][0]
        n_long = int(round(cfg["long_factor"] * cfg["t_train"] / dt))
        rows, long_rows, tip_series, energy_series = [], [], {}, {}
        lin_nl = {"a": a_max, "y_linear": y_linear, "y_nonlinear": runs[a_max][0].Y}
        fom_seconds = {a: runs[a][1] for a in runs}
        rng = np.random.default_rng(17)
        for r in cfg["r_values"]:
            basis = basis_full.truncate(r)
            Vb = basis.V
            datas = []
            for a in cfg["train_amps"]:
                Qh = basis.project(runs[a][0].Q)
                datas.append(pl.midpoint_data(Qh, dt, half_step_inputs(a, Qh.shape[1] - 1, dt)))
            data = pl._concat(datas)
            Qh_train = np.hstack([basis.project(runs[a][0].Q) for a in cfg["train_amps"]])
            models, fits = {}, {}
            # polynomial L-OpInf (SOS-bounded potential)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ops = pl.fit_polynomial(data, constraint="sos")
            models["poly_lopinf"] = (ops.potential, ops.C, ops.B)
            fits["poly_lopinf"] = ops.certificate
            # linear L-OpInf on the same relation
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                lops = lo.infer_mechanical(data.Qbar, data.D1, data.D2, data.Ubar)
            lin_pot = pl.PolynomialPotential(lops.K, np.zeros(pl.n_unknowns(r)["cubic"]),
                                             np.zeros(pl.n_unknowns(r)["quartic"]))
            models["lopinf"] = (lin_pot, lops.C, lops.B)
            fits["lopinf"] = {"seconds": time.perf_counter() - t0,
                              "status": lops.certificate.get("status"),
                              "duality_gap": lops.certificate.get("duality_gap")}
            # intrusive Galerkin polynomial ROM
            t0 = time.perf_counter()
            ipot, imisfit = intrusive_potential(cant, Vb, Qh_train, rng)
            Ch = alpha * np.eye(r) + beta * ipot.K
            models["intrusive"] = (ipot, Ch, (Vb.T @ b_state)[:, None])
            fits["intrusive"] = {"seconds": time.perf_counter() - t0, "force_misfit": imisfit}
            # unconstrained polynomial OpInf
            force, Cf, Bf, fcert = pl.fit_force(data)
            models["opinf_poly"] = (force, Cf, Bf)
            fits["opinf_poly"] = fcert
            print(f"  r = {r}: poly L-OpInf fit {ops.certificate['seconds']:.2f} s "
                  f"({ops.certificate['n_unknowns']['total']} unknowns, gap "
                  f"{ops.certificate['duality_gap']:.1e}, min eig G {ops.certificate['min_eig_gram']:.1e}), "
                  f"intrusive force misfit {imisfit:.1e}")
            # --- unseen amplitudes -------------------------------------------------------------
            for a in cfg["test_amps"]:
                snaps = runs[a][0]
                u_mid = half_step_inputs(a, n_test_steps, dt)
                for method, (model, C, B) in models.items():
                    rom = pl.PolynomialROM(model, C, B)
                    tr = rom.simulate(np.zeros(r), np.zeros(r), dt, n_test_steps, u_mid)
                    Qrec = Vb @ tr.Qh
                    Y = E_state @ Qrec
                    state_err = lo.relative_error(snaps.Q, Qrec) if tr.stable else float("inf")
                    tip_err = lo.relative_error(snaps.Y, Y) if tr.stable else float("inf")
                    rows.append({"material": material, "method": method, "r": r, "amplitude": a,
                                 "state_error": state_err, "tip_error": tip_err,
                                 "projection_error": basis.projection_error(snaps.Q),
                                 "stable": bool(tr.stable), "rom_seconds": tr.seconds,
                                 "fom_seconds": fom_seconds[a],
                                 "newton_iterations": tr.newton_iterations,
                                 "fit_seconds": fits[method].get("seconds")})
                    if a == a_max and r == max(cfg["r_values"]):
                        tip_series[method] = Y
            # --- long undamped, unforced run: energy -------------------------------------------
            Qh_l = basis.project(snaps_long.Q[:, -3:])
            q0 = Qh_l[:, 1]
            v0 = (Qh_l[:, 2] - Qh_l[:, 0]) / (2 * dt)
            E_fom = lambda Q, P, ipot=ipot: 0.5 * np.sum(P * P, axis=0) + ipot.value(Q)  # noqa: E731
            for method, (model, _, _) in models.items():
                for scheme in (("midpoint", "avf") if method == "poly_lopinf" else ("midpoint",)):
                    tr = pl.PolynomialROM(model).simulate(q0, v0, dt, n_long, scheme=scheme)
                    e_fom = E_fom(tr.Qh, tr.P) if tr.stable else None
                    row = {"material": material, "method": method, "r": r, "scheme": scheme,
                           "t_long": n_long * dt, "stable": bool(tr.stable),
                           "rom_seconds": tr.seconds}
                    if tr.energy is not None and tr.stable:
                        row["rom_energy_drift"] = float(np.abs(tr.energy - tr.energy[0]).max()
                                                        / abs(tr.energy[0]))
                    if e_fom is not None:
                        e0 = float(E_fom(q0[:, None], v0[:, None])[0])
                        row["fom_energy_error"] = float(np.abs(e_fom - e0).max() / abs(e0))
                        if r == max(cfg["r_values"]) and scheme == "midpoint":
                            energy_series[method] = e_fom
                    long_rows.append(row)
            for method in METHODS:
                cert = {k: v for k, v in fits[method].items() if k != "n_unknowns"}
                if "n_unknowns" in fits[method]:
                    cert["n_unknowns"] = fits[method]["n_unknowns"]
                metrics["materials"].setdefault(material, {}).setdefault("fits", []).append(
                    {"r": r, "method": method, **plain(cert)})
        mm = metrics["materials"][material]
        mm.update(n_dofs=int(len(cant.state_map.order)), rows=rows, long_runs=long_rows,
                  fom_seconds={str(a): s for a, s in fom_seconds.items()},
                  linear_vs_nonlinear_tip_difference=float(
                      lo.relative_error(lin_nl["y_nonlinear"], lin_nl["y_linear"])))
        _figures(out, material, cfg, lin_nl, tip_series, energy_series, rows, dt, n_long)
        _print_table(material, rows, long_rows, cfg)
    metrics["linear_fom_seconds"] = lin_info["seconds"]
    metrics["seconds"] = time.perf_counter() - t_start
    harness.write_metrics(out, metrics)
    print(f"wrote {out / 'metrics.json'} ({metrics['seconds']:.0f} s)")
    return metrics


def _figures(out, material, cfg, lin_nl, tip_series, energy_series, rows, dt, n_long):
    r_max = max(cfg["r_values"])
    a = lin_nl["a"]
    t = dt * np.arange(lin_nl["y_nonlinear"].shape[1])
    series = {f"FOM ({material})": lin_nl["y_nonlinear"][1]}
    series.update({f"{LABELS[m]} r={r_max}": y[1] for m, y in tip_series.items()
                   if m != "opinf_poly" or np.all(np.isfinite(y))})
    series["linear FOM (small strain)"] = lin_nl["y_linear"][1]
    render.curves(out / f"tip_{material}.png", t, series, ylabel="tip z-displacement [m]",
                  title=f"{material}: unseen amplitude a = {a:g} (trained at "
                        f"{', '.join(f'{x:g}' for x in cfg['train_amps'])})",
                  colors=["k", "C0", "C3", "C2", "C1", "C7"])
    # error vs r (largest unseen amplitude)
    rs = {}
    for m in METHODS:
        vals = [next(row["tip_error"] for row in rows if row["method"] == m and row["r"] == r
                     and row["amplitude"] == a) for r in cfg["r_values"]]
        rs[LABELS[m]] = np.array([v if np.isfinite(v) else np.nan for v in vals])
    render.curves(out / f"error_vs_r_{material}.png", np.array(cfg["r_values"], float), rs,
                  ylabel="relative tip error", logy=True, xlabel="r",
                  title=f"{material}: tip error at a = {a:g} vs r", colors=["C0", "C3", "C2", "C1"])
    if energy_series:
        tl = dt * np.arange(n_long + 1)
        e = {LABELS[m]: v for m, v in energy_series.items()}
        render.curves(out / f"energy_{material}.png", tl, e, ylabel="FOM energy of V q [J]",
                      title=f"{material}: undamped, unforced run 5x training, r = {r_max}",
                      colors=["C0", "C3", "C2", "C1"])


def _print_table(material, rows, long_rows, cfg):
    print(f"  tip error ({material}) per amplitude / r:")
    for m in METHODS:
        for r in cfg["r_values"]:
            errs = [f"{row['tip_error']:.2e}" for row in rows if row["method"] == m and row["r"] == r]
            print(f"    {m:12s} r={r}: " + "  ".join(errs))
    for row in long_rows:
        print(f"    long {row['method']:12s} r={row['r']} {row['scheme']:8s} stable={row['stable']} "
              f"rom drift {row.get('rom_energy_drift', float('nan')):.2e} "
              f"FOM energy err {row.get('fom_energy_error', float('nan')):.2e}")


if __name__ == "__main__":
    main()
