"""Reduced Lagrangian models: simulate with the FOM's variational integrator, energy, outputs.

A ``LagrangianROM`` is the forced Euler-Lagrange equation of

    L_h(qh, qh_t) = 1/2 qh_t^T Mh qh_t - 1/2 qh^T Kh qh,   f_h = -Ch qh_t + Bh u,

i.e. Mh qh_tt + Ch qh_t + Kh qh = Bh u, with output y = Eh qh (Mh = I for L-OpInf).

Midpoint variational integrator in position-momentum form (p = Mh qh_t), step dt,
discrete Lagrangian L_d(q0, q1) = dt L_h((q0+q1)/2, (q1-q0)/dt), discrete forces
f_d^+- = dt/2 f_h(midpoint, slope, t+dt/2):

    p0 + D1 L_d(q0, q1) + f_d^-  = 0  ->  (Mh + dt/2 Ch + dt^2/4 Kh) q1
                                          = (Mh + dt/2 Ch - dt^2/4 Kh) q0 + dt p0 + dt^2/2 Bh u_mid
    p1 = D2 L_d(q0, q1) + f_d^+   =  Mh (q1-q0)/dt - dt/4 Kh (q0+q1) - Ch (q1-q0)/2 + dt/2 Bh u_mid

For a linear ROM one step is an affine map x1 = G x0 + H u_mid on x = [q; p], formed once.
Loading and simulating needs numpy only.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ._checks import check_finite


@dataclass(frozen=True)
class Trajectory:
    """A ROM trajectory: times (K,), Qh (r, K), Vh (r, K) velocities, Y (p, K) or None."""

    times: np.ndarray
    Qh: np.ndarray
    Vh: np.ndarray
    Y: np.ndarray | None = None
    seconds: float = 0.0


@dataclass(frozen=True)
class LagrangianROM:
    """Reduced model Mh qh_tt + Ch qh_t + Kh qh = Bh u,  y = Eh qh.

    Attributes:
        K: (r, r) stiffness.  M: (r, r) mass (identity when None).  C: (r, r) damping or None.
        B: (r, m) input operator or None.  E: (p, r) output operator or None.
        meta: free-form metadata (method, basis size, certificate, ...).
    """

    K: np.ndarray
    M: np.ndarray | None = None
    C: np.ndarray | None = None
    B: np.ndarray | None = None
    E: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        K = np.asarray(self.K, dtype=float)
        if K.ndim != 2 or K.shape[0] != K.shape[1]:
            raise ValueError(f"K must be square, got shape {K.shape}")
        check_finite(K, "K")
        object.__setattr__(self, "K", K)
        r = K.shape[0]
        for name, shape in (("M", (r, r)), ("C", (r, r))):
            value = getattr(self, name)
            if value is not None:
                value = np.asarray(value, dtype=float)
                if value.shape != shape:
                    raise ValueError(f"{name} must have shape {shape}, got {value.shape}")
                object.__setattr__(self, name, value)
        if self.B is not None:
            B = np.asarray(self.B, dtype=float)
            object.__setattr__(self, "B", B.reshape(r, -1))

    @property
    def r(self) -> int:
        return self.K.shape[0]

    @property
    def mass(self) -> np.ndarray:
        return np.eye(self.r) if self.M is None else self.M

    def energy(self, Qh: np.ndarray, Vh: np.ndarray) -> np.ndarray:
        """ROM energy 1/2 v^T Mh v + 1/2 q^T Kh q for (r, K) arrays (per column)."""
        M, K = self.mass, self.K
        return 0.5 * np.einsum("ik,ij,jk->k", Vh, M, Vh) + 0.5 * np.einsum("ik,ij,jk->k", Qh, K, Qh)

    def propagator(self, dt: float) -> tuple[np.ndarray, np.ndarray | None]:
        """(G, H): one midpoint step is [q1; p1] = G [q0; p0] + H u_mid."""
        M, K = self.mass, self.K
        C = np.zeros_like(K) if self.C is None else self.C
        A = M + 0.5 * dt * C + 0.25 * dt**2 * K
        rhs_q = np.hstack([M + 0.5 * dt * C - 0.25 * dt**2 * K, dt * np.eye(self.r)])
        Gq = np.linalg.solve(A, rhs_q)  # q1 = Gq [q0; p0] (+ input part)
        Pq1 = M / dt - 0.25 * dt * K - 0.5 * C  # p1 = Pq1 q1 - Pq0 q0 (+ input part)
        Pq0 = np.hstack([M / dt + 0.25 * dt * K - 0.5 * C, np.zeros_like(K)])
        G = np.vstack([Gq, Pq1 @ Gq - Pq0])
        H = None
        if self.B is not None:
            Hq = np.linalg.solve(A, 0.5 * dt**2 * self.B)
            H = np.vstack([Hq, Pq1 @ Hq + 0.5 * dt * self.B])
        return G, H

    def simulate(self, q0, v0, dt: float, n_steps: int, *, inputs=None, every: int = 1) -> Trajectory:
        """Integrate with the midpoint variational integrator.

        Args:
            q0, v0: (r,) initial reduced position and velocity.
            dt: time step; n_steps: number of steps; every: keep every ``every``-th step.
            inputs: for a forced ROM, a callable u(t) -> (m,) or an (m, n_steps) array of
                inputs at the step midpoints t_k + dt/2.

        Returns:
            :class:`Trajectory` sampled at t = 0, every*dt, ... (velocities v = Mh^{-1} p).
        """
        r = self.r
        q0, v0 = (np.asarray(a, dtype=float).reshape(-1) for a in (q0, v0))
        if q0.shape != (r,) or v0.shape != (r,):
            raise ValueError(f"q0 and v0 must have shape ({r},), got {q0.shape} and {v0.shape}")
        if n_steps < 0 or every < 1:
            raise ValueError("n_steps must be >= 0 and every >= 1")
        U = self._input_array(inputs, dt, n_steps)
        t0 = time.perf_counter()
        G, H = self.propagator(dt)
        x = np.concatenate([q0, self.mass @ v0])
        n_out = n_steps // every + 1
        X = np.empty((2 * r, n_out))
        X[:, 0] = x
        j = 1
        for k in range(n_steps):
            x = G @ x
            if H is not None:
                x += H @ U[:, k]
            if (k + 1) % every == 0:
                X[:, j] = x
                j += 1
        Qh, P = X[:r], X[r:]
        Vh = np.linalg.solve(self.mass, P)
        seconds = time.perf_counter() - t0
        Y = None if self.E is None else self.E @ Qh
        times = dt * every * np.arange(n_out)
        return Trajectory(times, Qh, Vh, Y, seconds)

    def _input_array(self, inputs, dt, n_steps):
        if self.B is None:
            if inputs is not None:
                raise ValueError("this ROM has no input operator B; do not pass inputs")
            return None
        m = self.B.shape[1]
        if inputs is None:
            raise ValueError(f"this ROM is forced (B has {m} columns): pass inputs")
        if callable(inputs):
            t_mid = dt * (np.arange(n_steps) + 0.5)
            U = np.column_stack([np.atleast_1d(inputs(t)) for t in t_mid]) if n_steps else np.zeros((m, 0))
        else:
            U = np.atleast_2d(np.asarray(inputs, dtype=float))
        if U.shape != (m, n_steps):
            raise ValueError(f"inputs must have shape ({m}, {n_steps}) (m, steps), got {U.shape}")
        check_finite(U, "inputs")
        return U
