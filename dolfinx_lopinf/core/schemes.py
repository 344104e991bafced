"""Time-integration schemes of M a + C v + K u = f: their data relations and their ROM step.

A dolfinx time loop's snapshots obey the *discrete* equations of its integrator exactly.
Fitting those equations (instead of finite-difference derivatives) identifies the operators
of the discrete dynamics, and a ROM stepped with the same scheme reproduces the loop's
numerical dissipation and period error. Every scheme here gives

* :meth:`Scheme.relation`: arrays (Qk, Qc, Qm, Uf) with  M Qm + C Qc + K Qk = B Uf  column by
  column - linear in the operators, so every scheme is the same convex L-OpInf fit;
* :meth:`Scheme.step`: the ROM's one-step map  x_{n+1} = G x_n + H F_n,  F_n = f(t_n + tau dt).

**Generalised-alpha** (Chung & Hulbert 1993), on the state (u, v, a)::

    u_{n+1} = u_n + dt v_n + dt^2 ((1/2 - beta) a_n + beta a_{n+1})
    v_{n+1} = v_n + dt ((1 - gamma) a_n + gamma a_{n+1})
    M ((1 - am) a_{n+1} + am a_n) + C ((1 - af) v_{n+1} + af v_n)
        + K ((1 - af) u_{n+1} + af u_n) = f(t_{n+1-af})                            (*)

alpha_m = alpha_f = 0 is Newmark(beta, gamma) (average acceleration 1/4, 1/2; linear
acceleration 1/6, 1/2; Fox-Goodwin 1/12, 1/2; explicit central differences 0, 1/2);
alpha_m = 0 is HHT-alpha. With E the shift (E u_n = u_{n+1}), the updates give
(E - 1)^2 u = dt^2 P(E) a and P(E) v = ((1 - gamma) + gamma E)(E - 1) u / dt, with
P(E) = (1/2 + beta - gamma) + (1/2 - 2 beta + gamma) E + beta E^2. Applying P(E) to (*)
eliminates v and a: a four-point relation in u alone,

    [M pm(E) + C pc(E) + K pk(E)] u_k = B P(E) F_k,   F_k = f(t_{k+1-af}),
    pm = (am + (1 - am) E)(E - 1)^2 / dt^2,
    pc = (af + (1 - af) E)((1 - gamma) + gamma E)(E - 1) / dt,
    pk = (af + (1 - af) E) P(E),

which holds exactly (no constant of integration: the updates hold step by step) for
k = 0 .. N - 3 whatever a_0 was. With v and a recorded, (*) itself is the relation
(:meth:`GeneralizedAlpha.state_relation`), and beta, gamma follow from the updates alone.

**Midpoint** variational integrator (linear Lagrangian, discrete forces at the step
midpoints): M D2 + C D1 + K Qbar = B (f_{k-1/2} + f_{k+1/2}) / 2 with D2, D1, Qbar the
three-point second difference, central difference and 1/4, 1/2, 1/4 average. Its ROM steps
(q, p = M v) as :meth:`dolfinx_lopinf.core.rom.LagrangianROM.propagator` documents.

**FiniteDifferences** ("continuous"): 8th-order central differences of the samples (any
integrator, an O((dt omega)^2) bias for modes the step does not resolve); its ROM steps
average-acceleration Newmark at the data's dt.

Inputs. A scheme evaluates the load at its own times t_n + tau dt (tau = 1 - alpha_f, 1/2
for the midpoint rule). Recorded inputs carry the times at which they act; they are
interpolated linearly to the scheme's times (exact where the two coincide - record the load
your loop applied, at the time it applied it, and a jump costs nothing).
"""

from __future__ import annotations

import functools
import re

import numpy as np

from ._checks import as_real_array, check_finite, check_real
from ..errors import InputError

_E_MINUS_1 = np.array([-1.0, 1.0])  # E - 1, ascending powers


def _poly(*factors) -> np.ndarray:
    out = np.array([1.0])
    for f in factors:
        out = np.convolve(out, np.asarray(f, dtype=float))
    return out


