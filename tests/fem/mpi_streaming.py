"""StreamingPOD on a vector P1 space with the mass matrix as weight; used by test_streaming.py
under 1 and 2 ranks. Writes the reduced coordinates, the gathered basis and a dense reference
(weighted POD of the gathered snapshots with the gathered mass matrix) on rank 0."""
import sys

import numpy as np

import dolfinx_lopinf  # noqa: F401  (first: the PyPI wheel orders MPI ahead of dolfinx)
from dolfinx_lopinf.fem._dolfinx import MPI, dolfinx, ufl
import dolfinx.fem.petsc
from dolfinx_lopinf.core.basis import pod
from dolfinx_lopinf.fem.state import StateMap, gather_states
from dolfinx_lopinf.fem.intrusive import dense_state_matrix
from dolfinx_lopinf.fem.streaming import StreamingPOD

out = sys.argv[1]
comm = MPI.COMM_WORLD
msh = dolfinx.mesh.create_unit_cube(comm, 4, 3, 3)
V = dolfinx.fem.functionspace(msh, ("Lagrange", 1, (3,)))
u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
M = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(ufl.inner(u, v) * ufl.dx))
M.assemble()
state_map = StateMap.from_coordinates(V)
q = dolfinx.fem.Function(V)
n_owned = V.dofmap.index_map.size_local * 3
local = []
with StreamingPOD(V, capacity=30, weight=M, chunk=17) as spod:
    for k in range(30):
        t = 0.1 * k
        q.interpolate(lambda x, t=t: np.vstack([np.sin(3 * x[0] + t), np.cos(2 * t) * x[1] * x[2],
                                           np.exp(-t) * x[0] ** 2 + np.sin(t) * x[2]]))
        spod.append(q)
        local.append(q.x.array[:n_owned].copy())
    basis_local, Qh, lam = spod.compute(4)
    disk = spod.disk_bytes
Vg = gather_states(V, basis_local, state_map)
Qg = gather_states(V, np.column_stack(local), state_map)
Mg = dense_state_matrix(ufl.inner(u, v) * ufl.dx, V, state_map)
if comm.rank == 0:
    ref = pod(Qg, 4, weight=Mg)
    np.savez(out, V=Vg, Qh=Qh, lam=lam, Q=Qg, M=Mg, V_ref=ref.V, Qh_ref=ref.V.T @ Mg @ Qg,
             disk=disk)
