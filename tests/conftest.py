"""Shared fixtures. After each test, collect garbage and synchronise ranks so PETSc objects
are destroyed collectively (as DOLFINx's own test-suite does)."""

import gc
import importlib.util
import os

import pytest

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
HAVE_DOLFINX = importlib.util.find_spec("dolfinx") is not None


@pytest.fixture(autouse=True)
def _collect():
    yield
    gc.collect()
    if HAVE_DOLFINX:
        from dolfinx_lopinf._dolfinx import MPI

        MPI.COMM_WORLD.Barrier()


@pytest.fixture(scope="session")
def beam():
    """The paper's beam (200 Hermite nodes, state in R^400)."""
    pytest.importorskip("dolfinx_lopinf._dolfinx")
    from dolfinx_lopinf.scenes import beam as scene

    return scene.build(200)
