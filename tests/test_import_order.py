"""Any import order works: the tutorials' orders, run in fresh interpreters.

With numba installed, ``dolfinx.fem.petsc`` loads libpetsc (and the wheel's HDF5) into the
global symbol scope; before this was fixed, ``import dolfinx_lopinf`` followed by
``from dolfinx.fem.petsc import LinearProblem`` made the first use of a DOLFINx-side name
(which imported h5py) fail with h5py's "Not a datatype". The FEM layer no longer needs h5py,
and the opinf peer imports it so that it binds its own HDF5 whatever came first.
"""

import importlib.util
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(importlib.util.find_spec("dolfinx") is None,
                                reason="needs DOLFINx")

#: what a user's script does after its imports: every lazy DOLFINx-side name, the scenes, a
#: recorder on a small mesh, a point output, and (when installed) the opinf peer with h5py I/O
USE = """
import numpy as np
from mpi4py import MPI
import dolfinx, dolfinx.fem, dolfinx.mesh
for name in lo._LAZY:
    getattr(lo, name)
import dolfinx_lopinf.scenes.beam, dolfinx_lopinf.scenes.cantilever, dolfinx_lopinf.scenes.fishtail
msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 4, 4)
V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
u = dolfinx.fem.Function(V)
rec = lo.SnapshotRecorder(u, output_matrix=lo.point_output_matrix(V, [[0.5, 0.5, 0.0]]))
for k in range(12):
    u.x.array[:] = np.sin(0.3 * k) * np.arange(u.x.array.size)
    rec.record(0.1 * k, u)
snaps = rec.snapshots()
assert snaps.Q.shape == (25, 12)
if importlib.util.find_spec("opinf"):
    from dolfinx_lopinf.studies import peers
    assert peers.have_opinf()
    import h5py, tempfile, os
    with tempfile.TemporaryDirectory() as d:
        with h5py.File(os.path.join(d, "t.h5"), "w") as f:
            f["a"] = np.arange(3.0)
        with h5py.File(os.path.join(d, "t.h5"), "r") as f:
            assert list(f["a"][:]) == [0.0, 1.0, 2.0]
print("ok")
"""

ORDERS = {
    "ours first, then the tutorial's LinearProblem":
        "import dolfinx_lopinf as lo\nfrom dolfinx.fem.petsc import LinearProblem\n",
    "ours first, then dolfinx.fem.petsc":
        "import dolfinx_lopinf as lo\nimport dolfinx.fem.petsc\n",
    "dolfinx first (wheel: dolfinx_solver), LinearProblem, then ours":
        "import dolfinx_solver\nimport dolfinx\nfrom dolfinx.fem.petsc import LinearProblem\n"
        "import dolfinx_lopinf as lo\n",
    "dolfinx.fem.petsc and ufl first, ours last":
        "import dolfinx_solver\nimport ufl\nimport dolfinx.fem.petsc\nimport dolfinx_lopinf as lo\n",
}


@pytest.mark.parametrize("order", list(ORDERS))
def test_import_order(order):
    imports = ORDERS[order]
    if "dolfinx_solver" in imports and importlib.util.find_spec("dolfinx_solver") is None:
        imports = imports.replace("import dolfinx_solver\n", "")  # conda/apt DOLFINx
    code = "import importlib.util\n" + imports + USE
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("ok"), \
        f"{order}:\n{proc.stderr[-3000:]}"
