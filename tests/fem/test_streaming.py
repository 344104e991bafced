"""Out-of-core (on-disk) method-of-snapshots POD: equals the dense weighted POD, and gives the
serial result under mpiexec -n 2."""

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

SCRIPT = __import__("pathlib").Path(__file__).with_name("mpi_streaming.py")


def _align(A, B):
    """Columns of A with the signs of B (POD vectors are defined up to sign)."""
    return A * np.sign(np.sum(A * B, axis=0))


@pytest.mark.mpi
def test_streaming_pod_equals_dense_and_serial(tmp_path, serial_and_parallel):
    a, b = serial_and_parallel(SCRIPT)
    for run in (a, b):
        # mass-orthonormal basis, and the same subspace/coordinates as the dense reference
        assert np.abs(run["V"].T @ run["M"] @ run["V"] - np.eye(4)).max() < 1e-10
        V_ref = _align(run["V_ref"], run["V"])
        assert np.abs(run["V"] - V_ref).max() < 1e-8 * np.abs(V_ref).max()
        Qh_ref = np.sign(np.sum(run["Qh_ref"] * run["Qh"], axis=1))[:, None] * run["Qh_ref"]
        assert np.abs(run["Qh"] - Qh_ref).max() < 1e-8 * np.abs(Qh_ref).max()
        # and Qh = V^T M Q
        assert np.allclose(run["Qh"], run["V"].T @ run["M"] @ run["Q"], atol=1e-10 * np.abs(run["Qh"]).max())
    # 1 vs 2 ranks: the same subspace and coordinates. Signs are aligned first: the package's
    # sign convention (largest entry > 0) is a decision two near-equal entries could flip.
    signs = np.sign(np.sum(a["V"] * b["V"], axis=0))
    assert np.abs(a["Qh"] - signs[:, None] * b["Qh"]).max() < 1e-10 * np.abs(a["Qh"]).max()
    assert np.abs(a["V"] - signs * b["V"]).max() < 1e-10 * np.abs(a["V"]).max()
    assert int(a["disk"]) == 2 * 30 * 8 * a["Q"].shape[0]


def test_streaming_pod_bad_input(tmp_path):
    from dolfinx_lopinf.fem._dolfinx import MPI, dolfinx
    from dolfinx_lopinf.fem.streaming import StreamingPOD

    msh = dolfinx.mesh.create_unit_interval(MPI.COMM_SELF, 8)
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
    with StreamingPOD(V, capacity=3, directory=tmp_path) as spod:
        with pytest.raises(ValueError, match="owns 9 dofs"):
            spod.append(np.zeros(5))
        with pytest.raises(ValueError, match="NaN"):
            spod.append(np.full(9, np.nan))
        spod.append(np.ones(9))
        with pytest.raises(ValueError, match="at least 2"):
            spod.compute(1)
        spod.append(2 * np.ones(9))
        with pytest.raises(ValueError, match="numerical rank 1"):
            spod.compute(2)
        spod.append(np.arange(9.0))
        with pytest.raises(ValueError, match="full"):
            spod.append(np.arange(9.0))
        basis, Qh, lam = spod.compute(2)
        assert basis.shape == (9, 2) and Qh.shape == (2, 3)
    assert not any(tmp_path.iterdir())  # the disk arrays are removed


MEMORY_SCRIPT = r'''
import sys
import numpy as np
from dolfinx_lopinf.fem._dolfinx import MPI, dolfinx
from dolfinx_lopinf.fem.streaming import StreamingPOD


def peak_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM"):
            return int(line.split()[1]) / 1024


msh = dolfinx.mesh.create_unit_cube(MPI.COMM_SELF, 24, 24, 24)
V = dolfinx.fem.functionspace(msh, ("Lagrange", 1, (3,)))
n = V.dofmap.index_map.size_local * 3
K = 250
q = np.random.default_rng(0).standard_normal(n)
rows = np.arange(n) / n
before = peak_mb()
with StreamingPOD(V, K, directory=sys.argv[1], chunk=2000) as spod:  # 4 MB buffers
    for k in range(K):
        spod.append(q * (1 + 1e-3 * k) + 1e-2 * np.sin(k * rows))
    appended = peak_mb()
    spod.compute(3)
    computed = peak_mb()
print(n * K * 8 / 2**20, appended - before, computed - before)
'''


@pytest.mark.skipif(not __import__("pathlib").Path("/proc/self/status").exists(),
                    reason="peak resident memory from /proc (Linux)")
def test_streaming_pod_memory_does_not_grow_with_the_snapshots(tmp_path):
    """Appending K snapshots adds nothing to the process's peak resident memory (the rows go
    to the file, not into a writable memory map whose pages would count), and the POD reads
    them in bounded chunks: ~100 MB of snapshots raise the peak by far less than their size
    (a fresh process, so its peak is this test's alone)."""
    import subprocess
    import sys

    script = tmp_path / "memory.py"
    script.write_text(MEMORY_SCRIPT)
    proc = subprocess.run([sys.executable, str(script), str(tmp_path)], capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    data_mb, after_append, after_compute = map(float, proc.stdout.split()[-3:])
    assert data_mb > 80
    assert after_append < 0.1 * data_mb, (data_mb, after_append)
    # the reading buffers (one chunk of each array), G and the basis - not the snapshots
    assert after_compute < 0.25 * data_mb, (data_mb, after_compute)
