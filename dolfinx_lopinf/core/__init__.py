"""The numpy core: every step of the pipeline, usable alone (numpy and scipy only; cvxpy and
numba are imported where used).

    Snapshots -> pod (Basis) -> a scheme's relation or derivatives -> infer_mechanical
      -> LagrangianROM.simulate -> Basis.reconstruct

and for a polynomial potential: point_data -> fit_polynomial -> PolynomialROM.simulate;
for a gray-box nonlinear wave: infer_wave -> WaveROM.simulate. ``lo.fit`` runs the first
chain in one call and chooses the scheme, the reduced mass and the damping from the data.
"""

from . import ddt, schemes
from .basis import Basis, pod
from .ddt import derivatives
from .fit import ReducedModel, fit
from .identify import identify
from .gram import MechanicalOperators
from .inference import infer_mechanical, infer_opinf, infer_output, infer_wave
from .metrics import energy_error, relative_error
from .polynomial import PolynomialROM, fit_polynomial, point_data
from .rom import LagrangianROM, Trajectory, WaveROM
from .selection import Choice, choose_r
from .snapshots import Snapshots

__all__ = ["Basis", "Choice", "LagrangianROM", "MechanicalOperators", "PolynomialROM",
           "ReducedModel", "Snapshots", "Trajectory", "WaveROM", "choose_r", "ddt",
           "derivatives", "energy_error", "fit", "fit_polynomial", "identify",
           "infer_mechanical", "infer_opinf", "infer_output", "infer_wave", "pod", "point_data",
           "relative_error", "schemes"]