class Scheme:
    """Base of the schemes: a data relation, a ROM step, a name that round-trips a file."""

    #: the load is evaluated at t_n + tau dt in step n -> n + 1
    tau: float = 1.0
    #: the ROM's state per reduced coordinate (u, v, a: 3; q, p: 2)
    state_blocks: int = 3

    @property
    def spec(self) -> str:
        """A text that :func:`from_spec` turns back into this scheme (stored in files)."""
        raise NotImplementedError

    @property
    def params(self) -> dict:
        return {}

    def __repr__(self) -> str:
        return self.spec

    def __eq__(self, other) -> bool:
        if isinstance(other, str):  # rom.scheme == "newmark"
            try:
                other = from_spec(other)
            except InputError:
                return False
        return isinstance(other, Scheme) and self.spec == other.spec

    def __hash__(self) -> int:
        return hash(self.spec)

    # -- data -----------------------------------------------------------------------------
    def coefficients(self, dt: float):
        """(cm, cc, ck, cu, tau_rel): the relation's weights on u_k .. u_{k+s-1} and on the
        loads f(t_k + (j + tau_rel) dt), j = 0 .. len(cu) - 1."""
        raise NotImplementedError

    def relation(self, Q, times, U=None, input_times=None, *, missing="drop"):
        """The scheme's displacement-only relation on samples Q (r, K) at uniform ``times``:
        ``(Qk, Qc, Qm, Uf)`` with M Qm + C Qc + K Qk = B Uf column by column (Uf None
        without inputs). U (m, K_u) are inputs acting at ``input_times`` (default: times);
        columns needing a load outside the recorded times are dropped (``missing="zero"``:
        set to zero, which keeps the number of columns)."""
        Q = as_real_array(Q, "states")
        times = as_real_array(times, "times")
        dt = float(np.mean(np.diff(times)))
        cm, cc, ck, cu, tau_rel = self.coefficients(dt)
        s = len(cm)
        K = Q.shape[-1]
        if K < s + 1:
            raise InputError(f"the {self.spec} relation needs at least {s + 1} samples, got {K}")
        cols = K - s + 1

        def combine(c, A, n):
            out = np.zeros(A.shape[:-1] + (n,))
            for j, w in enumerate(c):
                if w != 0.0:
                    out += w * A[..., j:j + n]
            return out

        Qm, Qc, Qk = (combine(c, Q, cols) for c in (cm, cc, ck))
        Uf = None
        if U is not None:
            t_load = times[0] + (np.arange(cols + len(cu) - 1) + tau_rel) * dt
            F = sample_inputs(U, times if input_times is None else input_times, t_load,
                              outside="nan")
            Uf = combine(cu, F, cols)
            return _with_loads(Qk, Qc, Qm, Uf, missing)
        return Qk, Qc, Qm, Uf

    def recurrence(self, M, C, K, B, dt):
        """The relation solved for its newest sample, as a companion map: with
        z_k = [u_k; ..; u_{k+s-2}], z_{k+1} = Gc z_k + Hc w_k, w_k = sum_j cu_j f(t_k + (j +
        tau_rel) dt). Returns (Gc, Hc, cu, tau_rel) - the multistep form of the scheme, which
        predicts from recorded samples alone (no velocities or accelerations needed)."""
        cm, cc, ck, cu, tau_rel = self.coefficients(dt)
        s, r = len(cm), K.shape[0]
        C = np.zeros_like(K) if C is None else C
        A = [cm[j] * M + cc[j] * C + ck[j] * K for j in range(s)]
        last = np.linalg.solve(A[-1], np.hstack([-A[j] for j in range(s - 1)]))
        Gc = np.zeros(((s - 1) * r, (s - 1) * r))
        Gc[:-r, r:] = np.eye((s - 2) * r)
        Gc[-r:] = last
        Hc = None
        if B is not None:
            Hc = np.zeros(((s - 1) * r, B.shape[1]))
            Hc[-r:] = np.linalg.solve(A[-1], B)
        return Gc, Hc, cu, tau_rel

    # -- ROM --------------------------------------------------------------------------------
    def step(self, M, C, K, B, dt):
        """(G, H): x_{n+1} = G x_n + H F_n for the ROM M a + C v + K u = B f."""
        raise NotImplementedError

    def initial_state(self, q0, v0, f0, M, C, K, B):
        raise NotImplementedError

    def unpack(self, X, M, C, K, B):
        """(Qh, Vh, Ah) from the stored states X (blocks x r, K); Ah None if not defined."""
        raise NotImplementedError


