"""Input checks shared by the public entry points: fail early, say what is wrong.

Every array that enters the numpy core passes through :func:`as_real_array` (directly or via
:func:`check_matrix` / :func:`check_vector`): it becomes a float64 array or an
:class:`~dolfinx_lopinf.errors.InputError` naming the argument says why not. Complex data are
refused (a cast would drop the imaginary part), as are text, ragged nesting and objects that
are not numbers; integers and booleans convert exactly. Each check is one pass over the data.
"""

from __future__ import annotations

import numbers
import operator

import numpy as np

from ..errors import InputError


def as_real_array(value, name: str, *, dtype=float) -> np.ndarray:
    """``value`` as a real floating array (float64 by default), or an ``InputError``.

    Refuses complex numbers (even with zero imaginary part: the caller must take ``.real``
    knowingly), strings, dates, ragged nested sequences and objects that are not real numbers.
    """
    try:
        a = np.asarray(value)
    except ValueError as exc:  # ragged nesting ("inhomogeneous shape")
        raise InputError(f"{name} is a ragged nested sequence (rows of different lengths), "
                         f"not an array: {exc}; pass a rectangular array") from None
    kind = a.dtype.kind
    if kind == "c":
        raise InputError(f"{name} is complex ({a.dtype}); the models here are real - pass "
                         f"{name}.real (or split real and imaginary parts) explicitly")
    if kind in "USV":
        raise InputError(f"{name} holds text or raw bytes ({a.dtype}), not numbers; convert "
                         "it to a float array")
    if kind in "mM":
        raise InputError(f"{name} holds dates/durations ({a.dtype}); convert it to float "
                         "seconds, e.g. (t - t[0]) / np.timedelta64(1, 's')")
    if kind == "O":
        flat = a.reshape(-1)
        for i, item in enumerate(flat):
            if isinstance(item, (numbers.Complex, np.complexfloating)) and not isinstance(
                    item, numbers.Real):
                raise InputError(f"{name} is complex (entry {i} of the object array is "
                                 f"{item!r}); pass {name}.real explicitly")
            if not isinstance(item, (numbers.Real, np.bool_)):
                raise InputError(f"{name} entry {i} is {item!r} ({type(item).__name__}), not "
                                 "a real number; pass a numeric array")
    try:
        return np.asarray(a, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} cannot be converted to a float array ({a.dtype}): {exc}") from None


def check_finite(array: np.ndarray, name: str,
                 remedy: str = "clean the data or shorten the window") -> None:
    """Raise ``InputError`` naming the first non-finite entry of ``array`` (and ``remedy``)."""
    finite = np.isfinite(array)
    if not finite.all():
        bad = np.argwhere(~finite)[0]
        raise InputError(
            f"{name} contains {int((~finite).sum())} non-finite value(s) (NaN or inf), "
            f"first at index {tuple(int(i) for i in bad)}; {remedy}"
        )


def check_matrix(array, name: str, rows: int | None = None, cols: int | None = None) -> np.ndarray:
    """Return ``array`` as a finite 2-D float array with the given shape."""
    a = as_real_array(array, name)
    if a.ndim != 2:
        raise InputError(f"{name} must be a 2-D array (rows, time), got shape {a.shape}")
    if rows is not None and a.shape[0] != rows:
        raise InputError(f"{name} must have {rows} rows, got shape {a.shape}")
    if cols is not None and a.shape[1] != cols:
        raise InputError(f"{name} must have {cols} columns (time samples), got shape {a.shape}")
    check_finite(a, name)
    return a


def check_vector(array, name: str, size: int | None = None) -> np.ndarray:
    """Return ``array`` as a finite 1-D float array (of ``size`` entries when given); a
    (size, 1) or (1, size) array is accepted and flattened."""
    a = as_real_array(array, name)
    if a.ndim != 1:
        if a.ndim == 2 and 1 in a.shape:
            a = a.reshape(-1)
        else:
            raise InputError(f"{name} must be a 1-D array, got shape {a.shape}")
    if size is not None and a.shape != (size,):
        raise InputError(f"{name} must have shape ({size},), got {a.shape}")
    check_finite(a, name)
    return a


