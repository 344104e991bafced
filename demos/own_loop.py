"""A second user loop, written the way the dolfinx elastodynamics tutorials write it.

    python demos/own_loop.py [--integrator newmark|gen-alpha|both] [--quick] [--out DIR]
    mpiexec -n 2 python demos/own_loop.py --quick

The program below `simulate` is not in this plugin's style (compare demos/existing_code.py,
which assembles M, C, K once and drives a raw PETSc KSP): a 3D cantilever of quadratic
hexahedra loaded by its own weight - a BODY force rho g(t), ramped up and then released -
solved for the new displacement each step with `dolfinx.fem.petsc.LinearProblem` (LU by
MUMPS, the matrix reassembled and refactorised every step, as the tutorial does), the
acceleration and velocity updated by interpolating UFL expressions (`dolfinx.fem.Expression`).
Two integrators, `--integrator`:

* ``newmark``: undamped average-acceleration Newmark (gamma = 1/2, beta = 1/4);
* ``gen-alpha``: Chung-Hulbert generalised-alpha (rho_inf = 0.8: alpha_m = 1/3,
  alpha_f = 4/9, gamma = 11/18, beta = 25/81) with light Rayleigh damping, the load taken at
  t_{n+1-alpha_f}. Its snapshots obey a four-point recurrence with numerical dissipation;
  lo.fit identifies it (scheme="auto") and the ROM steps with it.

Three lines attach the plugin (create the recorder, `record` once per step - with the load
the step applied and the time it was applied at - and `snapshots()`). Then
`lo.fit(train, r, scheme=s, mass=m)` for s in auto / the loop's own scheme (named) /
continuous (8th-order differences), r = 2, 4, 8, four ways: the default (basis ``"l2"``: the
POD in the L2 Gram matrix of the space, which the recorder records - for this uniform density
the mass-orthonormal POD, where Mh = I is exact and auto should keep it), and the same
snapshots without that inner product (basis ``"euclidean"``: what a pure array of states
gives, ``mass="auto"``: Mh = I or learned, chosen on a held-back end), with Mh = I and with
the learned Mh forced.
Each model predicts the tip deflection under a body-force history it has never seen.
Writes DIR/metrics.json, DIR/tip_<integrator>.png, DIR/tip_error_<integrator>.png and the
recorded snapshots DIR/{train,test}_<integrator>.npz (re-fit them without the FOM:
``lo.Snapshots.load``).
"""

from __future__ import annotations

import dataclasses
import time
import warnings

import numpy as np

import dolfinx_lopinf as lo  # before dolfinx (the PyPI wheel loads its MPI first)
from dolfinx_lopinf.viz import render
from dolfinx_lopinf.studies import harness

import dolfinx  # noqa: E402
import dolfinx.fem.petsc  # noqa: E402
import ufl  # noqa: E402
from mpi4py import MPI  # noqa: E402

L, W, H = 1.0, 0.1, 0.1          # cantilever [m], clamped at x = 0
E_MOD, NU, RHO = 1.0e3, 0.3, 1.0  # a soft material: bending modes at 0.51, ~3.2, ~9 Hz
G0 = 0.1                          # body force per unit mass: the tip moves up to ~2.5 % of L
T_RAMP, T_RELEASE = 0.4, 0.8      # training load: ramp to 1, hold, release at once


def train_load(t):
    """Weight ramped up over T_RAMP, held, then released at T_RELEASE (free vibration)."""
    return float(min(t / T_RAMP, 1.0)) if t < T_RELEASE - 1e-12 else 0.0


def test_load(t):
    """Unseen: a 1.6 Hz shake that fades in, with a short reversed push at 1.2 s."""
    shake = np.sin(2 * np.pi * 1.6 * t) * (1 - np.exp(-t / 0.3))
    push = -0.8 * np.exp(-((t - 1.2) / 0.08) ** 2)
    return float(0.7 * shake + push)


