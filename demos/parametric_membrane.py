"""Parametric L-OpInf on a 2D membrane: one certified reduced model for a family of designs.

    python demos/parametric_membrane.py [--quick] [--study contrast|radius|both] [--out DIR]

The membrane of :mod:`dolfinx_lopinf.scenes.membrane2d` (a wave in 2D, q = 0 on the boundary,
a Gaussian source driven by u(t)) with a stiff inclusion, c(x; mu)^2 = c0^2 + mu c1(x)^2:

* ``contrast``: mu is a UFL Constant of the Lagrangian; the plugin reads K(mu) = K[1] +
  mu K[mu] from the forms (printed), checks the split against the assembled forms, and
  fits parametric L-OpInf - K[1], K[mu] symmetric PSD, one certified convex problem - from
  two trajectories (two inputs) at each of 4 (quick) / 6 training contrasts in [1, 4].
  Stability is certified for every mu >= 0.
* ``radius``: the inclusion's radius R sits inside the tanh of c1: non-affine (the split
  says so); per-radius L-OpInf fits interpolated on the SPD manifold (log-Euclidean).

Both are tested at unseen parameters inside the training range and 20 % outside it, under
an input none of the training runs saw, beside the intrusive parametric Galerkin ROM, the
projection floor and opinf's parametric model (extra ``[peers]``), at several r.
Writes DIR/metrics.json (rows: method, r, mu, split, test_error, stable), DIR/error_vs_mu_<study>.png
and DIR/fields_<study>.png (pyvista: the fields at an unseen parameter).
"""

from __future__ import annotations

import numpy as np

import dolfinx_lopinf as lo  # noqa: F401  (before dolfinx: the PyPI wheel loads its MPI first)
from dolfinx_lopinf.scenes import membrane2d as mb
from dolfinx_lopinf.studies import harness, param_study
from dolfinx_lopinf.studies.peers import have_opinf

SIZES = {
    "quick": {"cells": 24, "dt": 0.01, "t_end": 1.2, "r": [8, 12],
              "contrast": {"train": [1.0, 2.0, 3.0, 4.0], "test": [1.5, 3.5, 0.4, 4.6]},
              "radius": {"train": [0.12, 0.16, 0.2, 0.24], "test": [0.14, 0.22, 0.096, 0.264]}},
    "default": {"cells": 48, "dt": 0.005, "t_end": 2.0, "r": [8, 12, 16, 24],
                "contrast": {"train": list(np.linspace(1.0, 4.0, 6)),
                             "test": [1.3, 2.5, 3.7, 0.4, 4.6]},
                "radius": {"train": list(np.linspace(0.12, 0.24, 5)),
                           "test": [0.135, 0.195, 0.225, 0.096, 0.264]}},
}


