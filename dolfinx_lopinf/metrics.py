"""Error measures of METHOD.md section 5 (numpy only)."""

from __future__ import annotations

import numpy as np


def relative_error(reference: np.ndarray, approximation: np.ndarray) -> float:
    """||reference - approximation||_F / ||reference||_F (state or output error)."""
    reference = np.asarray(reference, dtype=float)
    approximation = np.asarray(approximation, dtype=float)
    if reference.shape != approximation.shape:
        raise ValueError(f"shapes differ: {reference.shape} vs {approximation.shape}")
    denom = np.linalg.norm(reference)
    if denom == 0:
        raise ValueError("the reference is identically zero; a relative error is undefined")
    return float(np.linalg.norm(reference - approximation) / denom)


def energy_error(energy: np.ndarray, relative: bool = True) -> np.ndarray:
    """|E(t) - E(0)| (divided by |E(0)| when ``relative``) along a trajectory."""
    energy = np.asarray(energy, dtype=float)
    err = np.abs(energy - energy[0])
    if relative:
        if energy[0] == 0:
            raise ValueError("E(0) = 0: use relative=False")
        err = err / abs(energy[0])
    return err


def is_stable(states: np.ndarray, energy_err: np.ndarray, bound: float = 1.0) -> bool:
    """A ROM run counts as stable when its states stay finite and its relative FOM energy
    error never exceeds ``bound`` (default: 100 % of the initial energy)."""
    return bool(np.all(np.isfinite(states)) and np.all(np.isfinite(energy_err))
                and np.max(energy_err) <= bound)
