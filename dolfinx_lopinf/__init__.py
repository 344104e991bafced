"""dolfinx_lopinf: structure-preserving, data-driven reduced-order models on DOLFINx.

Pipeline (each stage a plain object, usable alone):

    LagrangianSystem -> run (FOM) -> Snapshots -> pod (Basis) -> ddt.derivatives
      -> infer_mechanical (L-OpInf) -> LagrangianROM.simulate -> Basis.reconstruct

and for a non-quadratic (polynomial) potential: pod -> probe (black-box FOM steps at lifted
samples) -> fit_polynomial -> PolynomialROM.simulate.

The numpy core (``ddt``, ``basis``, ``inference``, ``rom``, ``metrics``, ``snapshots``)
imports without DOLFINx; the FOM layer (``LagrangianSystem``, ``MidpointIntegrator``,
``run``, ``galerkin_rom``) is loaded on first use.
"""

import importlib.util as _ilu

if _ilu.find_spec("dolfinx_solver") is not None:
    # The PyPI DOLFINx wheel must load its MPI before anything imports dolfinx; doing it here
    # lets users write `import dolfinx_lopinf` then `import dolfinx` in their own code.
    import dolfinx_solver  # noqa: F401

from . import errors, parametric
from .core import ddt, schemes
from .core.basis import Basis, pod
from .core.fit import ReducedModel, fit
from .core.ddt import derivatives, newmark_data, variational_data
from .core.inference import (MechanicalOperators, infer_mechanical, infer_opinf, infer_output,
                        infer_wave)
from .core.metrics import energy_error, relative_error
from .core.polynomial import PolynomialROM, fit_polynomial, point_data
from .core.rom import LagrangianROM, Trajectory, WaveROM, load_rom, save_rom
from .core.selection import Choice, choose_r
from .core.snapshots import Snapshots

__version__ = "0.1.0"

_LAZY = {
    "LagrangianSystem": "fem.lagrangian",
    "MidpointIntegrator": "fem.integrators",
    "StepFailed": "fem.integrators",
    "run": "fem.fom",
    "StateMap": "fem.fom",
    "point_output_matrix": "fem.fom",
    "galerkin_rom": "fem.intrusive",
    "SnapshotRecorder": "fem.recorder",
    "write_vtx": "fem.vtx",
    "states_to_function": "fem.vtx",
    "state_rows": "fem.vtx",
    "probe": "fem.probes",
    "probe_points": "fem.probes",
    "GalerkinForce": "fem.galerkin_nonlinear",
    "DerivedOutput": "fem.derived",
}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["ddt", "errors", "parametric", "schemes", "fit", "ReducedModel", "Basis", "Choice", "LagrangianROM", "MechanicalOperators", "Snapshots", "Trajectory",
           "derivatives", "newmark_data", "variational_data", "energy_error", "infer_mechanical", "infer_opinf", "infer_output",
           "choose_r", "infer_wave", "WaveROM", "load_rom", "pod", "relative_error", "save_rom",
           "fit_polynomial", "PolynomialROM", "point_data", *_LAZY]
