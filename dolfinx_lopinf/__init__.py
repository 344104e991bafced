"""dolfinx_lopinf: structure-preserving, data-driven reduced-order models on DOLFINx.

The front door - the one-call path, fifteen names::

    rec = lo.SnapshotRecorder(u)                # your own dolfinx time loop ...
    model = lo.fit(rec.snapshots(), r=4)        # ... or lo.run(lo.LagrangianSystem(L, ...))
    traj = model.predict(n_steps, inputs=load)  # the ROM, stepped with your loop's scheme
    lo.write_vtx("rom.bp", V, model.reconstruct(traj.Qh), traj.times)

``fit``, ``ReducedModel``, ``Snapshots``, ``pod``, ``relative_error``, ``schemes`` (the time
integrators as objects), ``errors``, ``core`` (every step of the pipeline, numpy only:
``core.infer_mechanical``, ``core.LagrangianROM``, ...) and ``parametric`` (one model for a
family of designs) import without DOLFINx; ``SnapshotRecorder``, ``LagrangianSystem``,
``run``, ``write_vtx``, ``point_output_matrix`` and ``fem`` (the DOLFINx layer: integrators,
state maps, probes, derived outputs, Galerkin projection) are loaded on first use, as is
``viz`` (off-screen pyvista renders and matplotlib figures).
"""

import importlib.util as _ilu

if _ilu.find_spec("dolfinx_solver") is not None:
    # The PyPI DOLFINx wheel must load its MPI before anything imports dolfinx; doing it here
    # lets users write `import dolfinx_lopinf` then `import dolfinx` in their own code.
    import dolfinx_solver  # noqa: F401

from . import _mpi_abort, core, errors, parametric
from .core import schemes
from .core.basis import pod
from .core.fit import ReducedModel, fit
from .core.metrics import relative_error
from .core.snapshots import Snapshots

__version__ = "0.2.0"

# Several MPI ranks: an exception left uncaught on one rank aborts the job instead of leaving
# the others waiting forever in a collective (see dolfinx_lopinf._mpi_abort).
_mpi_abort.install()

_LAZY = {
    "SnapshotRecorder": "fem.recorder",
    "LagrangianSystem": "fem.lagrangian",
    "run": "fem.fom",
    "write_vtx": "fem.vtx",
    "point_output_matrix": "fem.state",
}


def __getattr__(name):
    import importlib

    if name in ("fem", "viz"):
        return importlib.import_module(f".{name}", __name__)
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r} (the step-by-step "
                         "functions are in dolfinx_lopinf.core and dolfinx_lopinf.fem)")


__all__ = ["fit", "ReducedModel", "Snapshots", "pod", "relative_error", "schemes", "errors",
           "core", "fem", "viz", "parametric", *_LAZY]
