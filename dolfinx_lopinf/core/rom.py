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

Every operator is checked once at construction (real, finite, shapes; M invertible), and a
model whose K, M or C are not those of a Lagrangian system (K, C not symmetric; K, M, C
indefinite) is named in a :class:`~dolfinx_lopinf.errors.NonLagrangianWarning` unless
``lagrangian=False`` says that is intended (standard OpInf), or refused with
``lagrangian=True``. The forcing of a forced model is formed chunk by chunk while
integrating, so memory does not grow with the number of steps.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ._checks import (as_real_array, check_finite, check_int, check_matrix, check_positive,
                      check_square, check_vector)
from . import compiled, schemes
from ..errors import FileFormatError, InputError, NonLagrangianWarning, StepFailedError, warn
from .io_atomic import atomic_savez, open_npz

#: Steps whose forcing is formed at once (memory 2 r x _CHUNK floats, whatever n_steps is).
_CHUNK = 1024
#: Simplified Newton (jacobian="lazy"): refresh J when |dq_k| > _LAZY_THETA |dq_{k-1}|.
_LAZY_THETA = 0.1
#: Relative tolerance of the symmetry / definiteness checks of the operators.
_STRUCTURE_RTOL = 1e-8


def _check_on_failure(on_failure):
    if on_failure not in ("raise", "stop"):
        raise InputError(f"on_failure must be 'raise' or 'stop', got {on_failure!r}")


def _initial_state(q0, v0, r):
    q0, v0 = (as_real_array(a, name).reshape(-1) for a, name in ((q0, "q0"), (v0, "v0")))
    if q0.shape != (r,) or v0.shape != (r,):
        raise InputError(f"q0 and v0 must have shape ({r},), got {q0.shape} and {v0.shape}")
    check_finite(q0, "q0", "pass a finite initial state")
    check_finite(v0, "v0", "pass a finite initial velocity")
    return q0, v0


def _structure_problems(name, A):
    """Why the square matrix A is not symmetric positive semidefinite, or [] (an exactly
    singular M is refused separately)."""
    out = []
    top = float(np.max(np.abs(A)))
    if top == 0:
        return out
    asym = float(np.max(np.abs(A - A.T)))
    if asym > _STRUCTURE_RTOL * top:
        out.append(f"{name} is not symmetric: max|{name} - {name}^T| = {asym:.3g} "
                   f"({asym / top:.2g} of max|{name}|)")
    eig = np.linalg.eigvalsh(0.5 * (A + A.T))
    if eig[0] < -_STRUCTURE_RTOL * max(abs(eig[0]), abs(eig[-1])):
        out.append(f"{name} is indefinite: the smallest eigenvalue of its symmetric part is "
                   f"{eig[0]:.6g} (largest {eig[-1]:.6g})")
    return out


def _affine_loop(G, x, forcing, n_steps: int, every: int, X, backend: str) -> None:
    """x <- G x (+ f_k) for ``n_steps`` steps, x stored in X[:, j] after every ``every``-th
    step (X[:, 0] holds x_0): the compiled loop (``compiled.affine_run``) or the numpy
    reference. ``forcing``: None (unforced) or an iterable of (k0, k1, [f_k0 .. f_k1-1] as a
    (2r, k1 - k0) array)."""
    j = 1
    if backend == "numba":
        G, x = np.ascontiguousarray(G), np.ascontiguousarray(x)
        if forcing is None:
            compiled.affine_run(G, x, None, n_steps, 0, every, X, j)
            return
        for k0, k1, F in forcing:
            j = compiled.affine_run(G, x, np.ascontiguousarray(F.T), k1 - k0, k0, every, X, j)
        return
    for k0, k1, F in forcing or [(0, n_steps, None)]:
        for i in range(k1 - k0):
            x = G @ x
            if F is not None:
                x += F[:, i]
            if (k0 + i + 1) % every == 0:
                X[:, j] = x
                j += 1