def check_square(array, name: str, size: int | None = None,
                 remedy: str = "an operator must be finite (did its fit fail?)") -> np.ndarray:
    """Return ``array`` as a finite square float matrix (size x size when given)."""
    a = as_real_array(array, name)
    if a.ndim != 2 or a.shape[0] != a.shape[1] or a.shape[0] == 0:
        raise InputError(f"{name} must be a non-empty square matrix, got shape {a.shape}")
    if size is not None and a.shape != (size, size):
        raise InputError(f"{name} must have shape ({size}, {size}), got {a.shape}")
    check_finite(a, name, remedy)
    return a


def check_int(value, name: str, minimum: int | None = None) -> int:
    """``value`` as a Python int (numpy integers accepted, floats and bools refused)."""
    if isinstance(value, (bool, np.bool_)):
        raise InputError(f"{name} must be an integer, got the boolean {value!r}")
    try:
        v = operator.index(value)
    except TypeError:
        raise InputError(f"{name} must be an integer, got {value!r} "
                         f"({type(value).__name__})") from None
    if minimum is not None and v < minimum:
        raise InputError(f"{name} must be >= {minimum}, got {v}")
    return v


def check_real(value, name: str) -> float:
    """``value`` as a finite Python float (a real scalar: strings, bytes, complex numbers,
    booleans and None refused)."""
    try:
        if isinstance(value, (str, bytes, complex, bool)) or value is None:
            raise TypeError
        x = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a real number, got {value!r}") from None
    if not np.isfinite(x):
        raise InputError(f"{name} must be finite, got {value!r}")
    return x


def check_positive(value, name: str) -> float:
    """``value`` as a positive finite float (a real scalar; bools and strings refused)."""
    a = None if isinstance(value, (bool, np.bool_, str, bytes)) else np.asarray(value)
    if a is None or a.ndim != 0 or a.dtype.kind not in "iuf":
        raise InputError(f"{name} must be a positive real number, got {value!r} "
                         f"({type(value).__name__})")
    v = float(a)
    if not (np.isfinite(v) and v > 0):
        raise InputError(f"{name} must be positive and finite, got {value!r}")
    return v


def check_uniform_times(times, rtol: float = 1e-6) -> float:
    """Return the spacing of a uniform, increasing time grid or raise ``InputError``.

    The check is relative to the spacing and allows for the rounding of the times
    themselves: a time t stored in a floating type with machine epsilon eps is known to
    about eps |t| / 2, so consecutive differences scatter by up to eps max|t| around the true
    spacing dt even on an exact grid (float32 times, or times offset by 1e6 s with dt = 1e-5:
    eps max|t| / dt ~ 1e-5 .. 1e-4). Differences must agree to ``rtol dt + 2 eps max|t|``.
    When that rounding is itself a quarter of the spacing or more, the times cannot show
    whether the grid is uniform (a missing or repeated sample would pass): refused with the
    remedy (float64 times, or times relative to the start).
    """
    raw = as_real_array(times, "times", dtype=None)
    if raw.dtype.kind not in "fiub":
        raw = as_real_array(raw, "times")
    eps = float(np.finfo(raw.dtype).eps) if raw.dtype.kind == "f" else float(np.finfo(float).eps)
    eps = max(eps, float(np.finfo(float).eps))
    t = np.asarray(raw, dtype=float)
    if t.ndim != 1 or len(t) < 2:
        raise InputError(f"times must be a 1-D array with at least 2 entries, got shape {t.shape}")
    check_finite(t, "times")
    steps = np.diff(t)
    dt = float(steps.mean())
    rounding = 2.0 * eps * float(np.max(np.abs(t)))
    if dt > 0 and rounding > 0.25 * dt:
        raise InputError(
            f"times are too coarse to resolve their spacing: {raw.dtype} times of magnitude "
            f"{np.max(np.abs(t)):.6g} are rounded to ~{rounding:.3g}, the spacing is {dt:.6g}; "
            "pass float64 times, or times relative to the first sample (t - t[0])")
    if not dt > 0 or steps.min() <= 0:
        k = int(np.argmin(steps))
        raise InputError(
            f"times must be strictly increasing; times[{k}] = {float(t[k])!r} is followed by "
            f"times[{k + 1}] = {float(t[k + 1])!r}; sort the samples and drop duplicates")
    tol = rtol * dt + rounding
    dev = np.abs(steps - dt)
    if dev.max() > tol:
        k = int(np.argmax(dev))
        raise InputError(
            "times must be uniformly spaced and increasing (finite differences assume it); "
            f"spacing ranges over [{steps.min():.6g}, {steps.max():.6g}] (mean {dt:.6g}), "
            f"worst between times[{k}] = {float(t[k])!r} and times[{k + 1}] = "
            f"{float(t[k + 1])!r}; resample "
            "the data onto a uniform grid or cut the window at the gap")
    return dt


