"""Black-box probe data: Galerkin-consistent reduced accelerations from short FOM steps.

Why. The reduced relation of a *projected* FOM trajectory, q = V^T M u(t), carries a closure
term: its force is V^T f(u), not V^T f(V q). For a structure in large deformation the stiff
(membrane) content outside span(V) makes that term huge: on the SVK cantilever
(``demos/svk_cantilever.py``, r = 8) the Galerkin operators miss the projected data's relation
by 2x to 680x each trailing coordinate's own acceleration, although the Galerkin ROM itself is
accurate to 3e-5. No reduced model satisfies such data, and a polynomial L-OpInf fit to it
blows up. The FOM, used only as a black-box time stepper, can give data without closure:

For each sample (q, v, u) lift (u0, p0) = (V q, M V v), set the input u, take ONE midpoint
step of a small size h and read the reduced acceleration

    a(h) = 2/h (V^T M (u1 - u0) / h - V^T M V v).

The midpoint relation M (u1 - u0)/h = p0 - h/2 [f(u_mid) + C (u1 - u0)/h - b u] gives

    a(h) = -(V^T f(V q) + V^T C V v - V^T b u) + a_1 h + a_2 h^2 + ...,

the Galerkin acceleration plus what the step creates outside span(V). Richardson extrapolation
over h, h/2, ..., h/2^(levels-1) removes the first levels-1 terms; the difference of the last
two extrapolants is the error estimate reported per sample. With an M-orthonormal V the data
(q, v, u, a) obey a = -grad U(q) - C v + B u for the Galerkin operators exactly (to that
error), so a polynomial L-OpInf fit of them (:func:`dolfinx_lopinf.core.polynomial.point_data`)
recovers the Galerkin ROM non-intrusively: the FOM is only stepped, never opened.

Accuracy against the exact Galerkin acceleration (SVK cantilever, 567 dofs, r = 8, measured):
one step of h = 1e-6 alone is 1.6e-2 off (the stiffness-proportional damping acting on the
stiff content, first order in h); h = 1e-6 with 3 levels 3e-6; h = 4e-6 with 5 levels
(4e-6 .. 2.5e-7) 6e-8. The estimate measures the truncation part (it said 2e-7 for the last);
the floor set by the nonlinear solver's tolerance is not in it (on a 4-cell mesh the error
was 2e-7 with an estimate of 4e-8). Two numerical
details matter: the increment u1 - u0 is formed in the full space before projecting
(V^T M V = I only to ~1e-12, which at h = 1e-6 would be a 1e-2 error), and the smallest step
must not drown in the nonlinear solver's tolerance (below ~2e-7 here the error grows again).
A polynomial L-OpInf fit of such data reproduces the intrusive Galerkin ROM's test errors to
two digits at r = 4, 6, 8 on the cantilever (``demos/svk_cantilever.py``).

This is the re-projection idea of Peherstorfer (2020) made exact for an implicit scheme by
taking the step size to zero; :mod:`dolfinx_lopinf.studies.reprojection` is the fixed-step
variant. Any number of ranks: the lifting and projection use the FOM's distributed mass
matrix, the r-vectors are summed over ranks.
"""

from __future__ import annotations

import gc
import time
from dataclasses import dataclass, field

import numpy as np

from ..core import polynomial as pl
from ..core._checks import check_int, check_positive
from ..errors import InputError, LOpInfWarning, StepFailedError, warn
from ._dolfinx import MPI, PETSc
from .agreement import agree, together
from .state import StateMap, _map_key
from .integrators import MidpointIntegrator
from .lagrangian import LagrangianSystem


#: samples the step search runs on, and how often it tries a smaller h at most
PILOT_SAMPLES, MAX_REFINEMENTS = 6, 6


@dataclass
class ProbeData:
    """Probe samples: states Q, velocities Vel (r, n), inputs (m, n) or None, Richardson
    accelerations A (r, n), per-sample relative error estimate, cost."""

    Q: np.ndarray
    Vel: np.ndarray
    inputs: np.ndarray | None
    A: np.ndarray
    error_estimate: np.ndarray
    step_size: float
    levels: int
    fom_steps: int
    seconds: float
    step_search: list = field(default_factory=list)  # (h, pilot estimate) tried, in order

    def data(self) -> pl.MidpointData:
        """The samples as data of :func:`~dolfinx_lopinf.core.polynomial.fit_polynomial`."""
        return pl.point_data(self.Q, self.Vel, self.A, self.inputs)

    def summary(self) -> dict:
        return {"samples": int(self.Q.shape[1]), "step_size": self.step_size, "levels": self.levels,
                "step_search": [list(x) for x in self.step_search],
                "fom_steps": self.fom_steps, "seconds": self.seconds,
                "error_estimate_max": float(self.error_estimate.max()),
                "error_estimate_median": float(np.median(self.error_estimate))}


