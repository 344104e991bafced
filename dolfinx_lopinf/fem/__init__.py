"""The DOLFINx layer: a UFL Lagrangian -> forms, integrators and the one time loop (``run``),
recording from your own loop (``SnapshotRecorder``) and state maps, point outputs and derived
outputs (UFL expressions of the reconstructed field), intrusive projection, the gray-box
nonlinearity, streaming POD, probes, VTX output; the affine parameter structure of a UFL
Lagrangian (``affine``) and the FOM at any parameter (``param_fom``). Importing it imports
DOLFINx."""

from .derived import DerivedOutput
from .fom import run
from .state import StateMap, output_matrix_in_state, point_output_matrix, state_gram
from .galerkin_nonlinear import GalerkinForce
from .integrators import MidpointIntegrator
from .newmark import NewmarkIntegrator
from .intrusive import galerkin_rom
from .lagrangian import LagrangianSystem
from .probes import probe, probe_points
from .recorder import SnapshotRecorder
from .vtx import state_rows, states_to_function, write_vtx

__all__ = ["DerivedOutput", "GalerkinForce", "LagrangianSystem", "MidpointIntegrator",
           "NewmarkIntegrator", "SnapshotRecorder", "StateMap", "galerkin_rom",
           "output_matrix_in_state", "point_output_matrix", "probe", "probe_points", "run",
           "state_gram", "state_rows", "states_to_function", "write_vtx"]
