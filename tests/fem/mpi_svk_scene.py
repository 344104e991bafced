"""The SVK cantilever scene's helpers (dolfinx_lopinf.scenes.svk_cantilever) on any number of
ranks; used by test_svk_mpi.py under 1 and 2 ranks. Saves (rank 0, OUT.npz) the load vector,
the clamped rows, the internal force and the potential at a few states (state coordinates, the
same on every rank) - and checks that every rank holds the same arrays."""
import sys

import numpy as np

from dolfinx_lopinf.fem._dolfinx import MPI  # the wheel's MPI before dolfinx
from dolfinx_lopinf.scenes import svk_cantilever as scene

comm = MPI.COMM_WORLD
out = {}
for material in ("svk", "neo-hookean"):
    cant = scene.build(material, (4, 1, 1), comm=comm)
    n = len(cant.state_map.order)
    x = np.linspace(0.0, 1.0, n)
    states = np.column_stack([0.01 * x * np.sin((a + 1) * 3.7 * x + a) for a in range(3)])
    key = material.replace("-", "")
    out.update({f"{key}_b": cant.load_vector(), f"{key}_clamped": cant.clamped_rows,
                f"{key}_f": cant.internal_force(states), f"{key}_f1": cant.internal_force(states[:, 0]),
                f"{key}_U": cant.potential(states)})
    q0, v0 = cant.initial_state()
    assert q0.shape == v0.shape == cant.system.q.x.array.shape  # local dof arrays
for k, v in out.items():  # results on every rank, the same everywhere
    v0 = comm.bcast(v, root=0)
    assert v0.shape == v.shape and np.array_equal(v0, v), k
if comm.rank == 0:
    np.savez(sys.argv[1], **out)
