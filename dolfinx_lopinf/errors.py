"""The package's errors and warnings (numpy core and DOLFINx layer alike).

Every error raised at a public entry point is one of these, so callers can catch the
package's complaints without catching unrelated bugs, and filter its warnings without
silencing everybody else's::

    import warnings, dolfinx_lopinf as lo
    warnings.simplefilter("ignore", lo.errors.IllConditionedDataWarning)

The error classes also derive from the builtin class the same complaint used to raise
(``ValueError``, ``RuntimeError``, ``OSError``), so existing ``except ValueError`` code keeps
working.
"""

from __future__ import annotations


class LOpInfError(Exception):
    """Base class of every error the package raises on purpose."""


class InputError(LOpInfError, ValueError):
    """An argument is wrong (shape, dtype, finiteness, space, time grid, ...): the message
    names the argument, the offending value and the remedy."""


class InputTypeError(InputError, TypeError):
    """An argument has the wrong type (e.g. not a dolfinx Function, not a UFL Form)."""


class RankDeficientDataError(InputError):
    """The data do not determine the operators (raised with ``strict=True``, or when a data
    row is identically zero)."""


class NonAffineParameterError(InputError):
    """A parameter enters a form non-affinely (its second derivative is not zero), so the
    form is not a sum theta_i(mu) L_i in it; the message names the parameter and the form.
    Attributes ``parameter`` and ``operator`` say which."""

    def __init__(self, message: str, parameter: str = "", operator: str = ""):
        super().__init__(message)
        self.parameter, self.operator = parameter, operator


class FileFormatError(LOpInfError, OSError):
    """A file is not one of ours, is truncated or corrupt, or lacks a required entry."""


class StepFailedError(LOpInfError, RuntimeError):
    """A time step failed: a reduced Newton iteration (numpy or compiled ROM loop) or the
    FOM's nonlinear solve (PETSc SNES) did not converge. The message names the step and time;
    a smaller dt or a lower amplitude is the usual remedy. ``step`` is the failed step (or
    None)."""

    def __init__(self, message, step=None):
        super().__init__(message)
        self.step = step


class SolverFailedError(LOpInfError, RuntimeError):
    """An optimisation solver (Clarabel through cvxpy) reported failure (infeasible, numerical
    error): no answer was returned."""


class CheckpointMismatchError(InputError):
    """A checkpoint belongs to another run (its fingerprint differs from this run's)."""


class RanksDisagreeError(InputError):
    """On several MPI ranks, an argument that must be the same on every rank (a time step, a
    number of steps, a basis) differs between them; raised on every rank, naming the
    argument and each rank's value."""


class OutOfSpaceError(LOpInfError, OSError):
    """Not enough free disk space for a file about to be written; nothing was written (the
    previous version of the file, if any, is untouched)."""


class LOpInfWarning(UserWarning):
    """Base class of the package's warnings."""


class IllConditionedDataWarning(LOpInfWarning, RuntimeWarning):
    """The data determine some operator directions only to within rounding; the fit was
    regularised there (see :func:`dolfinx_lopinf.core.gram.gram_data`)."""


class SolverWarning(LOpInfWarning, RuntimeWarning):
    """A solver stopped without meeting its tolerance; the result is returned with its
    certificate."""


class NonLagrangianWarning(LOpInfWarning, RuntimeWarning):
    """A reduced model's operators are not those of a Lagrangian system (K or C not
    symmetric, K or M indefinite): its energy is not conserved or dissipated and its
    trajectory may grow without bound. Legitimate for standard OpInf models; pass
    ``lagrangian=False`` to :class:`dolfinx_lopinf.core.LagrangianROM` to say so."""


class SchemeMismatchWarning(LOpInfWarning):
    """The integrator the caller named does not match the recording: another scheme fits the
    data clearly better (the message names it), or the named one fits clearly better with the
    recorded input times moved (loads recorded at other times than the loop applied them:
    the message gives the shift)."""


class PoorPredictionWarning(LOpInfWarning):
    """The model lo.fit chose predicts the held-back end of its own training data poorly: the
    choice between the candidates, and the accuracy on new loads, are in doubt. The message
    gives the error and the usual causes (r too small, snapshots that are not consecutive
    steps, loads recorded at other times than applied or that are not forces, a record too
    short for its first part to determine the operators)."""


class InputCorrectedWarning(LOpInfWarning):
    """An input was made consistent rather than refused (e.g. an initial state moved onto its
    Dirichlet conditions); the message says what changed and by how much."""


class ParameterRangeWarning(LOpInfWarning):
    """A parametric reduced model predicts at a parameter outside the range it was trained
    on: its stability is still certified (inside the cone), its accuracy is not."""


def warn(message: str, category: type[Warning]) -> None:
    """``warnings.warn`` attributed to the first caller outside this package (the user's line),
    however deep inside the package the warning arises."""
    import os
    import sys
    import warnings

    if sys.version_info >= (3, 12):
        warnings.warn(message, category, skip_file_prefixes=(os.path.dirname(__file__),))
    else:  # pragma: no cover - Python < 3.12 (DOLFINx from conda/apt): the nearest frame
        warnings.warn(message, category, stacklevel=2)
