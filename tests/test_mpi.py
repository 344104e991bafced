"""FOM, recording and Galerkin projection under mpiexec -n 2 give the serial result."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf._dolfinx")

SCRIPT = Path(__file__).with_name("mpi_beam.py")


def _mpiexec():
    exe = Path(sys.executable).with_name("mpiexec")
    return str(exe) if exe.exists() else shutil.which("mpiexec")


@pytest.mark.mpi
def test_beam_fom_two_ranks_equals_serial(tmp_path):
    mpiexec = _mpiexec()
    if mpiexec is None:
        pytest.skip("no mpiexec")
    serial, parallel = tmp_path / "serial.npz", tmp_path / "parallel.npz"
    subprocess.run([sys.executable, str(SCRIPT), str(serial)], check=True, timeout=300)
    proc = subprocess.run([mpiexec, "-n", "2", sys.executable, str(SCRIPT), str(parallel)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    a, b = np.load(serial), np.load(parallel)
    for key in ("Q", "V", "Y", "E", "M", "K"):
        scale = np.abs(a[key]).max()
        assert np.abs(a[key] - b[key]).max() <= 1e-10 * scale, key


@pytest.mark.mpi
def test_recorder_two_ranks_equals_serial(tmp_path):
    """A user's own dolfinx loop recorded on 1 and 2 ranks gives identical snapshot arrays."""
    mpiexec = _mpiexec()
    if mpiexec is None:
        pytest.skip("no mpiexec")
    script = Path(__file__).with_name("mpi_recorder.py")
    serial, parallel = tmp_path / "serial.npz", tmp_path / "parallel.npz"
    subprocess.run([sys.executable, str(script), str(serial)], check=True, timeout=300)
    proc = subprocess.run([mpiexec, "-n", "2", sys.executable, str(script), str(parallel)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    a, b = np.load(serial), np.load(parallel)
    assert a["Q"].shape == (143, 40)
    for key in ("Q", "U", "Y", "t"):
        assert np.abs(a[key] - b[key]).max() <= 1e-12 * max(np.abs(a[key]).max(), 1.0), key
