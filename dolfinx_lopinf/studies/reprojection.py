"""Re-projected training data for the implicit midpoint integrator (the paper's open problem).

Instead of projecting a FOM trajectory, march in reduced coordinates and let the black-box
FOM take each step from the lifted reduced state:

    (q, p) = (V qh_k, M V ph_k)  --FOM step-->  (q1, p1),   qh_{k+1} = V^T M q1,  ph_{k+1} = V^T p1

for an M-orthonormal basis V (V^T M V = I). The result is the trajectory of "one FOM step,
then project" - free of the closure error that a projected FOM trajectory carries. Measured on
the beam: it does *not* remove the r > 12 plateau of L-OpInf with 8th-order differences (the
plateau comes from fitting continuous-time derivatives to midpoint dynamics; see
:func:`dolfinx_lopinf.core.ddt.variational_data`, which does remove it).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..fem.state import StateMap
from ..fem.integrators import MidpointIntegrator


def reprojected_trajectory(integrator: MidpointIntegrator, V: np.ndarray, M: np.ndarray,
                           state_map: StateMap, q0: np.ndarray, v0: np.ndarray,
                           n_steps: int) -> np.ndarray:
    """Re-projected reduced states (r, n_steps + 1) (serial; small dense M in state coords).

    Args:
        integrator: the FOM's midpoint integrator (used only through ``advance``).
        V: (n, r) M-orthonormal basis in state coordinates; M: (n, n) mass in state coords.
        q0, v0: (n,) initial state and velocity in state coordinates.
    """
    if integrator.system.V.mesh.comm.size > 1:
        raise NotImplementedError("re-projection is implemented for serial runs")
    if not np.allclose(V.T @ M @ V, np.eye(V.shape[1]), atol=1e-8):
        raise InputError("re-projection needs an M-orthonormal basis (V^T M V = I)")
    order, scale = state_map.order, state_map.scale
    p_vec = integrator.p.duplicate()
    qh, ph = V.T @ M @ q0, V.T @ M @ v0
    out = np.empty((V.shape[1], n_steps + 1))
    out[:, 0] = qh
    for k in range(1, n_steps + 1):
        q_state, p_state = V @ qh, M @ (V @ ph)
        q_dofs = np.zeros(len(order))
        q_dofs[order] = q_state / scale
        p_dofs = np.zeros(len(order))
        p_dofs[order] = p_state * scale  # momentum is dual: p_dof = S p_state
        p_vec.array[:] = p_dofs
        q1, p1 = integrator.advance(q_dofs, p_vec)
        qh = V.T @ M @ (scale * q1[order])
        ph = V.T @ (p1.array[order] / scale)
        out[:, k] = qh
    return out


def main(argv=None):
    """``python -m dolfinx_lopinf.studies.reprojection``: beam test error vs r - L-OpInf from projected
    data, from re-projected data, from discrete Euler-Lagrange data; intrusive; projection."""
    import warnings

    from .. import run
    from ..core import LagrangianROM, derivatives, infer_mechanical, pod, relative_error
    from ..core.ddt import variational_data
    from ..fem.intrusive import dense_state_matrix
    from ..scenes import beam as scene

    warnings.simplefilter("ignore", RuntimeWarning)
    b = scene.build(200)
    q0, v0 = b.initial_state()
    snaps, _ = run(b.system, q0, v0, scene.DT, scene.T_END, state_map=b.state_map, progress=False,
                   energy_every=0)
    M = dense_state_matrix(b.system.mass_form, b.system.V, b.state_map)
    K = dense_state_matrix(b.system.stiffness_form, b.system.V, b.state_map)
    train = snaps.window(0.0, scene.T_TRAIN)
    n_train, n_all = len(train.times), int(round(scene.T_END / scene.DT))
    full = pod(train.Q, 20, weight=M)
    integrator = MidpointIntegrator(b.system, scene.DT, prefix="reproj_")
    test_cols = slice(n_train // 10, None)
    print(f"{'r':>3} {'projected':>10} {'re-projected':>12} {'DEL data':>9} {'intrusive':>9} {'projection':>10}")
    rows = []
    for r in (4, 8, 12, 16, 20):
        V = full.truncate(r).V
        data = {"projected": V.T @ M @ train.Q,
                "reprojected": reprojected_trajectory(integrator, V, M, b.state_map, train.Q[:, 0],
                                                      train.V[:, 0], n_train - 1)}
        errors = {}
        for name, Qh_all in data.items():
            Qh, _, ddQh = derivatives(Qh_all, train.times)
            errors[name] = infer_mechanical(Qh, None, ddQh, damping=False).K
        Qbar, D2 = variational_data(data["projected"], train.times)
        errors["del"] = infer_mechanical(Qbar, None, D2, damping=False).K
        errors["intrusive"] = V.T @ K @ V
        qh0 = V.T @ M @ snaps.Q[:, 0]
        sub = snaps.Q[:, ::10]
        row = {"r": r, "projection": float(relative_error(sub[:, test_cols], V @ (V.T @ M @ sub[:, test_cols])))}
        for name, Kh in errors.items():
            tr = LagrangianROM(K=Kh).simulate(qh0, np.zeros(r), scene.DT, n_all, every=10)
            row[name] = float(relative_error(sub[:, test_cols], (V @ tr.Qh)[:, test_cols]))
        rows.append(row)
        print(f"{r:>3} {row['projected']:10.2e} {row['reprojected']:12.2e} {row['del']:9.2e} "
              f"{row['intrusive']:9.2e} {row['projection']:10.2e}")
    return rows


if __name__ == "__main__":
    main()
