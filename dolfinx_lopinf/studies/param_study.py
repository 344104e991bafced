"""The parametric demos' shared study: FOM runs at training and test parameters, the four
methods at every r, one row per (method, r, mu, split).

Methods (``method`` of a row):

* ``lopinf``: parametric L-OpInf (:func:`dolfinx_lopinf.core.parametric.fit_affine`; a
  non-affine parameter: :func:`dolfinx_lopinf.core.interpolated.fit_interpolated`,
  log-Euclidean SPD interpolation);
* ``intrusive``: the intrusive parametric Galerkin ROM - the affine terms projected
  (:meth:`dolfinx_lopinf.fem.affine.ParametricSystem.intrusive`); for a non-affine parameter
  the Galerkin ROM assembled and projected at each test parameter (what a code with the
  operators at hand can do at every mu);
* ``projection``: the projection floor ||Q - V V^T M Q|| / ||Q|| of the FOM trajectory;
* ``opinf``: opinf's parametric model (:mod:`dolfinx_lopinf.studies.param_peers`; affine or
  interpolated as the parameter is).

All in one basis: the POD of every training trajectory, orthonormal in the parameter-free
mass (so Mh = I is exact for the Galerkin ROM and for L-OpInf), truncated to each r. Every
ROM starts from rest and is driven by the trajectory's recorded inputs; ``test_error`` is
the relative Frobenius error of the reconstructed states over the whole window (``train``
rows: the worst of the training trajectories at that parameter); ``max_energy_error`` the
largest |E(V qh, V vh) - E_FOM(t)| / max E_FOM (:func:`energy_error`: the FOM energy of the
reconstructed state, exact through V^T K(mu) V) and ``stable`` :func:`harness.stable` of
the states with that energy error.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from ..core.basis import pod
from ..core.interpolated import fit_interpolated
from ..core.parametric import fit_affine
from ..core.rom import LagrangianROM
from ..errors import ParameterRangeWarning
from ..fem import param_fom
from ..fem.intrusive import reduced_matrix
from . import harness


def run_foms(psys, mus, loads, dt, n_steps, scheme="newmark"):
    """[(mu, Snapshots)] for every mu and load, on every rank (the FOM runs on all ranks, its
    gathered snapshots are broadcast: the reduced fits then run alike everywhere), and the
    total FOM seconds."""
    comm = psys.V.mesh.comm
    out, seconds = [], 0.0
    for mu in mus:
        for load in loads:
            snap, sec = param_fom.simulate(psys, mu, dt, n_steps, inputs=load, scheme=scheme)
            if comm.size > 1:
                snap = comm.bcast(snap, root=0)
            out.append((np.atleast_1d(np.asarray(mu, float)), snap))
            seconds += sec
    return out, seconds


def galerkin_at(psys, mu, basis, scheme):
    """The Galerkin ROM at one mu (forms assembled there, projected)."""
    ops = psys.assemble(mu)
    V = basis.V

    def red(A):
        R = reduced_matrix(A, psys.V, V, psys.state_map)
        return 0.5 * (R + R.T)

    M, K = red(ops["M"]), red(ops["K"])
    C = None if ops["C"] is None else red(ops["C"])
    B = None
    if ops["b"]:
        B = np.column_stack([V.T @ psys._state_vector(b) for b in ops["b"]])
    for A in [ops["M"], ops["K"], ops["C"], *ops["b"]]:
        if A is not None:
            A.destroy()
    return LagrangianROM(K=K, M=M, C=C, B=B, scheme=scheme, lagrangian=False)


def energy_error(Qh, Vh, Kg, fom_energy):
    """|E(V qh, V vh) - E_FOM(t)| / max E_FOM per sample: the FOM energy of the reconstructed
    state, 1/2 vh^T vh + 1/2 qh^T (V^T K(mu) V) qh (the basis orthonormal in the mass)."""
    with np.errstate(all="ignore"):
        e = 0.5 * np.sum(Vh * Vh, axis=0) + 0.5 * np.einsum("ik,ij,jk->k", Qh, Kg, Qh)
        return np.abs(e - fom_energy) / np.max(np.abs(fom_energy))


def _error(Q, V, Qh):
    return float(np.linalg.norm(Q - V @ Qh) / np.linalg.norm(Q))


def _inside(mu, lo, hi):
    return bool(np.all(mu >= lo - 1e-12) and np.all(mu <= hi + 1e-12))


def study(psys, *, train, test, loads, test_load, dt, n_steps, r_list, scheme="newmark",
          peers=True, timing_repeats=5):
    """Run the study (module docstring). Returns a dict: ``rows``, ``fits`` (per method and
    r: seconds, certificate), ``fom_seconds``, the data and the last models (for figures)."""
    affine = psys.structure is not None
    train_data, fom_train = run_foms(psys, train, loads, dt, n_steps, scheme)
    test_data, fom_test = run_foms(psys, test, [test_load], dt, n_steps, scheme)
    mu_train = np.array([mu for mu, _ in train_data])
    lo, hi = mu_train.min(axis=0), mu_train.max(axis=0)
    W = psys.mass_matrix()
    big = pod(np.hstack([s.Q for _, s in train_data]), max(r_list), weight=W)
    cases = []
    for mu in np.unique(mu_train, axis=0):
        cases.append(("train", mu, [s for m, s in train_data if np.array_equal(m, mu)]))
    for mu, s in test_data:
        cases.append(("test", mu, [s]))
    rows, fits, models = [], [], {}
    for r in r_list:
        b = big.truncate(r)
        mine = {}
        t0 = time.perf_counter()
        if affine:
            model = fit_affine(train_data, psys.structure, basis=b, scheme=scheme)
            mine["intrusive"] = psys.intrusive(b, scheme, dt, mu_train)
        else:
            model = fit_interpolated(train_data, basis=b, scheme=scheme,
                                     damping=psys.forms["damping"] is not None)
        total = time.perf_counter() - t0
        mine["lopinf"] = model
        fit = {"method": "lopinf", "r": r, "fit_seconds": model.report["fit_seconds"],
               "fit_total_seconds": total, "report": _plain_report(model.report)}
        if affine:
            fit["fit_seconds_min"], fit["fit_cpu_seconds_min"] = _timed_refit(
                train_data, psys.structure, b, scheme, model.report["damping"], timing_repeats)
        fit["form_seconds"] = _form_time(model, test_data[0][0])
        fits.append(fit)
        if peers:
            from .param_peers import opinf_parametric

            peer = opinf_parametric(train_data, b, kind="affine" if affine else "interpolated",
                                    structure=psys.structure)
            mine["opinf"] = peer
            fits.append({"method": "opinf", "r": r, "fit_seconds": peer.fit_seconds,
                         "regularizer": peer.regularizer})
        for split, mu, snaps in cases:
            inside = _inside(mu, lo, hi)
            base = {"r": r, "mu": mu.tolist(), "split": split, "inside": inside}
            proj = max(b.projection_error(s.Q) for s in snaps)
            rows.append({"method": "projection", **base, "test_error": proj, "stable": True})
            galerkin = None if affine else galerkin_at(psys, mu, b, scheme)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ParameterRangeWarning)
                Kg = mine["intrusive"].operators(mu)[2] if affine else galerkin.K
            runs = dict(mine)
            if not affine and split == "test":
                runs["intrusive"] = galerkin
            for name, m in runs.items():
                errs, e_errs, ok, secs = [], [], True, 0.0
                for s in snaps:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", ParameterRangeWarning)
                        if name == "opinf":
                            t1 = time.perf_counter()
                            Qh, Vh, finite = m.predict(mu, s.times, s.U)
                            secs = max(secs, time.perf_counter() - t1)
                        else:
                            traj = (m.simulate(np.zeros(r), np.zeros(r), dt, n_steps, inputs=s.U)
                                    if m is galerkin else m.predict(mu, n_steps, inputs=s.U))
                            Qh, Vh, finite, secs = traj.Qh, traj.Vh, True, max(secs, traj.seconds)
                    errs.append(_error(s.Q, b.V, Qh))
                    e_err = energy_error(Qh, Vh, Kg, s.energy)
                    e_errs.append(float(np.max(e_err)) if np.all(np.isfinite(e_err)) else float("inf"))
                    ok = ok and finite and harness.stable(Qh, e_err)
                rows.append({"method": name, **base, "test_error": max(errs), "stable": bool(ok),
                             "max_energy_error": max(e_errs), "rom_seconds": secs,
                             "projection_error": proj,
                             **({"note": "Galerkin ROM assembled at this mu"} if m is galerkin else {})})
        models[r] = (b, mine)
    return {"rows": rows, "fits": fits, "fom_seconds": fom_train + fom_test, "train": train_data,
            "test": test_data, "models": models, "mu_range": [lo.tolist(), hi.tolist()]}


def _timed_refit(train_data, structure, basis, scheme, damping, repeats):
    """The smallest fit time (wall, CPU) over ``repeats`` fits with the chosen damping (the
    engine's time on a shared machine: the minimum is the least disturbed)."""
    best = [np.inf, np.inf]
    for _ in range(repeats):
        m = fit_affine(train_data, structure, basis=basis, scheme=scheme, damping=damping)
        best = [min(best[0], m.report["fit_seconds"]), min(best[1], m.report["fit_cpu_seconds"])]
    return best


def _form_time(model, mu, repeats=50):
    """The median time to form the fixed-parameter ROM at a new mu from the r x r terms (its
    operators and the LagrangianROM's checks): the online cost a new parameter adds."""
    times = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ParameterRangeWarning)
        for _ in range(repeats):
            t0 = time.perf_counter()
            model.rom(mu)
            times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _plain_report(report):
    keep = ("method", "damping", "held_back_errors", "trajectories", "parameters_trained",
            "samples", "r", "mass", "fit_seconds", "fit_cpu_seconds", "project_seconds",
            "choice_seconds", "scheme",
            "structure", "stable_for", "certificates")
    out = {k: report[k] for k in keep if k in report}
    if "certificate" in report:
        c = report["certificate"]
        out["certificate"] = {k: c[k] for k in ("solver", "converged", "duality_gap", "iterations",
                                                "relative_residual", "stable_for", "cone",
                                                "min_eig", "psd_blocks", "free_columns",
                                                "solve_seconds") if k in c}
    return out


def table(rows, methods=("lopinf", "intrusive", "projection", "opinf")) -> str:
    """A text table: one line per (r, mu, split), one column per method."""
    keys = sorted({(r["r"], tuple(r["mu"]), r["split"]) for r in rows},
                  key=lambda k: (k[0], k[2] != "train", k[1]))
    head = f"{'r':>3} {'split':>5} {'mu':>22} " + " ".join(f"{m:>11}" for m in methods) + "  stable"
    lines = [head]
    for r, mu, split in keys:
        sel = {x["method"]: x for x in rows if x["r"] == r and tuple(x["mu"]) == mu
               and x["split"] == split}
        cells = " ".join(f"{sel[m]['test_error']:11.3e}" if m in sel else f"{'-':>11}"
                         for m in methods)
        inside = next(iter(sel.values()))["inside"]
        stable = all(x["stable"] for x in sel.values())
        mu_txt = ", ".join(f"{v:.4g}" for v in mu) + ("" if inside else " (out)")
        lines.append(f"{r:>3} {split:>5} {mu_txt:>22} {cells}  {stable}")
    return "\n".join(lines)
