"""The user-loop study: record each loop with ``lo.SnapshotRecorder``, fit ``lo.fit`` with
today's defaults, and score it against the intrusive ROM of the loop's own scheme and the
projection floor (the "before" figures for scheme-aware fitting).

Per loop and r, on the unseen test load (predictions from rest, the loop's own inputs):

* ``lofit``: ``lo.fit(train, r)`` (defaults), ``model.predict(n, inputs=test.U)`` - the
  inputs as the loop recorded them (``applied_load``, taken at the loop's own load times);
* ``intrusive``: Galerkin operators W^T {M, C, K, B} in the same POD basis W (``model.basis``)
  integrated by :func:`reference.integrate` with the loop's scheme, step and load times;
* ``floor``: ||Q - W W^T Q||_F / ||Q||_F of the test states (no ROM in span W does better).

Errors are relative Frobenius errors of the point output y (``loop.OUTPUT``) and of the
states. The membrane loop also runs a long free vibration (source off after 0.5 s) and
reports the drift of the central-difference energy
E_{k+1/2} = 1/2 d_k^T M d_k + 1/2 q_k^T K q_{k+1}, d_k = (q_{k+1} - q_k)/dt (exactly
conserved by the unforced loop) of the FOM and of both ROMs' reconstructed states.

Rounding (``copies``): each recording is also fitted as ``copies - 1`` copies whose snapshots
differ from it at 1e-15 (what another BLAS or rank layout does): the choices and test errors
of the copies should agree, since a choice that rounding decides is a choice nobody can
reproduce.
"""

from __future__ import annotations

import dataclasses
import importlib
import time
import warnings
from pathlib import Path

import numpy as np

import dolfinx_lopinf as lo
from . import operators, reference

LOOPS = ("comet_gen_alpha", "hht_plane_strain", "membrane_central_difference",
         "newmark_nonlinear_problem", "newmark_every_k")


def load_loop(name):
    if name not in LOOPS:
        raise ValueError(f"unknown loop {name!r}; one of {LOOPS}")
    return importlib.import_module(f"{__package__}.{name}")


#: how the user attaches the recorder: ``"at_t"`` - the load value at the record time,
#: ``rec.record(t, u, inputs=[load(t)])`` (what a user writes without thinking about the
#: scheme); ``"applied"`` - the value the loop applied and when,
#: ``rec.record(t, u, inputs=[p], input_time=t_applied)``; ``"uva"`` - as "applied", with the
#: loop's velocity and acceleration Functions handed to the recorder (where it has them)
STYLES = ("at_t", "applied", "uva")


def record(loop, load, t_end, size, *, collect=False, style="applied"):
    """Run the loop with a recorder on ``on_step``: (snapshots, recorder, info, collector)."""
    held = {}
    col = operators.Collector() if collect else None

    def on_step(t, u, v, a, applied_load, applied_time):
        if "rec" not in held:  # the user's three lines: make the recorder, record, snapshots()
            V = u.function_space
            E = lo.point_output_matrix(V, np.array(loop.OUTPUT["points"], dtype=float),
                                       component=loop.OUTPUT.get("component"))
            fields = {"velocity": v, "acceleration": a} if style == "uva" and a is not None else {}
            held["rec"] = lo.SnapshotRecorder(u, output_matrix=E, **fields)
        if style == "at_t":
            held["rec"].record(t, u, inputs=[load(t)])
        else:
            held["rec"].record(t, u, inputs=[applied_load], input_time=applied_time)
        if col is not None:
            col(t, u, v, a, applied_load, applied_time)

    t0 = time.perf_counter()
    info = loop.simulate(load, t_end, size=size, on_step=on_step)
    info["wall_seconds"] = time.perf_counter() - t0
    return held["rec"].snapshots(), held["rec"], info, col