def main(argv=None):
    args = harness.parse(__doc__, argv, out="results/parametric_membrane",
                         quick="24 x 24 cells, 1.2 s, r in {8, 12}",
                         extra=lambda p: p.add_argument("--study", default="both",
                                                        choices=["contrast", "radius", "both"]))
    cfg = SIZES["quick" if args.quick else "default"]
    studies = ["contrast", "radius"] if args.study == "both" else [args.study]
    n_steps = int(round(cfg["t_end"] / cfg["dt"]))
    rows, fits, found, checks, fom_seconds = [], [], {}, {}, {}
    for name in studies:
        scene = mb.build(cfg["cells"], study=name)
        psys = scene.psys
        found[name] = psys.describe()
        if harness.is_root():
            print(f"--- {name}: affine terms found in the UFL forms\n{found[name]}")
        if psys.structure is not None:
            checks[name] = psys.check_split()
        res = param_study.study(psys, train=cfg[name]["train"], test=cfg[name]["test"],
                                loads=mb.train_loads(), test_load=mb.test_load, dt=cfg["dt"],
                                n_steps=n_steps, r_list=cfg["r"], peers=have_opinf())
        fom_seconds[name] = res["fom_seconds"]
        rows += [dict(x, study=name) for x in res["rows"]]
        fits += [dict(x, study=name) for x in res["fits"]]
        if harness.is_root():
            print(param_study.table(res["rows"]))
            _figures(args.out, name, scene, res, cfg)
    metrics = harness.metrics("parametric_membrane", error="state", quick=args.quick, roms=rows,
                              fits=fits, affine_terms=found, split_check=checks,
                              fom_seconds=fom_seconds, n_dofs=int(len(psys.state_map.order)),
                              dt=cfg["dt"], t_end=cfg["t_end"], scheme="newmark",
                              methods=param_study.__doc__.split("Methods")[0].strip())
    harness.write_metrics(args.out, metrics)
    if harness.is_root():
        for f in fits:
            if f["method"] == "lopinf":
                c = f["report"].get("certificate", {})
                print(f"{f['study']} r = {f['r']}: fit {1e3 * f['fit_seconds']:.1f} ms"
                      + (f" (best of 5: {1e3 * f['fit_seconds_min']:.1f} ms wall, "
                         f"{1e3 * f['fit_cpu_seconds_min']:.1f} ms CPU)" if "fit_seconds_min" in f
                         else "")
                      + (f", duality gap {c.get('duality_gap')}, damping {f['report'].get('damping')}"
                         if c else "") + f"; {f['report'].get('stable_for', c.get('stable_for', ''))}")
    return metrics


def _figures(out, name, scene, res, cfg):
    from dolfinx_lopinf.viz import render

    out.mkdir(parents=True, exist_ok=True)
    symbol = "contrast mu" if name == "contrast" else "inclusion radius R"
    render.error_vs_parameter(out / f"error_vs_mu_{name}.png",
                              [r for r in res["rows"] if r["split"] == "test"], name=symbol,
                              train_values=cfg[name]["train"],
                              title=f"membrane, {name}: unseen parameters and an unseen input "
                                    "(shaded: training range)",
                              labels=None if name == "contrast" else
                              {"lopinf": "L-OpInf, SPD-interpolated (log-Euclidean)",
                               "opinf": "opinf interpolated (peer)"})
    if scene.V.mesh.comm.size > 1:  # the fields live on the ranks' pieces of the mesh
        print("(fields rendered in serial runs only)")
        return
    import dolfinx.plot
    import pyvista

    V = scene.V
    grid = pyvista.UnstructuredGrid(*dolfinx.plot.vtk_mesh(V))
    mu, snap = next((m, s) for m, s in res["test"] if cfg[name]["train"][0] < m[0] < cfg[name]["train"][-1])
    r = max(res["models"])
    basis, models = res["models"][r]
    sm = scene.psys.state_map
    n_steps = len(snap.times) - 1
    preds = {"L-OpInf": models["lopinf"].predict(mu, n_steps, inputs=snap.U).Qh}
    if "intrusive" in models:
        preds["intrusive"] = models["intrusive"].predict(mu, n_steps, inputs=snap.U).Qh
    ks = [n_steps // 3, 2 * n_steps // 3, n_steps]
    frames = []
    for k in ks:
        frame = {"FOM": sm.to_local_dofs(V, snap.Q[:, k])}
        for label, Qh in preds.items():
            frame[label] = sm.to_local_dofs(V, basis.V @ Qh[:, k])
        frame["|L-OpInf - FOM| (error)"] = np.abs(frame["L-OpInf"] - frame["FOM"])
        frames.append(frame)
    render.scalar_fields(out / f"fields_{name}.png", grid, frames,
                         titles=[f"t = {snap.times[k]:.2f} s" for k in ks], warp=1.0,
                         title=f"unseen {symbol} = {mu[0]:.4g}, unseen input, r = {r}",
                         overlay=_circle(mb.INCLUSION_AT, mu[0] if name == "radius"
                                         else mb.INCLUSION_RADIUS))


def _circle(centre, radius, n=80):
    a = np.linspace(0, 2 * np.pi, n)
    return np.column_stack([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a)])


if __name__ == "__main__":
    main()
