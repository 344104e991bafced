"""Import DOLFINx the right way for every kind of install.

The PyPI wheel ``dolfinx-solver-real`` must be imported before ``dolfinx`` (it loads
its bundled MPI first); conda/apt/docker installs have no such package and need
nothing. Every module of this package that needs DOLFINx imports it from here.
"""

from __future__ import annotations

import importlib.util

if importlib.util.find_spec("dolfinx_solver") is not None:  # the PyPI wheel
    import dolfinx_solver  # noqa: F401  (orders MPI ahead of the compiled bindings)

try:
    import dolfinx
    import dolfinx.fem
    import dolfinx.fem.petsc
    import dolfinx.mesh
    import ufl
    from mpi4py import MPI
    from petsc4py import PETSc
except ImportError as exc:  # pragma: no cover - exercised only without dolfinx
    raise ImportError(
        "dolfinx_lopinf needs DOLFINx (>= 0.10) with petsc4py for its FOM layer. Install it "
        "with `pip install 'dolfinx_lopinf[dolfinx]'` (PyPI wheel, Python >= 3.12) or use a "
        "conda/apt/docker DOLFINx. The numpy-only parts (basis, ddt, inference, rom, "
        "metrics) work without it."
    ) from exc

from .._mpi_abort import install as _install_abort_hook

_install_abort_hook()  # MPI is loaded now: the safety net of multi-rank runs (_mpi_abort)

__all__ = ["MPI", "PETSc", "dolfinx", "ufl"]