def true_scheme(info):
    """The loop's integrator as a dolfinx_lopinf.schemes object."""
    s = info["scheme"]
    if s["alpha_m"] == 0 and s["alpha_f"] == 0:
        return lo.schemes.Newmark(s["beta"], s["gamma"])
    return lo.schemes.GeneralizedAlpha(s["alpha_m"], s["alpha_f"], s["beta"], s["gamma"])


def verify(loop, size="quick", load=None, t_end=None, *, keep=False):
    """The reference with the full basis I[:, free] (r = n) against the loop's own (u, v, a):
    relative errors per field, and the sizes (``keep``: also the snapshots, the collected
    arrays, the loop's info and the operators, for the tests)."""
    load = loop.train_load if load is None else load
    t_end = loop.SIZES[size]["t_train"] if t_end is None else t_end
    snaps, rec, info, col = record(loop, load, t_end, size, collect=True)
    ops = operators.fe_operators(loop, info["V"], rec.state_map)
    X = col.arrays(rec.state_map)
    free = ops["free"]
    W = np.eye(len(free) + int(ops["fixed"].sum()))[:, free]
    sch = info["scheme"]
    t0 = time.perf_counter()
    ref = reference.integrate(reference.galerkin(ops, W), sch, info["dt"], info["n_steps"],
                              inputs=load, every=sch["record_every"])
    out = {"n": int(W.shape[0]), "n_free": int(len(free)), "samples": len(X["times"]),
           "reference_seconds": time.perf_counter() - t0, "fixed_max": float(np.abs(X["Q"][ops["fixed"]]).max()),
           "times_error": float(np.abs(X["times"] - ref["times"]).max()),
           "recorded_equals_collected": bool(np.array_equal(snaps.Q, X["Q"]))}
    for key in ("Q", "V", "A"):
        out[key] = None if X[key] is None else reference.rel_error(X[key][free], ref[key])
    if keep:
        out.update(snapshots=snaps, collected=X, info=info, ops=ops)
    return out


def _fit(train, r, **kwargs):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t0 = time.perf_counter()
        model = lo.fit(train, r, **kwargs)
        seconds = time.perf_counter() - t0
    return model, seconds, sorted({f"{w.category.__name__}: {str(w.message)[:160]}" for w in caught})


#: the relative size of the perturbation of a rounding copy (:func:`perturbed`)
COPY_DELTA = 1e-15


def perturbed(snaps, seed):
    """A copy of ``snaps`` whose states are multiplied by 1 + COPY_DELTA N(0, 1) (seeded)."""
    rng = np.random.default_rng(seed)
    return dataclasses.replace(snaps, Q=snaps.Q * (1.0 + COPY_DELTA * rng.standard_normal(snaps.Q.shape)))


def _copies(train, test, r, copies, n_test, load, first):
    """The rounding copies of one fit: their choices (mass/damping/scheme) and output errors,
    the unperturbed fit (``first``, a _scored dict) included."""
    rows = [first]
    for seed in range(1, copies):
        try:
            rows.append(_scored(*_fit(perturbed(train, seed), r), test, n_test, load))
        except Exception as exc:  # noqa: BLE001 - a failing copy is a disagreement, recorded
            rows.append({"failure": f"{type(exc).__name__}: {exc}"[:200]})
    choices = [None if "failure" in x else f"{x['mass']}/{x['damping']}/{x['scheme']}" for x in rows]
    errors = [x.get("output") for x in rows]
    ok = [e for e in errors if e is not None]
    return {"choices": choices, "outputs": errors, "agree": len(set(choices)) == 1 and None not in choices,
            "spread": (max(ok) / max(min(ok), 1e-300)) if ok else None}


def _scored(model, seconds, warns, test, n_test, load):
    """A fitted model's row entries on the unseen load (predicted from rest with the load as a
    callable: the ROM evaluates it where its scheme does)."""
    pred = model.predict(n_test, inputs=load)
    return {"output": reference.rel_error(test.Y, pred.Y),
            "state": reference.rel_error(test.Q, model.reconstruct(pred.Qh)),
            "fit_seconds": seconds, "rom_seconds": pred.seconds, "scheme": model.scheme.spec,
            "mass": model.report.get("mass"), "damping": model.report.get("damping"),
            "identification": model.report["identification"].get("why", ""), "warnings": warns}