def pow2_scale(*arrays) -> float:
    """The power of two nearest to the largest magnitude in ``arrays`` (None entries and empty
    arrays skipped; 1.0 if all are zero). Dividing by it is exact (barring subnormals) and
    brings the data near 1, so sums of squares neither overflow (data ~ 1e160) nor underflow
    (data ~ 1e-170)."""
    big = max((float(np.abs(a).max()) for a in arrays if a is not None and a.size), default=0.0)
    return 1.0 if big == 0 or not np.isfinite(big) else float(2.0 ** np.round(np.log2(big)))


def fro_norm(a: np.ndarray) -> float:
    """Frobenius norm without overflow or underflow for any finite data (scaled first)."""
    s = pow2_scale(a)
    return float(np.linalg.norm(a / s) * s) if s != 1.0 else float(np.linalg.norm(a))


def _row_list(rows: np.ndarray, limit: int = 10) -> str:
    shown = ", ".join(str(int(i)) for i in rows[:limit])
    return shown + (f", ... ({len(rows)} in all)" if len(rows) > limit else "")


def check_blocks(blocks, n: int, name: str = "blocks") -> dict:
    """Validate named row blocks of an n-row state: ``{name: int64 rows}``.

    The blocks must partition the rows 0 .. n-1: integer indices (a boolean mask of length n
    is taken as ``np.flatnonzero(mask)``), none empty, none outside the range, none repeated
    within a block, no row in two blocks (a block-diagonal basis would not be orthonormal),
    no row in none (its data would be silently dropped from every projection). O(n) per block.
    """
    if blocks is None:
        return {}
    if not hasattr(blocks, "items"):
        raise InputError(f"{name} must be a dict name -> row indices, got {type(blocks).__name__}")
    out, owner = {}, np.full(n, -1, dtype=np.int64)
    names = [str(k) for k in blocks]
    for b, (key, value) in enumerate(blocks.items()):
        label = f"{name}[{str(key)!r}]"
        raw = np.asarray(value)
        if raw.dtype.kind == "b":
            if raw.shape != (n,):
                raise InputError(f"{label} is a boolean mask of shape {raw.shape}; a mask must "
                                 f"have shape ({n},)")
            rows = np.flatnonzero(raw)
        else:
            rows = as_real_array(raw, label, dtype=None) if raw.dtype.kind not in "iu" else raw
            if rows.dtype.kind not in "iu":
                rows = rows.astype(float)
                if not np.all(np.isfinite(rows)) or np.any(rows != np.round(rows)):
                    raise InputError(f"{label} must hold integer row indices, got {raw.dtype} "
                                     f"values such as {rows[rows != np.round(rows)][:3]}")
            rows = rows.astype(np.int64)
        if rows.ndim != 1 or rows.size == 0:
            raise InputError(f"{label} must be a non-empty 1-D array of row indices, got shape "
                             f"{rows.shape}")
        if rows.min() < 0 or rows.max() >= n:
            bad = rows[(rows < 0) | (rows >= n)]
            raise InputError(f"{label} indexes rows outside 0..{n - 1}: {_row_list(bad)}")
        counts = np.bincount(rows, minlength=n)
        if counts.max() > 1:
            raise InputError(f"{label} repeats row(s) {_row_list(np.flatnonzero(counts > 1))}; "
                             "list each row once")
        taken = owner[rows]
        if np.any(taken >= 0):
            other = names[int(taken[taken >= 0][0])]
            shared = np.sort(rows[taken >= 0])
            raise InputError(
                f"{name} overlap: {other!r} and {str(key)!r} share {len(shared)} row(s): "
                f"{_row_list(shared)}; each state row must belong to exactly one block")
        owner[rows] = b
        out[str(key)] = rows
    if out and np.any(owner < 0):
        missing = np.flatnonzero(owner < 0)
        raise InputError(
            f"{len(missing)} of {n} state rows belong to no block of {name} "
            f"({', '.join(map(repr, out))}): {_row_list(missing)}; add them to a block, or "
            "drop them from the states before building the basis")
    return out


