"""Inference benchmark: our structured solvers against cvxpy (Clarabel), side by side.

    python -m dolfinx_lopinf.studies.benchmark [--out FILE.json] [--quick] [--naive-up-to R]
    python -m dolfinx_lopinf.studies.benchmark --table      # the certified-fit inference table
    python -m dolfinx_lopinf.studies.benchmark --table --r 4,12 --sets mixed   # a selection
    python -m dolfinx_lopinf.studies.benchmark --table --mass --poly   # all three tables
    python -m dolfinx_lopinf.studies.benchmark --no-mh --fit a.npz,b.npz   # lo.fit end to end

For r in {2, 4, ..., 20} and K in {3000, 6000, 10000} snapshots it times

* ``ours``        - :func:`dolfinx_lopinf.core.infer_mechanical` / ``infer_wave`` (Gram pass + solve),
* ``cvxpy_comp``  - cvxpy/Clarabel on the same compressed problem (after our Gram pass),
* ``cvxpy_naive`` - cvxpy/Clarabel on the raw ||ddQh + K Qh + ...||_F over all K snapshots
                    (slow: by default only for r <= ``--naive-up-to``),

and reports objective gaps and minimum eigenvalues, on three data sets:

1. ``beam``      - conservative fit (Kh only) on block-POD data of our beam FOM;
2. ``forced``    - Kh, Ch, Bh on a forced, damped synthetic system with 1e-3 noise, where the
                   unconstrained fit is indefinite (the PSD constraints are active);
3. ``wave``      - the symmetric-only wave problem (Kh = Kh^T, qh_tt = Kh qh - Fh);
4. ``rigid``, ``mixed``, ``short`` - forced data where BOTH Kh and Ch are active at the
                   optimum (:func:`~dolfinx_lopinf.core.synthetic.active_data`: rigid-body
                   modes, overdamped + undamped + softening modes, a short noisy record);
5. ``chain``     - held-out style: a free-free spring chain, two inputs, half the dampers
                   missing (:func:`~dolfinx_lopinf.core.synthetic.chain_data`; in
                   ``--table``). Its fits take more
                   iterations (13 at r = 12, K = 993, where the others take 8-11), not
                   more time per iteration (per-phase CPU time at K = 993: the same cost
                   per iteration as the other kinds); a whole ``infer_mechanical`` call
                   also pays the Gram pass and the certificate around the solve.
6. ``file:PATH`` - recorded snapshots (``lo.Snapshots.save``, e.g. the loops study's):
                   Euclidean POD to r and the Newmark relation, every sample (one row per r;
                   K is the number of samples). On recorded loops the fits take 17-29
                   iterations at r = 20 where the synthetic kinds take 7-11: the normal matrix
                   has a condition of 1e18-1e20, the unconstrained minimiser is indefinite
                   along directions it hardly sees, and the interior point's start, made
                   positive, has an objective 1e9-1e12 times the optimum's.

``--mass`` and ``--poly`` add the learned-mass and polynomial tables
(:mod:`dolfinx_lopinf.studies.benchmark_mass`): our interior points against Clarabel on the
same problem.

``--table``: r in {4, 6, 12, 20}, K in {3000, 10000}, sets forced, rigid, mixed, short,
chain (others with ``--sets``), no naive cvxpy; the ``(solve)`` column is then the median of the
certified solve alone (compressed problem in, Kh, Ch, Bh out; inference's certificate
included; ``(min)`` its minimum), ``(numpy)`` the same with the interior point's numpy
iteration instead of the compiled one (:mod:`dolfinx_lopinf.core.lsq._compiled`, compiled
before any timer), the two interleaved,
``cvx-comp`` the median of 3 Clarabel runs on the same compressed problem, and
``active`` the number of eigenvalues of Kh and Ch at eps (r - face rank, from the solver's
certificate): the "both active" check.

Times are medians over repeats (``ours``) or single runs (cvxpy). Prints a table, writes JSON.
"""

from __future__ import annotations

import argparse
import functools
import json
import time
import warnings
from pathlib import Path

import numpy as np

from ..core import inference, lsq
from ..core.ddt import derivatives
from ..core.synthetic import ACTIVE_KINDS, HELD_OUT_KINDS, MASS_KINDS, mechanical_data, wave_data
from ..errors import InputError

