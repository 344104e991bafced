"""Finite-difference time derivatives of snapshot data: the continuous data relation.

Eighth-order central differences on a uniform grid, time along the last axis:

    d1_k = [ 4/5 (q_{k+1}-q_{k-1}) - 1/5 (q_{k+2}-q_{k-2})
             + 4/105 (q_{k+3}-q_{k-3}) - 1/280 (q_{k+4}-q_{k-4}) ] / dt
    d2_k = [ -205/72 q_k + 8/5 (q_{k+1}+q_{k-1}) - 1/5 (q_{k+2}+q_{k-2})
             + 8/315 (q_{k+3}+q_{k-3}) - 1/560 (q_{k+4}+q_{k-4}) ] / dt^2

The stencil needs four neighbours on each side, so the derivatives exist at the interior
columns 4 .. K-5 only; :func:`derivatives` returns the trimmed states alongside them so all
three arrays line up column by column.
"""

from __future__ import annotations

import numpy as np

from ._checks import as_real_array, check_finite, check_positive, check_uniform_times
from ..errors import InputError

#: Half-width of the central stencils.
HALF_WIDTH = 4
_D1 = np.array([4 / 5, -1 / 5, 4 / 105, -1 / 280])  # antisymmetric weights for offsets 1..4
_D2_CENTER = -205 / 72
_D2 = np.array([8 / 5, -1 / 5, 8 / 315, -1 / 560])  # symmetric weights for offsets 1..4


def _check(states: np.ndarray, dt: float, n_min: int = 2 * HALF_WIDTH + 1) -> np.ndarray:
    states = as_real_array(states, "states")
    if states.ndim not in (1, 2):
        raise InputError(f"states must be (r, K) or (K,), got shape {states.shape}")
    n_times = states.shape[-1]
    if n_times < n_min:
        what = ("the 8th-order central difference needs" if n_min == 2 * HALF_WIDTH + 1
                else "the discrete Euler-Lagrange data need")
        raise InputError(
            f"{what} at least {n_min} time samples, got {n_times}; record a longer window or "
            "more often"
        )
    check_positive(dt, "dt")
    check_finite(states, "states")
    return states


def _check_grid(states, times, n_min: int = 2 * HALF_WIDTH + 1):
    """(states, dt) for states sampled at uniform ``times``, checked once."""
    dt = check_uniform_times(times)
    q = _check(states, dt, n_min)
    if q.shape[-1] != len(times):
        raise InputError(f"states have {q.shape[-1]} columns but times has {len(times)} entries; "
                         "pass one time per column")
    return q, dt


def first_derivative(states: np.ndarray, dt: float) -> np.ndarray:
    """Eighth-order central first derivative.

    Args:
        states: (r, K) or (K,) samples at uniform spacing ``dt``.
        dt: sample spacing.

    Returns:
        (r, K-8) derivative at the interior columns 4 .. K-5.
    """
    q = _check(states, dt)
    K, h = q.shape[-1], HALF_WIDTH
    out = np.zeros(q.shape[:-1] + (K - 2 * h,))
    for j, w in enumerate(_D1, start=1):
        out += w * (q[..., h + j : K - h + j] - q[..., h - j : K - h - j])
    return out / dt


def second_derivative(states: np.ndarray, dt: float) -> np.ndarray:
    """Eighth-order central second derivative; shapes as in :func:`first_derivative`."""
    q = _check(states, dt)
    K, h = q.shape[-1], HALF_WIDTH
    out = _D2_CENTER * q[..., h : K - h]
    for j, w in enumerate(_D2, start=1):
        out = out + w * (q[..., h + j : K - h + j] + q[..., h - j : K - h - j])
    return out / dt**2


