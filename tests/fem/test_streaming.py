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