R_VALUES = list(range(2, 21, 2))
K_VALUES = [3000, 6000, 10000]


def _median_time(fn, repeats):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def _cvxpy_compressed(gram, eps, kind):
    import cvxpy as cp

    r = gram.r
    zn = np.linalg.norm(gram.Z)
    s = zn / max(np.linalg.norm(gram.L), 1e-300)
    if kind == "wave":
        K = cp.Variable((r, r), symmetric=True)
        prob = cp.Problem(cp.Minimize(cp.sum_squares(K @ (gram.L * s / zn) + gram.Z / zn)))
        prob.solve(solver=cp.CLARABEL)
        return s * K.value
    ops = inference._solve_cvxpy(gram, eps)
    return np.hstack([ops.K] + ([ops.C] if ops.C is not None else [])
                     + ([-ops.B] if ops.B is not None else []))


def _cvxpy_naive(Qh, dQh, ddQh, U, eps, kind):
    import cvxpy as cp

    r = Qh.shape[0]
    K = cp.Variable((r, r), symmetric=True)
    if kind == "wave":
        expr, cons = ddQh - K @ Qh, []  # ddQh here already holds ddQh + Fh
    else:
        expr, cons = ddQh + K @ Qh, [K >> eps * np.eye(r)]
        if dQh is not None:
            C = cp.Variable((r, r), symmetric=True)
            expr, cons = expr + C @ dQh, cons + [C >> eps * np.eye(r)]
        if U is not None:
            B = cp.Variable((r, U.shape[0]))
            expr = expr - B @ U
    prob = cp.Problem(cp.Minimize(cp.sum_squares(expr)), cons)
    prob.solve(solver=cp.CLARABEL)
    return float(prob.value)


def beam_data(k_max: int):
    """Block-POD training data of our beam FOM: (Q (400, k_max+1), times, blocks)."""
    from .. import run
    from ..scenes import beam as scene

    b = scene.build(200)
    q0, v0 = b.initial_state()
    snaps, _ = run(b.system, q0, v0, scene.DT, k_max * scene.DT, state_map=b.state_map,
                   record_velocity=False, energy_every=0, progress=False)
    return snaps


def _fit_for(kind: str, r: int, K: int, beam, eps: float):
    """The fit to time on one data set: ``(fit, Qh, dQh, target, U, damping)``; ``fit()`` runs
    :func:`~dolfinx_lopinf.core.infer_mechanical` (or ``infer_wave``) and takes ``solver=``."""
    if kind == "beam":
        from ..core.basis import pod

        win = beam.window(0.0, (K + 7) * beam.dt)
        basis = pod(win.Q, r, blocks=win.blocks)
        Qh, _, ddQh = derivatives(basis.project(win.Q), win.times)
        fit = functools.partial(inference.infer_mechanical, Qh, None, ddQh, damping=False, eps=eps)
        return fit, Qh, None, ddQh, None, False
    if kind.startswith("file:"):  # recorded snapshots: every sample, K ignored
        from .benchmark_mass import mass_data

        Qh, dQh, ddQh, U = mass_data(kind, r)
        fit = functools.partial(inference.infer_mechanical, Qh, dQh, ddQh, U, eps=eps)
        return fit, Qh, dQh, ddQh, U, True
    if kind in ("forced", *ACTIVE_KINDS, *HELD_OUT_KINDS):
        Qh, dQh, ddQh, U = mechanical_data(kind, r, K)
        fit = functools.partial(inference.infer_mechanical, Qh, dQh, ddQh, U, eps=eps)
        return fit, Qh, dQh, ddQh, U, True
    Qh, ddQh, Fh = wave_data(r, K)
    return functools.partial(inference.infer_wave, Qh, ddQh, Fh), Qh, None, ddQh + Fh, None, False


