"""Stability suite: hard cases, each with its result, error and energy bound.

    python -m dolfinx_lopinf.studies.stability [--out FILE.json]

Cases (beam: the paper's scene, block POD, r = 10, trained on [0, 0.03] s, run to T = 2 s):

* clean data, L-OpInf and standard OpInf;
* snapshots with 1e-4 and 1e-3 relative noise (differenced on every 10th sample, i.e.
  dt = 1e-4, since 8th-order differences at 1e-5 amplify noise by ~1e10);
* badly scaled blocks (theta multiplied by 1e8);
* a forced cantilever (scenes/cantilever.py, the model of demos/existing_code.py) driven by a
  hard step load;
* sine-Gordon FOM with a too large time step (must fail clearly);
* rank-deficient training data (a warning naming the rank and a regularised fit; an error
  with strict=True).

"bounded" means finite states and no growth of the relative FOM energy error: its maximum over
the last quarter of [0, T] is less than 3x its maximum over the first quarter.
"""

from __future__ import annotations

import argparse
import json
import re
import time
import warnings
from pathlib import Path

import numpy as np


def _beam_case(snaps, M, K, noise, scale_theta, method, r=10, every=10, seed=0, t_long=2.0):
    from ..core import ddt
    from ..core.basis import pod
    from ..core.inference import infer_mechanical, infer_opinf
    from ..core.rom import LagrangianROM

    rng = np.random.default_rng(seed)
    train = snaps.window(0.0, 0.03)
    scale = np.ones(snaps.n_states)
    scale[snaps.blocks["theta"]] = scale_theta
    Q = train.Q[:, ::every] * scale[:, None]
    t = train.times[::every]
    if noise:
        Q = Q + noise * np.abs(Q).max(axis=1, keepdims=True) * rng.standard_normal(Q.shape)
    basis = pod(Q, r, blocks=train.blocks)
    Qh, _, ddQh = ddt.derivatives(basis.project(Q), t)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ops = (infer_mechanical if method == "lopinf" else infer_opinf)(Qh, None, ddQh, damping=False)
    rom = LagrangianROM(K=ops.K, lagrangian=False if method == "opinf" else None)
    dt = snaps.dt
    W = basis.V / scale[:, None]  # back to physical state coordinates
    qh0 = basis.project(snaps.Q[:, 0] * scale)
    tr = rom.simulate(qh0, np.zeros(r), dt, int(round(t_long / dt)), every=100)
    Mg, Kg = W.T @ M @ W, W.T @ K @ W
    E = 0.5 * np.einsum("ik,ij,jk->k", tr.Vh, Mg, tr.Vh) + 0.5 * np.einsum("ik,ij,jk->k", tr.Qh, Kg, tr.Qh)
    energy_err = np.abs(E - E[0]) / abs(E[0])
    quarter = max(len(energy_err) // 4, 1)
    growth = float(np.nanmax(energy_err[-quarter:]) / max(np.nanmax(energy_err[1:quarter + 1]), 1e-300))
    test = snaps.window(0.03, snaps.times[-1])
    k0 = int(round(0.03 / dt)) // 100
    k1 = int(round(snaps.times[-1] / dt)) // 100
    Q_rom = W @ tr.Qh[:, k0:k1 + 1]
    err = float(np.linalg.norm(test.Q[:, ::100] - Q_rom) / np.linalg.norm(test.Q[:, ::100]))
    finite = bool(np.all(np.isfinite(tr.Qh)))
    ev = np.linalg.eigvals(ops.K)
    # bounded = finite and no growth of the energy error from the first to the last quarter
    bounded = finite and growth < 3.0
    return {"result": "bounded" if bounded else "GROWING / blown up",
            "energy_growth_last_vs_first_quarter": growth if finite else float("inf"),
            "test_error": err, "max_energy_error": float(np.nanmax(energy_err)) if finite else float("inf"),
            "symmetric": bool(np.array_equal(ops.K, ops.K.T)),
            "min_real_eig_K": float(ev.real.min())}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="results/stability.json")
    args = parser.parse_args(argv)
    from .. import run
    from ..fem.intrusive import dense_state_matrix
    from ..scenes import beam as scene

    b = scene.build(200)
    q0, v0 = b.initial_state()
    snaps, _ = run(b.system, q0, v0, scene.DT, 0.18, state_map=b.state_map, record_velocity=False,
                   energy_every=0, progress=False)
    M = dense_state_matrix(b.system.mass_form, b.system.V, b.state_map)
    K = dense_state_matrix(b.system.stiffness_form, b.system.V, b.state_map)
    rows = []

    def add(case, fn):
        t0 = time.perf_counter()
        try:
            row = fn()
        except Exception as exc:  # the "must fail clearly" cases land here
            row = {"result": f"error: {type(exc).__name__}: {str(exc)[:160]}"}
        row = {"case": case, **row, "seconds": time.perf_counter() - t0}
        rows.append(row)
        print(f"{case:<44} {row['result'][:70]:<70} "
              f"{row.get('test_error', float('nan')):9.2e} {row.get('max_energy_error', float('nan')):9.2e}",
              flush=True)

    print(f"{'case':<44} {'result':<70} {'test err':>9} {'energy':>9}")
    for method in ("lopinf", "opinf"):
        add(f"beam clean, {method}", lambda m=method: _beam_case(snaps, M, K, 0.0, 1.0, m, every=1))
        for noise in (1e-4, 1e-3):
            add(f"beam noise {noise:g}, {method}", lambda n=noise, m=method: _beam_case(snaps, M, K, n, 1.0, m))
        add(f"beam theta block x 1e8, {method}", lambda m=method: _beam_case(snaps, M, K, 0.0, 1e8, m, every=1))
    add("cantilever, hard step load, lopinf", _step_case)
    add("sine-Gordon FOM, dt = 5 (too large)", _large_dt_case)
    add("rank-deficient training data", _rank_deficient_case)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=1))
    return rows


