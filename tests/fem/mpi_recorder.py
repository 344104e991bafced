"""A plain dolfinx wave loop (P1 on a box, explicit central differences) recorded with
SnapshotRecorder; used by test_mpi.py under 1 and 2 ranks. The recorders' weights: the default
L2 Gram matrix, a mass matrix handed over as an assembled PETSc Mat, and the dense reference
(dense_state_matrix) of the same run."""
import sys

import numpy as np

import dolfinx_lopinf as lo
from dolfinx_lopinf.fem.intrusive import dense_state_matrix
import dolfinx
import dolfinx.fem.petsc
import ufl
from mpi4py import MPI
from petsc4py import PETSc

out = sys.argv[1]
msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 12, 10)
V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
# lumped mass -> explicit update
ml = dolfinx.fem.petsc.assemble_vector(dolfinx.fem.form(v * ufl.dx))
K = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx))
K.assemble()
ml.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
q, q_old = dolfinx.fem.Function(V), dolfinx.fem.Function(V)
q.interpolate(lambda x: np.exp(-40 * ((x[0] - 0.4) ** 2 + (x[1] - 0.6) ** 2)))
q_old.x.array[:] = q.x.array
# several points, on different ranks under 2 (one point at a time had hidden a crash)
E = lo.point_output_matrix(V, np.array([[0.5, 0.5, 0.0], [0.1, 0.2, 0.0], [0.9, 0.85, 0.0]]))
rec = lo.SnapshotRecorder(q, output_matrix=E, order="coordinates")  # identical on any ranks
by_dofs = lo.SnapshotRecorder(q)  # rows = global dof numbers (differ between 1 and 2 ranks)
mass = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(3.0 * u * v * ufl.dx))
mass.assemble()  # the user's own mass matrix, distributed over the ranks' rows
by_mat = lo.SnapshotRecorder(q, order="coordinates", weight=mass)
dt, kq = 0.01, q.x.petsc_vec.duplicate()
for n in range(40):
    rec.record(n * dt, q, inputs=[np.sin(n * dt)])
    by_dofs.record(n * dt, q)
    by_mat.record(n * dt, q)
    K.mult(q.x.petsc_vec, kq)
    new = 2 * q.x.petsc_vec.array - q_old.x.petsc_vec.array - dt**2 * kq.array / ml.array
    q_old.x.petsc_vec.array[:] = q.x.petsc_vec.array
    q.x.petsc_vec.array[:] = new
    q.x.scatter_forward(); q_old.x.scatter_forward()
snaps, raw, weighted = rec.snapshots(), by_dofs.snapshots(), by_mat.snapshots()
# a weight that assembles to no inner product: the same InputError on every rank (rank 0
# gathers and checks it; the others would otherwise go on with None)
negative = lo.SnapshotRecorder(q, weight=-u * v * ufl.dx)
negative.record(0.0, q)
negative.record(dt, q)
try:
    negative.snapshots()
    refused = 0
except lo.errors.InputError as exc:
    refused = int("diagonal entry <= 0" in str(exc))
refused_everywhere = MPI.COMM_WORLD.allreduce(refused, op=MPI.MIN)
W_dense = dense_state_matrix(ufl.inner(u, v) * ufl.dx, V, rec.state_map)
# the coordinates of every global dof, to compare the dof-ordered rows across layouts
imap = V.dofmap.index_map
glob = imap.local_to_global(np.arange(imap.size_local, dtype=np.int32))
pieces = MPI.COMM_WORLD.gather((glob, V.tabulate_dof_coordinates()[:imap.size_local]), root=0)
if MPI.COMM_WORLD.rank == 0:
    X = np.empty((imap.size_global, 3))
    for g, x in pieces:
        X[g] = x
    np.savez(out, Q=snaps.Q, U=snaps.U, Y=snaps.Y, t=snaps.times, Q_dofs=raw.Q, X_dofs=X,
             W=snaps.weight.toarray(), W_dense=W_dense, W_mat=weighted.weight.toarray(),
             W_dofs=raw.weight.toarray(), refused_everywhere=refused_everywhere)