def _time_fit(fit, with_numpy: bool, repeats: int):
    """``(ops, wall s median, solve s median, solve s min, numpy solve s median)``: the fit
    ``repeats`` times, each followed by the same fit with the numpy interior point when
    ``with_numpy`` (interleaved: a load that comes and goes hits both alike). The solve time
    is the certificate's ``seconds`` (compressed problem in, operators out)."""
    wall, solve, solve_np, ops = [], [], [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        ops = fit()
        wall.append(time.perf_counter() - t0)
        solve.append(ops.certificate.get("seconds", float("nan")))
        if with_numpy:
            solve_np.append(fit(solver=lsq.Auto(backend="numpy")).certificate["seconds"])
    return (ops, float(np.median(wall)), float(np.median(solve)), float(np.min(solve)),
            float(np.median(solve_np)) if solve_np else float("nan"))


def _set_name(kind: str) -> str:
    """The table's name of a data set (a recorded file: the start of its stem)."""
    return Path(kind[5:]).stem[:6] if kind.startswith("file:") else kind


def _print_row(row: dict) -> None:
    it, gap, active = row["iterations"], row["certified_gap"], row["active_eigenvalues"]
    print(f"{_set_name(row['set']):>6} {row['r']:>3} {row['K']:>6} {row['ours_seconds'] * 1e3:9.2f} "
          f"{row['ours_solve_seconds'] * 1e3:8.2f} {row['ours_solve_seconds_min'] * 1e3:6.2f} "
          f"{row['ours_solve_seconds_numpy'] * 1e3:8.2f} "
          f"{row['cvxpy_compressed_seconds'] * 1e3:11.1f} {row['cvxpy_naive_seconds'] * 1e3:12.1f} "
          f"{row['cvxpy_compressed_seconds'] / row['ours_seconds']:8.1f} "
          f"{row['relative_gap']:11.2e} {row['min_eig_K']:10.3e} "
          f"{it if it is not None else '-':>5} {gap if gap is not None else float('nan'):9.1e} "
          f"{'/'.join(map(str, active)) if active else '-':>7} {row['solver']}", flush=True)


def _bench_one(kind: str, r: int, K: int, beam, eps: float, args) -> dict:
    """One row of the benchmark: ours (and its numpy iteration) against cvxpy/Clarabel."""
    fit, Qh, dQh, target, U, damping = _fit_for(kind, r, K, beam, eps)
    if kind.startswith("file:"):
        K = Qh.shape[1]  # recorded snapshots: every sample
    ops, t_ours, solve_s, solve_min, solve_np = _time_fit(fit, damping, args.repeats)  # damped: numpy too
    gram = inference.gram_data(Qh, dQh, target, U, damping=damping)
    t_comp, theta_ref = _median_time(
        functools.partial(_cvxpy_compressed, gram, eps, kind), 3 if args.table else 1)
    ranks = ops.certificate.get("face_ranks")
    if kind == "wave":  # min ||(-Kh) Qh + (ddQh + Fh)||: theta = -Kh
        obj_ours, obj_ref = gram.objective(-ops.K), gram.objective(theta_ref)
    else:
        obj_ours, obj_ref = ops.certificate["objective"], gram.objective(theta_ref)
    t_naive = float("nan")
    if r <= args.naive_up_to:
        t0 = time.perf_counter()
        _cvxpy_naive(Qh, dQh, target, U, eps, kind)
        t_naive = time.perf_counter() - t0
    return {"set": kind, "r": r, "K": K, "ours_seconds": t_ours,
            "ours_solve_seconds": solve_s, "ours_solve_seconds_min": solve_min,
            "ours_solve_seconds_numpy": solve_np,
            "ipm_backend": (ops.certificate.get("ipm") or {}).get("backend"),
            "cvxpy_compressed_seconds": t_comp,
            "cvxpy_naive_seconds": t_naive, "objective_ours": obj_ours,
            "objective_cvxpy": obj_ref,
            "relative_gap": (obj_ours - obj_ref) / abs(obj_ref),
            "min_eig_K": float(np.linalg.eigvalsh(ops.K).min()),
            "min_eig_C": ops.certificate.get("min_eig_C"),
            "solver": ops.certificate.get("solver"),
            "iterations": ops.certificate.get("iterations"),
            "certified_gap": ops.certificate.get("duality_gap"),
            "symmetric": bool(np.array_equal(ops.K, ops.K.T)
                              and (ops.C is None or np.array_equal(ops.C, ops.C.T))),
            "active_eigenvalues": [r - k for k in ranks] if ranks else None}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="results/benchmark_inference.json")
    parser.add_argument("--quick", action="store_true", help="r in {4, 20}, K in {3000, 10000}")
    parser.add_argument("--naive-up-to", type=int, default=8,
                        help="run the naive cvxpy formulation for r <= this (it is slow)")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--sets", default=None,
                        help="comma-separated from beam, forced, wave, rigid, mixed, short, chain, "
                             "file:PATH (recorded snapshots) (default beam,forced,wave; with --table "
                             "forced,rigid,mixed,short,chain)")
    parser.add_argument("--table", action="store_true",
                        help="the certified-fit table: r in {4, 6, 12, 20}, K in {3000, 10000}, "
                             "both-active sets included, ours vs Clarabel compressed (ms), "
                             "iterations, certified gap, active eigenvalues of Kh/Ch")
    parser.add_argument("--r", default=None, help="comma-separated r values (overrides the above)")
    parser.add_argument("--mass", action="store_true",
                        help="also the learned-mass table (benchmark_mass: kinds modal, chainpod, "
                             "active; r in 2, 4, 8, 12, 16, 20; ours vs Clarabel on the same problem)")
    parser.add_argument("--mass-sets", default=None,
                        help="comma-separated learned-mass kinds (modal, chainpod, active, file:PATH)")
    parser.add_argument("--mass-r", default="2,4,8,12,16,20")
    parser.add_argument("--clarabel-up-to", type=int, default=12,
                        help="run Clarabel on the learned-mass problem for r <= this (it is slow)")
    parser.add_argument("--poly", action="store_true",
                        help="also the polynomial sos table (r in 4, 6, 8: ours vs Clarabel)")
    parser.add_argument("--poly-r", default="4,6,8")
    parser.add_argument("--no-mh", action="store_true", help="skip the Mh = I table")
    parser.add_argument("--fit", default=None, metavar="NPZ[,NPZ...]",
                        help="time lo.fit with its defaults end to end on recorded snapshots "
                             "(lo.Snapshots.save files, e.g. the loops study's)")
    parser.add_argument("--fit-r", default="4,8,12,20")
    args = parser.parse_args(argv)
    r_values = [4, 20] if args.quick else R_VALUES
    k_values = [3000, 10000] if args.quick else K_VALUES
    if args.table:
        r_values, k_values, args.naive_up_to = [4, 6, 12, 20], [3000, 10000], 0
    if args.r:
        r_values = [int(v) for v in args.r.split(",")]
    if args.sets is None:
        args.sets = "forced,rigid,mixed,short,chain" if args.table else "beam,forced,wave"
    eps, sets = 1e-8, args.sets.split(",")
    from ..core.lsq import _compiled

    jit_s = _compiled.warm_up()  # before any timer: compiled (or loaded from numba's cache) now
    print("interior point iteration: " + (f"compiled (numba), compile/cache load {jit_s:.2f} s, "
                                          "not in any timing" if jit_s is not None else
                                          "numpy (numba unavailable or DOLFINX_LOPINF_JIT=0)"))
    beam = beam_data(max(k_values) + 8) if "beam" in sets else None
    warnings.simplefilter("ignore", RuntimeWarning)
    print(f"{'set':>6} {'r':>3} {'K':>6} {'ours ms':>9} {'(solve)':>8} {'(min)':>6} {'(numpy)':>8} {'cvx-comp ms':>11} "
          f"{'cvx-naive ms':>12} {'speed-up':>8} {'gap vs cvx':>11} {'min eig K':>10} {'its':>5} "
          f"{'cert. gap':>9} {'active':>7} solver")
    rows = []
    for kind in sets if not args.no_mh else ():
        for r in r_values:
            for K in k_values if not kind.startswith("file:") else k_values[:1]:
                try:
                    rows.append(_bench_one(kind, r, K, beam, eps, args))
                except InputError as exc:  # recorded snapshots that cannot carry r: a row saying so
                    if not kind.startswith("file:"):
                        raise
                    rows.append({"set": kind, "r": r, "refused": str(exc)[:160]})
                    print(f"{_set_name(kind):>6} {r:>3} refused: {rows[-1]['refused'][:90]}")
                    continue
                _print_row(rows[-1])
    extra = _mass_and_poly(args)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"eps": eps, "ipm_compile_seconds": jit_s, "rows": rows, **extra},
                              indent=1, default=float))
    print(f"wrote {out}")
    return rows