class GeneralizedAlpha(Scheme):
    """Generalised-alpha (module docstring), by its four parameters or by rho_inf.

    ``GeneralizedAlpha(rho_inf=0.8)`` is Chung-Hulbert's optimal choice
    alpha_m = (2 rho - 1) / (rho + 1), alpha_f = rho / (rho + 1); given alpha_m and alpha_f,
    gamma and beta default to the second-order accurate, optimally dissipative
    gamma = 1/2 + alpha_f - alpha_m, beta = (gamma + 1/2)^2 / 4 (the COMET elastodynamics
    tutorial uses alpha_m = 0.2, alpha_f = 0.4 so). Stable range (refused outside):
    gamma >= 1/2, beta >= 0, -1 <= alpha_m <= 1/2, 0 <= alpha_f <= 1/2, 0 <= rho_inf <= 1.
    """

    family = "generalized_alpha"

    def __init__(self, alpha_m=None, alpha_f=None, beta=None, gamma=None, *, rho_inf=None):
        if rho_inf is not None:
            if alpha_m is not None or alpha_f is not None:
                raise InputError("give rho_inf or (alpha_m, alpha_f), not both")
            rho = check_real(rho_inf, "rho_inf")
            if not 0.0 <= rho <= 1.0:
                raise InputError(f"rho_inf must lie in [0, 1] (the spectral radius at infinite "
                                 f"frequency), got {rho_inf!r}")
            alpha_m, alpha_f = (2 * rho - 1) / (rho + 1), rho / (rho + 1)
        if alpha_m is None or alpha_f is None:
            raise InputError("GeneralizedAlpha needs rho_inf, or alpha_m and alpha_f")
        am, af = check_real(alpha_m, "alpha_m"), check_real(alpha_f, "alpha_f")
        g = 0.5 + af - am if gamma is None else check_real(gamma, "gamma")
        b = 0.25 * (g + 0.5) ** 2 if beta is None else check_real(beta, "beta")
        problems = []
        if g < 0.5 - 1e-12:
            problems.append(f"gamma = {g:.6g} < 1/2 (amplifies: negative numerical damping)")
        if b < 0:
            problems.append(f"beta = {b:.6g} < 0")
        if not -1.0 - 1e-12 <= am <= 0.5 + 1e-12:
            problems.append(f"alpha_m = {am:.6g} outside [-1, 1/2]")
        if not -1e-12 <= af <= 0.5 + 1e-12:
            problems.append(f"alpha_f = {af:.6g} outside [0, 1/2]")
        if problems:
            raise InputError(f"{type(self).__name__}: parameters outside the stable range: "
                             + "; ".join(problems))
        self.alpha_m, self.alpha_f, self.beta, self.gamma = am, af, b, g

    @property
    def tau(self) -> float:
        return 1.0 - self.alpha_f

    @property
    def params(self) -> dict:
        return {"alpha_m": self.alpha_m, "alpha_f": self.alpha_f, "beta": self.beta,
                "gamma": self.gamma}

    @property
    def spec(self) -> str:
        p = self.params
        return (f"generalized_alpha(alpha_m={p['alpha_m']!r}, alpha_f={p['alpha_f']!r}, "
                f"beta={p['beta']!r}, gamma={p['gamma']!r})")

    @property
    def P(self) -> np.ndarray:
        b, g = self.beta, self.gamma
        return np.array([0.5 + b - g, 0.5 - 2 * b + g, b])

    def coefficients(self, dt):
        am, af, g = self.alpha_m, self.alpha_f, self.gamma
        lead_m, lead_f = [am, 1 - am], [af, 1 - af]
        cm = _poly(lead_m, _E_MINUS_1, _E_MINUS_1) / dt**2
        cc = _poly(lead_f, [1 - g, g], _E_MINUS_1) / dt
        ck = _poly(lead_f, self.P)
        return cm, cc, ck, self.P.copy(), 1.0 - af

    def state_relation(self, Q, V, A, times, U=None, input_times=None, *, missing="drop"):
        """(*) on recorded (u, v, a) (r, K) each: (Qk, Qc, Qm, Uf) with K - 1 columns."""
        times = as_real_array(times, "times")
        dt = float(np.mean(np.diff(times)))
        am, af = self.alpha_m, self.alpha_f
        Qm = (1 - am) * A[:, 1:] + am * A[:, :-1]
        Qc = (1 - af) * V[:, 1:] + af * V[:, :-1]
        Qk = (1 - af) * Q[:, 1:] + af * Q[:, :-1]
        if U is None:
            return Qk, Qc, Qm, None
        t_load = times[:-1] + self.tau * dt
        Uf = sample_inputs(U, times if input_times is None else input_times, t_load, outside="nan")
        return _with_loads(Qk, Qc, Qm, Uf, missing)

    def step(self, M, C, K, B, dt):
        """(G, H) on x = [u; v; a] (3r): solve (*) for a_{n+1}, then the updates."""
        r = K.shape[0]
        am, af, b, g = self.alpha_m, self.alpha_f, self.beta, self.gamma
        C = np.zeros_like(K) if C is None else C
        I = np.eye(r)
        A = (1 - am) * M + (1 - af) * g * dt * C + (1 - af) * b * dt**2 * K
        R = np.hstack([-K, -C - (1 - af) * dt * K,
                       -am * M - (1 - af) * (1 - g) * dt * C - (1 - af) * (0.5 - b) * dt**2 * K])
        Z = np.zeros((r, r))
        base = np.block([[I, dt * I, (0.5 - b) * dt**2 * I], [Z, I, (1 - g) * dt * I],
                         [Z, Z, Z]])
        lift = np.vstack([b * dt**2 * I, g * dt * I, I])
        G = base + lift @ np.linalg.solve(A, R)
        H = None if B is None else lift @ np.linalg.solve(A, B)
        return G, H

    def initial_state(self, q0, v0, f0, M, C, K, B):
        """[q0; v0; a0] with the consistent a0 = M^-1 (B f(t_0) - C v0 - K q0)."""
        rhs = -K @ q0 - (0 if C is None else C @ v0)
        if B is not None and f0 is not None:
            rhs = rhs + B @ f0
        return np.concatenate([q0, v0, np.linalg.solve(M, rhs)])

    def unpack(self, X, M, C, K, B):
        r = K.shape[0]
        return X[:r], X[r:2 * r], X[2 * r:]


