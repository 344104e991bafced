"""A vector P2 field on a unit cube recorded with SnapshotRecorder and written back with
write_vtx; used by test_vtx.py under 1 and 2 ranks. Saves (rank 0, OUT.npz): the recorded
states, the states gathered back from states_to_function, the number of steps in the .bp
index, and - where the adios2 python module is importable - the values read from the file,
one row per distinct mesh point sorted by coordinates."""
import sys
from pathlib import Path

import numpy as np

import dolfinx_lopinf as lo
from dolfinx_lopinf.fem._dolfinx import MPI, dolfinx  # the wheel's MPI before dolfinx
from dolfinx_lopinf.fem.state import gather_states
from dolfinx_lopinf.fem.vtx import states_to_function, write_vtx

out = Path(sys.argv[1])
comm = MPI.COMM_WORLD
msh = dolfinx.mesh.create_unit_cube(comm, 2, 2, 2)
V = dolfinx.fem.functionspace(msh, ("Lagrange", 2, (3,)))
u = dolfinx.fem.Function(V)
rec = lo.SnapshotRecorder(u, order="coordinates")  # the same rows on 1 and 2 ranks
for k in range(4):
    t = 0.1 * k
    u.interpolate(lambda x, t=t: np.vstack([x[0] + t, x[1] * x[2] * (1 + t), np.sin(3 * x[0] + t)]))
    rec.record(t, u)
snaps = rec.snapshots()
Q = snaps.Q if comm.rank == 0 else None
times = snaps.times if comm.rank == 0 else None
bp = write_vtx(out.with_suffix(".bp"), V, Q, times, state_map=rec.state_map)  # Q on rank 0 only

refused = 0
try:  # a NaN on rank 0 only: every rank refuses, nothing is written
    write_vtx(out.with_name("bad.bp"), V, None if Q is None else np.where(Q == Q.max(), np.nan, Q),
              times, state_map=rec.state_map)
except lo.errors.InputError:
    refused = 1
refused = comm.allreduce(refused, op=MPI.MIN)

n_owned = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
cols = [states_to_function(V, None if Q is None else Q[:, k], rec.state_map).x.array[:n_owned]
        for k in range(4)]
back = gather_states(V, np.column_stack(cols), rec.state_map)

if comm.rank == 0:
    data = {"Q": Q, "back": back, "t": times,
            "index_steps": (bp / "md.idx").stat().st_size // 64 - 1,
            "refused": refused, "bad_written": out.with_name("bad.bp").exists()
            or any(p.name.endswith(".tmp") for p in out.parent.iterdir())}
    try:
        import adios2
    except ImportError:
        adios2 = None
    if adios2 is not None:
        steps, values = [], []
        with adios2.Stream(str(bp), "r") as f:
            for st in f.steps():
                nblocks = len(f.all_blocks_info("u")[st.current_step()])
                X = np.vstack([f.read("geometry", block_id=b) for b in range(nblocks)])
                U = np.vstack([f.read("u", block_id=b) for b in range(nblocks)])
                key, first = np.unique(np.round(X, 10), axis=0, return_index=True)
                steps.append(float(f.read("step")))
                values.append(U[first])
        data.update(read_t=np.array(steps), read_u=np.array(values), read_x=key)
    np.savez(out, **data)