def _mass_and_poly(args) -> dict:
    """The learned-mass and polynomial tables (:mod:`.benchmark_mass`) when asked for."""
    out = {}
    if args.mass:
        from ..core.lsq import _fractional_compiled
        from . import benchmark_mass as bm

        jit_s = _fractional_compiled.warm_up()
        print(f"\nlearned-mass iteration compiled (numba), compile/cache load {jit_s:.2f} s" if jit_s is not None
              else "\nlearned-mass iteration: numpy")
        bm.print_mass_header()
        kinds = args.mass_sets.split(",") if args.mass_sets else list(MASS_KINDS)
        out["mass_rows"] = []
        for kind in kinds:
            for r in (int(v) for v in args.mass_r.split(",")):
                row = bm.mass_row(kind, r, repeats=max(1, min(args.repeats, 5)),
                                  clarabel=r <= args.clarabel_up_to)
                bm.print_mass_row(row)
                out["mass_rows"].append(row)
    if args.poly:
        from . import benchmark_mass as bm

        bm.print_poly_header()
        out["poly_rows"] = []
        for r in (int(v) for v in args.poly_r.split(",")):
            row = bm.poly_row(r)
            bm.print_poly_row(row)
            out["poly_rows"].append(row)
    if args.fit:
        out["fit_rows"] = fit_table(args.fit.split(","), [int(v) for v in args.fit_r.split(",")],
                                    repeats=max(1, min(args.repeats, 3)))
    return out


