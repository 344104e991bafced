"""Euler-Bernoulli beam, unseen initial conditions: one ROM from several trajectories.

    python demos/beam_unseen_ic.py [--quick] [--out DIR]

The paper's second beam experiment (docs/method.md#beam): initial deflections
w(x, 0) = 0.001 (a x^5 - 2 l x^4 + (10a/3 - 4) l^2 x^3 + (6 - 10a/3 - a) l^4 x), at rest.

1. FOM (midpoint VI, dt = 1e-5 s): four training trajectories a = 0.2, 0.3, 0.4, 0.5 to
   t = 0.03 s, two test trajectories a = 0.1 and 0.6 to t = 0.18 s.
2. ``lo.fit([four Snapshots], r)`` in two bases of all training states: the paper's
   block-diagonal Euclidean POD (w, theta), and a mass-orthonormal POD (V^T M V = I, M the mass
   form of the Lagrangian, so Mh = I is exact; a black box's snapshots alone lack M). The data
   relation formed per trajectory and stacked, L-OpInf (Mh, Kh SPD, the reduced mass learned).
   Two data relations:
   ``scheme="auto"`` (it chooses the scheme's own three-point relation) and
   ``scheme="continuous"`` (8th-order differences, the paper's method); ``lopinf_mass_I`` is
   the auto fit with Mh = I (the paper's model form). Beside them the intrusive Galerkin ROM
   in the same basis.
3. Each ROM is run from the test trajectories' initial states (projected) to 0.18 s with the
   midpoint rule; errors are relative state errors over both test trajectories together.

Writes DIR/metrics.json (rows tagged with their ``basis``), DIR/error_vs_r.png (block POD, the
paper's basis) and DIR/error_vs_r_mass_orthonormal.png. ``--quick``: shorter runs, r in {4, 8}.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

import dolfinx_lopinf as lo
from dolfinx_lopinf.viz import render
from dolfinx_lopinf.fem._dolfinx import MPI
from dolfinx_lopinf.fem.intrusive import dense_state_matrix
from dolfinx_lopinf.scenes import beam as scene
from dolfinx_lopinf.studies import harness

TRAIN_A, TEST_A = (0.2, 0.3, 0.4, 0.5), (0.1, 0.6)
FULL = dict(t_train=scene.T_TRAIN, t_test=scene.T_END, r_values=list(range(4, 21, 2)))
QUICK = dict(t_train=0.01, t_test=0.03, r_values=[4, 8])
PAPER_2R20 = {"lopinf": 0.0223, "intrusive": 0.0401}  # the paper's errors at 2r = 20


def main(argv=None):
    args = harness.parse(__doc__, argv, out="results/beam_unseen_ic", quick="short runs, r in {4, 8}")
    cfg = QUICK if args.quick else FULL
    comm = MPI.COMM_WORLD
    out = args.out
    beam = scene.build(200, comm)
    dt = scene.DT

    def fom(a, t_end):
        q0, v0 = beam.initial_state(a)
        snaps, info = lo.run(beam.system, q0, v0, dt, t_end, state_map=beam.state_map,
                             progress=False, energy_every=0)
        return snaps, info["seconds"]

    t0 = time.perf_counter()
    train = [fom(a, cfg["t_train"])[0] for a in TRAIN_A]
    tests = [fom(a, cfg["t_test"]) for a in TEST_A]
    fom_seconds = time.perf_counter() - t0
    root = harness.is_root(comm)
    mass = dense_state_matrix(beam.system.mass_form, beam.system.V, beam.state_map)
    Q_train = np.hstack([s.Q for s in train])
    rows = []
    for r in cfg["r_values"]:
        bases = comm.bcast({"euclidean-block": lo.pod(Q_train, r, blocks=train[0].blocks),
                            "mass-orthonormal": lo.pod(Q_train, r, weight=mass)} if root else None)
        for name, basis in bases.items():
            galerkin = lo.fem.galerkin_rom(beam.system, basis.V, beam.state_map)
            if root:
                rows += [dict(row, basis=name) for row in
                         _fit_and_score(train, [s for s, _ in tests], basis, galerkin, dt)]
    if not root:
        return None
    metrics = harness.metrics(
        "beam_unseen_ic", error="state", quick=args.quick, roms=rows,
        n_dofs=int(train[0].n_states), dt=dt, train_a=list(TRAIN_A), test_a=list(TEST_A),
        t_train=cfg["t_train"], t_end=cfg["t_test"], fom_seconds=fom_seconds,
        fom_test_seconds=sum(s for _, s in tests), paper_2r20=PAPER_2R20)
    harness.write_metrics(out, metrics)
    # both curves are the two unseen initial conditions: "train" is the training time window
    # [0, t_train], "test" the long horizon [0, t_end] (the training trajectories' own error
    # is in metrics.json and the table, not in the figure)
    windows = (("test_error_train_window", f"train: window [0, {cfg['t_train']:g}] s"),
               ("test_error", f"test: horizon [0, {cfg['t_test']:g}] s"))
    floors = (("projection_error_test_train_window", "projection, train window"),
              ("projection_error_test", "projection, test horizon"))
    for name, png, label in (("euclidean-block", "error_vs_r.png", "block POD"),
                             ("mass-orthonormal", "error_vs_r_mass_orthonormal.png",
                              "mass-orthonormal POD")):
        render.error_vs_r(out / png, [row for row in rows if row["basis"] == name],
                          series=windows, floors=floors,
                          ylabel="relative state error (unseen ICs a = 0.1, 0.6)",
                          title=f"beam, unseen initial conditions (a = 0.1, 0.6): state error of "
                                f"each ROM against r ({label})")
    harness.summary(rows, [("basis", "basis"), ("method", "method"), ("r", "r"), ("scheme", "scheme"),
                           ("train_error", "train"), ("test_error_train_window", "test<=t_tr"),
                           ("projection_error_test_train_window", "proj"),
                           ("test_error", "test<=t_end"), ("projection_error_test", "proj")],
                    widths=[16, 13, 3, 10, 9, 10, 9, 11, 9])
    return metrics


def _fit_and_score(train, tests, basis, galerkin, dt):
    """L-OpInf (auto and finite differences) and the intrusive ROM in ``basis``, scored on the
    test trajectories from their projected initial states."""
    models = {}
    for method, scheme, mass in (("lopinf", "auto", "learned"), ("lopinf_fd", "continuous", "learned"),
                                 ("lopinf_mass_I", "auto", "identity")):
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", lo.errors.LOpInfWarning)  # rank warnings at large r
            model = lo.fit(train, basis.r, basis=basis, scheme=scheme, damping=False, mass=mass)
        models[method] = (model.rom, time.perf_counter() - t0, model.scheme.spec)
    models["intrusive"] = (galerkin, 0.0, "-")
    def run(rom, trajs):
        recon, seconds = [], 0.0
        for s in trajs:
            tr = rom.simulate(basis.project(s.Q[:, 0]), basis.project(s.V[:, 0]), dt, len(s.times) - 1)
            recon.append(basis.reconstruct(tr.Qh))
            seconds += tr.seconds
        return np.hstack(recon), seconds

    Q_test, Q_train = np.hstack([s.Q for s in tests]), np.hstack([s.Q for s in train])
    # the test trajectories on the training time window [0, t_train] too (unseen initial
    # conditions only, no extrapolation in time)
    k = len(train[0].times)
    early = np.concatenate([np.arange(i * len(s.times), i * len(s.times) + k) for i, s in enumerate(tests)])
    rows = []
    for method, (rom, infer_s, scheme) in models.items():
        rec, seconds = run(rom, tests)
        rows.append(harness.rom_row(
            method, basis.r, scheme=scheme,
            train_error=lo.relative_error(Q_train, run(rom, train)[0]),
            test_error=lo.relative_error(Q_test, rec),
            test_error_train_window=lo.relative_error(Q_test[:, early], rec[:, early]),
            projection_error_test_train_window=basis.projection_error(Q_test[:, early]),
            projection_error_test=basis.projection_error(Q_test),
            infer_seconds=infer_s, rom_seconds=seconds, stable=harness.stable(rec)))
    return rows


if __name__ == "__main__":
    main()
