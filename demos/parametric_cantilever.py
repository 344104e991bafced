"""Parametric L-OpInf for a design sweep of a 3D cantilever: Young's modulus and damping.

    python demos/parametric_cantilever.py [--quick] [--out DIR]

The cantilever of :mod:`dolfinx_lopinf.scenes.param_cantilever` (linear elasticity, P1
hexahedra, clamped at x = 0, a vertical tip traction u(t), Newmark average acceleration) with
two parameters in its UFL: Young's modulus E (in the Lagrangian) and the damping level zeta
of its Rayleigh dissipation function D = zeta/2 (a0 rho |q_t|^2 + a1 sigma_E(q_t) : eps(q_t)).
The plugin reads K(mu) = E K[E], C(mu) = zeta C[zeta] + E zeta C[E*zeta] from the forms
and fits all of them jointly, each symmetric PSD - stability certified for every E >= 0,
zeta >= 0 - from two trajectories (two tip loads) at each of 4 (quick: the corners) / 6
training designs in E in [0.6e4, 1.4e4] Pa, zeta in [0.5, 2]. Tests: designs on the two
lines through the centre of that box, inside it and 20 % outside it, under a tip load no
training run saw, beside the intrusive parametric Galerkin ROM, the projection floor and
opinf's affine parametric model (extra ``[peers]``).
Writes DIR/metrics.json (rows: method, r, mu, split, test_error, stable), DIR/error_vs_E.png,
DIR/error_vs_zeta.png and DIR/deformed.png (pyvista: FOM | ROMs at an unseen design).
"""

from __future__ import annotations

import numpy as np

import dolfinx_lopinf as lo  # noqa: F401  (before dolfinx: the PyPI wheel loads its MPI first)
from dolfinx_lopinf.core.parametric import sample_design
from dolfinx_lopinf.scenes import param_cantilever as pc
from dolfinx_lopinf.studies import harness, param_study
from dolfinx_lopinf.studies.peers import have_opinf

BOX = [(0.6e4, 1.4e4), (0.5, 2.0)]
CENTRE = (1.0e4, 1.25)
#: 20 % of the box's width outside it, on each line through the centre
OUT_E, OUT_Z = (0.44e4, 1.56e4), (0.2, 2.3)
SIZES = {
    "quick": {**pc.SIZES["quick"], "r": [6, 10], "n_train": 4,
              "test": [(0.44e4, 1.25), (1.2e4, 1.25), (1.56e4, 1.25), (1.0e4, 0.2), (1.0e4, 2.3)]},
    "default": {**pc.SIZES["default"], "r": [6, 10, 14, 20], "n_train": 6,
                "test": [(0.44e4, 1.25), (0.8e4, 1.25), (1.2e4, 1.25), (1.56e4, 1.25),
                         (1.0e4, 0.2), (1.0e4, 0.8), (1.0e4, 1.7), (1.0e4, 2.3)]},
}


def main(argv=None):
    args = harness.parse(__doc__, argv, out="results/parametric_cantilever",
                         quick="12 x 2 x 2 cells, 0.6 s, 4 training designs, r in {6, 10}")
    cfg = SIZES["quick" if args.quick else "default"]
    n_steps = int(round(cfg["t_end"] / cfg["dt"]))
    scene = pc.build(cfg["cells"])
    psys = scene.psys
    found = psys.describe()
    check = psys.check_split(mus=[[0.8e5, 1.3], [1.2e5, 0.6], [0.5e5, 2.1]])
    if harness.is_root():
        print(f"affine terms found in the UFL forms\n{found}\nsplit vs assembled: {check}")
    train = [tuple(p) for p in sample_design(BOX, cfg["n_train"])]
    res = param_study.study(psys, train=train, test=cfg["test"], loads=pc.train_loads(),
                            test_load=pc.test_load, dt=cfg["dt"], n_steps=n_steps, r_list=cfg["r"],
                            peers=have_opinf())
    metrics = harness.metrics("parametric_cantilever", error="state", quick=args.quick,
                              roms=res["rows"], fits=res["fits"], affine_terms=found,
                              split_check=check, fom_seconds=res["fom_seconds"], train=train,
                              n_dofs=int(len(psys.state_map.order)), dt=cfg["dt"],
                              t_end=cfg["t_end"], scheme="newmark", cone=psys.structure.cone)
    harness.write_metrics(args.out, metrics)
    if harness.is_root():
        print(param_study.table(res["rows"]))
        for f in res["fits"]:
            if f["method"] == "lopinf":
                c = f["report"]["certificate"]
                print(f"r = {f['r']}: fit {1e3 * f['fit_seconds']:.1f} ms (best of 5: "
                      f"{1e3 * f['fit_seconds_min']:.1f} ms wall, "
                      f"{1e3 * f['fit_cpu_seconds_min']:.1f} ms CPU), duality gap {c.get('duality_gap')}, "
                      f"damping {f['report']['damping']}; stable for {c['stable_for']}")
        _figures(args.out, scene, res, train, cfg)
    return metrics