class Newmark(GeneralizedAlpha):
    """Newmark(beta, gamma): alpha_m = alpha_f = 0; defaults to average acceleration
    (beta = 1/4, gamma = 1/2: unconditionally stable, energy conserving, no dissipation)."""

    family = "newmark"

    def __init__(self, beta=0.25, gamma=0.5):
        super().__init__(0.0, 0.0, beta, gamma)

    @property
    def spec(self) -> str:
        return f"newmark(beta={self.beta!r}, gamma={self.gamma!r})"

    @property
    def params(self) -> dict:
        return {"beta": self.beta, "gamma": self.gamma}

    def coefficients(self, dt):
        # the generalised-alpha weights have the common factor E here: drop it (three points,
        # the loads at t_{k+1} .. t_{k+3} on u_{k+1} .. u_{k+3} - relabelled from k)
        cm, cc, ck, cu, _ = super().coefficients(dt)
        return cm[1:], cc[1:], ck[1:], cu, 0.0

    def relation(self, Q, times, U=None, input_times=None, *, missing="drop"):
        # the first three-point relation needs the balance at t_0 (a_0 as the loop set it);
        # drop it, so a loop that started from an inconsistent a_0 (a = 0 under load) fits
        Qk, Qc, Qm, Uf = super().relation(Q, times, U, input_times, missing=missing)
        return Qk[:, 1:], Qc[:, 1:], Qm[:, 1:], None if Uf is None else Uf[:, 1:]