def probe_points(Qh: np.ndarray, Vh: np.ndarray, n: int, *, rng, spread: float = 0.5,
                 scale_max: float = 1.6, inputs_range=None, pair_velocities: bool = True):
    """Sample points (q, v, u) around reduced trajectories Qh, Vh (r, K).

    Half of the states are training states, half are training states scaled by a factor in
    [1, ``scale_max``] (to reach amplitudes beyond the training ones); every state and velocity
    gets Gaussian noise of ``spread`` x its coordinate's standard deviation. With
    ``pair_velocities`` every (q, u) is probed with +v and -v: the damping term (odd in v)
    then decouples exactly from the potential and the input (even), so noise in one cannot
    leak into the other. Returns (Q, Vel, U) with 2 n columns when paired (U None when
    ``inputs_range`` is None, else uniform in [lo, hi] per input row).
    """
    Qh, Vh = np.asarray(Qh, float), np.asarray(Vh, float)
    if Qh.ndim != 2 or Qh.shape != Vh.shape or Qh.shape[1] < 1:
        raise InputError(f"Qh and Vh must be (r, K) arrays of the same shape, got {Qh.shape} and "
                         f"{Vh.shape}")
    if not (np.all(np.isfinite(Qh)) and np.all(np.isfinite(Vh))):
        raise InputError("Qh and Vh contain NaN or inf")
    n = check_int(n, "n (points to sample)", minimum=1)
    for name, value, low in (("spread", spread, 0.0), ("scale_max", scale_max, 1.0)):
        try:
            ok = bool(np.isfinite(float(value)) and float(value) >= low)
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise InputError(f"{name} must be a finite number >= {low:g}, got {value!r} (NaN or "
                             "inf would make every sampled point NaN)")
    spread, scale_max = float(spread), float(scale_max)
    if not isinstance(rng, np.random.Generator):
        raise InputError(f"rng must be a numpy Generator (np.random.default_rng(seed)), got "
                         f"{type(rng).__name__}")
    lo_hi = None
    if inputs_range is not None:
        try:
            lo_hi = np.atleast_2d(np.asarray(inputs_range, float))
        except (TypeError, ValueError):
            lo_hi = np.zeros((0, 0))
        if lo_hi.ndim != 2 or lo_hi.shape[1] != 2 or not np.all(np.isfinite(lo_hi)) \
                or np.any(lo_hi[:, 0] > lo_hi[:, 1]):
            raise InputError(f"inputs_range must be finite (lo, hi) with lo <= hi, or one such "
                             f"pair per input, got {inputs_range!r}")
    r, K = Qh.shape
    idx = rng.integers(0, K, n)
    scale = np.where(np.arange(n) % 2 == 0, 1.0, rng.uniform(1.0, scale_max, n))
    Q = Qh[:, idx] * scale + spread * Qh.std(axis=1)[:, None] * rng.standard_normal((r, n))
    Vel = Vh[:, idx] * scale + spread * Vh.std(axis=1)[:, None] * rng.standard_normal((r, n))
    U = None
    if lo_hi is not None:
        U = lo_hi[:, :1] + (lo_hi[:, 1:] - lo_hi[:, :1]) * rng.uniform(size=(len(lo_hi), n))
    if pair_velocities:
        Q, Vel = np.hstack([Q, Q]), np.hstack([Vel, -Vel])
        U = None if U is None else np.hstack([U, U])
    return Q, Vel, U


def _integrators(black_box, step_size, levels, petsc_options):
    steps = [step_size / 2**k for k in range(levels)]
    if isinstance(black_box, LagrangianSystem):
        # the integrators' own unique option prefixes (the same on every rank)
        return [MidpointIntegrator(black_box, h, petsc_options=petsc_options) for h in steps], True
    if callable(black_box):
        made = [black_box(h) for h in steps]
        missing = [a for a in ("advance", "p", "t", "dt", "system", "mass_matrix")
                   if not hasattr(made[0], a)]
        if missing:
            raise InputError(f"the integrator black_box(h) returned lacks {', '.join(missing)} "
                             "(see MidpointIntegrator)")
        return made, False
    raise InputError("black_box must be a LagrangianSystem or a callable dt -> integrator with "
                     f"advance(q, p); got {type(black_box).__name__}")


