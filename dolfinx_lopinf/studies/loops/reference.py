"""Independent reference for the user-loop study (numpy only; shares no code with the package's
ROM, data-relation or fit modules - it is the cross-check they are measured against).

Galerkin projection. For FE operators M, C, K (n, n) and an input matrix B (n, m), all in
snapshot row order, and a basis W (n, r):

    Mr = W^T M W,   Cr = W^T C W,   Kr = W^T K W,   Br = W^T B.

The generalised-alpha family (Chung & Hulbert 1993). State (u, v, a) at t_n, step dt:

    u_{n+1} = u_n + dt v_n + dt^2 ((1/2 - beta) a_n + beta a_{n+1})
    v_{n+1} = v_n + dt ((1 - gamma) a_n + gamma a_{n+1})
    M a_{n+1-am} + C v_{n+1-af} + K u_{n+1-af} = B f(t_{n+1-af}),
    x_{n+1-alpha} = (1 - alpha) x_{n+1} + alpha x_n,   t_{n+1-af} = t_{n+1} - af dt.

Members: Newmark (am = af = 0; average acceleration beta = 1/4, gamma = 1/2), HHT-alpha
(am = 0, af = alpha), generalised-alpha (am, af), central differences (am = af = 0,
beta = 0, gamma = 1/2: with C = 0 this is u_{n+1} - 2 u_n + u_{n-1} = dt^2 M^{-1}(B f_n - K u_n)
exactly). Each step solves for a_{n+1}:

    S a_{n+1} = B f - am M a_n - C (v_n + (1 - af) dt (1 - gamma) a_n)
                - K (u_n + (1 - af)(dt v_n + dt^2 (1/2 - beta) a_n)),
    S = (1 - am) M + (1 - af) gamma dt C + (1 - af) beta dt^2 K,

with S^{-1} formed once and one step of iterative refinement per solve (so the r = n
verification is limited by rounding, not by the conditioning of S). The initial acceleration
is the one given, else the consistent M a_0 = B f(t_0) - C v_0 - K u_0.

Errors: the projection floor ||Q - W W^T Q||_F / ||Q||_F (W orthonormal, e.g. the POD of the
training states) and the relative Frobenius error ||X - Y||_F / ||X||_F.
"""

from __future__ import annotations

import numpy as np

__all__ = ["galerkin", "integrate", "load_times", "pod_basis", "projection_floor", "rel_error"]


def galerkin(ops: dict, W: np.ndarray) -> dict:
    """Reduced operators W^T A W of ``ops`` (keys M, K, optional C, B; dense, row order of W).

    Returns a dict with M, C, K (r, r; C zero when absent) and B (r, m) or None."""
    W = np.asarray(W, dtype=float)
    r = W.shape[1]
    out = {}
    for key in ("M", "C", "K"):
        A = ops.get(key)
        out[key] = np.zeros((r, r)) if A is None else W.T @ (np.asarray(A) @ W)
    B = ops.get("B")
    out["B"] = None if B is None else W.T @ np.asarray(B).reshape(W.shape[0], -1)
    return out


def load_times(scheme: dict, dt: float, n_steps: int, t0: float = 0.0) -> np.ndarray:
    """The times t_{n+1} - alpha_f dt (n = 0 .. n_steps - 1) at which the scheme takes its load."""
    af = float(scheme.get("alpha_f", 0.0))
    return t0 + dt * (np.arange(1, n_steps + 1) - af)


def _inputs(inputs, t, m):
    if inputs is None:
        return np.zeros(m)
    return np.atleast_1d(np.asarray(inputs(t), dtype=float)).ravel()


