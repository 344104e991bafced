"""ROM time loops, numpy vs compiled, side by side in one run (issue 16).

    python -m dolfinx_lopinf.studies.bench_rom [--repeats N] [--synthetic] [--json PATH]

(a) linear Newmark ROM, r = 2, one input, 2,000 steps;
(b) beam-like linear midpoint ROM, r = 20 (undamped, bending spectrum w_k ~ (2k-1)^2 up to
    w dt ~ 2), 300,000 steps kept every 10, against a flop-count estimate: one step is the
    2r x 2r matvec, 2 (2r)^2 flops, at the single-thread dgemm rate measured in this run;
(c) the sine-Gordon L-OpInf ROM, r = 14, t = 25 (dt = 0.005, 5,000 steps), ECSW-sampled
    (tol 1e-5) at n = 2,000 and 20,000, and the full nonlinearity at n = 2,000; numpy loop,
    compiled fresh Newton, compiled simplified (lazy-Jacobian) Newton. At n = 2,000 the ROM is
    fitted to the FOM exactly as demos/sine_gordon.py does (DOLFINx FOM to t = 25, timed:
    the speed-up), at n = 20,000 to the exact kink-antikink solution on that grid (no FOM;
    ``--synthetic`` does that at both n and needs no DOLFINx).

Times are medians over ``--repeats`` runs of ``Trajectory.seconds`` (integration only:
propagators and Newton included, compilation and input callables excluded). Compilation is
reported separately: cold (a fresh numba cache, in a subprocess) and cache load.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from ..core import compiled
from ..core.rom import LagrangianROM, WaveROM


def _median(f, repeats):
    out = [f() for _ in range(repeats)]
    return float(np.median([o.seconds for o in out])), out[-1]


def _rel(a, b):
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(a)), 1e-300))


#: run in a fresh process by compile_seconds: compiles (or loads) every ROM-loop kernel
WARM_UP = "from dolfinx_lopinf.core import compiled; print(compiled.warm_up())"


def compile_seconds() -> dict:
    """Cold compile (fresh NUMBA_CACHE_DIR) and cache-load seconds, each in a new process."""
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for key in ("cold_compile_s", "cache_load_s"):
            res = subprocess.run([sys.executable, "-c", WARM_UP], env=env, capture_output=True,
                                 text=True, check=True)
            out[key] = float(res.stdout.strip().splitlines()[-1])
    return out


def dgemm_gflops() -> float:
    """Single-thread dgemm rate (GFLOP/s), the reference of the flop-count estimate."""
    from threadpoolctl import threadpool_limits

    A = np.random.default_rng(0).standard_normal((1200, 1200))
    with threadpool_limits(1):
        A @ A
        best = min(_timed(lambda: A @ A) for _ in range(3))
    return 2 * 1200**3 / best / 1e9


def _timed(f):
    t0 = time.perf_counter()
    f()
    return time.perf_counter() - t0


def newmark_r2(repeats):
    K = np.array([[4.0, 1.0], [1.0, 9.0]])
    rom = LagrangianROM(K=K, C=0.05 * np.eye(2), B=np.array([[1.0], [0.5]]), E=np.ones((1, 2)),
                        scheme="newmark")
    n, dt = 2000, 0.01
    U = np.sin(dt * np.arange(n + 1))[None]
    res = {}
    for backend in ("numpy", "numba"):
        res[backend], tr = _median(lambda b=backend: rom.simulate(np.zeros(2), np.zeros(2), dt, n,
                                                                  inputs=U, backend=b), repeats)
        res[f"tr_{backend}"] = tr
    res["rel_diff"] = _rel(res.pop("tr_numpy").Qh, res.pop("tr_numba").Qh)
    return res


def beam_r20(repeats, gflops):
    r, dt, n, every = 20, 1e-5, 300_000, 10
    rng = np.random.default_rng(1)
    w = 2 * np.pi * 20.0 * (2 * np.arange(1, r + 1) - 1.0) ** 2  # w_20 dt ~ 1.9
    Phi = np.linalg.qr(rng.standard_normal((r, r)))[0]
    K = Phi @ np.diag(w**2) @ Phi.T
    rom = LagrangianROM(K=0.5 * (K + K.T))
    q0 = Phi @ (1.0 / w**2)
    res = {}
    trs = {}
    for backend, reps in (("numba", repeats), ("numpy", max(1, repeats // 2))):
        res[backend], trs[backend] = _median(
            lambda b=backend: rom.simulate(q0, np.zeros(r), dt, n, every=every, backend=b), reps)
    flops = 2 * (2 * r) ** 2 * n
    res.update(flops=flops, estimate=flops / (gflops * 1e9), gflops=gflops,
               rel_diff=_rel(trs["numpy"].Qh, trs["numba"].Qh))
    return res


# ---------------------------------------------------------------------------------------------
# (c) sine-Gordon
# ---------------------------------------------------------------------------------------------

R_SG, DT_SG, T_TRAIN, T_END, EVERY = 14, 0.005, 5.0, 25.0, 10


def _kink_antikink_data(n):
    """Exact kink-antikink states on the periodic grid of n points (the FOM's x), t in [0, 25]."""
    x = -20.0 + (40.0 / n) * np.arange(n)  # the scene's [-20, 20), without importing DOLFINx
    times = DT_SG * np.arange(int(round(T_END / DT_SG)) + 1)
    Q = 4.0 * np.arctan(times[None, :] / np.cosh(x[:, None]))  # scenes.sine_gordon's formula
    return x, times, Q, 4.0 / np.cosh(x), None


def _fom_data(n):
    """The DOLFINx FOM (as demos/sine_gordon.py runs it) to t = 25: states and seconds."""
    from ..fem._dolfinx import MPI
    from ..fem.fom import run
    from ..scenes import sine_gordon as scene

    sg = scene.build(n, MPI.COMM_SELF)
    v0 = 4.0 / np.cosh(sg.x_local)
    snaps, info = run(sg.system, np.zeros_like(v0), v0, DT_SG, T_END, state_map=sg.state_map,
                      record_velocity=False, energy_every=0, progress=False)
    return sg.x, snaps.times, snaps.Q, 4.0 / np.cosh(sg.x), info["seconds"]


def _sine_gordon_rom(Q, times):
    """POD of [Q, sin Q] on [0, 5], L-OpInf (symmetric Kh), ECSW (tol 1e-5): as the demo."""
    from ..core.basis import pod
    from ..core.ddt import derivatives
    from ..core.hyper import ecsw
    from ..core.inference import infer_wave

    k_train = int(round(T_TRAIN / DT_SG))
    Qt, tt = Q[:, :k_train + 1], times[:k_train + 1]
    Ft = np.sin(Qt)
    V = pod(np.hstack([Qt, Ft]), R_SG).V
    Qh, _, ddQh = derivatives(V.T @ Qt, tt)
    K = infer_wave(Qh, ddQh, (V.T @ Ft)[:, 4:-4]).K
    U = lambda z: 1.0 - np.cos(z)  # noqa: E731
    full = WaveROM(K=K, V=V, g=np.sin, dg=np.cos, U=U)
    sample = ecsw(V, V.T @ Qt[:, ::max(1, Qt.shape[1] // 200)], np.sin, tol=1e-5)
    hyper = WaveROM(K=K, V=V[sample.rows], g=np.sin, dg=np.cos, U=U, weights=sample.weights)
    return V, full, hyper


def sine_gordon(n, repeats, use_fom, full_too):
    x, times, Q, v0, fom_s = _fom_data(n) if use_fom else _kink_antikink_data(n)
    V, full, hyper = _sine_gordon_rom(Q, times)
    n_steps = int(round(T_END / DT_SG))
    q0h, v0h = V.T @ Q[:, 0], V.T @ v0
    k_test = int(round(T_TRAIN / DT_SG)) // EVERY
    Q_sub = Q[:, ::EVERY]
    rows = []
    variants = [("ecsw", hyper)] + ([("full", full)] if full_too else [])
    for label, rom in variants:
        ref = None
        for backend, jac in (("numpy", "fresh"), ("numba", "fresh"), ("numba", "lazy")):
            reps = max(1, repeats // 2) if backend == "numpy" else repeats
            sec, tr = _median(lambda rom=rom, b=backend, j=jac: rom.simulate(
                q0h, v0h, DT_SG, n_steps, every=EVERY, backend=b, jacobian=j), reps)
            E = rom.energy(tr.Qh, tr.Vh)
            row = {"n": n, "rows": label, "points": int(rom.V.shape[0]), "backend": backend,
                   "jacobian": jac, "seconds": sec, "step_us": 1e6 * sec / n_steps,
                   "test_error": float(np.linalg.norm(Q_sub[:, k_test:] - V @ tr.Qh[:, k_test:])
                                       / np.linalg.norm(Q_sub[:, k_test:])),
                   "energy_drift": float(np.max(np.abs(E - E[0])) / abs(E[0])),
                   "newton_iterations": tr.info["newton_iterations"],
                   "jacobians": tr.info["jacobians"], "fom_seconds": fom_s}
            if ref is None:
                ref = tr
            row["diff_vs_numpy"] = _rel(ref.Qh, tr.Qh)
            rows.append(row)
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=7, help="runs per figure (median)")
    parser.add_argument("--synthetic", action="store_true",
                        help="sine-Gordon from the exact solution at both n: no DOLFINx, no FOM")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    args = parser.parse_args(argv)
    if not compiled.available():
        raise SystemExit("the compiled loops are unavailable (pip install 'dolfinx_lopinf[fast]', "
                         "and do not set DOLFINX_LOPINF_JIT=0)")
    comp = compile_seconds()
    comp["this_process_s"] = compiled.warm_up()
    print(f"compile: cold {comp['cold_compile_s']:.2f} s, cache load {comp['cache_load_s']:.2f} s "
          f"(separate processes; not in any time below)")
    gflops = dgemm_gflops()
    a = newmark_r2(args.repeats)
    print("\n(a) linear Newmark ROM r = 2, 2,000 steps, one input")
    print(f"    numpy {1e3 * a['numpy']:.3f} ms | compiled {1e3 * a['numba']:.3f} ms | speed-up "
          f"{a['numpy'] / a['numba']:.0f}x | target <= 0.2 ms | max rel. diff {a['rel_diff']:.1e}")
    b = beam_r20(args.repeats, gflops)
    print("\n(b) beam-like linear midpoint ROM r = 20, 300,000 steps (every 10 kept)")
    print(f"    numpy {1e3 * b['numpy']:.1f} ms | compiled {1e3 * b['numba']:.1f} ms | speed-up "
          f"{b['numpy'] / b['numba']:.1f}x | max rel. diff {b['rel_diff']:.1e}")
    print(f"    flop estimate: 2 (2r)^2 = {2 * 40 ** 2} flops/step x 300,000 = {b['flops']:.2e} "
          f"flops at the single-thread dgemm rate {gflops:.1f} GFLOP/s = "
          f"{1e3 * b['estimate']:.1f} ms; compiled / estimate = {b['numba'] / b['estimate']:.1f} "
          f"(target <= 3)")
    use_fom = not args.synthetic
    if use_fom:
        try:
            from ..fem import _dolfinx  # noqa: F401
        except ImportError:
            print("\nDOLFINx not importable: sine-Gordon from the exact solution (--synthetic)")
            use_fom = False
    c = sine_gordon(2000, args.repeats, use_fom, full_too=True) + \
        sine_gordon(20000, args.repeats, False, full_too=False)
    print(f"\n(c) sine-Gordon L-OpInf ROM r = {R_SG} to t = {T_END:g} ({int(T_END / DT_SG)} steps);"
          " data: " + ("FOM at n = 2,000, exact solution at n = 20,000" if use_fom
                       else "exact solution"))
    fom = c[0]["fom_seconds"]
    if fom:
        print(f"    FOM (DOLFINx, SNES every step) n = 2,000 to t = 25: {fom:.2f} s")
    print(f"    {'n':>6} {'rows':>5} {'pts':>5} {'loop':>14} {'ms':>9} {'us/step':>8} "
          f"{'vs FOM':>7} {'vs numpy':>8} {'test err':>9} {'E drift':>8} {'Newton':>6} "
          f"{'J':>5} {'diff':>8}")
    base = {}
    for row in c:
        key = (row["n"], row["rows"])
        base.setdefault(key, row["seconds"])
        loop = row["backend"] + ("" if row["backend"] == "numpy" else f" {row['jacobian']}")
        vs_fom = f"{fom / row['seconds']:.0f}x" if (fom and row["n"] == 2000) else "-"
        print(f"    {row['n']:>6} {row['rows']:>5} {row['points']:>5} {loop:>14} "
              f"{1e3 * row['seconds']:9.2f} {row['step_us']:8.2f} {vs_fom:>7} "
              f"{base[key] / row['seconds']:7.0f}x {row['test_error']:9.3e} "
              f"{row['energy_drift']:8.1e} {row['newton_iterations']:>6} {row['jacobians']:>5} "
              f"{row['diff_vs_numpy']:8.1e}")
    print("    (diff: max |Qh - Qh numpy| / max |Qh numpy|; E drift: max relative ROM energy change)")
    result = {"compile": comp, "newmark_r2": a, "beam_r20": b, "sine_gordon": c,
              "gflops_dgemm_1thread": gflops}
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=1)
    return result


if __name__ == "__main__":
    main()