@dataclass(frozen=True)
class Trajectory:
    """A ROM trajectory - the one result type of every reduced model's ``simulate``: times
    (K,), Qh (r, K), Vh (r, K) velocities, Y (p, K) or None; ``seconds`` of integration, the
    ``backend`` that ran it (``"numpy"`` or ``"numba"``), ``info`` (Newton counts of the
    nonlinear ROMs: ``newton_iterations``, ``jacobians``; ``failure``: why and where a run
    stopped with ``on_failure="stop"``) and Ah (r, K), the scheme's accelerations where it has
    them (Newmark / generalised-alpha). ``stable``: every state finite.

    The contract shared by :class:`LagrangianROM`, :class:`WaveROM` and
    :class:`~dolfinx_lopinf.core.polynomial.PolynomialROM`:
    ``simulate(q0, v0, dt, n_steps, *, inputs=None, every=1, backend="auto",
    on_failure=...)``: a step that cannot be taken raises
    :class:`~dolfinx_lopinf.errors.StepFailedError` (``"raise"``) or ends the run, the states
    after it NaN (``"stop"``)."""

    times: np.ndarray
    Qh: np.ndarray
    Vh: np.ndarray
    Y: np.ndarray | None = None
    seconds: float = 0.0
    backend: str = "numpy"
    info: dict = field(default_factory=dict)
    Ah: np.ndarray | None = None

    @property
    def stable(self) -> bool:
        """Whether every state is finite (a failed or blown-up run is not)."""
        return bool(np.all(np.isfinite(self.Qh)))