def integrate(ops: dict, scheme: dict, dt: float, n_steps: int, *, q0=None, v0=None, a0=None,
              inputs=None, every: int = 1, t0: float = 0.0, cond: bool = False) -> dict:
    """Integrate M a + C v + K u = B f(t) with a generalised-alpha family member.

    Args:
        ops: dict with M, K (r, r), optional C (r, r) and B (r, m) (e.g. from :func:`galerkin`).
        scheme: dict with alpha_m, alpha_f, beta, gamma (missing alphas are 0).
        dt, n_steps: the scheme's own step and number of steps.
        q0, v0, a0: initial state (default rest; a0 default: consistent with f(t0)).
        inputs: callable t -> (m,) load values, evaluated at the scheme's times
            (:func:`load_times`; t0 for the consistent a0); None: unforced.
        every: keep every ``every``-th step (a loop that records every k-th step).
        cond: also return S_cond, the condition number of the step matrix S (an SVD).

    Returns:
        dict with times (K,), Q, V, A (r, K) sampled at t0, every dt, ... (and S_cond).
    """
    M, K = np.asarray(ops["M"], float), np.asarray(ops["K"], float)
    r = M.shape[0]
    C = np.zeros((r, r)) if ops.get("C") is None else np.asarray(ops["C"], float)
    B = None if ops.get("B") is None else np.asarray(ops["B"], float).reshape(r, -1)
    am, af = float(scheme.get("alpha_m", 0.0)), float(scheme.get("alpha_f", 0.0))
    beta, gamma = float(scheme["beta"]), float(scheme["gamma"])
    m = 0 if B is None else B.shape[1]

    def force(t):
        return np.zeros(r) if B is None or inputs is None else B @ _inputs(inputs, t, m)

    u = np.zeros(r) if q0 is None else np.array(q0, dtype=float)
    v = np.zeros(r) if v0 is None else np.array(v0, dtype=float)
    a = np.linalg.solve(M, force(t0) - C @ v - K @ u) if a0 is None else np.array(a0, dtype=float)
    S = (1 - am) * M + (1 - af) * gamma * dt * C + (1 - af) * beta * dt**2 * K
    S_inv = np.linalg.inv(S)

    def solve(b):
        x = S_inv @ b
        return x + S_inv @ (b - S @ x)  # one step of iterative refinement

    n_out = n_steps // every + 1
    Q, Vv, A = (np.empty((r, n_out)) for _ in range(3))
    Q[:, 0], Vv[:, 0], A[:, 0] = u, v, a
    times = t0 + dt * every * np.arange(n_out)
    tf = load_times(scheme, dt, n_steps, t0)
    for n in range(n_steps):
        u_pred = u + dt * v + dt**2 * (0.5 - beta) * a
        v_pred = v + dt * (1 - gamma) * a
        rhs = (force(tf[n]) - am * (M @ a) - C @ ((1 - af) * v_pred + af * v)
               - K @ ((1 - af) * u_pred + af * u))
        a = solve(rhs)
        u = u_pred + beta * dt**2 * a
        v = v_pred + gamma * dt * a
        if (n + 1) % every == 0:
            k = (n + 1) // every
            Q[:, k], Vv[:, k], A[:, k] = u, v, a
    out = {"times": times, "Q": Q, "V": Vv, "A": A}
    if cond:
        out["S_cond"] = float(np.linalg.cond(S))
    return out


def pod_basis(Q: np.ndarray, r: int) -> np.ndarray:
    """The r leading left singular vectors of Q (n, K): an orthonormal (n, r) POD basis."""
    U, _, _ = np.linalg.svd(np.asarray(Q, dtype=float), full_matrices=False)
    return U[:, :r]


def projection_floor(Q: np.ndarray, W: np.ndarray) -> float:
    """||Q - W W^T Q||_F / ||Q||_F for an orthonormal W (the best any ROM in span W can do)."""
    Q = np.asarray(Q, dtype=float)
    return float(np.linalg.norm(Q - W @ (W.T @ Q)) / np.linalg.norm(Q))


def rel_error(X: np.ndarray, Y: np.ndarray) -> float:
    """||X - Y||_F / ||X||_F (inf when Y is not finite)."""
    X, Y = np.asarray(X, dtype=float), np.asarray(Y, dtype=float)
    if X.shape != Y.shape:
        raise ValueError(f"shapes differ: {X.shape} vs {Y.shape}")
    if not np.all(np.isfinite(Y)):
        return float("inf")
    return float(np.linalg.norm(X - Y) / np.linalg.norm(X))