#: a weight is symmetric when max |W - W^T| <= WEIGHT_SYMMETRY max |W| (assembled mass
#: matrices are symmetric to the last bits; anything further off is not an inner product)
WEIGHT_SYMMETRY = 1e-10


def check_weight(weight, n: int, name: str = "weight"):
    """An inner-product matrix of the states: ``weight`` as a float64 ``scipy.sparse``
    CSR array (when sparse) or a dense (n, n) array, symmetrised, with a named
    ``InputError`` unless it is (n, n), finite, symmetric (:data:`WEIGHT_SYMMETRY`) and has a
    positive diagonal (positive definiteness on the data's span is checked where it is used,
    :func:`~dolfinx_lopinf.core.basis.pod`)."""
    import scipy.sparse as sp

    if sp.issparse(weight):
        if weight.dtype.kind not in "fiu":
            raise InputError(f"{name} must be a real matrix, got dtype {weight.dtype}")
        W = sp.csr_array(weight, dtype=float)
        values = W.data
    else:
        W = as_real_array(weight, name)
        values = W
    if W.ndim != 2 or W.shape != (n, n):
        raise InputError(f"{name} must be ({n}, {n}) - an inner product of the {n} state rows, "
                         f"e.g. the mass matrix - got shape {W.shape}")
    if sp.issparse(W) and not np.all(np.isfinite(values)):  # name (row, column), not the
        k = int(np.flatnonzero(~np.isfinite(values))[0])    # position in the CSR storage
        row = int(np.searchsorted(W.indptr, k, side="right")) - 1
        raise InputError(f"{name} contains {int((~np.isfinite(values)).sum())} non-finite "
                         f"value(s) (NaN or inf), first at ({row}, {int(W.indices[k])}); an "
                         "inner-product matrix must be finite")
    check_finite(values, name, "an inner-product matrix must be finite")
    top = float(np.abs(values).max()) if values.size else 0.0
    asym = abs(W - W.T)
    asym = float(asym.max()) if sp.issparse(asym) else float(np.max(asym))
    if asym > WEIGHT_SYMMETRY * top:
        raise InputError(f"{name} is not symmetric (max |W - W^T| = {asym:.3g} against max |W| = "
                         f"{top:.3g}); an inner product is symmetric positive definite (the mass "
                         "matrix is)")
    diag = W.diagonal()
    if not np.all(diag > 0):
        i = int(np.argmin(diag))
        raise InputError(f"{name} has a diagonal entry <= 0 (row {i}: {float(diag[i])!r}); an inner "
                         "product is positive definite - assemble the mass matrix with its "
                         "Dirichlet rows kept (diagonal 1), or pass weight=None")
    return 0.5 * (W + W.T)