def _intrusive(ops, W, info, load, n_fine):
    sch = info["scheme"]
    red = reference.galerkin(ops, W)
    traj = reference.integrate(red, sch, info["dt"], n_fine, inputs=load, every=sch["record_every"])
    return W @ traj["Q"]


def leapfrog_energy(Q, M, K, dt):
    """E_{k+1/2} = 1/2 d^T M d + 1/2 q_k^T K q_{k+1}, d = (q_{k+1} - q_k)/dt, per column pair."""
    D = np.diff(Q, axis=1) / dt
    return 0.5 * np.einsum("ik,ik->k", D, M @ D) + 0.5 * np.einsum("ik,ik->k", Q[:, :-1], K @ Q[:, 1:])


def run_loop(name, size="default", rs=(2, 4, 8), save_to=None, peer=True, copies=1):
    """Everything the table shows for one loop (a plain dict for metrics.json); with ``save_to``,
    the recorded Snapshots are saved there too (``{name}_{style}_{train,test}.npz``, to re-fit
    without running the loop: ``lo.Snapshots.load``).

    Rows per r (unseen test load, predicted from rest): ``lo.fit`` defaults on each recording
    style (:data:`STYLES`), ``lo.fit(scheme=<the loop's scheme>)`` on the "applied" recording,
    the intrusive ROM of the loop's scheme and the projection floor in the defaults' basis,
    and opinf's first-order model (the peer) where installed; with ``copies`` > 1 the
    defaults' fits also on rounding copies of each recording (module docstring)."""
    loop = load_loop(name)
    pre = loop.SIZES[size]
    data = {}
    for style in STYLES:
        train, rec, info, _ = record(loop, loop.train_load, pre["t_train"], size, style=style)
        if style == "uva" and train.A is None:
            continue  # the loop keeps no acceleration
        test, _, info_test, _ = record(loop, loop.test_load, pre["t_test"], size, style=style)
        data[style] = (train, test)
        if save_to is not None:
            train.save(Path(save_to) / f"{name}_{style}_train.npz")
            test.save(Path(save_to) / f"{name}_{style}_test.npz")
    train, test = data["applied"]
    V, sch = info["V"], info["scheme"]
    ops = operators.fe_operators(loop, V, rec.state_map)
    _, E_state = operators.output_matrix(loop, V, rec.state_map)
    truth = true_scheme(info)
    out = {"loop": name, "size": size, "n_dofs": int(train.n_states), "n_free": int(len(ops["free"])),
           "dt": info["dt"], "record_dt": float(train.dt), "scheme": sch, "true_scheme": truth.spec,
           "steps_train": info["n_steps"], "steps_test": info_test["n_steps"],
           "samples_train": len(train.times), "samples_test": len(test.times),
           "fom_seconds_train": info["seconds"], "fom_seconds_test": info_test["seconds"],
           "output_check": reference.rel_error(train.Y, E_state @ train.Q),
           "max_abs_output_test": float(np.abs(test.Y).max()), "styles": list(data), "rows": []}
    n_test = len(test.times) - 1
    free_run = None
    if hasattr(loop, "free_load"):
        free, _, info_free, _ = record(loop, loop.free_load, pre["t_free"], size)
        if save_to is not None:
            free.save(Path(save_to) / f"{name}_free.npz")
        k_off = int(np.searchsorted(free.times, 0.5 + 1e-9))
        e_fom = leapfrog_energy(free.Q, ops["M"], ops["K"], free.dt)[k_off:]
        free_run = {"t_free": pre["t_free"], "steps": info_free["n_steps"],
                    "fom_energy_drift": float(np.max(np.abs(e_fom - e_fom[0])) / e_fom[0])}
        out["free_run"] = free_run
    peers = _peers(train, test, rs, E_state, loop) if peer else {}
    for r in tuple(rs) + tuple(x for x in pre.get("extra_r", ()) if x not in rs):
        row = {"r": r, "fits": {}}
        for key, style, kwargs in [(st, st, {}) for st in data] + [("named", "applied", {"scheme": truth})]:
            try:
                model, fit_s, warns = _fit(data[style][0], r, **kwargs)
                row["fits"][key] = _scored(model, fit_s, warns, data[style][1], n_test, loop.test_load)
                if copies > 1 and not kwargs:
                    row["fits"][key]["copies"] = _copies(data[style][0], data[style][1], r, copies,
                                                         n_test, loop.test_load, row["fits"][key])
                if key == "applied":  # the span of lo.fit's basis, Euclidean-orthonormal (its
                    # own V is orthonormal in the recorded weight): the floor and the
                    # Galerkin ROM of that span
                    W, default_model = np.linalg.qr(model.basis.V)[0], model
            except Exception as exc:  # record the failure, keep going
                row["fits"][key] = {"failure": f"{type(exc).__name__}: {exc}"[:300]}
        if "applied" not in row["fits"] or "failure" in row["fits"]["applied"]:
            W, default_model = reference.pod_basis(train.Q, r), None
        t0 = time.perf_counter()
        Q_int = _intrusive(ops, W, info, loop.test_load, info_test["n_steps"])
        row.update(intrusive_output=reference.rel_error(test.Y, E_state @ Q_int),
                   intrusive_state=reference.rel_error(test.Q, Q_int),
                   intrusive_seconds=time.perf_counter() - t0,
                   floor_state=reference.projection_floor(test.Q, W),
                   floor_output=reference.rel_error(test.Y, E_state @ (W @ (W.T @ test.Q))))
        if r in peers:
            row["opinf_output"] = peers[r]
        if free_run is not None:
            Q_int_free = _intrusive(ops, W, info_free, loop.free_load, info_free["n_steps"])
            row["intrusive_free_energy_drift"] = _drift(Q_int_free, ops, free.dt, k_off)
            if default_model is not None:
                pf = default_model.predict(len(free.times) - 1, inputs=loop.free_load)
                row["lofit_free_energy_drift"] = _drift(default_model.reconstruct(pf.Qh), ops,
                                                        free.dt, k_off)
                row["lofit_free_output"] = reference.rel_error(free.Y, pf.Y)
                row["rom_own_energy_drift"] = _rom_energy_drift(default_model, pf, free.dt, k_off)
        out["rows"].append(row)
    return out