class CentralDifference(Newmark):
    """Explicit central differences: Newmark(beta = 0, gamma = 1/2) (stable for dt omega < 2)."""

    family = "central_difference"

    def __init__(self):
        super().__init__(0.0, 0.5)

    @property
    def spec(self) -> str:
        return "central_difference()"


class HHT(GeneralizedAlpha):
    """HHT-alpha (Hilber-Hughes-Taylor): alpha_m = 0, alpha_f = alpha in [0, 1/3],
    gamma = 1/2 + alpha, beta = (1 + alpha)^2 / 4. ``alpha`` is the dissipative parameter
    as a positive number (Hilber's paper writes it as -alpha)."""

    family = "hht"

    def __init__(self, alpha=0.1):
        a = check_real(alpha, "alpha")
        if not 0.0 <= a <= 1.0 / 3.0 + 1e-12:
            hint = (f" (Hilber et al. write alpha = {a:g}; pass alpha={-a:g})" if -1 / 3 <= a < 0
                    else "")
            raise InputError(f"HHT alpha must lie in [0, 1/3], got {alpha!r}{hint}")
        super().__init__(0.0, a, (1 + a) ** 2 / 4, 0.5 + a)
        self.alpha = a

    @property
    def spec(self) -> str:
        return f"hht(alpha={self.alpha!r})"

    @property
    def params(self) -> dict:
        return {"alpha": self.alpha}


class Midpoint(Scheme):
    """The midpoint variational integrator (loads at the step midpoints); ROM on (q, p)."""

    family = "midpoint"
    tau = 0.5
    state_blocks = 2

    @property
    def spec(self) -> str:
        return "midpoint()"

    def coefficients(self, dt):
        return (np.array([1.0, -2.0, 1.0]) / dt**2, np.array([-0.5, 0.0, 0.5]) / dt,
                np.array([0.25, 0.5, 0.25]), np.array([0.5, 0.5]), 0.5)

    def step(self, M, C, K, B, dt):
        """(G, H) on x = [q; p], p = M v: with the discrete Lagrangian
        L_d = dt L((q0 + q1)/2, (q1 - q0)/dt) and forces f_d = dt/2 f at the midpoint,
        (M + dt/2 C + dt^2/4 K) q1 = (M + dt/2 C - dt^2/4 K) q0 + dt p0 + dt^2/2 B f_mid,
        p1 = (M/dt - dt/4 K - C/2) q1 - (M/dt + dt/4 K - C/2) q0 + dt/2 B f_mid."""
        r = K.shape[0]
        C = np.zeros_like(K) if C is None else C
        A = M + 0.5 * dt * C + 0.25 * dt**2 * K
        Gq = np.linalg.solve(A, np.hstack([M + 0.5 * dt * C - 0.25 * dt**2 * K, dt * np.eye(r)]))
        Pq1 = M / dt - 0.25 * dt * K - 0.5 * C
        Pq0 = np.hstack([M / dt + 0.25 * dt * K - 0.5 * C, np.zeros_like(K)])
        G = np.vstack([Gq, Pq1 @ Gq - Pq0])
        H = None
        if B is not None:
            Hq = np.linalg.solve(A, 0.5 * dt**2 * B)
            H = np.vstack([Hq, Pq1 @ Hq + 0.5 * dt * B])
        return G, H

    def initial_state(self, q0, v0, f0, M, C, K, B):
        return np.concatenate([q0, M @ v0])

    def unpack(self, X, M, C, K, B):
        r = K.shape[0]
        return X[:r], np.linalg.solve(M, X[r:]), None