def probe(black_box, V: np.ndarray, state_map: StateMap, Q: np.ndarray, Vel: np.ndarray,
          inputs: np.ndarray | None = None, *, set_input=None, step_size: float, levels: int = 5,
          step_tol: float | None = 1e-6, petsc_options: dict | None = None) -> ProbeData:
    """Richardson-extrapolated Galerkin accelerations at the samples (see the module docstring).
    Runs on any number of ranks (every rank passes the same arguments) with the serial result.

    Args:
        black_box: a :class:`LagrangianSystem` (midpoint integrators of step h / 2^k are made
            for it) or a callable ``h -> integrator`` returning an integrator like
            :class:`MidpointIntegrator`: ``advance(q_dofs, p_vec) -> (q1_dofs, p1_vec)``, its
            momentum Vec ``p``, time ``t``, ``system`` and the mass matrix ``mass_matrix``.
        V: (n, r) M-orthonormal basis in state coordinates (``lo.pod(..., weight=M)``), on
            every rank. state_map: the FOM's :class:`StateMap` (state = scale * dofs[order]).
        Q, Vel: (r, N) reduced states and velocities; inputs: (m, N) or None.
        set_input: ``set_input(integrator, u)`` makes the next step's forcing the input u (m,);
            required when ``inputs`` is given. Called before every step (with an empty u when
            ``inputs`` is None and ``set_input`` is given).
        step_size: h, the first step tried (small against the stiff content).
        levels: Richardson levels (h, h/2, ..., h/2^(levels-1); >= 2).
        step_tol: h is divided by 4 on the first few samples until their Richardson estimate
            is <= step_tol, or until a smaller h stops helping (then a warning says what was
            reached); None uses ``step_size`` as given. The search is in ``step_search``.
            Measured on the SVK cantilever: h = 4e-6 meets 1e-6 on 10 cells (estimate 2e-7)
            but not on 80 (2e-5: the r = 6 fit 5.6x the intrusive error), where h = 1e-6 does.
    """
    # a callable black box shows its communicator only once called: its checks use COMM_WORLD
    comm = black_box.V.mesh.comm if isinstance(black_box, LagrangianSystem) else MPI.COMM_WORLD
    args, problem = None, None
    try:
        args = _probe_args(black_box, V, state_map, Q, Vel, inputs, set_input, step_size, levels,
                           step_tol, petsc_options)
    except Exception as exc:  # noqa: BLE001 - every rank must hear of it
        problem = exc
    agree(comm, "probe", problem, **({} if args is None else args.pop("settings")))
    with together(comm, "probe"):
        return _probe(black_box, state_map, set_input, petsc_options, **args)


def _probe_args(black_box, V, state_map, Q, Vel, inputs, set_input, step_size, levels, step_tol,
                petsc_options) -> dict:
    """:func:`probe`'s checks on this rank alone (raises; no collective)."""
    if not isinstance(black_box, LagrangianSystem) and not callable(black_box):
        raise InputError("black_box must be a LagrangianSystem or a callable dt -> integrator "
                         f"with advance(q, p); got {type(black_box).__name__}")
    V = np.asarray(V, float)
    Q, Vel = np.atleast_2d(np.asarray(Q, float)), np.atleast_2d(np.asarray(Vel, float))
    levels = check_int(levels, "levels (Richardson needs two step sizes)", minimum=2)
    step_size = check_positive(step_size, "step_size")
    step_tol = None if step_tol is None else check_positive(step_tol, "step_tol")
    problem = None
    if not isinstance(state_map, StateMap):
        problem = f"state_map must be a StateMap, got {type(state_map).__name__}"
    elif V.ndim != 2 or V.shape[0] != len(state_map.order):
        problem = (f"V must be a finite (n, r) array with n = {len(state_map.order)} state rows, got "
                   f"shape {V.shape}")
    elif not np.all(np.isfinite(V)):
        problem = _nonfinite("V", V)
    elif Q.shape[0] != V.shape[1] or Q.shape != Vel.shape:
        problem = f"Q and Vel must both be (r = {V.shape[1]}, N), got {Q.shape} and {Vel.shape}"
    elif not (np.all(np.isfinite(Q)) and np.all(np.isfinite(Vel))):
        problem = "Q or Vel contains NaN or inf"
    elif inputs is not None and set_input is None:
        problem = "inputs were given without set_input(integrator, u) to apply them"
    if problem:
        raise InputError(problem)
    U = None
    if inputs is not None:
        U = np.atleast_2d(np.asarray(inputs, float))
        if U.shape[1] != Q.shape[1] or not np.all(np.isfinite(U)):
            raise InputError(f"inputs must be finite with N = {Q.shape[1]} columns, got {U.shape}")
    if petsc_options is not None and not isinstance(petsc_options, dict):
        raise InputError(f"petsc_options must be a dict, got {type(petsc_options).__name__}")
    settings = {"V": V, "state_map": _map_key(state_map), "Q": Q, "Vel": Vel, "inputs": U,
                "set_input": set_input is not None, "step_size": step_size, "levels": levels,
                "step_tol": step_tol, "petsc_options": petsc_options}
    return {"V": V, "Q": Q, "Vel": Vel, "U": U, "step_size": step_size, "levels": levels,
            "step_tol": step_tol, "settings": settings}