def _peers(train, test, rs, E_state, loop):
    """opinf's first-order model (studies.peers) per r: unseen-load output error, or {}."""
    from .. import peers

    if not peers.have_opinf():
        return {}
    out = {}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            models = peers.opinf_first_order(train.Q, train.times, list(rs), inputs=loop.train_load,
                                             output_matrix=E_state)
        for r, peer in zip(rs, models):
            pred = peer.predict(test.Q[:, 0], np.zeros(test.n_states), test.times, loop.test_load,
                                full=False)
            out[r] = reference.rel_error(test.Y, pred.Y) if pred.finite else float("inf")
    except Exception as exc:  # the peer is a comparison: its failure is a result
        return {r: f"failed: {type(exc).__name__}: {str(exc)[:120]}" for r in rs}
    return out


def _rom_energy_drift(model, traj, dt, k_off):
    """Relative drift, after the source is off, of the energy the ROM's own scheme conserves
    when it has no damping: the leapfrog energy with (Mh, Kh) for central differences, the
    nodal 1/2 v^T Mh v + 1/2 q^T Kh q otherwise (average acceleration, midpoint); None for a
    damped or dissipative ROM."""
    rom = model.rom
    if rom.C is not None:
        return None
    if isinstance(rom.scheme, lo.schemes.Newmark) and rom.scheme.beta == 0:
        e = leapfrog_energy(traj.Qh, rom.mass, rom.K, dt)[k_off:]
    elif rom.scheme in (lo.schemes.Newmark(), lo.schemes.Midpoint()):
        e = rom.energy(traj.Qh, traj.Vh)[k_off:]
    else:
        return None
    return float(np.max(np.abs(e - e[0])) / abs(e[0])) if e[0] else float("inf")