@dataclass(frozen=True)
class LagrangianROM:
    """Reduced model Mh qh_tt + Ch qh_t + Kh qh = Bh u,  y = Eh qh.

    Attributes:
        K: (r, r) stiffness.  M: (r, r) mass (identity when None).  C: (r, r) damping or None.
        B: (r, m) input operator or None.  E: (p, r) output operator or None.
        scheme: the time integrator, a :mod:`dolfinx_lopinf.core.schemes` object or its name
            (``"midpoint"``: loads at the step midpoints; ``"newmark"``: average acceleration;
            ``schemes.GeneralizedAlpha(rho_inf=0.8)``, ...): a ROM is integrated with the
            same scheme as its FOM, so it carries the same numerical dissipation.
        meta: free-form, JSON-serialisable metadata (method, basis size, certificate, ...).
    """

    K: np.ndarray
    M: np.ndarray | None = None
    C: np.ndarray | None = None
    B: np.ndarray | None = None
    E: np.ndarray | None = None
    meta: dict = field(default_factory=dict)
    scheme: schemes.Scheme | str = "midpoint"
    lagrangian: bool | None = None

    def __post_init__(self):
        object.__setattr__(self, "scheme", schemes.rom_scheme(schemes.from_spec(self.scheme)))
        if self.lagrangian not in (None, True, False):
            raise InputError(f"lagrangian must be None, True or False, got {self.lagrangian!r}")
        K = check_square(self.K, "K")
        object.__setattr__(self, "K", K)
        r = K.shape[0]
        for name in ("M", "C"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, check_square(getattr(self, name), name, r))
        if self.M is not None:
            s = np.linalg.svd(self.M, compute_uv=False)
            if s[-1] <= r * np.finfo(float).eps * s[0] or s[0] == 0:
                raise InputError(f"M is singular (singular values {s[0]:.3g} .. {s[-1]:.3g}); "
                                 "the mass matrix must be invertible")
        if self.B is not None:
            B = as_real_array(self.B, "B")
            if B.ndim == 1 and B.shape == (r,):
                B = B.reshape(r, 1)
            if B.ndim != 2 or B.shape[0] != r or B.shape[1] == 0:
                raise InputError(f"B must have shape ({r}, m) with m >= 1, got {B.shape} "
                                 "(pass B=None for an unforced model)")
            check_finite(B, "B", "an operator must be finite (did its fit fail?)")
            object.__setattr__(self, "B", B)
        if self.E is not None:
            E = as_real_array(self.E, "E")
            E = E.reshape(1, -1) if E.ndim == 1 else E
            if E.ndim != 2 or E.shape[1] != r or E.shape[0] == 0:
                raise InputError(f"E must have shape (p, {r}), got {E.shape}")
            check_finite(E, "E", "an operator must be finite (did its fit fail?)")
            object.__setattr__(self, "E", E)
        if self.lagrangian is not False:
            problems = _structure_problems("K", K)
            for name in ("M", "C"):
                if getattr(self, name) is not None:
                    problems += _structure_problems(name, getattr(self, name))
            if problems:
                msg = ("; ".join(problems) + ". This model is not the Euler-Lagrange equation of "
                       "a Lagrangian: its energy is neither conserved nor dissipated and its "
                       "trajectory may grow without bound (infer_mechanical fits a structured "
                       "model). Pass lagrangian=False if that is intended (e.g. standard "
                       "OpInf), lagrangian=True to make this an error.")
                if self.lagrangian:
                    raise InputError(msg)
                warn(msg, NonLagrangianWarning)

    @property
    def r(self) -> int:
        return self.K.shape[0]

    @property
    def mass(self) -> np.ndarray:
        return np.eye(self.r) if self.M is None else self.M

    def energy(self, Qh: np.ndarray, Vh: np.ndarray) -> np.ndarray:
        """ROM energy 1/2 v^T Mh v + 1/2 q^T Kh q for (r, K) arrays (per column)."""
        M, K = self.mass, self.K
        Qh, Vh = as_real_array(Qh, "Qh"), as_real_array(Vh, "Vh")
        if Qh.ndim != 2 or Qh.shape[0] != self.r or Vh.shape != Qh.shape:
            raise InputError(f"Qh and Vh must both be ({self.r}, K) arrays, got {Qh.shape} and "
                             f"{Vh.shape}")
        # non-finite columns (a trajectory that blew up) give non-finite energies: a result
        return 0.5 * np.einsum("ik,ij,jk->k", Vh, M, Vh) + 0.5 * np.einsum("ik,ij,jk->k", Qh, K, Qh)

    def step(self, dt: float):
        """(G, H): one step of the ROM's scheme is x1 = G x0 + H f(t0 + tau dt) on its state
        x ([q; v; a] for the Newmark / generalised-alpha family, [q; p] for the midpoint rule;
        :mod:`dolfinx_lopinf.core.schemes`)."""
        dt = check_positive(dt, "dt")
        return self.scheme.step(self.mass, self.C, self.K, self.B, dt)

    def simulate(self, q0, v0, dt: float, n_steps: int, *, inputs=None, every: int = 1,
                 backend: str = "auto", on_failure: str = "raise") -> Trajectory:
        """Integrate with the ROM's scheme (:attr:`scheme`) from (q0, v0).

        Args:
            q0, v0: (r,) initial reduced position and velocity.
            dt: time step; n_steps: number of steps; every: keep every ``every``-th step.
            inputs: for a forced ROM, a callable u(t) -> (m,) - evaluated where the scheme
                evaluates its load (t_n + tau dt: t_{n+1} for Newmark, t_{n+1-alpha_f} for
                generalised-alpha, the midpoints for the midpoint rule), and at t_0 for the
                initial acceleration - or an array: (m, n_steps + 1) at t_0 .. t_n
                (interpolated linearly to the scheme's times), or, for the midpoint rule,
                (m, n_steps) at the step midpoints. None: no load (the free response).
            backend: ``"numpy"`` (the reference loop), ``"numba"`` (the compiled loop of
                :mod:`dolfinx_lopinf.core.compiled`: the same step and forcing, equal to
                rounding) or ``"auto"`` (numba when installed and not disabled by
                ``DOLFINX_LOPINF_JIT=0``). Compilation happens before the timer starts.
            on_failure: the shared contract's option (:class:`Trajectory`); a linear step
                cannot fail - a model that blows up returns non-finite states
                (``trajectory.stable`` is False).

        Returns:
            :class:`Trajectory` at t = 0, every*dt, ...: positions Qh, velocities Vh and, for
            the Newmark / generalised-alpha family, the scheme's accelerations Ah.
        """
        _check_on_failure(on_failure)
        r = self.r
        q0, v0 = _initial_state(q0, v0, r)
        n_steps = check_int(n_steps, "n_steps", 0)
        every = check_int(every, "every", 1)
        dt = check_positive(dt, "dt")
        backend = compiled.resolve_backend(backend)
        if backend == "numba":
            compiled.kernels()  # compile / load from the cache outside the timed region
        loads, f0 = self._loads(inputs, dt, n_steps)
        t0 = time.perf_counter()
        G, H = self.step(dt)
        x = self.scheme.initial_state(q0, v0, f0, self.mass, self.C, self.K, self.B)
        n_out = n_steps // every + 1
        X = np.empty((len(x), n_out))
        X[:, 0] = x
        timing = {"inputs": 0.0}  # evaluating a callable input is not integration time

        def forcing_chunks():
            """(k0, k1, the forcing H F_k of steps k0 .. k1-1 as a (d, k1-k0) array)."""
            for k0 in range(0, n_steps, _CHUNK):
                k1 = min(k0 + _CHUNK, n_steps)
                ti = time.perf_counter()
                F = loads(k0, k1)
                timing["inputs"] += time.perf_counter() - ti
                yield k0, k1, H @ F

        _affine_loop(G, x, None if loads is None else forcing_chunks(), n_steps, every, X,
                     backend)
        Qh, Vh, Ah = self.scheme.unpack(X, self.mass, self.C, self.K, self.B)
        seconds = time.perf_counter() - t0 - timing["inputs"]
        Y = None if self.E is None else self.E @ Qh
        times = dt * every * np.arange(n_out)
        return Trajectory(times, Qh, Vh, Y, seconds, backend, Ah=Ah)

    def _loads(self, inputs, dt, n_steps):
        """(loads, f0): loads(k0, k1) -> (m, k1 - k0) the scheme's loads F_k = u(t_k + tau dt)
        of steps k0 .. k1-1 (None for the free response), and u(t_0) (or None). An array is
        checked once here; a callable's values are checked chunk by chunk."""
        if self.B is None:
            if inputs is not None:
                raise InputError("this ROM has no input operator B (it is unforced); do not "
                                 "pass inputs")
            return None, None
        m = self.B.shape[1]
        if inputs is None:
            return None, None
        tau = self.scheme.tau
        midpoint = isinstance(self.scheme, schemes.Midpoint)
        if not callable(inputs):
            U = as_real_array(inputs, "inputs")
            U = U.reshape(1, -1) if U.ndim == 1 else U
            shapes = [(m, n_steps + 1)] + ([(m, n_steps)] if midpoint else [])
            if U.shape not in shapes:
                where = (f"({m}, {n_steps + 1}) at t_0 .. t_n"
                         + (f" or ({m}, {n_steps}) at the step midpoints" if midpoint else ""))
                raise InputError(f"inputs must have shape {where} (m = {m} inputs, one per "
                                 f"column of B), got {U.shape}")
            check_finite(U, "inputs", "the forcing must be finite")
            if U.shape[1] == n_steps:  # midpoint rule, at the midpoints already
                return (lambda k0, k1: U[:, k0:k1]), None
            grid = dt * np.arange(n_steps + 1)
            F = schemes.sample_inputs(U, grid, grid[:-1] + tau * dt)
            return (lambda k0, k1: F[:, k0:k1]), U[:, 0]

        def evaluate(times):
            cols = [np.atleast_1d(np.asarray(inputs(t))) for t in times]
            try:
                U = np.column_stack(cols)
            except ValueError:
                sizes = sorted({c.shape for c in cols})
                raise InputError(f"inputs(t) returned arrays of different shapes {sizes}; it "
                                 f"must return ({m},) at every t") from None
            U = as_real_array(U, "inputs(t)")
            if U.shape != (m, len(times)):
                raise InputError(f"inputs(t) must return {m} value(s) (one per column of B), "
                                 f"got shape {cols[0].shape} at t = {times[0]:.6g}")
            finite = np.isfinite(U)
            if not finite.all():
                i, k = np.argwhere(~finite)[0]
                raise InputError(f"inputs(t) returned a non-finite value {U[i, k]} (input {i}) "
                                 f"at t = {times[k]:.6g}; the forcing must be finite")
            return U

        f0 = None if midpoint else evaluate(np.array([0.0]))[:, 0]
        return (lambda k0, k1: evaluate(dt * (np.arange(k0, k1) + tau))), f0


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def save_rom(path, rom: LagrangianROM, *, basis_rows: np.ndarray | None = None,
             rows: np.ndarray | None = None, basis_dual: np.ndarray | None = None) -> Path:
    """Write a ROM to one ``.npz``: operators, scheme, metadata (JSON) and optionally rows of
    its basis (e.g. the dofs of an output point, for partial reconstruction). The write is
    atomic: an interrupted save leaves any previous file at ``path`` intact.

    Args:
        basis_rows: (len(rows), r) rows of the basis V to ship with the ROM.
        rows: their indices in the full state.
        basis_dual: with a weighted basis (V^T W V = I), the (n, r) W V that projects full
            states (shipped with the whole basis only).

    Returns:
        The path written (``.npz`` appended unless ``path`` ends in it).
    """
    if not isinstance(rom, LagrangianROM):
        raise InputError(f"rom must be a LagrangianROM, got {type(rom).__name__}")
    try:
        meta = json.dumps(rom.meta, default=_json_default)
    except (TypeError, ValueError) as exc:
        raise InputError(f"rom.meta must be JSON-serialisable (numbers, strings, lists, dicts, "
                         f"numpy scalars/arrays): {exc}") from None
    arrays = {"K": rom.K, "scheme": np.array(rom.scheme.spec), "meta": np.array(meta),
              "lagrangian": np.array(json.dumps(rom.lagrangian))}
    for name in ("M", "C", "B", "E"):
        if getattr(rom, name) is not None:
            arrays[name] = getattr(rom, name)
    if basis_rows is not None:
        basis_rows = check_matrix(basis_rows, "basis_rows")
        if basis_rows.shape[1] != rom.r:
            raise InputError(f"basis_rows must be (k, {rom.r}), got {basis_rows.shape}")
        if rows is None:
            rows = np.arange(len(basis_rows))
        rows = np.asarray(rows)
        if rows.dtype.kind not in "iu" or rows.shape != (len(basis_rows),):
            raise InputError(f"rows must be {len(basis_rows)} integer indices (one per row of "
                             f"basis_rows), got {rows.dtype} of shape {rows.shape}")
        arrays["basis_rows"] = basis_rows
        arrays["rows"] = rows
        if basis_dual is not None:
            basis_dual = check_matrix(basis_dual, "basis_dual")
            if basis_dual.shape != basis_rows.shape:
                raise InputError(f"basis_dual must have the shape of basis_rows "
                                 f"{basis_rows.shape}, got {basis_dual.shape}")
            arrays["basis_dual"] = basis_dual
    elif basis_dual is not None:
        raise InputError("basis_dual given without basis_rows")
    elif rows is not None:
        raise InputError("rows given without basis_rows; pass both or neither")
    return atomic_savez(path, **arrays)