def _figures(out, scene, res, train, cfg):
    from dolfinx_lopinf.viz import render

    out.mkdir(parents=True, exist_ok=True)
    rows = [r for r in res["rows"] if r["split"] == "test"]
    tr = np.array(train)
    render.error_vs_parameter(out / "error_vs_E.png", rows, index=0, name="E [Pa]",
                              train_values=tr[:, 0], select=lambda r: r["mu"][1] == CENTRE[1],
                              title=f"cantilever, unseen designs at zeta = {CENTRE[1]} and an unseen "
                                    "tip load (shaded: training range)")
    render.error_vs_parameter(out / "error_vs_zeta.png", rows, index=1, name="damping level zeta",
                              train_values=tr[:, 1], select=lambda r: r["mu"][0] == CENTRE[0],
                              title=f"cantilever, unseen designs at E = {CENTRE[0]:.3g} Pa and an "
                                    "unseen tip load (shaded: training range)")
    if scene.V.mesh.comm.size > 1:  # the fields live on the ranks' pieces of the mesh
        print("(fields rendered in serial runs only)")
        return
    import dolfinx.plot
    import pyvista

    V = scene.V
    grid = pyvista.UnstructuredGrid(*dolfinx.plot.vtk_mesh(V))
    mu, snap = next((m, s) for m, s in res["test"] if tuple(m) == (1.2e4, 1.25))
    r = max(res["models"])
    basis, models = res["models"][r]
    sm = scene.psys.state_map
    n_steps = len(snap.times) - 1
    preds = {f"L-OpInf r={r}": models["lopinf"].predict(mu, n_steps, inputs=snap.U).Qh,
             f"intrusive r={r}": models["intrusive"].predict(mu, n_steps, inputs=snap.U).Qh}
    ks = [n_steps // 4, n_steps // 2, n_steps]
    frames = []
    for k in ks:
        frame = {"FOM": sm.to_local_dofs(V, snap.Q[:, k]).reshape(-1, 3)}
        for label, Qh in preds.items():
            frame[label] = sm.to_local_dofs(V, basis.V @ Qh[:, k]).reshape(-1, 3)
        frames.append(frame)
    amp = max(np.abs(f["FOM"]).max() for f in frames)
    render.deformed_side_by_side(
        out / "deformed.png", grid, frames, magnify=0.15 / amp,
        titles=[f"t = {snap.times[k]:.2f} s" for k in ks],
        title=f"unseen design E = {mu[0]:.3g} Pa, zeta = {mu[1]:.3g}, unseen load (x{0.15 / amp:.0f})",
        panel=(440, 230), camera=[(0.5, -2.6, 0.05), (0.5, 0.0, 0.05), (0, 0, 1)],
        parallel_scale=0.35,
        scalar_bar={"title": "|u| [m]", "vertical": False, "position_x": 0.25, "position_y": 0.05,
                    "width": 0.5, "height": 0.12, "fmt": "%.3f"})


if __name__ == "__main__":
    main()
