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

Newmark (gamma = 1/2, beta = 1/4, average acceleration; variational too) on x = [q; v],
with a_k = Mh^{-1} (Bh u_k - Ch v_k - Kh q_k):

    q* = q0 + dt v0 + dt^2/4 a0,   v* = v0 + dt/2 a0
    (Mh + dt/2 Ch + dt^2/4 Kh) a1 = Bh u1 - Ch v* - Kh q*
    q1 = q* + dt^2/4 a1,   v1 = v* + dt/2 a1              ->  x1 = G x0 + H0 u0 + H1 u1.

Save/load to one ``.npz`` (operators, scheme, metadata, optionally basis rows); loading and
simulating needs numpy only.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

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
        scheme: ``"midpoint"`` (inputs at step midpoints) or ``"newmark"`` (inputs at steps);
            a ROM is integrated with the same scheme as its FOM.
        meta: free-form, JSON-serialisable metadata (method, basis size, certificate, ...).
    """

    K: np.ndarray
    M: np.ndarray | None = None
    C: np.ndarray | None = None
    B: np.ndarray | None = None
    E: np.ndarray | None = None
    meta: dict = field(default_factory=dict)
    scheme: str = "midpoint"

    def __post_init__(self):
        if self.scheme not in ("midpoint", "newmark"):
            raise ValueError(f"scheme must be 'midpoint' or 'newmark', got {self.scheme!r}")
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
            if B.ndim > 2 or B.shape[0] != r:
                raise ValueError(f"B must have {r} rows (r, m), got shape {B.shape}")
            object.__setattr__(self, "B", B.reshape(r, -1))
        if self.E is not None:
            E = np.atleast_2d(np.asarray(self.E, dtype=float))
            if E.shape[1] != r:
                raise ValueError(f"E must have {r} columns (p, r), got shape {E.shape}")
            object.__setattr__(self, "E", E)

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

    def newmark_propagator(self, dt: float):
        """(G, H0, H1): one Newmark step is [q1; v1] = G [q0; v0] + H0 u0 + H1 u1."""
        r, M, K = self.r, self.mass, self.K
        C = np.zeros_like(K) if self.C is None else self.C
        m = 0 if self.B is None else self.B.shape[1]
        B = np.zeros((r, m)) if self.B is None else self.B
        A = M + 0.5 * dt * C + 0.25 * dt**2 * K
        # columns: q0 (r), v0 (r), u0 (m), u1 (m)
        n_in = 2 * r + 2 * m
        Iq, Iv = np.eye(r, n_in), np.eye(r, n_in, r)
        U0 = np.zeros((m, n_in)); U0[:, 2 * r:2 * r + m] = np.eye(m)
        U1 = np.zeros((m, n_in)); U1[:, 2 * r + m:] = np.eye(m)
        a0 = np.linalg.solve(M, B @ U0 - C @ Iv - K @ Iq)
        qs, vs = Iq + dt * Iv + 0.25 * dt**2 * a0, Iv + 0.5 * dt * a0
        a1 = np.linalg.solve(A, B @ U1 - C @ vs - K @ qs)
        X1 = np.vstack([qs + 0.25 * dt**2 * a1, vs + 0.5 * dt * a1])
        return X1[:, :2 * r], X1[:, 2 * r:2 * r + m], X1[:, 2 * r + m:]

    def simulate(self, q0, v0, dt: float, n_steps: int, *, inputs=None, every: int = 1) -> Trajectory:
        """Integrate with the midpoint variational integrator.

        Args:
            q0, v0: (r,) initial reduced position and velocity.
            dt: time step; n_steps: number of steps; every: keep every ``every``-th step.
            inputs: for a forced ROM, a callable u(t) -> (m,), or an array of inputs: (m,
                n_steps) at the step midpoints t_k + dt/2 (midpoint) or (m, n_steps + 1) at
                t_0 .. t_n (Newmark).

        Returns:
            :class:`Trajectory` sampled at t = 0, every*dt, ... (velocities v = Mh^{-1} p).
        """
        r = self.r
        q0, v0 = (np.asarray(a, dtype=float).reshape(-1) for a in (q0, v0))
        if q0.shape != (r,) or v0.shape != (r,):
            raise ValueError(f"q0 and v0 must have shape ({r},), got {q0.shape} and {v0.shape}")
        if n_steps < 0 or every < 1:
            raise ValueError("n_steps must be >= 0 and every >= 1")
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be positive and finite, got {dt}")
        U = self._input_array(inputs, dt, n_steps)
        t0 = time.perf_counter()
        n_out = n_steps // every + 1
        X = np.empty((2 * r, n_out))
        if self.scheme == "midpoint":
            G, H = self.propagator(dt)
            x = np.concatenate([q0, self.mass @ v0])
            forcing = None if H is None else H @ U  # (2r, n_steps), one product up front
        else:
            G, H0, H1 = self.newmark_propagator(dt)
            x = np.concatenate([q0, v0])
            forcing = None if U is None else H0 @ U[:, :-1] + H1 @ U[:, 1:]
        X[:, 0] = x
        j = 1
        for k in range(n_steps):
            x = G @ x
            if forcing is not None:
                x += forcing[:, k]
            if (k + 1) % every == 0:
                X[:, j] = x
                j += 1
        Qh = X[:r]
        Vh = np.linalg.solve(self.mass, X[r:]) if self.scheme == "midpoint" else X[r:]
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
        n_u = n_steps if self.scheme == "midpoint" else n_steps + 1
        if callable(inputs):
            times = dt * (np.arange(n_steps) + 0.5) if self.scheme == "midpoint" else dt * np.arange(n_u)
            U = np.column_stack([np.atleast_1d(np.asarray(inputs(t), dtype=float)) for t in times]) \
                if n_u else np.zeros((m, 0))
        else:
            U = np.atleast_2d(np.asarray(inputs, dtype=float))
        if U.shape != (m, n_u):
            where = "step midpoints" if self.scheme == "midpoint" else "steps t_0 .. t_n"
            raise ValueError(f"inputs must have shape ({m}, {n_u}) (m inputs at the {where}), "
                             f"got {U.shape}")
        check_finite(U, "inputs")
        return U


def save_rom(path, rom: LagrangianROM, *, basis_rows: np.ndarray | None = None,
             rows: np.ndarray | None = None) -> Path:
    """Write a ROM to one ``.npz``: operators, scheme, metadata (JSON) and optionally rows of
    its basis (e.g. the dofs of an output point, for partial reconstruction).

    Args:
        basis_rows: (len(rows), r) rows of the basis V to ship with the ROM.
        rows: their indices in the full state.
    """
    path = Path(path)
    arrays = {"K": rom.K, "scheme": np.array(rom.scheme), "meta": np.array(json.dumps(rom.meta))}
    for name in ("M", "C", "B", "E"):
        if getattr(rom, name) is not None:
            arrays[name] = getattr(rom, name)
    if basis_rows is not None:
        basis_rows = np.asarray(basis_rows, dtype=float)
        if basis_rows.ndim != 2 or basis_rows.shape[1] != rom.r:
            raise ValueError(f"basis_rows must be (k, {rom.r}), got {basis_rows.shape}")
        arrays["basis_rows"] = basis_rows
        arrays["rows"] = np.arange(len(basis_rows)) if rows is None else np.asarray(rows)
    np.savez(path, **arrays)
    return path if path.suffix == ".npz" else path.with_suffix(path.suffix + ".npz")


def load_rom(path) -> tuple[LagrangianROM, dict]:
    """Read a ROM written by :func:`save_rom`; returns ``(rom, extras)`` where extras may hold
    ``basis_rows`` and ``rows``."""
    with np.load(path, allow_pickle=False) as data:
        kw = {name: data[name] for name in ("K", "M", "C", "B", "E") if name in data.files}
        rom = LagrangianROM(**kw, scheme=str(data["scheme"]), meta=json.loads(str(data["meta"])))
        extras = {k: data[k] for k in ("basis_rows", "rows") if k in data.files}
    return rom, extras


@dataclass(frozen=True)
class WaveROM:
    """Gray-box Lagrangian wave ROM  qh_tt = Kh qh - V^T (w * g(V qh))  (METHOD.md s. 4).

    It is the Euler-Lagrange equation of
        L_h = 1/2 |qh_t|^2 + 1/2 qh^T Kh qh - sum_i w_i U(V_i qh),
    so the midpoint variational integrator applies (one small Newton solve per step).

    Attributes:
        K: (r, r) symmetric Kh.
        V: (s, r) the basis rows the nonlinearity is sampled at (all n rows, or a
            hyper-reduced subset).
        g, dg, U: numpy functions of the pointwise nonlinearity, U' = g, g' = dg.
        weights: (s,) sampling weights w_i (ones without hyper-reduction).
        meta: free-form metadata.
    """

    K: np.ndarray
    V: np.ndarray
    g: object
    dg: object
    U: object
    weights: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    @property
    def r(self) -> int:
        return self.K.shape[0]

    def _w(self):
        return np.ones(self.V.shape[0]) if self.weights is None else self.weights

    def force(self, qh: np.ndarray) -> np.ndarray:
        """Reduced nonlinear force V^T (w * g(V qh)) for (r,) or (r, K)."""
        w = self._w()
        z = self.V @ qh
        return self.V.T @ ((w if z.ndim == 1 else w[:, None]) * self.g(z))

    def energy(self, Qh: np.ndarray, Vh: np.ndarray) -> np.ndarray:
        """ROM energy 1/2 |v|^2 - 1/2 q^T Kh q + sum_i w_i U(V_i q), per column."""
        pot = self._w() @ self.U(self.V @ Qh)
        return 0.5 * np.sum(Vh**2, axis=0) - 0.5 * np.einsum("ik,ij,jk->k", Qh, self.K, Qh) + pot

    def simulate(self, q0, v0, dt: float, n_steps: int, *, every: int = 1, tol: float = 1e-12,
                 max_newton: int = 20) -> Trajectory:
        """Midpoint variational integrator in position-momentum form (p = qh_t):

            R(q1) = p0 - (q1 - q0)/dt + dt/2 (Kh m - F(m)) = 0,  m = (q0 + q1)/2
            p1    = (q1 - q0)/dt + dt/2 (Kh m - F(m)),

        each step solved by Newton with J = -I/dt + dt/4 (Kh - V^T diag(w g'(V m)) V).
        Raises ``RuntimeError`` naming the step if Newton does not converge.
        """
        r, K, V, w = self.r, self.K, self.V, self._w()
        q = np.asarray(q0, dtype=float).copy()
        p = np.asarray(v0, dtype=float).copy()
        if q.shape != (r,) or p.shape != (r,):
            raise ValueError(f"q0 and v0 must have shape ({r},)")
        t0 = time.perf_counter()
        n_out = n_steps // every + 1
        Q, P = np.empty((r, n_out)), np.empty((r, n_out))
        Q[:, 0], P[:, 0] = q, p
        eye = np.eye(r)
        j = 1
        for k in range(n_steps):
            q1 = q + dt * p  # explicit predictor
            for it in range(max_newton):
                m = 0.5 * (q + q1)
                z = V @ m
                F = V.T @ (w * self.g(z))
                R = p - (q1 - q) / dt + 0.5 * dt * (K @ m - F)
                J = -eye / dt + 0.25 * dt * (K - (V.T * (w * self.dg(z))) @ V)
                dq = np.linalg.solve(J, -R)
                q1 = q1 + dq
                if np.linalg.norm(dq) <= tol * max(np.linalg.norm(q1), 1.0):
                    break
            else:
                raise RuntimeError(f"reduced Newton did not converge at step {k + 1} "
                                   f"(t = {(k + 1) * dt:.6g}): |R| = {np.linalg.norm(R):.3e}")
            m = 0.5 * (q + q1)
            p = (q1 - q) / dt + 0.5 * dt * (K @ m - V.T @ (w * self.g(V @ m)))
            q = q1
            if (k + 1) % every == 0:
                Q[:, j], P[:, j] = q, p
                j += 1
        return Trajectory(dt * every * np.arange(n_out), Q, P, None, time.perf_counter() - t0)
