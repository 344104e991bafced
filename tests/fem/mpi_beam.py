"""Run the beam FOM (and a Galerkin projection) and save the result; used by test_mpi.py
under 1 and 2 ranks."""
import sys

import numpy as np

import dolfinx_lopinf as lo
from dolfinx_lopinf.fem._dolfinx import MPI
from dolfinx_lopinf.scenes import beam as scene

out = sys.argv[1]
b = scene.build(200, MPI.COMM_WORLD)
q0, v0 = b.initial_state()
snaps, info = lo.run(b.system, q0, v0, scene.DT, 0.002, state_map=b.state_map,
                     output_matrix=b.output_matrix, progress=False)
basis = MPI.COMM_WORLD.bcast(lo.pod(snaps.Q, 6, blocks=snaps.blocks) if snaps is not None else None)
rom = lo.fem.galerkin_rom(b.system, basis.V, b.state_map)
if MPI.COMM_WORLD.rank == 0:
    # the non-intrusive operators from the gathered snapshots, as a user would fit them
    Qh, _, ddQh = lo.core.derivatives(basis.project(snaps.Q), snaps.times)
    fit = lo.core.infer_mechanical(Qh, None, ddQh, damping=False)
    np.savez(out, Q=snaps.Q, V=snaps.V, Y=snaps.Y, E=snaps.energy, M=rom.M, K=rom.K,
             K_lopinf=fit.K, fit_condition=fit.certificate["data_condition"], basis=basis.V)