def _drift(Q, ops, dt, k_off):
    e = leapfrog_energy(Q, ops["M"], ops["K"], dt)[k_off:]
    if not np.all(np.isfinite(e)) or e[0] == 0:
        return float("inf")
    return float(np.max(np.abs(e - e[0])) / abs(e[0]))


def _fmt(x):
    if x is None:
        return "failed"
    return f"{x:.2e}" if isinstance(x, float) else str(x)


def table(result) -> str:
    """The per-loop table: lo.fit (defaults on each recording style, the named scheme) vs the
    intrusive ROM of the same scheme vs the projection floor vs opinf; output errors."""
    s = result["scheme"]
    lines = [f"{result['loop']}: {result['n_dofs']} dofs ({result['n_free']} free), {result['true_scheme']}"
             f", dt {result['dt']:g}, recorded every {s['record_every']} (dt {result['record_dt']:g}), "
             f"{result['samples_train']} training samples, FOM {result['fom_seconds_train']:.2f} s train / "
             f"{result['fom_seconds_test']:.2f} s test",
             f"  {'r':>2}  " + "  ".join(f"{k:>10}" for k in result["styles"] + ["named"])
             + f"  {'intrusive':>10}  {'floor':>10}  {'opinf':>10}  fit s (applied)  chose (applied)"]
    for x in result["rows"]:
        cells = [_fmt(x["fits"].get(k, {}).get("output")) for k in result["styles"] + ["named"]]
        ap = x["fits"].get("applied", {})
        op = x.get("opinf_output")
        lines.append(f"  {x['r']:>2}  " + "  ".join(f"{c:>10}" for c in cells)
                     + f"  {_fmt(x['intrusive_output']):>10}  {_fmt(x['floor_output']):>10}  "
                     f"{_fmt(op) if not isinstance(op, str) else 'failed':>10}  "
                     f"{_fmt(ap.get('fit_seconds')):>14}  {ap.get('mass', '-')}/"
                     f"{'damped' if ap.get('damping') else 'undamped'}/{ap.get('scheme', '-')}")
    copies = [(x["r"], k, f["copies"]) for x in result["rows"] for k, f in x["fits"].items() if "copies" in f]
    if copies:
        n = len(copies[0][2]["choices"])
        split = [f"r = {r} {k}: {' '.join(sorted(set(map(str, c['choices']))))}" for r, k, c in copies if not c["agree"]]
        spread = max((c["spread"] for _, _, c in copies if c["spread"] is not None), default=float("nan"))
        lines.append(f"  rounding copies ({n} per fit, {COPY_DELTA:g} apart): the choice agrees in "
                     f"{sum(c['agree'] for _, _, c in copies)} of {len(copies)} fits"
                     + (f" (differs: {'; '.join(split)})" if split else "")
                     + f"; output errors within {spread:.2f}x")
    if "free_run" in result:
        fr = result["free_run"]
        lines.append(f"  free run to t = {fr['t_free']:g} ({fr['steps']} steps), energy drift after the "
                     f"source: FOM {fr['fom_energy_drift']:.1e}; " + "; ".join(
                         f"r = {x['r']}: lo.fit {_fmt(x.get('lofit_free_energy_drift'))} (its own "
                         f"energy {_fmt(x.get('rom_own_energy_drift'))}), intrusive "
                         f"{_fmt(x['intrusive_free_energy_drift'])}" for x in result["rows"]))
    return "\n".join(lines)
