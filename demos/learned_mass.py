"""Learned reduced mass against Mh = I in Euclidean (black-box) bases: beam and cantilever.

    python demos/learned_mass.py [--quick] [--out DIR]

L-OpInf with Mh = I is exact only in a mass-orthonormal basis; a black-box user has a
Euclidean POD basis. ``mass="learned"`` fits Mh too (dolfinx_lopinf/core/mass.py). Rows:

* beam (docs/method.md#beam, the paper's block POD of [0, 0.03] s, midpoint data relation
  ``variational_data``): relative state error on the test window [0.03, 0.18] s for
  Mh = I, learned Mh, the intrusive Galerkin ROM and the projection, r = 4..20;
* cantilever of demos/existing_code.py (Euclidean POD, Newmark relation, forced, damped):
  unseen-load tip error for Mh = I and learned Mh, r = 2, 4, 8.

Each fit row carries its certificate in the one vocabulary of the fits: ``solver``,
``certified``, ``duality_gap``, ``iterations`` (the intrusive rows: none). Writes
DIR/metrics.json.
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

import numpy as np

import dolfinx_lopinf as lo
from dolfinx_lopinf.fem._dolfinx import MPI
from dolfinx_lopinf.scenes import beam as scene
from dolfinx_lopinf.studies import harness

sys.path.insert(0, str(Path(__file__).parent))
import existing_code as cantilever  # noqa: E402  (the user's own loop, unchanged)


def _certificate(cert: dict) -> dict:
    """The row's certificate entries (empty for the intrusive ROM: no fit)."""
    return {"solver": cert.get("solver", "-"), "certified": cert.get("certified"),
            "duality_gap": cert.get("duality_gap"), "iterations": cert.get("iterations")}


def beam_rows(r_values, t_end):
    beam = scene.build(200, MPI.COMM_WORLD)
    q0, v0 = beam.initial_state()
    t0 = time.perf_counter()
    snaps, _ = lo.run(beam.system, q0, v0, scene.DT, t_end, state_until=t_end,
                      state_map=beam.state_map)
    fom_s = time.perf_counter() - t0
    train, test = snaps.window(0, scene.T_TRAIN), snaps.window(scene.T_TRAIN, t_end)
    rows = []
    for r in r_values:
        basis = lo.pod(train.Q, r, blocks=train.blocks)
        galerkin = lo.fem.galerkin_rom(beam.system, basis.V, beam.state_map)
        Qbar, D2 = lo.core.ddt.variational_data(basis.project(train.Q), train.times)
        roms = {"intrusive": (galerkin, 0.0, {})}
        for mass in ("identity", "learned"):
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", lo.errors.IllConditionedDataWarning)
                ops = lo.core.infer_mechanical(Qbar, None, D2, damping=False, mass=mass)
            roms[f"lopinf_mass_{mass}"] = (lo.core.LagrangianROM(K=ops.K, M=ops.M),
                                           time.perf_counter() - t0, ops.certificate)
        for method, (rom, infer_s, cert) in roms.items():
            tr = rom.simulate(basis.project(snaps.Q[:, 0]), basis.project(snaps.V[:, 0]),
                              scene.DT, len(snaps.times) - 1)
            rec = basis.reconstruct(tr.Qh[:, len(train.times) - 1:])
            rows.append({"scene": "beam", "method": method, "r": r, "error": "state",
                         "test_error": lo.relative_error(test.Q, rec),
                         "projection_error_test": basis.projection_error(test.Q),
                         "infer_seconds": infer_s, "fom_seconds": fom_s,
                         **_certificate(cert)})
    return rows


def cantilever_rows(r_values, quick):
    cells, t_end = ((12, 2, 2), 1.0) if quick else ((30, 4, 4), 2.0)
    tip = np.array([[cantilever.LENGTH, 0.5 * cantilever.WIDTH, 0.5 * cantilever.HEIGHT]])

    def factory(q):
        E = lo.point_output_matrix(q.function_space, tip, component=2)
        return lo.SnapshotRecorder(q, output_matrix=E, weight=None)  # Euclidean: the point here

    _, rec_train, _ = cantilever.simulate_cantilever(cantilever.train_load, t_end, cells, factory)
    _, rec_test, fom_s = cantilever.simulate_cantilever(cantilever.test_load, t_end, cells, factory)
    train, test = rec_train.snapshots(), rec_test.snapshots()
    rows = []
    for r in r_values:
        for mass in ("identity", "learned"):
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", lo.errors.LOpInfWarning)
                model = lo.fit(train, r, scheme="newmark", mass=mass)
            infer_s = time.perf_counter() - t0
            pred = model.predict(len(test.times) - 1, inputs=cantilever.test_load)
            cert = model.report["certificate"]
            rows.append({"scene": "cantilever", "method": f"lopinf_mass_{mass}", "r": r,
                         "error": "output", "test_error": lo.relative_error(test.Y, pred.Y),
                         "projection_error_test": model.basis.projection_error(test.Q),
                         "infer_seconds": infer_s, "fom_seconds": fom_s,
                         **_certificate(cert)})
    return rows


def main(argv=None):
    args = harness.parse(__doc__, argv, out="results/learned_mass", quick="r in {4, 8}, shorter runs")
    if MPI.COMM_WORLD.size > 1:
        raise SystemExit("learned_mass.py is a serial study (its fits are small); run it without mpiexec")
    rows = beam_rows([4, 8] if args.quick else list(range(4, 21, 4)), 0.06 if args.quick else scene.T_END)
    rows += cantilever_rows([2, 4] if args.quick else [2, 4, 8], args.quick)
    # two scenes in one study: each row names its error kind (harness.ERRORS)
    harness.write_metrics(args.out, {"rows": rows, "quick": bool(args.quick),
                                     "error_definitions": harness.ERRORS})
    harness.summary(rows, [("scene", "scene"), ("method", "method"), ("r", "r"), ("error", "error"),
                           ("test_error", "test error"), ("projection_error_test", "projection"),
                           ("infer_seconds", "fit s"), ("duality_gap", "gap"), ("certified", "cert")],
                    widths=[10, 20, 3, 6, 10, 10, 9, 9, 5])
    return rows


if __name__ == "__main__":
    main()