def derivatives(states: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """States and their first and second time derivatives on a common (trimmed) grid.

    Args:
        states: (r, K) reduced states Qh at ``times``.
        times: (K,) uniformly spaced sample times.

    Returns:
        ``(Qh, dQh, ddQh)``, each (r, K-8): columns 4 .. K-5 of the input and their
        derivatives.

    Example:
        >>> t = np.linspace(0, 1, 101); Q = np.sin(t)[None]
        >>> Qh, dQh, ddQh = derivatives(Q, t)
        >>> bool(np.allclose(ddQh, -Qh, atol=1e-9))
        True
    """
    q, dt = _check_grid(states, times)
    h = HALF_WIDTH
    return q[..., h:-h], first_derivative(q, dt), second_derivative(q, dt)


def variational_data(states: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Data on which L-OpInf matches the midpoint variational integrator exactly.

    For ``L = 1/2 |q_t|^2 - 1/2 q^T K q`` the midpoint discrete Euler-Lagrange equations read

        (q_{k+1} - 2 q_k + q_{k-1}) / dt^2 + K (q_{k+1} + 2 q_k + q_{k-1}) / 4 = 0,

    so fitting ``infer_mechanical(Qbar, None, D2, damping=False)`` with

        Qbar_k = (q_{k+1} + 2 q_k + q_{k-1}) / 4,   D2_k = (q_{k+1} - 2 q_k + q_{k-1}) / dt^2

    identifies the operator of the *discrete* dynamics the snapshots obey (and the ROM is
    integrated with the same scheme), instead of a continuous-time K from high-order
    differences, which for stiff modes (dt omega not small) is biased by O((dt omega)^2).

    Args:
        states: (r, K) samples of a midpoint trajectory at every step (uniform ``times``).

    Returns:
        ``(Qbar, D2)``, each (r, K-2), for k = 1 .. K-2.
    """
    q, dt = _check_grid(states, times, 3)
    return (q[..., 2:] + 2 * q[..., 1:-1] + q[..., :-2]) / 4, (q[..., 2:] - 2 * q[..., 1:-1] + q[..., :-2]) / dt**2


def newmark_data(states: np.ndarray, times: np.ndarray, inputs: np.ndarray | None = None):
    """Data on which L-OpInf matches Newmark (gamma = 1/2, beta = 1/4) trajectories exactly.

    Eliminating velocities and accelerations from the average-acceleration recurrences of
    M q_tt + C q_t + K q = B u (uniform dt) leaves a three-point relation between states,

        M D2_k + C D1_k + K Qbar_k = B Ubar_k,
        D2_k = (q_{k+1} - 2 q_k + q_{k-1}) / dt^2,   D1_k = (q_{k+1} - q_{k-1}) / (2 dt),
        Qbar_k = (q_{k+1} + 2 q_k + q_{k-1}) / 4,    Ubar_k = (u_{k+1} + 2 u_k + u_{k-1}) / 4,

    (for C = 0 and u = 0 it is the midpoint rule's discrete Euler-Lagrange equation, see
    :func:`variational_data`). Fitting ``infer_mechanical(Qbar, D1, D2, Ubar)`` identifies the
    operators of the discrete dynamics the FOM snapshots obey, and a ROM integrated with
    Newmark reproduces them; finite-difference derivatives instead carry an O((dt omega)^2)
    bias for modes that the time step does not resolve.

    Args:
        states: (r, K) states at every step of a uniform grid ``times``.
        inputs: optional (m, K) inputs on the same grid.

    Returns:
        ``(Qbar, D1, D2, Ubar)``, each with K - 2 columns (k = 1 .. K-2); Ubar is None
        without inputs.
    """
    q, dt = _check_grid(states, times, 3)
    Qbar = (q[..., 2:] + 2 * q[..., 1:-1] + q[..., :-2]) / 4
    D2 = (q[..., 2:] - 2 * q[..., 1:-1] + q[..., :-2]) / dt**2
    D1 = (q[..., 2:] - q[..., :-2]) / (2 * dt)
    Ubar = None
    if inputs is not None:
        u = as_real_array(inputs, "inputs")
        u = u.reshape(1, -1) if u.ndim == 1 else u
        if u.ndim != 2 or u.shape[-1] != q.shape[-1]:
            raise InputError(f"inputs have shape {u.shape} but states have {q.shape[-1]} columns; "
                             f"pass (m, {q.shape[-1]}) inputs at the same times")
        check_finite(u, "inputs")
        Ubar = (u[:, 2:] + 2 * u[:, 1:-1] + u[:, :-2]) / 4
    return Qbar, D1, D2, Ubar