def fit_table(paths, r_values, repeats: int = 3) -> list[dict]:
    """``lo.fit(snapshots, r)`` with every default (scheme identification, mass and damping
    chosen on a held-back end) on recorded snapshots: the best wall time of ``repeats`` after
    one warm-up fit (kernels compiled or loaded before), what it chose, the certificate, and
    how many warnings the user saw. A reduced dimension the data cannot carry is a row with
    its refusal."""
    from ..core import compiled
    from ..core.lsq import _compiled, _fractional_compiled
    from ..core.fit import PARALLEL_FROM_R, fit, fit_threads
    from ..core.snapshots import Snapshots

    compiled.warm_up()
    _compiled.warm_up()
    _fractional_compiled.warm_up()
    threads = fit_threads()
    print(f"\nlo.fit defaults end to end (best of {repeats}, after one warm-up fit; the candidates "
          f"on {threads} thread{'s' if threads > 1 else ''} from r = {PARALLEL_FROM_R} on)\n"
          f"{'snapshots':>28} {'r':>3} {'wall s':>7} {'mass':>8} {'gap':>9} cert warn scheme")
    rows = []
    for path in paths:
        S = Snapshots.load(path)
        name = Path(path).stem
        for r in r_values:
            row = {"snapshots": name, "n_states": int(S.Q.shape[0]), "n_samples": int(S.Q.shape[1]), "r": r}
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    fit(S, r)
            except InputError as exc:  # lo.fit's refusal (e.g. r above the data's rank) is the row
                row["refused"] = str(exc)[:160]
                print(f"{name[:28]:>28} {r:>3} refused: {row['refused'][:70]}")
                rows.append(row)
                continue
            best = float("inf")
            for _ in range(repeats):
                with warnings.catch_warnings(record=True) as seen:
                    warnings.simplefilter("always")
                    t0 = time.perf_counter()
                    model = fit(S, r)
                    best = min(best, time.perf_counter() - t0)
            rep, cert = model.report, model.report["certificate"]
            row.update(seconds=best, mass=rep["mass"], damping=rep["damping"], scheme=rep["scheme"],
                       duality_gap=cert.get("duality_gap"), certified=bool(cert.get("certified")),
                       warnings=len(seen), threads=threads if r >= PARALLEL_FROM_R else 1)
            gap = row["duality_gap"]
            print(f"{name[:28]:>28} {r:>3} {best:7.3f} {rep['mass']:>8} "
                  f"{'-' if gap is None else format(gap, '9.1e'):>9} "
                  f"{'yes' if row['certified'] else 'NO':>4} {len(seen):>4} {rep['scheme'][:40]}")
            rows.append(row)
    return rows


if __name__ == "__main__":
    main()
