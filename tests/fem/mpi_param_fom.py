"""The parametric FOM and the intrusive projection on 1 and 2 ranks (test_affine.py)."""
import sys

import numpy as np

import dolfinx_lopinf as lo
from dolfinx_lopinf.fem import param_fom
from dolfinx_lopinf.scenes import membrane2d

out = sys.argv[1]
scene = membrane2d.build(8)
psys = scene.psys
snap, _ = param_fom.simulate(psys, 2.2, 0.02, 30, inputs=membrane2d.test_load)
W = psys.mass_matrix()                      # every rank
Q = snap.Q if snap is not None else None
Q = psys.V.mesh.comm.bcast(Q, root=0)
basis = lo.pod(Q, 6, weight=W)
model = psys.intrusive(basis, "newmark", 0.02)
split = psys.check_split(mus=[[0.7], [3.1]])
if psys.V.mesh.comm.rank == 0:
    np.savez(out, Q=snap.Q, E=snap.energy, U=snap.U, K=model.terms["stiffness"][1],
             B=model.terms["inputs"][0], split=max(split.values()))
