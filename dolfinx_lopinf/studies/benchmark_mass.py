"""The learned-mass and polynomial tables of the inference benchmark
(``python -m dolfinx_lopinf.studies.benchmark --mass --poly``): our certified interior points
against Clarabel on the same problem, on held-out-style data.

Learned-mass data kinds (:func:`mass_data`), each a forced, damped system whose mass is not I
in the coordinates the fit sees (the first three with sensor noise;
:func:`dolfinx_lopinf.core.synthetic.mass_data`):

* ``modal``: a random SPD mass (two decades), stiffness and Rayleigh damping in random
  coordinates - the learned mass test's system, r coordinates;
* ``chainpod``: a 60-mass chain (non-uniform masses, both ends free: a rigid mode, half the
  dampers missing) in the Euclidean POD basis of its Newmark trajectory - the state
  covariance W of POD coordinates, eigenvalues over many decades (ill-conditioned W), as a
  black-box user's basis gives;
* ``active``: a modal system with rigid and undamped modes in random non-orthogonal
  coordinates: the K and C floors active at the optimum;
* ``nearexact``: near-exact data, as a recorded dolfinx loop gives them - a 150-node bar
  (consistent mass, Rayleigh damping) under a smooth body load, integrated with the
  average-acceleration Newmark scheme, Euclidean POD to r without noise: the POD spectrum
  falls to 1e-6 .. 1e-8 by r = 8 .. 16 and the fit's residual is the truncation alone
  (:func:`dolfinx_lopinf.core.synthetic.near_exact` also predicts an unseen load against the free fit and the intrusive
  ROM);
* ``nearbeam``: the same with a clamped Euler-Bernoulli beam (Hermite elements): its modal
  amplitudes fall as omega^-2 ~ k^-4, the POD spectrum to 1e-8 / 7e-10 by r = 8 / 12 - the
  regime of the recorded 3D cantilevers;
* ``file:PATH``: recorded snapshots (``lo.Snapshots.save``, e.g. ``demos/own_loop.py``'s
  train_newmark.npz), Euclidean POD to r, the Newmark relation.

The Clarabel row solves the same problem (the same regulariser tau, taken from our answer)
through cvxpy with its default tolerances; ``phi`` compares the objectives, ``gap`` is each
solver's own certificate (ours: the dual bound; Clarabel: its primal-dual gap).

Polynomial data (:func:`poly_data`): the sum-of-squares potential of the polynomial tests
(:func:`dolfinx_lopinf.core.synthetic.stiff_potential`: coordinates 1 .. 1e-4 in scale), sampled
as probe data with 1e-4 noise.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from ..core import synthetic
from ..core.polynomial import n_unknowns
from ..core.synthetic import potential_samples, stiff_potential


MASS_KINDS = synthetic.MASS_KINDS


def mass_data(kind: str, r: int, n: int = 1500, seed: int = 0):
    """(Qbar, D1, D2, Ubar) of a learned-mass data set: a kind of
    :func:`dolfinx_lopinf.core.synthetic.mass_data`, or ``file:PATH`` (recorded snapshots:
    Euclidean POD to r, the Newmark relation)."""
    if isinstance(kind, str) and kind.startswith("file:"):
        from ..core.basis import pod
        from ..core.ddt import newmark_data
        from ..core.snapshots import Snapshots

        S = Snapshots.load(kind[5:])
        return newmark_data(pod(S.Q, r).project(S.Q), S.times, S.U)
    return synthetic.mass_data(kind, r, n, seed)


def _phi(problem, theta, tau):
    r = problem.r
    x = problem.index.vech(theta.reshape(r, problem.n_blocks, r).transpose(1, 0, 2)) - problem.x_floor
    return problem.misfit(x) - tau * np.linalg.slogdet(theta[:, :r] - problem.floors[0])[1]


def mass_row(kind: str, r: int, repeats: int = 3, clarabel: bool = True) -> dict:
    """One learned-mass row: ours (median of ``repeats`` solves, compiled when numba is there)
    against Clarabel on the same problem."""
    from ..core import mass
    from ..core.lsq.fractional import MassInteriorPoint

    data = mass_data(kind, r)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prep = mass.prepare(*data, damping=True, eps=1e-8, ridge=1e-9, strict=False, rho=mass.RHO)
    p = prep.problem
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        xs, Y, tau, cert = MassInteriorPoint().solve(p)
        times.append(time.perf_counter() - t0)
    row = {"set": kind, "r": r, "ours_ms": 1e3 * float(np.median(times)), "iterations": cert.iterations,
           "gap": cert.duality_gap, "certified": bool(cert.converged), "backend": cert.details["backend"],
           "phi": _phi(p, p.theta(xs), tau), "clarabel_ms": float("nan"), "clarabel_gap": float("nan"),
           "clarabel_phi": float("nan"), "clarabel_status": None}
    if clarabel:
        try:
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                theta, info = mass.solve_cvxpy(p, tau=tau)
            row.update(clarabel_ms=1e3 * (time.perf_counter() - t0), clarabel_gap=info["duality_gap"],
                       clarabel_phi=_phi(p, theta, tau), clarabel_status=info["clarabel_status"])
        except Exception as exc:  # noqa: BLE001 - a failed reference is a row entry, not a crash
            row["clarabel_status"] = f"failed: {exc}"[:80]
    scale = max(abs(row["phi"]), 1e-300)
    row["phi_difference"] = (row["clarabel_phi"] - row["phi"]) / scale
    row.update(_default_path(data))
    return row


def _default_path(data) -> dict:
    """What a user's call gives on the same data: ``infer_mechanical(mass="learned")`` with its
    defaults - the interior point at the default ridge and, where that is not certified, the
    ridge raised (:func:`dolfinx_lopinf.core.inference._certified_by_ridge`). Its certificate
    is for the problem at the ridge it names."""
    from ..core.inference import RIDGE, infer_mechanical

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cert = infer_mechanical(*data, mass="learned").certificate
    return {"default_ms": 1e3 * (time.perf_counter() - t0), "default_certified": bool(cert["certified"]),
            "default_gap": cert["duality_gap"], "default_ridge": cert.get("ridge", RIDGE)}


def poly_data(r: int, seed: int = 2):
    """Probe-style data of the polynomial tests' sum-of-squares potential (1e-4 noise)."""
    pot, scales = stiff_potential(r, seed)
    N = int(3 * n_unknowns(r, 1)["total"] / r) + 10
    return potential_samples(pot, scales, N, np.random.default_rng(4), noise=1e-4)[0]