def simulate(load, t_end, dt, integrator="newmark", cells=(10, 2, 2), record=None):
    """The user's code: returns the displacement Function's space, the recorder, seconds."""
    domain = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0.0, 0.0, 0.0], [L, W, H]], list(cells),
                                     dolfinx.mesh.CellType.hexahedron)
    V = dolfinx.fem.functionspace(domain, ("Lagrange", 2, (3,)))

    def clamped(x):
        return np.isclose(x[0], 0.0)

    clamped_dofs = dolfinx.fem.locate_dofs_geometrical(V, clamped)
    bcs = [dolfinx.fem.dirichletbc(np.zeros(3), clamped_dofs, V)]

    # material
    E = dolfinx.fem.Constant(domain, E_MOD)
    nu = dolfinx.fem.Constant(domain, NU)
    rho = dolfinx.fem.Constant(domain, RHO)
    lmbda = E * nu / (1 + nu) / (1 - 2 * nu)
    mu = E / 2 / (1 + nu)

    def epsilon(v):
        return ufl.sym(ufl.grad(v))

    def sigma(v):
        return lmbda * ufl.tr(epsilon(v)) * ufl.Identity(3) + 2 * mu * epsilon(v)

    # time integration parameters
    if integrator == "newmark":
        alpha_m, alpha_f, eta_m, eta_k = 0.0, 0.0, 0.0, 0.0
        gamma, beta = 0.5, 0.25
    elif integrator == "gen-alpha":
        rho_inf = 0.8
        alpha_m = (2 * rho_inf - 1) / (rho_inf + 1)
        alpha_f = rho_inf / (rho_inf + 1)
        gamma = 0.5 + alpha_f - alpha_m
        beta = 0.25 * (gamma + 0.5) ** 2
        eta_m, eta_k = 0.05, 2e-4  # Rayleigh damping
    else:
        raise ValueError(f"unknown integrator {integrator!r}")

    u_ = ufl.TestFunction(V)
    du = ufl.TrialFunction(V)
    u = dolfinx.fem.Function(V, name="Displacement")
    u_old = dolfinx.fem.Function(V)
    v_old = dolfinx.fem.Function(V)
    a_old = dolfinx.fem.Function(V)
    v = dolfinx.fem.Function(V, name="Velocity")
    a = dolfinx.fem.Function(V, name="Acceleration")
    f = dolfinx.fem.Constant(domain, np.zeros(3))  # body force per unit mass

    def update_a(u, u_old, v_old, a_old):
        return (u - u_old - dt * v_old) / beta / dt**2 - (1 - 2 * beta) / 2 / beta * a_old

    def update_v(a, u_old, v_old, a_old):
        return v_old + dt * ((1 - gamma) * a_old + gamma * a)

    def avg(x_old, x_new, alpha):
        return alpha * x_old + (1 - alpha) * x_new

    def m(w, u_):
        return rho * ufl.inner(w, u_) * ufl.dx

    def k(w, u_):
        return ufl.inner(sigma(w), epsilon(u_)) * ufl.dx

    def c(w, u_):
        return eta_m * m(w, u_) + eta_k * k(w, u_)

    a_new = update_a(du, u_old, v_old, a_old)
    v_new = update_v(a_new, u_old, v_old, a_old)
    residual = (m(avg(a_old, a_new, alpha_m), u_) + c(avg(v_old, v_new, alpha_f), u_)
                + k(avg(u_old, du, alpha_f), u_) - rho * ufl.inner(f, u_) * ufl.dx)
    problem = dolfinx.fem.petsc.LinearProblem(
        ufl.lhs(residual), ufl.rhs(residual), u=u, bcs=bcs,
        petsc_options_prefix="cantilever_",
        petsc_options={"ksp_type": "preonly", "pc_type": "lu",
                       "pc_factor_mat_solver_type": "mumps"})

    # the updates, as expressions of the new displacement u
    a_expr = dolfinx.fem.Expression(update_a(u, u_old, v_old, a_old), V.element.interpolation_points)
    v_expr = dolfinx.fem.Expression(update_v(update_a(u, u_old, v_old, a_old), u_old, v_old, a_old),
                                    V.element.interpolation_points)

    recorder = record(u) if record else None               # <- dolfinx_lopinf, line 1
    if recorder is not None:
        recorder.record(0.0, u, inputs=[load(0.0)])         # <- line 2 (here and in the loop)
    applied = 0.0

    num_steps = int(round(t_end / dt))
    start = time.perf_counter()
    for n in range(num_steps):
        t = (n + 1) * dt
        applied = load(t - alpha_f * dt)
        f.value[2] = -G0 * applied  # external load at t_{n+1-alpha_f}
        problem.solve()
        u.x.scatter_forward()
        a.interpolate(a_expr)
        v.interpolate(v_expr)
        u_old.x.array[:] = u.x.array
        v_old.x.array[:] = v.x.array
        a_old.x.array[:] = a.x.array
        if recorder is not None:  # the load this step applied, and when
            recorder.record(t, u, inputs=[applied], input_time=t - alpha_f * dt)
    seconds = MPI.COMM_WORLD.allreduce(time.perf_counter() - start, op=MPI.MAX)
    return V, recorder, seconds