def _step_case():
    from ..scenes import cantilever
    from ..core import LagrangianROM, derivatives, infer_mechanical, infer_output, pod, relative_error
    from .. import SnapshotRecorder, point_output_matrix

    def hard_step(t):
        return 1.0 if t >= 0.2 else 0.0

    def factory(q):
        E = point_output_matrix(q.function_space, np.array([[cantilever.LENGTH, 0.05, 0.05]]), component=2)
        return SnapshotRecorder(q, output_matrix=E)

    _, rec_train, _ = cantilever.simulate(cantilever.train_load, 1.0, (12, 2, 2), factory)
    _, rec_test, _ = cantilever.simulate(hard_step, 1.0, (12, 2, 2), factory)
    train, test = rec_train.snapshots(), rec_test.snapshots()
    basis = pod(train.Q, 8)
    Qh_all = basis.project(train.Q)
    ops = infer_mechanical(*derivatives(Qh_all, train.times), train.U[:, 4:-4])
    rom = LagrangianROM(K=ops.K, C=ops.C, B=ops.B, E=infer_output(Qh_all, train.Y), scheme="newmark")
    tr = rom.simulate(np.zeros(8), np.zeros(8), cantilever.DT, len(test.times) - 1,
                      inputs=lambda t: np.array([hard_step(t)]))
    err = relative_error(test.Y, tr.Y)
    return {"result": "bounded" if np.all(np.isfinite(tr.Qh)) else "blown up", "test_error": err}


def _large_dt_case():
    from .. import run
    from ..scenes import sine_gordon as sg

    s = sg.build(400)
    run(s.system, np.zeros_like(s.x_local), 4 / np.cosh(s.x_local), 5.0, 20.0, progress=False,
        record_velocity=False, energy_every=0)
    return {"result": "no error (the large step was accepted)"}


def _rank_deficient_case():
    """Exactly dependent rows: by default a warning naming the rank and a ridge-regularised fit
    (symmetric, >= eps I, fitting what the data determine); with strict=True a clear error."""
    from ..core import derivatives, infer_mechanical
    from ..errors import IllConditionedDataWarning, RankDeficientDataError

    t = np.linspace(0, 1, 200)
    Q = np.vstack([np.sin(3 * t), 2 * np.sin(3 * t), np.cos(5 * t)])  # row 2 = 2 x row 1
    Qh, _, ddQh = derivatives(Q, t)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", IllConditionedDataWarning)
        ops = infer_mechanical(Qh, None, ddQh, damping=False)
    said = [str(w.message) for w in caught if issubclass(w.category, IllConditionedDataWarning)]
    try:
        infer_mechanical(Qh, None, ddQh, damping=False, strict=True)
        strict = "strict=True: no error"
    except RankDeficientDataError:
        strict = "strict=True: RankDeficientDataError"
    cert = ops.certificate
    found = re.search(r"rank \d+ < \d+", said[0]) if said else None
    warned = f"warns ({found.group(0)})" if found else "NO WARNING"
    return {"result": f"{warned}, ridge fit: residual {cert['relative_residual']:.1e}; {strict}",
            "symmetric": bool(np.array_equal(ops.K, ops.K.T)), "min_real_eig_K": cert["min_eig_K"],
            "fit_relative_residual": cert["relative_residual"]}


if __name__ == "__main__":
    main()