def poly_row(r: int, data=None, label: str = "stiff") -> dict:
    from ..core import polynomial as pl

    data = poly_data(r) if data is None else data
    row = {"set": label, "r": r}
    for solver in ("ipm", "cvxpy"):
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ops = pl.fit_polynomial(data, constraint="sos", solver=solver)
        c = ops.certificate
        row[solver] = {"seconds": time.perf_counter() - t0, "gap": c["duality_gap"], "certified": c["certified"],
                       "iterations": c.get("iterations"), "relative_residual": c["relative_residual"],
                       "min_eig_gram": c["min_eig_gram"]}
    return row


def print_mass_header():
    print(f"\nlearned mass: ours (certified interior point) vs Clarabel on the same problem\n"
          f"{'set':>9} {'r':>3} {'ours ms':>9} {'its':>4} {'gap':>9} {'Clarabel ms':>12} {'gap':>9} "
          f"{'speed-up':>9} {'phi diff':>9} cert  | user's default: ms, certified (ridge)")


def print_mass_row(row):
    speed = row["clarabel_ms"] / row["ours_ms"] if row["ours_ms"] > 0 else float("nan")
    print(f"{row['set'][:9]:>9} {row['r']:>3} {row['ours_ms']:9.2f} {row['iterations']:>4} {row['gap']:9.1e} "
          f"{row['clarabel_ms']:12.1f} {row['clarabel_gap']:9.1e} {speed:9.1f} "
          f"{row['phi_difference']:9.1e} {row['certified']!s:5} | {row['default_ms']:8.1f} "
          f"{row['default_certified']} ({row['default_ridge']:g})", flush=True)


def print_poly_header():
    print(f"\npolynomial sos fit: ours (solver='ipm', what the default 'auto' runs) vs Clarabel (solver='cvxpy')\n"
          f"{'set':>6} {'r':>3} {'ipm s':>8} {'gap':>9} {'rel.res':>9} {'Clarabel s':>11} {'gap':>9} "
          f"{'rel.res':>9}")


def print_poly_row(row):
    a, b = row["ipm"], row["cvxpy"]
    print(f"{row['set']:>6} {row['r']:>3} {a['seconds']:8.2f} {a['gap']:9.1e} {a['relative_residual']:9.2e} "
          f"{b['seconds']:11.2f} {b['gap']:9.1e} {b['relative_residual']:9.2e}", flush=True)