def load_rom(path) -> tuple[LagrangianROM, dict]:
    """Read a ROM written by :func:`save_rom`; returns ``(rom, extras)`` where extras may hold
    ``basis_rows``, ``rows`` and ``basis_dual``.

    Raises:
        FileNotFoundError: no such file.
        FileFormatError: naming the file, when it is not a ROM file (text, a single ``.npy``,
            truncated or corrupt, no ``K`` or ``scheme``, unreadable metadata) or its operators
            are invalid (non-finite, wrong shapes).
    """
    what = "ROM (save_rom)"
    with open_npz(path, what) as (data, read):
        missing = [k for k in ("K", "scheme") if k not in data.files]
        if missing:
            hint = " (a Snapshots file? use Snapshots.load)" if "Q" in data.files else ""
            raise FileFormatError(f"{path}: lacks {', '.join(map(repr, missing))} (entries found: "
                                  f"{sorted(data.files)}); not a file written by save_rom{hint}")
        kw = {name: read(name) for name in ("K", "M", "C", "B", "E") if name in data.files}
        scheme = read("scheme")
        texts = {"meta": "{}", "lagrangian": "null"}
        for key in texts:
            if key in data.files:
                value = read(key)
                if value.dtype.kind != "U" or value.ndim != 0:
                    raise FileFormatError(f"{path}: entry {key!r} must be a JSON string, got "
                                          f"{value.dtype} of shape {value.shape}")
                texts[key] = str(value)
        extras = {k: read(k) for k in ("basis_rows", "rows", "basis_dual") if k in data.files}
    if scheme.ndim != 0 or scheme.dtype.kind != "U":
        raise FileFormatError(f"{path}: entry 'scheme' must be a string, got {scheme.dtype} of "
                              f"shape {scheme.shape}")
    parsed = {}
    for key, text in texts.items():
        try:
            parsed[key] = json.loads(text)
        except ValueError as exc:
            raise FileFormatError(f"{path}: entry {key!r} is not valid JSON ({exc}): "
                                  f"{text[:60]!r}") from None
    if parsed["lagrangian"] not in (None, True, False):
        raise FileFormatError(f"{path}: entry 'lagrangian' must be null, true or false, got "
                              f"{texts['lagrangian']!r}")
    try:
        rom = LagrangianROM(**kw, scheme=str(scheme), meta=parsed["meta"],
                            lagrangian=parsed["lagrangian"])
    except InputError as exc:
        raise FileFormatError(f"{path}: the stored ROM is invalid: {exc}") from exc
    return rom, extras