# ---------------------------------------------------------------------------------------
# the plugin side: fit from the recorded arrays, predict the unseen load

SCHEMES = ("auto", "named", "continuous")
#: the loops' own integrators, as dolfinx_lopinf.schemes objects (the "named" fits)
OWN_SCHEME = {"newmark": lo.schemes.Newmark(), "gen-alpha": lo.schemes.GeneralizedAlpha(rho_inf=0.8)}
# (basis, reduced mass): the Euclidean POD of the snapshots without their inner product
# (mass="auto": Mh = I or learned, whichever predicts the held-back end clearly better; then
# each mass model forced) and the default, the POD in the recorded L2 Gram matrix (here the
# mass-orthonormal POD: Mh = I exact), mass="auto"
VARIANTS = (("euclidean", "auto"), ("euclidean", "identity"), ("euclidean", "learned"),
            ("l2", "auto"))


def run_integrator(integrator, args, out):
    comm = MPI.COMM_WORLD
    cells = (8, 1, 1) if args.quick else (10, 2, 2)
    dt = 0.01
    t_train, t_test = (2.0, 1.6) if args.quick else (3.0, 2.0)
    tip = np.array([[L, 0.5 * W, 0.5 * H]])

    def record(u):  # the recorder of the user's displacement, with the tip deflection as output
        return lo.SnapshotRecorder(u, output_matrix=lo.point_output_matrix(u.function_space, tip,
                                                                           component=2))

    V, rec_train, fom_train_s = simulate(train_load, t_train, dt, integrator, cells, record)
    _, rec_test, fom_test_s = simulate(test_load, t_test, dt, integrator, cells, record)
    train, test = rec_train.snapshots(), rec_test.snapshots()   # <- line 3 (None off rank 0)
    if not harness.is_root(comm):
        return None
    train.save(out / f"train_{integrator}.npz")   # to re-fit later without the FOM
    test.save(out / f"test_{integrator}.npz")
    n_test, n_train = len(test.times) - 1, len(train.times) - 1
    rows, preds = [], {}
    for basis_name, mass_model in VARIANTS:
        for r in args.r:
            # the recorder's inner product (the default) or none (a Euclidean POD)
            data = train if basis_name == "l2" else dataclasses.replace(train, weight=None)
            for scheme in SCHEMES:
                t0 = time.perf_counter()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", lo.errors.LOpInfWarning)  # in the rows
                    model = lo.fit(data, r, mass=mass_model,
                                   scheme=OWN_SCHEME[integrator] if scheme == "named" else scheme)
                fit_s = time.perf_counter() - t0
                pred = model.predict(n_test, inputs=test_load)     # inputs at t_0 .. t_n
                refit = model.predict(n_train, inputs=train_load)
                stable = harness.stable(pred.Y)
                rows.append(harness.rom_row(
                    "lopinf", r, integrator=integrator, basis=basis_name, mass=mass_model,
                    requested=scheme, mass_chosen=model.report["mass"],
                    damping_chosen=model.report["damping"], scheme=model.scheme.spec,
                    identification=model.report["identification"].get("why", ""),
                    test_error=lo.relative_error(test.Y, pred.Y) if stable else float("inf"),
                    train_error=lo.relative_error(train.Y, refit.Y),
                    projection_error_test=model.basis.projection_error(test.Q),
                    infer_seconds=fit_s, rom_seconds=pred.seconds, stable=stable))
                preds[(basis_name, mass_model, scheme, r)] = pred
    r_show = 4 if 4 in args.r else args.r[-1]
    err = {(x["basis"], x["mass"], x["requested"]): x for x in rows if x["r"] == r_show}
    series = {"FOM (unseen load)": test.Y[0]}
    for b, mm, s in (("euclidean", "auto", "auto"), ("euclidean", "identity", "auto"),
                     ("euclidean", "auto", "named"), ("euclidean", "auto", "continuous"),
                     ("l2", "auto", "auto")):
        x = err[(b, mm, s)]
        label = ("Euclidean POD" if b == "euclidean" else "L2 POD (default)") \
            + (", Mh = I" if mm == "identity" else f", mass auto ({x['mass_chosen']})") \
            + f", {s}" + (f" ({x['scheme'].split('(')[0]})" if s == "auto" else "")
        series[f"{label}: {x['test_error']:.1e}"] = preds[(b, mm, s, r_show)].Y[0]
    render.curves(out / f"tip_{integrator}.png", test.times, series,
                  colors=["C7", "C0", "C3", "C2", "C4", "C1"], ylabel="tip deflection u_z [m]",
                  title=f"{integrator} loop, {train.n_states} dofs: unseen body force, r = {r_show}")
    fom_y = series.pop("FOM (unseen load)")
    render.curves(out / f"tip_error_{integrator}.png", test.times,
                  {k: np.abs(v - fom_y) for k, v in series.items()}, logy=True,
                  colors=["C0", "C3", "C2", "C4", "C1"], ylabel="|ROM - FOM| tip deflection [m]",
                  title=f"{integrator} loop: tip error on the unseen load, r = {r_show} "
                        f"(FOM max {np.max(np.abs(fom_y)):.1e} m)")
    print(f"[{integrator}] n = {train.n_states} dofs, FOM {fom_test_s:.1f} s for {n_test} steps "
          f"(train {fom_train_s:.1f} s for {n_train}), {comm.size} rank(s)")
    harness.summary([dict(x, basis=x["basis"][:6], scheme=x["scheme"].split("(")[0],
                          mass=x["mass"] if x["mass"] != "auto" else f"auto:{x['mass_chosen'][:3]}")
                     for x in rows],
                    [("basis", "basis"), ("mass", "Mh"), ("r", "r"), ("requested", "requested"),
                     ("scheme", "chose"), ("test_error", "unseen err"), ("train_error", "train err"),
                     ("projection_error_test", "proj err"), ("infer_seconds", "fit s"),
                     ("rom_seconds", "ROM s")], widths=[6, 8, 2, 10, 18, 10, 9, 9, 9, 9])
    return {"integrator": integrator, "n_dofs": int(train.n_states), "dt": dt,
            "cells": list(cells), "t_train": t_train, "t_end": t_test,
            "fom_seconds": fom_test_s, "fom_train_seconds": fom_train_s,
            "max_abs_tip_test": float(np.max(np.abs(test.Y))),
            "max_abs_tip_train": float(np.max(np.abs(train.Y))), "roms": rows}


def _options(parser):
    parser.add_argument("--integrator", choices=("newmark", "gen-alpha", "both"), default="both")
    parser.add_argument("--r", default="2,4,8", help="reduced dimensions, comma-separated")


def main(argv=None):
    args = harness.parse(__doc__, argv, out="results/own_loop", quick="coarse mesh, short runs",
                         extra=_options)
    args.r = [int(x) for x in args.r.split(",")]
    out = args.out
    if harness.is_root():
        out.mkdir(parents=True, exist_ok=True)
    integrators = ("newmark", "gen-alpha") if args.integrator == "both" else (args.integrator,)
    results = [run_integrator(i, args, out) for i in integrators]
    if not harness.is_root():
        return None
    # one ROM table per loop (integrator); each row's errors are tip (output) errors
    metrics = harness.metrics("own_loop_cantilever", error="output", quick=args.quick, roms=None,
                              ranks=MPI.COMM_WORLD.size, loops={x["integrator"]: x for x in results})
    harness.write_metrics(out, metrics)
    return metrics


if __name__ == "__main__":
    main()