def _probe(black_box, state_map, set_input, petsc_options, *, V, Q, Vel, U, step_size, levels,
           step_tol) -> ProbeData:
    """:func:`probe` once every rank agreed on its arguments."""
    t0 = time.perf_counter()
    h, search = step_size, []
    pilot = np.arange(min(PILOT_SAMPLES, Q.shape[1]))
    while step_tol is not None:
        # refine h on a few samples until the Richardson estimate meets step_tol; stop where
        # a smaller h no longer helps (the nonlinear solver's tolerance takes over)
        try:
            est = _probe_at(black_box, h, levels, petsc_options, V, state_map, Q[:, pilot],
                            Vel[:, pilot], None if U is None else U[:, pilot], set_input)[1].max()
        except StepFailedError:
            if not search:
                raise
            break  # the step drowned in the solver's tolerance: keep the best h so far
        search.append((h, float(est)))
        if est <= step_tol or len(search) == MAX_REFINEMENTS or \
                (len(search) > 1 and est >= search[-2][1]):
            break
        h /= 4.0
    if search:
        h, best = min(search, key=lambda he: he[1])
        if best > step_tol:
            warn(f"probe step: the Richardson estimate reached only {best:.1e} (asked "
                 f"{step_tol:.1e}) at h = {h:.3g} after {len(search)} tries {search}; the "
                 "data are no more accurate than that", LOpInfWarning)
    A, est = _probe_at(black_box, h, levels, petsc_options, V, state_map, Q, Vel, U, set_input)
    steps = levels * (Q.shape[1] + len(search) * len(pilot))
    return ProbeData(Q, Vel, U, A, est, h, levels, steps, time.perf_counter() - t0, search)


def _probe_at(black_box, h, levels, petsc_options, V, state_map, Q, Vel, U, set_input):
    """(Richardson accelerations, per-sample estimate) with steps h, h/2, ..., h/2^(levels-1)."""
    integrators, own = _integrators(black_box, h, levels, petsc_options)
    lift = None
    try:
        lift = _DofBasis(integrators[0], V, state_map)
        raw = [_probe_level(integ, lift, Q, Vel, U, set_input) for integ in integrators]
    finally:
        if lift is not None:
            lift.close()
        if own:
            for integ in integrators:
                integ.close()
            # the integrators hold reference cycles (the SNES residual callback) and dolfinx
            # vectors wrapping PETSc Vecs, whose destroy is collective: collect them here, at
            # the same point on every rank, not whenever each rank's garbage collector runs
            # (a 2-rank probe test hung in the full test suite, twice, after the step search
            # began to make and drop integrators mid-run)
            integrators = None
            gc.collect()
    # Richardson: a(h) = a0 + a1 h + a2 h^2 + ...; with h_k = h / 2^k eliminate order by order
    table, prev = raw, None
    for order in range(1, len(raw)):
        prev = table
        table = [(2**order * table[k + 1] - table[k]) / (2**order - 1) for k in range(len(table) - 1)]
    A = table[0]
    return A, np.linalg.norm(A - prev[-1], axis=0) / np.maximum(np.linalg.norm(A, axis=0), 1e-300)