@dataclass(frozen=True)
class WaveROM:
    """Gray-box Lagrangian wave ROM  qh_tt = Kh qh - V^T (w * g(V qh))  (docs/method.md#wave-and-sine-gordon).

    It is the Euler-Lagrange equation of
    ``L_h = 1/2 |qh_t|^2 + 1/2 qh^T Kh qh - sum_i w_i U(V_i qh)``,
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

    def __post_init__(self):
        K = check_square(self.K, "K")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "V", check_matrix(self.V, "V", cols=K.shape[0]))
        if self.weights is not None:
            w = check_vector(self.weights, "weights", self.V.shape[0])
            if np.any(w < 0):
                raise InputError(f"weights must be >= 0 (ECSW weights), got min {w.min():.3g}")
            object.__setattr__(self, "weights", w)
        for name in ("g", "dg", "U"):
            if not callable(getattr(self, name)):
                raise InputError(f"{name} must be a callable (a numpy function of the pointwise "
                                 f"nonlinearity), got {type(getattr(self, name)).__name__}")

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
        """ROM energy ``1/2 |v|^2 - 1/2 q^T Kh q + sum_i w_i U(V_i q)``, per column."""
        pot = self._w() @ self.U(self.V @ Qh)
        return 0.5 * np.sum(Vh**2, axis=0) - 0.5 * np.einsum("ik,ij,jk->k", Qh, self.K, Qh) + pot

    def simulate(self, q0, v0, dt: float, n_steps: int, *, inputs=None, every: int = 1,
                 backend: str = "auto", on_failure: str = "raise", tol: float = 1e-12,
                 max_newton: int = 20, jacobian: str = "fresh") -> Trajectory:
        """Midpoint variational integrator in position-momentum form (p = qh_t):

            R(q1) = p0 - (q1 - q0)/dt + dt/2 (Kh m - F(m)) = 0,  m = (q0 + q1)/2
            p1    = (q1 - q0)/dt + dt/2 (Kh m - F(m)),

        each step solved by Newton with J = -I/dt + dt/4 (Kh - V^T diag(w g'(V m)) V), from
        the predictor q1 = q0 + dt p0, stopped when ``|dq| <= tol max(|q1|, 1)``.

        Args:
            jacobian: ``"fresh"`` (Newton: J at every iterate) or ``"lazy"`` (simplified
                Newton: the last J is kept, across steps too, and formed afresh at the next
                iterate only when convergence slows, ``|dq_k| > theta |dq_{k-1}|`` with
                theta = 0.1). Same stopping test; the converged states agree to the Newton
                tolerance.
            backend: ``"numpy"`` (the reference loop, any g), ``"numba"`` (the compiled loop of
                :mod:`dolfinx_lopinf.core.compiled`; for g = sin, dg = cos, the sine-Gordon
                nonlinearity, also as compiled from UFL by ``nonlinear.identify``) or
                ``"auto"`` (numba when installed, enabled and g is sin, else numpy).

            inputs: must be None (this model has no forcing; the shared contract's argument).
            on_failure: ``"raise"`` (default): :class:`~dolfinx_lopinf.errors.StepFailedError`
                naming the step if Newton does not converge; ``"stop"``: the trajectory up to
                the failed step, NaN after it, ``info["failure"]`` saying where.
        """
        _check_on_failure(on_failure)
        if inputs is not None:
            raise InputError("this wave ROM has no input operator; do not pass inputs")
        q, p = (a.copy() for a in _initial_state(q0, v0, self.r))
        dt = check_positive(dt, "dt")
        n_steps = check_int(n_steps, "n_steps", 0)
        every = check_int(every, "every", 1)
        max_newton = check_int(max_newton, "max_newton", 1)
        tol = check_positive(tol, "tol")
        if jacobian not in ("fresh", "lazy"):
            raise InputError(f"jacobian must be 'fresh' or 'lazy', got {jacobian!r}")
        backend = self._backend(backend)
        t0 = time.perf_counter()
        n_out = n_steps // every + 1
        Q, P = np.empty((self.r, n_out)), np.empty((self.r, n_out))
        Q[:, 0], P[:, 0] = q, p
        loop = self._run_compiled if backend == "numba" else self._run_numpy
        try:
            info = loop(q, p, dt, n_steps, every, tol, max_newton, jacobian == "lazy", Q, P)
        except StepFailedError as exc:
            if on_failure == "raise" or exc.step is None:
                raise
            first = (exc.step - 1) // every + 1  # the first stored column not reached
            Q[:, first:] = np.nan
            P[:, first:] = np.nan
            info = {"failure": str(exc)}
        return Trajectory(dt * every * np.arange(n_out), Q, P, None, time.perf_counter() - t0,
                          backend, info)

    def _backend(self, backend: str) -> str:
        """The loop that runs: numba only for the sine nonlinearity (compiled, or loaded from
        the cache, here - before the timer)."""
        requested, backend = backend, compiled.resolve_backend(backend)
        if backend == "numba" and not compiled.is_sine(self.g, self.dg):
            if requested == "numba":
                raise InputError("backend='numba' compiles the wave ROM for g = sin, dg = cos "
                                 "(sine-Gordon) only; this ROM's g is another function - "
                                 "pass backend='auto' or 'numpy'")
            return "numpy"
        if backend == "numba":
            compiled.kernels()
        return backend

    def _run_compiled(self, q, p, dt, n_steps, every, tol, max_newton, lazy, Q, P) -> dict:
        """:meth:`simulate`'s loop compiled (``compiled._wave_sine_run``); fills Q, P."""
        stats = np.zeros(3, dtype=np.int64)
        C = np.ascontiguousarray
        rnorm = compiled.kernels()["_wave_sine_run"](
            C(self.K.T), C(self.V), C(self.V.T), C(self._w(), dtype=float), C(q), C(p), dt,
            n_steps, every, tol, max_newton, lazy, _LAZY_THETA, Q, P, stats)
        if stats[0] > 0:
            k = int(stats[0])
            raise StepFailedError(f"reduced Newton did not converge at step {k} "
                                  f"(t = {k * dt:.6g}): |R| = {rnorm:.3e}; try a smaller dt", step=k)
        if stats[0] < 0:
            raise np.linalg.LinAlgError(f"Singular matrix (the Newton Jacobian at step "
                                        f"{-int(stats[0])})")
        return {"newton_iterations": int(stats[2]), "jacobians": int(stats[1])}

    def _run_numpy(self, q, p, dt, n_steps, every, tol, max_newton, lazy, Q, P) -> dict:
        """:meth:`simulate`'s loop in numpy (the reference); fills Q, P."""
        K, V, w = self.K, self.V, self._w()
        eye = np.eye(self.r)
        J = None
        n_it = n_jac = 0
        j = 1
        for k in range(n_steps):
            q1 = q + dt * p  # explicit predictor
            refresh = not lazy or J is None
            prev = np.inf
            for _ in range(max_newton):
                n_it += 1
                m = 0.5 * (q + q1)
                z = V @ m
                F = V.T @ (w * self.g(z))
                R = p - (q1 - q) / dt + 0.5 * dt * (K @ m - F)
                if refresh:
                    J = -eye / dt + 0.25 * dt * (K - (V.T * (w * self.dg(z))) @ V)
                    n_jac += 1
                    refresh = not lazy
                dq = np.linalg.solve(J, -R)
                q1 = q1 + dq
                step = np.linalg.norm(dq)
                if step <= tol * max(np.linalg.norm(q1), 1.0):
                    break
                if lazy and step > _LAZY_THETA * prev:
                    refresh = True  # convergence slowed: a fresh Jacobian at the next iterate
                prev = step
            else:
                raise StepFailedError(f"reduced Newton did not converge at step {k + 1} "
                                      f"(t = {(k + 1) * dt:.6g}): |R| = {np.linalg.norm(R):.3e}; "
                                      "try a smaller dt", step=k + 1)
            m = 0.5 * (q + q1)
            p = (q1 - q) / dt + 0.5 * dt * (K @ m - V.T @ (w * self.g(V @ m)))
            q = q1
            if (k + 1) % every == 0:
                Q[:, j], P[:, j] = q, p
                j += 1
        return {"newton_iterations": n_it, "jacobians": n_jac}
