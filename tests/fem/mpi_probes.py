"""Probe accelerations of the SVK cantilever on a basis from a short FOM run, on any number of
ranks; used by test_probes.py under 1 and 2 ranks. Saves (rank 0, OUT.npz) the basis Gram
before orthonormalisation and the Richardson accelerations."""
import sys

import numpy as np

from dolfinx_lopinf.fem._dolfinx import MPI  # the wheel's MPI before dolfinx
import dolfinx_lopinf as lo
from dolfinx_lopinf.fem import probes
from dolfinx_lopinf.scenes import svk_cantilever as scene

comm = MPI.COMM_WORLD
cant = scene.build("svk", (6, 1, 1), comm=comm)
cant.amplitude.value = 250.0
snaps, _ = lo.run(cant.system, *cant.initial_state(), scene.DT, 0.2, output_matrix=cant.output_matrix,
                  state_map=cant.state_map, progress=False, record_velocity=False, energy_every=0)
Q = comm.bcast(snaps.Q if comm.rank == 0 else None, root=0)
B = np.linalg.svd(Q, full_matrices=False)[0][:, :3]
integ = lo.fem.MidpointIntegrator(cant.system, 1e-6)
G = probes.mass_gram(integ, B, cant.state_map)
integ.close()
V = B @ np.linalg.inv(np.linalg.cholesky(G)).T
Qh = np.linalg.lstsq(V, Q, rcond=None)[0]
rng = np.random.default_rng(2)
Qs, Vs, U = probes.probe_points(Qh, np.gradient(Qh, scene.DT, axis=1), 4, rng=rng, inputs_range=(0, 250))
pd = probes.probe(cant.system, V, cant.state_map, Qs, Vs, U, set_input=cant.set_probe_input,
                  step_size=4e-6)
if comm.rank == 0:
    np.savez(sys.argv[1], G=G, A=pd.A, estimate=pd.error_estimate)
