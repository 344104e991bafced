"""The FOM-assembled Galerkin force of the SVK and neo-Hookean cantilevers, full and ECSW,
on a fixed basis; used by test_galerkin_nonlinear.py under 1 and 2 ranks. Saves (rank 0,
OUT.npz) f_r, J_r, U_r at a reduced state, the ECSW cells / weights / residual and the ECSW
force, Jacobian and energy, per material."""
import sys

import numpy as np

from dolfinx_lopinf.fem._dolfinx import MPI  # the wheel's MPI before dolfinx
from dolfinx_lopinf.fem import galerkin_nonlinear as gn
from dolfinx_lopinf.scenes import svk_cantilever as scene

out = {}
for material in ("svk", "neo-hookean"):
    cant = scene.build(material, (6, 1, 1), comm=MPI.COMM_WORLD)
    n = len(cant.state_map.order)
    rng = np.random.default_rng(5)
    x = np.linspace(0.0, 1.0, n)
    basis = np.column_stack([x * np.sin((a + 1) * 2.1 * x + a) for a in range(3)]) * 0.02
    q = np.array([0.6, -0.4, 0.3])
    Qh = 0.5 * rng.standard_normal((3, 12))
    full = gn.GalerkinForce(cant.energy_form, cant.system.q, basis, cant.state_map)
    f, J = full.force_and_jacobian(q)
    s = gn.ecsw_sampling(cant.energy_form, cant.system.q, basis, cant.state_map, Qh, tol=0.05)
    ecsw = gn.GalerkinForce(cant.energy_form, cant.system.q, basis, cant.state_map, sampling=s)
    fe, Je = ecsw.force_and_jacobian(q)
    key = material.replace("-", "")
    out.update({f"{key}_f": f, f"{key}_J": J, f"{key}_U": full.value(q), f"{key}_cells": s.cells,
                f"{key}_weights": s.weights, f"{key}_residual": s.residual, f"{key}_fe": fe,
                f"{key}_Je": Je, f"{key}_Ue": ecsw.value(q)})
if MPI.COMM_WORLD.rank == 0:
    np.savez(sys.argv[1], **out)
