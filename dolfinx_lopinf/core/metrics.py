"""Error measures of reduced models: relative state or output errors and energy errors
(numpy only)."""

from __future__ import annotations

import numpy as np

from ._checks import as_real_array, check_finite, pow2_scale
from ..errors import InputError


def relative_error(reference: np.ndarray, approximation: np.ndarray) -> float:
    """||reference - approximation||_F / ||reference||_F (state or output error).

    Both arrays are divided by one power of two near their largest entry before the norms are
    formed, so the ratio is the same for data of any finite magnitude (no overflow at 1e160,
    no underflow at 1e-170). A non-finite ``approximation`` (a blown-up ROM) gives ``inf``
    or ``nan`` - it is a result, not an input error; a non-finite ``reference`` is refused.
    """
    reference = as_real_array(reference, "reference")
    approximation = as_real_array(approximation, "approximation")
    if reference.shape != approximation.shape:
        raise InputError(f"shapes differ: {reference.shape} vs {approximation.shape}")
    check_finite(reference, "reference")
    finite = approximation[np.isfinite(approximation)] if approximation.size else approximation
    s = pow2_scale(reference, finite)
    denom = np.linalg.norm(reference / s)
    if denom == 0:
        raise InputError("the reference is identically zero; a relative error is undefined")
    return float(np.linalg.norm(reference / s - approximation / s) / denom)


def energy_error(energy: np.ndarray, relative: bool = True) -> np.ndarray:
    """``|E(t) - E(0)|`` (divided by ``|E(0)|`` when ``relative``) along a trajectory.

    E(0) must be finite; later non-finite energies (a trajectory that blew up) give
    non-finite errors, which :func:`is_stable` reports as unstable."""
    energy = as_real_array(energy, "energy")
    if energy.ndim != 1 or energy.size < 1:
        raise InputError(f"energy must be a 1-D array with at least 1 entry, got shape "
                         f"{energy.shape}")
    if not np.isfinite(energy[0]):
        raise InputError(f"energy contains a non-finite initial value E(0) = {energy[0]}; the "
                         "reference energy must be finite")
    e0 = energy[0]
    err = np.abs(energy - e0)
    if relative:
        if e0 == 0:
            raise InputError("E(0) = 0: use relative=False")
        err = err / abs(e0)
    return err


def is_stable(states: np.ndarray, energy_err: np.ndarray, bound: float = 1.0) -> bool:
    """A ROM run counts as stable when its states stay finite and its relative FOM energy
    error never exceeds ``bound`` (default: 100 % of the initial energy)."""
    return bool(np.all(np.isfinite(states)) and np.all(np.isfinite(energy_err))
                and np.max(energy_err) <= bound)