class FiniteDifferences(Scheme):
    """8th-order central differences of the samples ("continuous"); the ROM steps
    average-acceleration Newmark at the data's dt."""

    family = "continuous"
    tau = 1.0
    state_blocks = 3

    @property
    def spec(self) -> str:
        return "continuous()"

    def relation(self, Q, times, U=None, input_times=None, *, missing="drop"):
        from . import ddt

        q, dq, ddq = ddt.derivatives(Q, times)
        h = ddt.HALF_WIDTH
        if U is None:
            return q, dq, ddq, None
        times = as_real_array(times, "times")
        Uf = sample_inputs(U, times if input_times is None else input_times, times[h:-h],
                           outside="nan")
        return _with_loads(q, dq, ddq, Uf, missing)

    def recurrence(self, M, C, K, B, dt):
        return Newmark().recurrence(M, C, K, B, dt)

    def step(self, M, C, K, B, dt):
        return Newmark().step(M, C, K, B, dt)

    def initial_state(self, q0, v0, f0, M, C, K, B):
        return Newmark().initial_state(q0, v0, f0, M, C, K, B)

    def unpack(self, X, M, C, K, B):
        return Newmark().unpack(X, M, C, K, B)


def rom_scheme(scheme: Scheme) -> Scheme:
    """The scheme a ROM fitted with ``scheme``'s relation is stepped with."""
    return Newmark() if isinstance(scheme, FiniteDifferences) else scheme


#: names accepted wherever a scheme is asked for (``lo.fit(scheme=...)``, the recorder)
ALIASES = {
    "newmark": Newmark, "average_acceleration": Newmark,
    "linear_acceleration": lambda: Newmark(1 / 6, 0.5), "fox_goodwin": lambda: Newmark(1 / 12, 0.5),
    "central_difference": CentralDifference, "midpoint": Midpoint,
    "continuous": FiniteDifferences, "hht": HHT,
}

_SPEC = re.compile(r"^\s*([a-z_]+)\s*\((.*)\)\s*$")


def from_spec(text) -> Scheme:
    """A scheme from its :attr:`Scheme.spec` text or an alias (``"newmark"``, ...)."""
    if isinstance(text, Scheme):
        return text
    if not isinstance(text, str):
        raise InputError(f"a scheme must be a dolfinx_lopinf.schemes object or one of "
                         f"{sorted(ALIASES)}, got {text!r}")
    name = text.strip().lower()
    head, paren, tail = name.partition("(")
    name = head.strip().replace("-", "_").replace(" ", "_") + paren + tail
    if name in ALIASES:
        return ALIASES[name]()
    match = _SPEC.match(name)
    builders = {"newmark": Newmark, "generalized_alpha": GeneralizedAlpha, "hht": HHT,
                "central_difference": CentralDifference, "midpoint": Midpoint,
                "continuous": FiniteDifferences}
    if match and match.group(1) in builders:
        kwargs = {}
        for item in filter(None, (x.strip() for x in match.group(2).split(","))):
            key, _, value = item.partition("=")
            try:
                kwargs[key.strip()] = float(value)
            except ValueError:
                raise InputError(f"cannot read the scheme {text!r}: {item!r}") from None
        try:
            return builders[match.group(1)](**kwargs)
        except TypeError as exc:
            raise InputError(f"cannot read the scheme {text!r}: {exc}") from None
    raise InputError(f"unknown scheme {text!r}: pass one of {sorted(ALIASES)} or an object of "
                     "dolfinx_lopinf.schemes (e.g. schemes.GeneralizedAlpha(rho_inf=0.8))")


def _with_loads(Qk, Qc, Qm, Uf, missing="drop"):
    """The relation's columns whose loads were recorded (NaN: a load time outside them),
    the others dropped or (``missing="zero"``) zeroed."""
    keep = np.all(np.isfinite(Uf), axis=0)
    if not keep.any():
        raise InputError("the recorded inputs do not cover the times at which the scheme needs "
                         "its loads; record the inputs at every step")
    if keep.all():
        return Qk, Qc, Qm, Uf
    if missing == "zero":
        out = [A.copy() for A in (Qk, Qc, Qm, Uf)]
        for A in out:
            A[:, ~keep] = 0.0
        return tuple(out)
    return Qk[:, keep], Qc[:, keep], Qm[:, keep], Uf[:, keep]


