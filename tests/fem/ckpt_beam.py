"""Beam FOM with checkpoints; used by test_checkpoint.py (argv: out.npz checkpoint|none)."""
import sys

import numpy as np

import dolfinx_lopinf as lo
from dolfinx_lopinf.scenes import beam as scene

out, prefix = sys.argv[1], sys.argv[2]
b = scene.build(200)
q0, v0 = b.initial_state()
snaps, info = lo.run(b.system, q0, v0, scene.DT, 0.06, state_map=b.state_map,
                     output_matrix=b.output_matrix, record_every=10, progress=False,
                     checkpoint=None if prefix == "none" else prefix, checkpoint_every=500)
np.savez(out, Q=snaps.Q, V=snaps.V, Y=snaps.Y, E=snaps.energy, resumed=info["resumed_from_step"])
