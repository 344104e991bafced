"""Large-deformation 3D cantilever: a polynomial Lagrangian ROM learned as one convex fit.

    python demos/svk_cantilever.py [--quick | --smoke] [--out DIR]

1. FOM (:mod:`dolfinx_lopinf.scenes.svk_cantilever`): St. Venant-Kirchhoff (and neo-Hookean)
   cantilever, Q2 hexahedra, midpoint VI with PETSc SNES Newton, dt = 2e-3 s, a vertical body
   load a s(t) (ramp, hold, release, free vibration, Rayleigh damping). Runs at the training
   amplitudes (to t_train) and at unseen ones, smaller and larger (to t_end); the linear
   (small-strain) FOM at the largest amplitude shows what the nonlinearity does.
2. Mass-orthonormal POD of the training snapshots (reduced mass exactly I; M is the one FOM
   operator the fit uses, as in the fishtail and beam demos).
3. Eight ROMs per r, all integrated by the midpoint VI with a reduced Newton step
   (:class:`PolynomialROM`; the polynomial ones by its compiled loop, numba, and again by its
   numpy reference loop for the timing):
   * ``poly_lopinf``: U(q) = quadratic + cubic + quartic, C >= eps I, B - the gradient of one
     potential with U = m^T G m, G >= eps_g I (bounded below), Clarabel with its duality gap
     (:mod:`dolfinx_lopinf.core.polynomial`), fitted to black-box probe data: the FOM steps once
     (h = 4e-6 .. 2.5e-7) from lifted samples (V q, M V v) around the training trajectories
     and the reduced accelerations are Richardson-extrapolated (:mod:`dolfinx_lopinf.fem.probes`);
   * ``poly_lopinf_ls``: the same data, gradient structure only (plain least squares);
   * ``poly_lopinf_traj``: the sos fit on the projected training trajectories' midpoint
     relation - fails: their reduced relation carries the truncated stiff content's closure;
   * ``lopinf``: the paper's linear L-OpInf (``lo.core.infer_mechanical``) on the trajectories;
   * ``intrusive``: the Galerkin polynomial ROM, its tensors from V^T F(V q) of the FOM at
     sampled q (exact for SVK, whose reduced force is a cubic polynomial; for neo-Hookean the
     best quartic-potential fit of the Galerkin force over the sampled region), C = alpha I +
     beta K_h, B = V^T b;
   * ``galerkin``: the genuine Galerkin ROM - the full-order internal force and tangent
     V^T f(V q), V^T K_t(V q) V assembled by DOLFINx at every reduced Newton iterate
     (:mod:`dolfinx_lopinf.fem.galerkin_nonlinear`; exact for any material);
   * ``galerkin_ecsw``: the same with ECSW hyper-reduction: cell weights by NNLS on the
     training states, the force summed over the sampled cells only;
   * ``opinf_poly``: unconstrained polynomial OpInf (free force coefficients up to cubic, free
     C and B) on the probe data: no potential.
4. Scores: per unseen amplitude the state and tip errors over [0, t_end]; the energy of an
   undamped, unforced run 5x the training length from the last training state (the ROM's own
   energy and the FOM energy of the reconstruction, U_FOM(V q) = the intrusive potential on
   SVK); fit times, certificates, ROM (compiled and numpy loop) and FOM times.
5. Deformed FOM | ROM renders (true scale, side view) at the largest unseen amplitude.

Runs on any number of ranks (``mpiexec -n N python demos/svk_cantilever.py``) with the serial
result: every rank holds the snapshots and does the ROM work (the Galerkin ROMs assemble on
all of them); rank 0 prints and writes.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np

import dolfinx_lopinf as lo
from dolfinx_lopinf.core import compiled
from dolfinx_lopinf.core import polynomial as pl
from dolfinx_lopinf.core.io_atomic import plain
from dolfinx_lopinf.fem import galerkin_nonlinear as gn
from dolfinx_lopinf.fem import probes
from dolfinx_lopinf.studies import harness
from dolfinx_lopinf.viz import render
from dolfinx_lopinf.fem._dolfinx import MPI
from dolfinx_lopinf.fem.state import output_matrix_in_state
from dolfinx_lopinf.fem.intrusive import dense_state_matrix
from dolfinx_lopinf.scenes import svk_cantilever as scene

FULL = dict(cells=(10, 1, 1), t_train=1.0, t_end=1.5, train_amps=[100.0, 250.0],
            test_amps=[50.0, 175.0, 350.0], r_values=[4, 6, 8], long_factor=5,
            materials=["svk", "neo-hookean"], ecsw_tol=1e-3, ecsw_states=150,
            ecsw_sweep=[1e-1, 3e-2, 1e-2, 1e-3, 1e-4], render_times=[0.25, 0.5, 0.6, 0.75])
QUICK = dict(cells=(6, 1, 1), t_train=0.8, t_end=1.0, train_amps=[100.0, 250.0],
             test_amps=[350.0], r_values=[4, 6], long_factor=5, materials=["svk"],
             ecsw_tol=1e-3, ecsw_states=80, ecsw_sweep=[], render_times=[0.3, 0.55, 0.7])
#: the test suite's size (tests/fem/test_svk_mpi.py: 1 vs 2 ranks): every step of the demo,
#: on 3 cells and short runs
SMOKE = dict(QUICK, cells=(3, 1, 1), t_train=0.5, t_end=0.6, r_values=[4], long_factor=1,
             ecsw_states=40, render_times=[0.3, 0.55])
METHODS = ("poly_lopinf", "poly_lopinf_ls", "poly_lopinf_traj", "lopinf", "intrusive", "galerkin",
           "galerkin_ecsw", "opinf_poly")
#: the polynomial L-OpInf fits whose long runs also use the energy-conserving AVF scheme
POTENTIAL_FITS = ("poly_lopinf", "poly_lopinf_ls")
#: black-box probes: one midpoint step of h, h/2, ..., h/16 per sample (fem/probes.py), and
#: probe samples per potential unknown and reduced equation
PROBE_STEP, PROBE_LEVELS, PROBES_PER_UNKNOWN = 4e-6, 5, 1.5
LABELS = {"poly_lopinf": "polynomial L-OpInf (probes, bounded U)",
          "poly_lopinf_ls": "polynomial L-OpInf (probes, gradient only)",
          "poly_lopinf_traj": "polynomial L-OpInf (projected trajectories)",
          "lopinf": "linear L-OpInf",
          "intrusive": "intrusive Galerkin (polynomial tensors)",
          "galerkin": "Galerkin (FOM force per iterate)", "galerkin_ecsw": "Galerkin + ECSW",
          "opinf_poly": "polynomial OpInf (probes, no potential)"}
COLORS = {"poly_lopinf": "C0", "poly_lopinf_ls": "C9", "poly_lopinf_traj": "C8", "lopinf": "C3",
          "intrusive": "C2", "galerkin": "C4", "galerkin_ecsw": "C5", "opinf_poly": "C1"}
#: the FOM-assembled ROMs: numpy loop only (DOLFINx assembly per Newton iterate). Their Newton
#: test is |R| <= tol (size + dt/2 f_train), f_train the largest reduced force on the training
#: states: an assembled force is a sum of cancelling cell terms, so near rest (small |R| terms)
#: a purely relative test asks for digits below its rounding (measured: Newton stalls at the
#: first steps of a = 50 with tol = 1e-9 and no absolute part)
ASSEMBLED = ("galerkin", "galerkin_ecsw")
ASSEMBLED_TOL = 1e-10


def half_step_inputs(amp, n_steps, dt):
    """u(t_{k+1/2}) = a s(t_{k+1/2}), k = 0 .. n_steps-1, as a (1, n_steps) row."""
    return (amp * scene.profile(dt * (np.arange(n_steps) + 0.5)))[None, :]


def say(*args, **kwargs):
    """print on rank 0 only."""
    if harness.is_root():
        print(*args, **kwargs)


def fom_runs(cfg, material):
    """Snapshots of every amplitude (training ones to t_train, test ones to t_end), on every
    rank (the run gathers them on rank 0; the ROM work on every rank needs them)."""
    cant = scene.build(material, cfg["cells"])
    integ = lo.fem.MidpointIntegrator(cant.system, scene.DT, prefix=f"svk_{material.replace('-', '')}_")
    runs = {}
    for amp in cfg["train_amps"] + cfg["test_amps"]:
        cant.amplitude.value = amp
        t_end = cfg["t_train"] if amp in cfg["train_amps"] else cfg["t_end"]
        snaps, info = lo.run(cant.system, *cant.initial_state(), scene.DT, t_end,
                             output_matrix=cant.output_matrix, state_map=cant.state_map,
                             integrator=integ, progress=False, record_velocity=False,
                             energy_every=0)
        snaps = MPI.COMM_WORLD.bcast(snaps, root=0)
        runs[amp] = (snaps, info["seconds"])
        say(f"  FOM {material} a = {amp:g}: {info['steps']} Newton steps in {info['seconds']:.1f} s, "
            f"tip z min {snaps.Y[1].min():+.3f} m, tip x min {snaps.Y[0].min():+.3f} m")
    return cant, runs


def intrusive_potential(galerkin, Qh_train, rng):
    """Coefficients of the reduced potential from the Galerkin force V^T F(V q) at sampled q
    (least squares over the gradient monomials); exact when F is a cubic polynomial (SVK)."""
    r = galerkin.r
    nu = pl.n_unknowns(r, 0, False)
    p = nu["K"] + nu["cubic"] + nu["quartic"]
    n_s = int(3 * p / r) + 20
    spread = Qh_train.std(axis=1) + 1e-3 * np.abs(Qh_train).max()
    X = spread[:, None] * rng.standard_normal((r, n_s)) * 1.5
    F = galerkin.gradient(X)  # (r, n_s)
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


def _fit_models(cant, cfg, basis, runs, b_state, rng):
    """The six ROMs at this basis: {method: (model, C, B)} and {method: fit info}."""
    dt, r, Vb = scene.DT, basis.r, basis.V
    alpha, beta = scene.RAYLEIGH
    datas = []
    for a in cfg["train_amps"]:
        Qh = basis.project(runs[a][0].Q)
        datas.append(pl.midpoint_data(Qh, dt, half_step_inputs(a, Qh.shape[1] - 1, dt)))
    data = pl.concat_data(datas)
    Qh_train = np.hstack([basis.project(runs[a][0].Q) for a in cfg["train_amps"]])
    models, fits = {}, {}
    # polynomial L-OpInf from black-box probes: one FOM midpoint step of h .. h/16 from lifted
    # samples (V q, M V v) with the input set, Richardson-extrapolated to the Galerkin
    # acceleration (fem/probes.py) - data without the closure of projected trajectories
    # velocities by central differences per trajectory (one-sided at its ends)
    Vh_train = np.hstack([np.gradient(basis.project(runs[a][0].Q), dt, axis=1)
                          for a in cfg["train_amps"]])
    n_samples = int(PROBES_PER_UNKNOWN * pl.n_unknowns(r, 1)["total"] / r) + 10
    Qs, Vs, Us = probes.probe_points(Qh_train, Vh_train, n_samples, rng=rng,
                                     inputs_range=(0.0, max(cfg["train_amps"])))
    pdata = probes.probe(cant.system, Vb, cant.state_map, Qs, Vs, Us,
                         set_input=cant.set_probe_input, step_size=PROBE_STEP, levels=PROBE_LEVELS)
    probe_info = plain(pdata.summary())
    for method, constraint in (("poly_lopinf", "sos"), ("poly_lopinf_ls", "none")):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ops = pl.fit_polynomial(pdata.data(), constraint=constraint)
        models[method] = (ops.potential, ops.C, ops.B)
        fits[method] = {**ops.certificate, "probes": probe_info}
    # the same fit on projected FOM trajectories (the closure makes it fail: kept to show it)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tops = pl.fit_polynomial(data, constraint="sos")
    models["poly_lopinf_traj"] = (tops.potential, tops.C, tops.B)
    fits["poly_lopinf_traj"] = tops.certificate
    # linear L-OpInf on the same relation
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lops = lo.core.infer_mechanical(data.Qbar, data.D1, data.D2, data.Ubar)
    lin_pot = pl.PolynomialPotential(lops.K, np.zeros(pl.n_unknowns(r)["cubic"]),
                                     np.zeros(pl.n_unknowns(r)["quartic"]))
    models["lopinf"] = (lin_pot, lops.C, lops.B)
    fits["lopinf"] = {"seconds": time.perf_counter() - t0, "status": lops.certificate.get("status"),
                      "duality_gap": lops.certificate.get("duality_gap")}
    # the genuine Galerkin ROM (FOM assembly per iterate): C = alpha I + beta V^T K_0 V, B = V^T b
    t0 = time.perf_counter()
    galerkin = gn.GalerkinForce(cant.energy_form, cant.system.q, Vb, cant.state_map)
    K0 = galerkin.force_and_jacobian(np.zeros(r))[1]
    Cg, Bg = alpha * np.eye(r) + beta * K0, (Vb.T @ b_state)[:, None]
    models["galerkin"] = (galerkin, Cg, Bg)
    f_train = float(np.abs(galerkin.gradient(Qh_train[:, ::max(1, Qh_train.shape[1] // 40)])).max())
    models["_atol"] = ASSEMBLED_TOL * 0.5 * dt * f_train
    fits["galerkin"] = {"seconds": time.perf_counter() - t0, "cells": galerkin.n_cells_used,
                        "newton_atol": models["_atol"]}
    # intrusive polynomial ROM: the reduced tensors of the Galerkin force (exact for SVK)
    t0 = time.perf_counter()
    ipot, imisfit = intrusive_potential(galerkin, Qh_train, rng)
    models["intrusive"] = (ipot, alpha * np.eye(r) + beta * ipot.K, Bg)
    fits["intrusive"] = {"seconds": time.perf_counter() - t0, "force_misfit": imisfit}
    # ECSW: cells and weights fitting the Galerkin force on (subsampled) training states
    t0 = time.perf_counter()
    step = max(1, Qh_train.shape[1] // cfg["ecsw_states"])
    sampling = gn.ecsw_sampling(cant.energy_form, cant.system.q, Vb, cant.state_map,
                                Qh_train[:, ::step], tol=cfg["ecsw_tol"])
    ecsw = gn.GalerkinForce(cant.energy_form, cant.system.q, Vb, cant.state_map, sampling=sampling)
    models["galerkin_ecsw"] = (ecsw, Cg, Bg)
    models["_ecsw_training"] = Qh_train[:, ::step]
    fits["galerkin_ecsw"] = {"seconds": time.perf_counter() - t0, "cells": len(sampling.cells),
                             "n_cells": sampling.n_cells, "ecsw_residual": sampling.residual,
                             "ecsw_tol": cfg["ecsw_tol"], "training_states": Qh_train[:, ::step].shape[1]}
    # unconstrained polynomial OpInf on the same probe data (free force: no potential)
    force, Cf, Bf, fcert = pl.fit_force(pdata.data())
    models["opinf_poly"] = (force, Cf, Bf)
    fits["opinf_poly"] = fcert
    models["_probes"] = pdata
    cert = fits["poly_lopinf"]
    say(f"  r = {r}: {pdata.Q.shape[1]} probes ({pdata.fom_steps} FOM steps, {pdata.seconds:.1f} s, "
        f"estimate {probe_info['error_estimate_max']:.1e}); poly L-OpInf fit {cert['seconds']:.2f} s "
        f"({cert['n_unknowns']['total']} unknowns, gap {cert['duality_gap']:.1e}, min eig G "
        f"{cert['min_eig_gram']:.1e}), gradient-only fit {fits['poly_lopinf_ls']['seconds']:.2f} s, "
        f"intrusive force misfit {imisfit:.1e}, ECSW {len(sampling.cells)} of "
        f"{sampling.n_cells} cells (residual {sampling.residual:.1e})")
    return models, fits, galerkin


def _simulate(method, rom, *args, atol=0.0, **kwargs):
    """(trajectory of the default loop, seconds of the numpy loop, relative max difference of
    the two loops' states or None): the polynomial models run compiled (numba, when available)
    and again with the numpy reference loop; the assembled Galerkin ROMs run the numpy loop
    (their force is a DOLFINx assembly) with the simplified Newton (jacobian='lazy': a force
    costs one assembly, its Jacobian r + 1, so keeping the Jacobian saves most of the work; the
    states equal fresh Newton's to 7e-10). The compiled and numpy loops do the same arithmetic in another order, so
    they agree to rounding at first; over long runs of a nonlinear (chaotic) model the
    difference grows - recorded, not hidden."""
    kwargs.setdefault("on_failure", "stop")  # an unstable fit is a result of the comparison
    if method in ASSEMBLED:
        tr = rom.simulate(*args, tol=ASSEMBLED_TOL, atol=atol, backend="numpy", jacobian="lazy",
                          **kwargs)
        return tr, tr.seconds, None
    # the same absolute floor as the assembled ROMs: with the relative test alone (tol 1e-13)
    # the compiled and numpy loops were seen to disagree on whether a step converged
    # (rounding of the force decides it; measured on a probe-fitted model at r = 6, a = 50)
    tr = rom.simulate(*args, atol=atol, **kwargs)
    if tr.backend == "numpy":
        return tr, tr.seconds, None
    ref = rom.simulate(*args, backend="numpy", atol=atol, **kwargs)
    diff = None
    if tr.stable and ref.stable:
        diff = float(np.abs(tr.Qh - ref.Qh).max() / max(np.abs(ref.Qh).max(), 1e-300))
    return tr, ref.seconds, diff


def _ecsw_sweep(material, cfg, cant, basis, models, runs, E_state, fom_seconds):
    """ECSW cells, tip error and ROM time against the NNLS tolerance (largest unseen amplitude)."""
    dt, r, a = scene.DT, basis.r, max(cfg["test_amps"])
    n = int(round(cfg["t_end"] / dt))
    _, Cg, Bg = models["galerkin"]
    rows = []
    for tol in cfg["ecsw_sweep"]:
        s = gn.ecsw_sampling(cant.energy_form, cant.system.q, basis.V, cant.state_map,
                             models["_ecsw_training"], tol=tol)
        ecsw = gn.GalerkinForce(cant.energy_form, cant.system.q, basis.V, cant.state_map, sampling=s)
        tr, *_ = _simulate("galerkin_ecsw", pl.PolynomialROM(ecsw, Cg, Bg), np.zeros(r), np.zeros(r),
                          dt, n, inputs=half_step_inputs(a, n, dt), atol=models["_atol"])
        err = lo.relative_error(runs[a][0].Y, E_state @ basis.V @ tr.Qh) if tr.stable else float("inf")
        rows.append({"material": material, "r": r, "amplitude": a, "tol": tol, "cells": len(s.cells),
                     "n_cells": s.n_cells, "ecsw_residual": s.residual, "tip_error": err,
                     "stable": bool(tr.stable), "rom_seconds": tr.seconds,
                     "speedup": fom_seconds[a] / tr.seconds})
        say(f"    ECSW tol {tol:g}: {len(s.cells)}/{s.n_cells} cells, tip error {err:.2e}, "
            f"ROM {tr.seconds:.2f} s")
    return rows


def _test_rows(material, cfg, r, basis, models, fits, runs, E_state, fom_seconds):
    dt = scene.DT
    n_test_steps = int(round(cfg["t_end"] / dt))
    rows, tips, states = [], {}, {}
    for a in cfg["test_amps"]:
        snaps = runs[a][0]
        u_mid = half_step_inputs(a, n_test_steps, dt)
        for method in METHODS:
            model, C, B = models[method]
            rom = pl.PolynomialROM(model, C, B)
            tr, sec_np, diff = _simulate(method, rom, np.zeros(r), np.zeros(r), dt, n_test_steps,
                                         inputs=u_mid, atol=models["_atol"])
            Qrec = basis.V @ tr.Qh
            Y = E_state @ Qrec
            state_err = lo.relative_error(snaps.Q, Qrec) if tr.stable else float("inf")
            tip_err = lo.relative_error(snaps.Y, Y) if tr.stable else float("inf")
            rows.append({"material": material, "method": method, "r": r, "amplitude": a,
                         "state_error": state_err, "tip_error": tip_err,
                         "projection_error": basis.projection_error(snaps.Q),
                         "stable": bool(tr.stable), "rom_seconds": tr.seconds,
                         "rom_backend": tr.backend, "rom_seconds_numpy": sec_np,
                         "loop_difference": diff, "fom_seconds": fom_seconds[a], "speedup": fom_seconds[a] / tr.seconds,
                         "speedup_numpy": fom_seconds[a] / sec_np,
                         "newton_iterations": tr.info["newton_iterations"],
                         "jacobians": tr.info["jacobians"],
                         "fit_seconds": fits[method].get("seconds"),
                         "cells": fits[method].get("cells")})
            if a == max(cfg["test_amps"]):
                tips[method] = Y
                states[method] = tr.Qh
    return rows, tips, states


def _long_rows(material, cfg, r, basis, models, galerkin, snaps_long):
    """Undamped, unforced runs long_factor x the training length from the last training
    state; the energy is scored by the FOM: 1/2 |p|^2 + U(V q) (assembled, any material)."""
    dt = scene.DT
    n_long = int(round(cfg["long_factor"] * cfg["t_train"] / dt))
    Qh_l = basis.project(snaps_long.Q[:, -3:])
    q0 = Qh_l[:, 1]
    v0 = (Qh_l[:, 2] - Qh_l[:, 0]) / (2 * dt)
    e0 = 0.5 * v0 @ v0 + galerkin.value(q0)
    rows, series = [], {}
    for method in METHODS:
        model = models[method][0]
        for scheme in (("midpoint", "avf") if method in POTENTIAL_FITS else ("midpoint",)):
            tr, sec_np, diff = _simulate(method, pl.PolynomialROM(model), q0, v0, dt, n_long,
                                         scheme=scheme, atol=models["_atol"])
            row = {"material": material, "method": method, "r": r, "scheme": scheme,
                   "t_long": n_long * dt, "stable": bool(tr.stable), "rom_seconds": tr.seconds,
                   "rom_backend": tr.backend, "rom_seconds_numpy": sec_np, "loop_difference": diff}
            energy = tr.info.get("energy")
            if energy is not None and tr.stable:
                row["rom_energy_drift"] = float(np.abs(energy - energy[0]).max() / abs(energy[0]))
            if tr.stable:
                e_fom = 0.5 * np.sum(tr.Vh**2, axis=0) + galerkin.value(tr.Qh)
                row["fom_energy_error"] = float(np.abs(e_fom - e0).max() / abs(e0))
                if r == max(cfg["r_values"]) and scheme == "midpoint":
                    series[method] = e_fom
            rows.append(row)
    return rows, series, n_long


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="6 cells, SVK only, r in {4, 6}, one test amplitude")
    parser.add_argument("--smoke", action="store_true",
                        help="the test suite's size: quick on 3 cells, training to 0.5 s, the "
                             "unseen amplitude to 0.6 s, r = 4, long runs 1x")
    parser.add_argument("--out", default="results/svk_cantilever")
    parser.add_argument("--cells", default=None,
                        help="Q2 cells 'nx,ny,nz' (default 10,1,1; quick 6,1,1) - e.g. 20,2,2 to "
                             "give ECSW cells to drop (80 cells, 3075 dofs: ~10x the FOM time)")
    args = parser.parse_args(argv)
    cfg = dict(SMOKE if args.smoke else QUICK if args.quick else FULL)
    if args.cells is not None:
        try:
            cells = tuple(int(c) for c in args.cells.split(","))
        except ValueError:
            cells = ()
        if len(cells) != 3 or min(cells) < 1:
            parser.error(f"--cells must be three positive integers 'nx,ny,nz', got {args.cells!r}")
        cfg["cells"] = cells
    root = harness.is_root()
    out = Path(args.out)
    if root:
        out.mkdir(parents=True, exist_ok=True)
    dt = scene.DT
    t_start = time.perf_counter()
    jit_seconds = compiled.warm_up_polynomial()  # compile / load the ROM loop before any timer
    metrics = {"scene": "svk_cantilever", "dt": dt, "t_train": cfg["t_train"], "t_end": cfg["t_end"],
               "train_amplitudes": cfg["train_amps"], "test_amplitudes": cfg["test_amps"],
               "r_values": cfg["r_values"], "quick": bool(args.quick), "smoke": bool(args.smoke),
               "materials": {},
               "jit_compile_seconds": jit_seconds, "ecsw_tol": cfg["ecsw_tol"]}

    # --- the linear FOM at the largest amplitude: what the nonlinearity changes ----------------
    a_max = max(cfg["test_amps"])
    lin = scene.build("linear", cfg["cells"])
    lin.amplitude.value = a_max
    lin_snaps, lin_info = lo.run(lin.system, *lin.initial_state(), dt, cfg["t_end"],
                                 output_matrix=lin.output_matrix, state_map=lin.state_map,
                                 progress=False, record_velocity=False, energy_every=0,
                                 state_until=2 * dt)
    y_linear = MPI.COMM_WORLD.bcast(lin_snaps.Y if root else None, root=0)

    for material in cfg["materials"]:
        say(f"[{material}]")
        cant, runs = fom_runs(cfg, material)
        if root:  # the FOM outputs every fit is scored against (and tests/fem compare)
            np.savez(out / f"fom_{material}.npz", **{f"Y_{a:g}": runs[a][0].Y for a in runs})
        M = dense_state_matrix(cant.system.mass_form, cant.V, cant.state_map)
        E_state = output_matrix_in_state(cant.V, cant.output_matrix, cant.state_map)
        b_state = cant.load_vector()
        Q_train = np.hstack([runs[a][0].Q for a in cfg["train_amps"]])
        basis_full = lo.pod(Q_train, max(cfg["r_values"]), weight=M)
        snaps_long = runs[max(cfg["train_amps"])][0]
        rows, long_rows, fits_out = [], [], []
        lin_nl = {"a": a_max, "y_linear": y_linear, "y_nonlinear": runs[a_max][0].Y}
        fom_seconds = {a: runs[a][1] for a in runs}
        rng = np.random.default_rng(17)
        for r in cfg["r_values"]:
            basis = basis_full.truncate(r)
            models, fits, galerkin = _fit_models(cant, cfg, basis, runs, b_state, rng)
            if root:  # the black-box probe data of this basis (the probe fits' only data) and
                p = models["_probes"]  # the tip output of the basis (y = EV qh)
                np.savez(out / f"probes_{material}_r{r}.npz", Q=p.Q, Vel=p.Vel, U=p.inputs, A=p.A,
                         error_estimate=p.error_estimate, EV=E_state @ basis.V)
            r_rows, tip_series, state_series = _test_rows(material, cfg, r, basis, models, fits,
                                                          runs, E_state, fom_seconds)
            rows += r_rows
            l_rows, energy_series, n_long = _long_rows(material, cfg, r, basis, models, galerkin,
                                                       snaps_long)
            long_rows += l_rows
            if r == max(cfg["r_values"]):
                sweep_rows = _ecsw_sweep(material, cfg, cant, basis, models, runs, E_state, fom_seconds)
            for method in METHODS:
                fits_out.append({"r": r, "method": method, **fits[method]})
        mm = metrics["materials"].setdefault(material, {})
        sv = np.concatenate(list(basis_full.singular_values.values()))
        mm.update(n_dofs=int(len(cant.state_map.order)), n_cells=int(np.prod(cfg["cells"])),
                  pod_singular_values=sv[:20].tolist(),
                  rows=rows, long_runs=long_rows, fits=fits_out, ecsw_sweep=sweep_rows,
                  fom_seconds={str(a): s for a, s in fom_seconds.items()},
                  linear_vs_nonlinear_tip_difference=float(
                      lo.relative_error(lin_nl["y_nonlinear"], lin_nl["y_linear"])))
        if root:
            _figures(out, material, cfg, lin_nl, tip_series, energy_series, rows, dt, n_long)
        mm["render"] = _render(out, material, cfg, cant, runs[a_max][0], basis, state_series, rows)
        if root:
            _print_table(material, rows, long_rows, cfg)
    metrics["linear_fom_seconds"] = lin_info["seconds"]
    metrics.update(report_rows(metrics))
    metrics["n_ranks"] = MPI.COMM_WORLD.size
    metrics["seconds"] = time.perf_counter() - t_start
    harness.write_metrics(out, metrics)
    say(f"wrote {out / 'metrics.json'} ({metrics['seconds']:.0f} s)")
    return metrics


def report_rows(metrics: dict) -> dict:
    """The harness's speed-vs-error vocabulary for ``python -m dolfinx_lopinf.studies.report``:
    SVK rows at the largest unseen amplitude (test_error = relative tip error; infer_seconds
    = the fit plus, for the probe fits, the probes' FOM steps; failed runs left out) and the
    FOM's seconds for that amplitude."""
    svk = metrics["materials"].get("svk")
    if not svk:
        return {}
    a = max(metrics["test_amplitudes"])
    fits = {(f["method"], f["r"]): f for f in svk["fits"]}
    roms = []
    for row in svk["rows"]:
        if row["amplitude"] != a or not np.isfinite(row["tip_error"]):
            continue
        fit = fits.get((row["method"], row["r"]), {})
        infer = (fit.get("seconds") or 0.0) + (fit.get("probes") or {}).get("seconds", 0.0)
        roms.append({"method": row["method"], "r": row["r"], "test_error": row["tip_error"],
                     "rom_seconds": row["rom_seconds"], "rom_seconds_numpy": row["rom_seconds_numpy"],
                     "rom_backend": row["rom_backend"], "infer_seconds": infer})
    return {"roms": roms, "error": "tip (a = %g)" % a, "fom_seconds": svk["fom_seconds"][str(a)],
            "n_dofs": svk["n_dofs"]}


def _figures(out, material, cfg, lin_nl, tip_series, energy_series, rows, dt, n_long):
    r_max = max(cfg["r_values"])
    a = lin_nl["a"]
    t = dt * np.arange(lin_nl["y_nonlinear"].shape[1])
    series = {f"FOM ({material})": lin_nl["y_nonlinear"][1]}
    colors = ["k"]
    for m in ("poly_lopinf", "poly_lopinf_traj", "lopinf", "galerkin_ecsw", "opinf_poly"):
        y = tip_series.get(m)
        if y is not None and np.all(np.isfinite(y)):
            series[f"{LABELS[m]} r={r_max}"] = y[1]
            colors.append(COLORS[m])
    series["linear FOM (small strain)"] = lin_nl["y_linear"][1]
    colors.append("C7")
    render.curves(out / f"tip_{material}.png", t, series, ylabel="tip z-displacement [m]",
                  title=f"{material}: unseen amplitude a = {a:g} (trained at "
                        f"{', '.join(f'{x:g}' for x in cfg['train_amps'])})", colors=colors)
    _error_vs_r(out / f"error_vs_r_{material}.png", rows, cfg, a,
                title=f"{material}: tip error at the unseen a = {a:g} vs r")
    if energy_series:
        tl = dt * np.arange(n_long + 1)
        e = {LABELS[m]: np.abs(v - v[0]) / abs(v[0]) for m, v in energy_series.items()}
        render.curves(out / f"energy_{material}.png", tl, e, logy=True,
                      ylabel="|E(t) - E(0)| / E(0),  E = FOM energy of V q",
                      title=f"{material}: undamped, unforced, {cfg['long_factor']}x training, r = {r_max}",
                      colors=[COLORS[m] for m in energy_series])


def _error_vs_r(path, rows, cfg, a, *, title):
    """Tip error vs r per method (markers; a failed run - blow-up or Newton failure - drawn
    as an open marker on the top edge)."""
    plt = render._pyplot()
    fig, ax = plt.subplots(figsize=(10.0, 3.8))
    rs = np.array(cfg["r_values"], float)
    markers = dict(zip(METHODS, "oPsD^v<x"))
    finite = [row["tip_error"] for row in rows if np.isfinite(row["tip_error"])]
    top = 3 * max(finite) if finite else 1.0
    for k, m in enumerate(METHODS):
        vals = np.array([next(row["tip_error"] for row in rows if row["method"] == m and row["r"] == r
                              and row["amplitude"] == a) for r in cfg["r_values"]], float)
        x = rs + 0.05 * (k - 3.5)  # a small offset: coinciding methods stay visible
        ok = np.isfinite(vals)
        ax.plot(x[ok], vals[ok], marker=markers[m], color=COLORS[m], lw=1, label=LABELS[m])
        if np.any(~ok):
            ax.plot(x[~ok], np.full((~ok).sum(), top), ls="none", marker=markers[m], mfc="none",
                    color=COLORS[m], ms=8)
    ax.set_yscale("log")
    ax.set_xticks(rs)
    ax.axhline(top, color="k", lw=0.6, ls=":")
    ax.text(rs[0], top * 1.15, "failed (blow-up / Newton)", fontsize=7)
    render._finish(fig, ax, path, xlabel="r", ylabel="relative tip error", title=title,
                   legend={"loc": "upper left", "bbox_to_anchor": (1.01, 1.0)})


def _render(out, material, cfg, cant, snaps, basis, state_series, rows):
    """Deformed shapes, true scale, side view: FOM | ROMs at the largest unseen amplitude.
    Collective (the ranks' pieces of the mesh are gathered); drawn on rank 0."""
    dt, r = scene.DT, basis.r
    a = max(cfg["test_amps"])
    grid = render.grid_on_root(cant.V)  # rank 0: the whole mesh, points = global dof blocks

    def field(state):  # state coordinates -> (points, 3)
        return cant.state_map.to_dofs(state).reshape(-1, 3)

    steps = [int(round(t / dt)) for t in cfg["render_times"]]
    columns = {"FOM": snaps.Q}
    for m in ("galerkin_ecsw", "poly_lopinf", "lopinf"):
        Qh = state_series.get(m)
        if Qh is not None and np.all(np.isfinite(Qh[:, steps])):
            columns[f"{LABELS[m]} r={r}"] = basis.V @ Qh[:, steps]
    frames = []
    for i, k in enumerate(steps):
        frames.append({label: field(Q[:, k] if label == "FOM" else Q[:, i])
                       for label, Q in columns.items()})
    path = out / f"deformed_{material}.png"
    if grid is not None:
        _side_by_side(path, grid, frames, titles=[f"t = {k * dt:.2f} s" for k in steps],
                      title=f"{material}, a = {a:g} (unseen), true scale")
    errs = {}
    for label, Q in columns.items():
        if label != "FOM":
            d = [np.linalg.norm(Q[:, i] - snaps.Q[:, k]) / np.linalg.norm(snaps.Q[:, k])
                 for i, k in enumerate(steps)]
            errs[label] = d
    return {"png": path.name, "times": [k * dt for k in steps], "columns": list(columns),
            "relative_state_error_per_time": errs}


def _side_by_side(path, grid, frames, *, titles, title):
    """One row per time, one column per label; side view (x right, z up), true scale."""
    return render.deformed_side_by_side(
        path, grid, frames, magnify=1.0, titles=titles, title=title, panel=(440, 230),
        camera=[(0.5, -2.6, -0.08), (0.5, 0.0, -0.08), (0, 0, 1)], parallel_scale=0.5,
        scalar_bar={"title": "displacement [m]", "vertical": False, "position_x": 0.25,
                    "position_y": 0.05, "width": 0.5, "height": 0.12, "fmt": "%.2f"})


def _print_table(material, rows, long_rows, cfg):
    print(f"  tip error ({material}) per amplitude / r   [ROM s compiled|numpy, FOM s]:")
    for m in METHODS:
        for r in cfg["r_values"]:
            sel = [row for row in rows if row["method"] == m and row["r"] == r]
            errs = "  ".join(f"{row['tip_error']:.2e}" for row in sel)
            print(f"    {m:14s} r={r}: {errs}   [{sel[-1]['rom_seconds']:.3f}|"
                  f"{sel[-1]['rom_seconds_numpy']:.3f} s, FOM {sel[-1]['fom_seconds']:.1f} s]")
    for row in long_rows:
        print(f"    long {row['method']:14s} r={row['r']} {row['scheme']:8s} stable={row['stable']} "
              f"rom drift {row.get('rom_energy_drift', float('nan')):.2e} "
              f"FOM energy err {row.get('fom_energy_error', float('nan')):.2e}")


if __name__ == "__main__":
    main()  # one rank failing aborts the job: the package's excepthook (dolfinx_lopinf._mpi_abort)