def mass_gram(integrator, V: np.ndarray, state_map: StateMap) -> np.ndarray:
    """V^T M V (r, r) with the integrator's (distributed) mass matrix, V (n, r) in state
    coordinates on every rank - e.g. to make a basis M-orthonormal on any number of ranks:
    ``V @ np.linalg.inv(np.linalg.cholesky(G)).T``. Collective: V must be the same on every
    rank (checked)."""
    if not hasattr(integrator, "mass_matrix") or not hasattr(integrator, "system"):
        raise InputError(f"integrator must be a MidpointIntegrator (mass_matrix, system), got "
                         f"{type(integrator).__name__}")
    comm = integrator.system.V.mesh.comm
    problem, V = None, np.asarray(V, dtype=float) if _is_numeric(V) else None
    if not isinstance(state_map, StateMap):
        problem = f"state_map must be a StateMap, got {type(state_map).__name__}"
    elif V is None or V.ndim != 2 or V.shape[0] != len(state_map.order):
        problem = (f"V must be a finite (n, r) array with n = {len(state_map.order)} state rows, "
                   f"got {'shape ' + str(V.shape) if V is not None else 'non-numbers'}")
    elif not np.all(np.isfinite(V)):
        problem = _nonfinite("V", V)
    elif getattr(integrator, "closed", False):
        problem = "the integrator was closed; make a new one"
    agree(comm, "mass_gram", problem, **({} if problem else {"V": V, "state_map": _map_key(state_map)}))
    basis = _DofBasis(integrator, V, state_map, check=False)
    try:
        return basis.G
    finally:
        basis.close()


def _nonfinite(name: str, a: np.ndarray) -> str:
    bad = np.argwhere(~np.isfinite(a))
    return (f"{name} contains {len(bad)} NaN/inf entries (first at index {tuple(int(i) for i in bad[0])}); "
            f"pass a finite {name}")


def _is_numeric(a) -> bool:
    try:
        np.asarray(a, dtype=float)
    except (TypeError, ValueError):
        return False
    return True


class _DofBasis:
    """The basis in this rank's dofs: W (owned + ghost rows, r) for lifting, and the Gram
    W^T M W (= V^T M V in state coordinates; summed over ranks) with the FOM's mass matrix."""

    def __init__(self, integ, V, state_map, check=True):
        space = integ.system.V
        self.W = np.ascontiguousarray(state_map.to_local_dofs(space, V))
        self.n_owned = space.dofmap.index_map.size_local * space.dofmap.index_map_bs
        self.comm = space.mesh.comm
        self.mass = integ.mass_matrix
        self._x, self._y = self.mass.createVecs()
        MW = np.column_stack([self.mass_times(self.W[:self.n_owned, j]) for j in range(V.shape[1])])
        self.MW = MW  # (owned, r)
        self.G = self.sum(self.W[:self.n_owned].T @ MW)
        r = V.shape[1]
        if check and not np.allclose(self.G, np.eye(r), atol=1e-8):
            self.close()
            raise InputError("probing needs an M-orthonormal basis (V^T M V = I); use "
                             "lo.pod(..., weight=M)")

    def close(self):
        """Destroy the work vectors now, on every rank together: left to the garbage
        collector, PETSc's collective destroy runs at different times on different ranks."""
        for vec in (self._x, self._y):
            vec.destroy()
        self.mass = None

    def mass_times(self, x_owned):
        self._x.array[:] = x_owned
        self.mass.mult(self._x, self._y)
        return self._y.array.copy()

    def sum(self, local):
        out = np.empty_like(local)
        self.comm.Allreduce(np.ascontiguousarray(local), out, op=MPI.SUM)
        return out


def _probe_level(integ, lift, Q, Vel, U, set_input):
    h = integ.dt
    n = lift.n_owned
    p0 = integ.p.duplicate()
    A = np.empty_like(Q)
    try:
        for j in range(Q.shape[1]):
            u0 = lift.W @ Q[:, j]  # local dofs (owned and ghosts)
            with p0.localForm() as loc:
                loc.set(0.0)
            p0.array[:] = lift.MW @ Vel[:, j]  # p0 = M W v (owned rows)
            p0.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
            if set_input is not None:
                set_input(integ, np.zeros(0) if U is None else U[:, j])
            q1, p1 = integ.advance(u0, p0)
            p1.destroy()
            # W^T M (u1 - u0): the increment formed in the full space before projecting
            dq = lift.sum(lift.MW.T @ (q1[:n] - u0[:n]))
            A[:, j] = 2.0 / h * (dq / h - lift.G @ Vel[:, j])
    finally:
        p0.destroy()
    return A