def kinks(U) -> np.ndarray:
    """(K_u,) True at the samples where the recorded load bends or jumps: its second
    difference exceeds KINK_FACTOR times the median one (and 1e-9 of max |U|). Between
    such samples the load is not linear, so a value interpolated there is not the load the
    loop applied (a ramp's corner, a release)."""
    U = np.asarray(U, dtype=float)
    U = U.reshape(1, -1) if U.ndim == 1 else U
    flag = np.zeros(U.shape[1], dtype=bool)
    if U.shape[1] < 3:
        return flag
    d2 = np.abs(U[:, 2:] - 2 * U[:, 1:-1] + U[:, :-2])
    floor = KINK_FACTOR * np.median(d2, axis=1, keepdims=True) + 1e-9 * np.abs(U).max(axis=1,
                                                                                  keepdims=True)
    flag[1:-1] = np.any(d2 > floor, axis=0)
    return flag


@functools.lru_cache(maxsize=16)
def _kinks_of(data: bytes, shape) -> np.ndarray:
    """:func:`kinks` of the float64 array with these bytes and shape (read-only, cached)."""
    out = kinks(np.frombuffer(data, dtype=float).reshape(shape))
    out.setflags(write=False)
    return out


#: a second difference this many times the median one marks a bend or jump of the load
KINK_FACTOR = 50.0


def sample_inputs(U, input_times, at, *, outside: str = "raise", bends: str = "nan") -> np.ndarray:
    """Inputs (m, len(at)) at times ``at``, linearly interpolated from U (m, K_u) acting at
    ``input_times`` (K_u,); exact where the times coincide (to 1e-9 of the spacing). Times
    outside the recorded ones raise an InputError, or (``outside="nan"``) give NaN - as do,
    with ``outside="nan"`` and ``bends="nan"``, values interpolated next to a bend or jump of
    the load (:func:`kinks`), which the samples do not determine (``bends="keep"``: the
    interpolated value, for a prediction that must go on)."""
    U = as_real_array(U, "inputs")
    U = U.reshape(1, -1) if U.ndim == 1 else U
    ti = as_real_array(input_times, "input_times")
    if U.ndim != 2 or U.shape[1] != len(ti):
        raise InputError(f"inputs have shape {U.shape} but there are {len(ti)} input times; "
                         "pass one time per input column")
    check_finite(U, "inputs")
    at = np.asarray(at, dtype=float)
    if len(ti) == 1:
        return np.repeat(U, len(at), axis=1)
    tol = 1e-9 * float(np.min(np.diff(ti))) + 4 * np.finfo(float).eps * float(np.max(np.abs(ti)))
    out = (at < ti[0] - tol) | (at > ti[-1] + tol)
    if out.any() and outside == "raise":
        raise InputError(f"the scheme needs the inputs at times [{at.min():.6g}, {at.max():.6g}] "
                         f"but they were recorded over [{ti[0]:.6g}, {ti[-1]:.6g}] only")
    at = np.clip(at, ti[0], ti[-1])
    k = np.clip(np.searchsorted(ti, at, side="right") - 1, 0, len(ti) - 2)
    w = (at - ti[k]) / (ti[k + 1] - ti[k])
    w[np.abs(w) * (ti[k + 1] - ti[k]) <= tol] = 0.0
    w[np.abs(1 - w) * (ti[k + 1] - ti[k]) <= tol] = 1.0
    F = U[:, k] * (1 - w) + U[:, k + 1] * w
    F[:, out] = np.nan
    if outside == "nan" and bends == "nan":
        bent = _kinks_of(U.tobytes(), U.shape)  # the identification samples one U many times
        between = (w > 0) & (w < 1)
        F[:, between & (bent[k] | bent[k + 1])] = np.nan
    return F
