"""Input checks shared by the public entry points: fail early, say what is wrong."""

from __future__ import annotations

import numpy as np


def check_finite(array: np.ndarray, name: str) -> None:
    """Raise ``ValueError`` naming the first non-finite entry of ``array``."""
    finite = np.isfinite(array)
    if not finite.all():
        bad = np.argwhere(~finite)[0]
        raise ValueError(
            f"{name} contains {int((~finite).sum())} non-finite value(s) (NaN or inf), "
            f"first at index {tuple(int(i) for i in bad)}; clean the data or shorten the window"
        )


def check_matrix(array, name: str, rows: int | None = None, cols: int | None = None) -> np.ndarray:
    """Return ``array`` as a finite 2-D float array with the given shape."""
    a = np.asarray(array, dtype=float)
    if a.ndim != 2:
        raise ValueError(f"{name} must be a 2-D array (rows, time), got shape {a.shape}")
    if rows is not None and a.shape[0] != rows:
        raise ValueError(f"{name} must have {rows} rows, got shape {a.shape}")
    if cols is not None and a.shape[1] != cols:
        raise ValueError(f"{name} must have {cols} columns (time samples), got shape {a.shape}")
    check_finite(a, name)
    return a


def check_uniform_times(times, rtol: float = 1e-6) -> float:
    """Return the spacing of a uniform, increasing time grid or raise."""
    t = np.asarray(times, dtype=float)
    if t.ndim != 1 or len(t) < 2:
        raise ValueError(f"times must be a 1-D array with at least 2 entries, got shape {t.shape}")
    check_finite(t, "times")
    steps = np.diff(t)
    dt = float(steps.mean())
    if dt <= 0 or np.max(np.abs(steps - dt)) > rtol * abs(dt):
        raise ValueError(
            "times must be uniformly spaced and increasing (finite differences assume it); "
            f"spacing ranges over [{steps.min():.6g}, {steps.max():.6g}]"
        )
    return dt
