"""The one-call pipeline: snapshots -> basis -> the data relation of the user's integrator ->
L-OpInf -> a reduced model that carries its basis, scheme and operators (numpy only).

    model = lo.fit(snapshots, r=4)                  # or a list of Snapshots (trajectories)
    traj = model.predict(n_steps=2000, inputs=u)    # from rest, or q0=/v0= full or reduced
    tip = traj.Y;  field = model.reconstruct(traj.Qh, rows=...)

Which data relation (``scheme=``). A time loop's snapshots obey the discrete equations of its
integrator exactly (:mod:`dolfinx_lopinf.core.schemes`); L-OpInf fitted to that relation
identifies the operators of the *discrete* dynamics, and the ROM is stepped with the same
scheme, so it reproduces the loop's numerical dissipation. ``scheme`` is a
:mod:`~dolfinx_lopinf.core.schemes` object (``schemes.GeneralizedAlpha(rho_inf=0.8)``,
``schemes.Newmark(beta, gamma)``, ``schemes.HHT(alpha)``, ...), a name (``"newmark"``,
``"midpoint"``, ``"central_difference"``, ``"continuous"`` = 8th-order differences), or
``"auto"``: the family and its parameters are identified from the data
(:func:`dolfinx_lopinf.core.identify.identify`: the relation's residual over the schemes
users run, then refined), with 8th-order differences as a fallback candidate.

Which model (``mass=``, ``damping=``). Mh = I or learned (:mod:`dolfinx_lopinf.core.mass`),
Ch >= eps I or none. With ``"auto"`` every candidate (mass model x damping x relation) is
fitted on the first ``1 - holdout`` of every trajectory and predicts the held-back end with
its scheme's multistep recurrence, started from the samples before it (relative error, the
worst trajectory counts). The simplest candidate - Mh = I before learned, undamped before
damped, the scheme's relation before differences - whose error is within ``MARGIN`` of the
best is kept: a near-tie (which rounding or another BLAS could flip) is decided by that order,
never by the last bits, and a richer model must earn its place by a clear margin. A learned
mass that is the identity up to a scale in every direction the data see is not a different
model: it is replaced by Mh = I (the data cannot separate them; the structurally exact model
extrapolates better). A learned-mass candidate is scored as the final fit returns it: where
its interior point stalls at the default ridge it is certified with the ridge raised
(:func:`~dolfinx_lopinf.core.infer_mechanical`), and the chosen model's final fit starts at
that ridge - a stalled fit's held-back error is not reproducible. A chosen model whose
held-back error exceeds ``HELD_BACK_WARN`` (5 %) gets a
:class:`~dolfinx_lopinf.errors.PoorPredictionWarning`. A named (or recorded) scheme whose
relation residual is 3x that of another whose relation holds to the data's rounding gets a
:class:`~dolfinx_lopinf.errors.SchemeMismatchWarning` naming the better one. From r = 12 on
the candidates are fitted on threads (the cores the process may use, shared among MPI ranks,
or ``DOLFINX_LOPINF_FIT_THREADS``); each is computed as alone, so the result does not depend
on the thread count.
"""

from __future__ import annotations

import os
import sys
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize

from . import compiled, lsq, schemes
from .holdout import prediction_error, split
from .basis import Basis, from_svd, leading_svd, pod, weighted_svd
from ._checks import as_real_array, check_finite, check_int
from ..errors import (FileFormatError, InputError, PoorPredictionWarning, RankDeficientDataError,
                      SchemeMismatchWarning, warn)
from .identify import (PREDICTION_FLOOR, REFINEMENT_GAIN, RESIDUAL_FLOOR, SHORTLIST, Residual,
                       _class_best, _equivalent, _load_kind, held_back_errors, identify, leading,
                       standard_members)
from ._blas import serial_blas, usable_cores
from .inference import RIDGE, infer_mechanical, infer_output
from .io_atomic import plain
from .rom import LagrangianROM, Trajectory, load_rom, save_rom
from .snapshots import Snapshots, check_scheme, common_weight

MASS_MODELS = ("auto", "identity", "learned")
DAMPING_MODELS = ("auto", True, False)
#: The first candidate (in the order of simplicity) whose held-back error is within this
#: factor of the best one wins.
MARGIN = 1.5
#: A learned mass whose eigenvalues, in the metric of the data, lie within this relative
#: spread of their mean is the identity up to scale (see :func:`_is_scaled_identity`).
IDENTITY_SPREAD = 0.05
#: The integrator is identified in up to this many POD coordinates, those whose singular
#: values exceed ID_RANK_RTOL of the largest (:func:`_identification_pieces`).
ID_MAX_R = 24
ID_RANK_RTOL = 1e-10
#: ... and at most so many that the free fit (2r + m unknowns per row) has this many samples
#: per unknown (fewer over-fit the truncated modes' closure error); the held-back check,
#: which fits three quarters of the samples, twice as many
ID_SAMPLES_PER_UNKNOWN = 4
#: lo.fit computes the leading max(r, ID_MAX_R) + LEADING_EXTRA singular triplets of the
#: snapshots (block subspace iteration) when min(n, K) is at least LEADING_FROM times that
#: (the same vectors to the data's rounding, a fraction of the cost: CHANGELOG); smaller
#: data: the full thin SVD
LEADING_EXTRA, LEADING_FROM = 16, 3
#: The relation of the data's scheme holds to this relative residual or better (the truncated
#: modes' closure, the data's rounding); above it no member is the data's scheme and the
#: choice between members is a matter of fit, not of identity (:func:`_relation_for`)
CLOSURE_LEVEL = 1e-3
#: A chosen model whose held-back prediction error exceeds this gets a PoorPredictionWarning.
#: On the data of 14 recorded loops (studies.loops) the chosen errors are 1e-11 .. 4e-3 from
#: r = 4 on (0.16 for a membrane at r = 2); recordings a model of this class cannot
#: represent - every third step of an implicit loop, the loads recorded one step late, a
#: prescribed displacement as the input, rigid-body modes of an acoustic cavity - gave 0.06 -
#: 1.5 with no other sign
HELD_BACK_WARN = 0.05
#: From this r on, the candidates are fitted on threads (:func:`fit_threads`; below it a fit
#: takes milliseconds and threads cost more than they give: measured in the CHANGELOG)
PARALLEL_FROM_R = 12
FIT_THREADS_ENV = "DOLFINX_LOPINF_FIT_THREADS"
#: A named scheme whose relation residual exceeds the best one's by this factor is contradicted
#: (when the best holds to RESIDUAL_FLOOR: :func:`_relation_for`).
MISMATCH = 3.0
#: ... and exceeds this (below it both relations hold to the data's accuracy)
MISMATCH_FLOOR = 1e-9
#: on truncated data a named scheme is contradicted when its free fit predicts the held-back
#: end (the first 1 - HOLDOUT_CHECK fitted) this many times worse than the best member's
PREDICTION_MISMATCH, HOLDOUT_CHECK = 30.0, 0.25


def _mass_candidates(mass):
    """The mass models ``mass`` allows. The learned mass is our own interior point
    (:mod:`~dolfinx_lopinf.core.mass`): "auto" takes both with or without cvxpy."""
    return ("identity", "learned") if mass == "auto" else (mass,)


@dataclass(frozen=True)
class ReducedModel:
    """A fitted L-OpInf model with its basis: predict, reconstruct, save/load.

    Attributes:
        rom: the reduced operators and scheme (:class:`~dolfinx_lopinf.core.rom.LagrangianROM`).
        basis: the POD basis (``basis.V``: (n, r)).
        scheme: the data relation fitted (a :mod:`~dolfinx_lopinf.core.schemes` object;
            compares equal to its name, e.g. ``model.scheme == "newmark"``).
        dt: the time step of the snapshots (the ROM's default step).
        report: how the fit went - the scheme identified and why, held-back errors per
            candidate, the solver certificate, data sizes.
    """

    rom: LagrangianROM
    basis: Basis
    scheme: schemes.Scheme
    dt: float
    report: dict = field(default_factory=dict)

    @property
    def r(self) -> int:
        return self.rom.r

    def _reduced(self, x, name):
        if x is None:
            return np.zeros(self.r)
        x = as_real_array(x, name)
        if x.shape == (self.r,):
            return x
        if x.shape == (self.basis.n,):
            return self.basis.project(x)
        raise InputError(f"{name} must be a reduced ({self.r},) or a full ({self.basis.n},) state, "
                         f"got shape {x.shape}")

    def predict(self, n_steps: int | None = None, *, t_end: float | None = None, q0=None, v0=None,
                inputs=None, dt: float | None = None, every: int = 1,
                backend: str = "auto") -> Trajectory:
        """Integrate the ROM with its scheme from (q0, v0) (full or reduced; rest by default).

        Args:
            n_steps or t_end: how far (one of the two; t_end must be a whole number of steps).
            inputs: for a forced model, u(t) -> (m,) (evaluated where the scheme applies its
                load) or an (m, n_steps + 1) array at t_0 .. t_n; None: the free response.
            dt: time step (default: the snapshots' dt); every: keep every ``every``-th step.
            backend: the time loop, as in :meth:`~dolfinx_lopinf.core.rom.LagrangianROM.simulate`.
        """
        dt = self.dt if dt is None else dt
        if (n_steps is None) == (t_end is None):
            raise InputError("give exactly one of n_steps and t_end")
        if n_steps is None:
            n_steps = _whole_steps(t_end, dt)
        return self.rom.simulate(self._reduced(q0, "q0"), self._reduced(v0, "v0"), dt, n_steps,
                                 inputs=inputs, every=every, backend=backend)

    def reconstruct(self, Qh: np.ndarray, rows=None) -> np.ndarray:
        """Full states V Qh, or only the given ``rows`` (partial reconstruction)."""
        return self.basis.reconstruct(Qh, rows=rows)

    def save(self, path):
        """One ``.npz`` (operators, basis, scheme, report); returns the path written."""
        meta = dict(self.rom.meta, fit_scheme=self.scheme.spec, fit_dt=self.dt,
                    fit_report=plain(self.report))
        rom = LagrangianROM(K=self.rom.K, M=self.rom.M, C=self.rom.C, B=self.rom.B, E=self.rom.E,
                            meta=meta, scheme=self.rom.scheme, lagrangian=self.rom.lagrangian)
        b = self.basis  # a weighted basis projects with W V (W itself is n x n: not stored)
        return save_rom(path, rom, basis_rows=b.V, rows=np.arange(b.n), basis_dual=b.saved_dual())

    @classmethod
    def load(cls, path) -> "ReducedModel":
        """Read a file written by :meth:`save` (numpy only). Raises
        :class:`~dolfinx_lopinf.errors.FileFormatError` naming the file and the entry when it is
        not such a file (a bare ROM, an unknown scheme, a non-finite basis, a bad time step)."""
        rom, extras = load_rom(path)
        missing = [k for k in ("fit_scheme", "fit_dt") if k not in rom.meta]
        if "basis_rows" not in extras or missing:
            raise FileFormatError(f"{path}: a ROM without the basis, scheme and time step of lo.fit "
                                  f"(missing: {['basis_rows'] * ('basis_rows' not in extras) + missing}); "
                                  "load it with lo.core.rom.load_rom")
        try:
            scheme = schemes.from_spec(rom.meta["fit_scheme"])
        except InputError as exc:
            raise FileFormatError(f"{path}: entry fit_scheme: {exc}") from None
        V = extras["basis_rows"]
        if V.ndim != 2 or V.shape[1] != rom.r or not np.all(np.isfinite(V)):
            raise FileFormatError(f"{path}: the stored basis must be a finite (n, {rom.r}) array, "
                                  f"got shape {V.shape}" + ("" if np.all(np.isfinite(V))
                                                            else " with NaN or inf"))
        dt = rom.meta["fit_dt"]
        if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not (np.isfinite(dt) and dt > 0):
            raise FileFormatError(f"{path}: entry fit_dt must be a positive number, got {dt!r}")
        dual = extras.get("basis_dual")
        if dual is not None and (dual.shape != V.shape or not np.all(np.isfinite(dual))):
            raise FileFormatError(f"{path}: entry basis_dual must be a finite {V.shape} array, got "
                                  f"shape {dual.shape}")
        return cls(rom, Basis(V, {}, {}, dual=dual), scheme, float(dt), rom.meta.get("fit_report", {}))


def _whole_steps(t_end, dt) -> int:
    """t_end / dt as a whole number of steps, or an InputError saying it is not one."""
    try:
        t = float(t_end)
    except (TypeError, ValueError):
        raise InputError(f"t_end must be a number, got {t_end!r}") from None
    n = t / dt
    if not np.isfinite(n) or n < 0.5 or abs(n - round(n)) > 1e-6 * max(n, 1.0):
        raise InputError(f"t_end = {t_end!r} is not a whole number (>= 1) of steps dt = {dt:.6g} "
                         f"({n:.6g} steps); pass n_steps, or t_end = k * dt")
    return int(round(n))


def _trajectories(snapshots) -> list[Snapshots]:
    if snapshots is None:
        raise InputError("fit got None instead of snapshots (SnapshotRecorder.snapshots() returns "
                         "the data on rank 0 only: fit there)")
    if hasattr(snapshots, "snapshots") and hasattr(snapshots, "record"):
        raise InputError("fit got the SnapshotRecorder itself; pass its data: lo.fit(rec.snapshots(), r)")
    trajs = [snapshots] if isinstance(snapshots, Snapshots) else list(snapshots)
    if not trajs:
        raise InputError("fit needs at least one Snapshots")
    for i, s in enumerate(trajs):
        if not isinstance(s, Snapshots):
            raise InputError(f"snapshots[{i}] is a {type(s).__name__}, not a Snapshots (record it "
                             "with lo.SnapshotRecorder or build lo.Snapshots(times, Q, ...))")
    first = trajs[0]
    for i, s in enumerate(trajs[1:], start=1):
        if s.n_states != first.n_states:
            raise InputError(f"snapshots[{i}] has {s.n_states} state rows, snapshots[0] has "
                             f"{first.n_states}: all trajectories must be of the same system")
        if abs(s.dt - first.dt) > 1e-9 * first.dt:
            raise InputError(f"snapshots[{i}] has dt = {s.dt!r}, snapshots[0] dt = {first.dt!r} "
                             f"(relative difference {abs(s.dt - first.dt) / first.dt:.2g}): the "
                             "data relation and the ROM's scheme need one time step")
        if (s.U is None) != (first.U is None) or (s.U is not None and s.U.shape[0] != first.U.shape[0]):
            raise InputError(f"snapshots[{i}] and snapshots[0] differ in their inputs "
                             f"({'none' if s.U is None else s.U.shape[0]} vs "
                             f"{'none' if first.U is None else first.U.shape[0]}): give every "
                             "trajectory the same inputs, or none")
        if (s.Y is None) != (first.Y is None) or (s.Y is not None and s.Y.shape[0] != first.Y.shape[0]):
            raise InputError(f"snapshots[{i}] and snapshots[0] differ in their outputs Y "
                             f"({'none' if s.Y is None else s.Y.shape[0]} vs "
                             f"{'none' if first.Y is None else first.Y.shape[0]} rows)")
    for i, s in enumerate(trajs):  # a Snapshots' arrays can be written to after it was built
        for name in ("Q", "V", "A", "U", "Y"):
            a = getattr(s, name, None)
            if a is not None:
                check_finite(a, f"snapshots[{i}].{name}" if len(trajs) > 1 else f"snapshots.{name}",
                             "a value was changed after the Snapshots were built: clean it or "
                             "record again")
        if s.Y is not None and s.output_times is not None and len(s.output_times) != len(s.times):
            raise InputError(f"snapshots[{i}] records outputs on their own time grid; fit needs "
                             "outputs at the state times (or none)")
    return trajs


def _stacked(parts):
    Qk, Qc, Qm = (np.hstack([p[i] for p in parts]) for i in range(3))
    Uf = None if parts[0][3] is None else np.hstack([p[3] for p in parts])
    return Qk, Qc, Qm, Uf


def _fit_relation(scheme, pieces, damping, eps, ridge, strict, mass="identity", solver="auto",
                  ridge_factor=1.0):
    """L-OpInf on the stacked relation data of several trajectories; a learned mass left
    uncertified at the default ridge raises it, from ``ridge_factor`` on (``raise_ridge`` of
    :func:`~dolfinx_lopinf.core.infer_mechanical`: candidates and final fit alike)."""
    Qk, Qc, Qm, Uf = _stacked([_relation_data(scheme, p) for p in pieces])
    return infer_mechanical(Qk, Qc if damping else None, Qm, Uf, damping=damping, eps=eps,
                            ridge=ridge, strict=strict, mass=mass, solver=solver,
                            _ridge_factor=ridge_factor)


def _relation_data(scheme, piece):
    Qh, times, U, ti, Vh, Ah = piece
    if Vh is not None and Ah is not None and isinstance(scheme, schemes.GeneralizedAlpha):
        return scheme.state_relation(Qh, Vh, Ah, times, U, ti)
    return scheme.relation(Qh, times, U, ti)


def _is_scaled_identity(M, Qh) -> bool:
    """Whether the learned mass is c I in every direction the data see: the eigenvalues of M
    in the metric of the data's covariance spread by less than IDENTITY_SPREAD."""
    W = Qh @ Qh.T
    w, V = np.linalg.eigh(W)
    keep = w > 1e-10 * w[-1]
    Vk = V[:, keep]
    ev = np.linalg.eigvalsh(Vk.T @ M @ Vk)
    return bool(ev[-1] - ev[0] <= IDENTITY_SPREAD * abs(ev.mean()))


def _candidates(relations, masses, dampings):
    """(mass, damping, relation) in the order of simplicity (module docstring)."""
    return [(m, d, rel) for rel in relations for m in masses for d in dampings]


def _compare(pieces, relations, masses, dampings, eps, ridge, holdout, dt):
    """Held-back error of every candidate (module docstring), notes on the failed ones, and
    the ridge factor each learned-mass candidate was certified with (where raised)."""
    try:
        fit_part, held = split(pieces, holdout)
    except InputError as exc:  # name only what is still being chosen
        still = [name for name, options in (("scheme", relations), ("mass", masses),
                                            ("damping", dampings)) if len(options) > 1]
        raise InputError(str(exc).split("; record longer")[0] + "; record longer, or pass "
                         + " and ".join(f"{n}=" for n in still) + " (chosen automatically "
                         "by comparing held-back predictions) to skip the comparison") from None
    backend = compiled.resolve_backend("auto")
    states = np.hstack([p[0] for p in fit_part])

    def evaluate(candidate):
        mass, damping, rel = candidate
        try:  # Mh = I: the interior point without its slow fallbacks (lsq.Auto); a learned
            # mass scored as the final fit returns it - certified with the ridge raised where
            # the first fit is not (an uncertified fit's held-back error is not reproducible)
            ops = _fit_relation(rel, fit_part, damping, eps, ridge, False, mass,
                                lsq.Auto(fallback=False) if mass == "identity" else "auto")
        except (RuntimeError, ValueError, np.linalg.LinAlgError) as exc:
            return float("inf"), str(exc)[:200], 1.0  # a failed candidate loses
        if mass == "learned" and _is_scaled_identity(ops.M, states):
            return float("inf"), "learned Mh = c I: the same model as Mh = I", 1.0
        factor = float(f"{ops.certificate.get('ridge', RIDGE) / RIDGE:.6g}") if ridge is None else 1.0
        return max(prediction_error(ops, schemes.rom_scheme(rel), h, dt, backend) for h in held), None, factor

    order = _candidates(relations, masses, dampings)
    with warnings.catch_warnings():  # the candidates' own warnings are not the user's
        warnings.simplefilter("ignore")
        results = _map(evaluate, order, states.shape[0], cost=_expected_cost)
    errors = {c: e for c, (e, _, _) in zip(order, results)}
    notes = {c: n for c, (_, n, _) in zip(order, results) if n is not None}
    factors = {c: f for c, (_, _, f) in zip(order, results)}
    return errors, notes, factors


def _expected_cost(candidate) -> int:
    """A rank of a candidate's fitting time: learned mass above Mh = I, damped above undamped
    (the learned, damped fits take 3-5x the others at r = 20)."""
    mass, damping, _ = candidate
    return 2 * (mass == "learned") + bool(damping)


def _map(func, items, r, cost=None):
    """[func(x) for x in items], on threads from r = PARALLEL_FROM_R on (:func:`fit_threads`):
    the fits' compiled kernels and LAPACK run without the GIL. The results come in the order of
    ``items`` and each is computed exactly as alone, so the choice does not depend on the
    threads' timing. ``cost``: a key of the expected time - the dearest start first (longest
    processing time first: the threads finish together instead of one waiting out the last
    dear fit)."""
    workers = min(len(items), fit_threads()) if r >= PARALLEL_FROM_R else 1
    if workers <= 1:
        return [func(x) for x in items]
    from concurrent.futures import ThreadPoolExecutor

    start = sorted(range(len(items)), key=lambda i: -cost(items[i])) if cost else range(len(items))
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="lopinf-candidate") as pool:
        futures = {i: pool.submit(func, items[i]) for i in start}
        return [futures[i].result() for i in range(len(items))]


def fit_threads() -> int:
    """Threads for the candidates' fits: the environment's DOLFINX_LOPINF_FIT_THREADS, else
    the cores this process may use, shared among the MPI ranks if mpi4py is running."""
    cores = usable_cores()
    mpi = sys.modules.get("mpi4py.MPI")
    if mpi is not None and mpi.Is_initialized() and not mpi.Is_finalized():
        cores = max(1, cores // mpi.COMM_WORLD.size)
    value = os.environ.get(FIT_THREADS_ENV)
    if value is None or value.strip() == "":
        return cores
    try:
        n = int(value)
    except ValueError:
        n = 0
    if n < 1:
        raise InputError(f"{FIT_THREADS_ENV}={value!r}: give a whole number of threads >= 1 "
                         "(1 fits the candidates one after another)")
    return n


def _preferred(errors, order):
    """The first candidate of ``order`` whose held-back error is within MARGIN of the best."""
    best = min(errors[c] for c in order)
    for cand in order:
        if errors[cand] <= MARGIN * best:
            return cand
    return order[0]


def _damping_candidates(damping):
    if damping == "auto" and isinstance(damping, str):
        return (False, True)
    if damping is True or damping is False or isinstance(damping, np.bool_):
        return (bool(damping),)
    raise InputError(f"damping must be True, False or 'auto', got {damping!r} (a string such as "
                     "'no' or 'False' is not a boolean)")


def _label(mass, damping, rel):
    return f"{mass}/{'damped' if damping else 'undamped'}/{rel.spec}"


@serial_blas  # small kernels: BLAS threads cost more than they give, and far more on a busy machine
def fit(snapshots, r: int, *, scheme=None, damping="auto", mass: str = "auto",
        basis: Basis | None = None, eps: float = 1e-8, ridge: float | None = None,
        strict: bool = False, holdout: float = 0.25) -> ReducedModel:
    """Fit an L-OpInf reduced model to one or several recorded trajectories.

    Args:
        snapshots: a :class:`~dolfinx_lopinf.Snapshots` or a list of them (trajectories with
            different initial conditions or input histories, same system and dt).
        r: reduced dimension (ignored when ``basis`` is given: its r is used).
        scheme: the integrator of the data (module docstring): a
            :mod:`~dolfinx_lopinf.core.schemes` object, a name, or ``"auto"`` (identify it);
            None: the scheme the snapshots were recorded with
            (``SnapshotRecorder(u, scheme=...)``), else ``"auto"``.
        damping: ``"auto"`` (default: Ch >= eps I or none, chosen on the held-back end),
            True or False (conservative: no Ch).
        mass: ``"auto"`` (default), ``"identity"`` (Mh = I: exact in a mass-orthonormal
            basis) or ``"learned"`` (Mh fitted too, SPD, coordinate-invariant:
            :mod:`dolfinx_lopinf.core.mass`; our own certified interior point, no extra needed).
        basis: a :class:`~dolfinx_lopinf.core.basis.Basis` to use; default the POD of all
            trajectories' states: in their inner product when they carry one
            (``Snapshots.weight``: the recorder's L2 Gram matrix, or a mass matrix - the
            Galerkin projection, much closer to the projection floor than the Euclidean
            POD), block-diagonal (Euclidean) when the snapshots name blocks, else Euclidean.
        eps, ridge, strict: as in :func:`~dolfinx_lopinf.core.infer_mechanical`.
        holdout: the fraction of every trajectory held back to choose the model.

    Returns:
        :class:`ReducedModel`; ``model.report`` says what was chosen and why.

    Example:
        >>> t = np.arange(0, 400) * 0.01
        >>> Q = np.vstack([np.cos(t), np.sin(t), np.cos(2 * t)])   # three coordinates
        >>> model = fit(Snapshots(t, Q), 3, damping=False)
        >>> model.scheme == "newmark"
        True
    """
    if mass not in MASS_MODELS:
        raise InputError(f"mass must be one of {MASS_MODELS}, got {mass!r}")
    if basis is None:  # r = 2.5, "4", True or 0 were a raw TypeError, r = 1 or a data error
        r = check_int(r, "r (the reduced dimension)", 1)
    dampings = _damping_candidates(damping)
    trajs = _trajectories(snapshots)
    requested = _requested_scheme(trajs, scheme)
    if not (isinstance(holdout, float) and 0.05 <= holdout <= 0.5):
        raise InputError(f"holdout must be a fraction in [0.05, 0.5], got {holdout!r}")
    dt = trajs[0].dt
    Q_all = np.hstack([s.Q for s in trajs])
    # the snapshots' inner product (none for blocks: each block keeps its own Euclidean POD;
    # with a basis given it serves only the identification's coordinates: Euclidean there
    # when the trajectories carry different ones)
    weight = None if trajs[0].blocks else common_weight(trajs, required=basis is None)
    # one (leading) SVD: the basis and the identification
    svd = _leading_modes(Q_all, r if basis is None else basis.r, weight)
    if basis is None:
        basis = pod(Q_all, r, blocks=trajs[0].blocks) if trajs[0].blocks \
            else from_svd(*svd, r, weight=weight)
        kind = ("block POD" if trajs[0].blocks else
                "POD in the snapshots' inner product" if weight is not None else "POD")
    elif not isinstance(basis, Basis) or basis.n != trajs[0].n_states:
        raise InputError(f"basis must be a Basis with {trajs[0].n_states} rows")
    else:
        kind = "given"
    pieces = _pieces(trajs, basis.projector())  # a loaded basis projects with its stored W V
    report = {"trajectories": len(trajs), "samples": [len(s.times) for s in trajs], "r": basis.r,
              "dt": dt, "basis": kind,
              # the basis' own error on its training states: the held-back errors that choose
              # the model are in reduced coordinates and do not see it (a wave at r = 4:
              # held-back 3.6 %, this 54 %)
              "projection_error": basis.projection_error(Q_all),
              "requested_scheme": requested if isinstance(requested, str) else requested.spec}
    relation, report["identification"] = _relation_for(requested, *_identification_pieces(
        trajs, svd, basis.r, weight))
    relations = [relation]
    if requested == "auto":
        # a refined scheme competes with the standard member nearest to it in the residual
        # (listed first: kept unless the refinement predicts clearly better - a closure-biased
        # refinement costs more at large r than the parameters it moved) and with differences
        # (on loads that cannot tell the schemes apart, the most standard member the residual
        # allows takes that place: _relation_for)
        standard = report["identification"].get("conservative_member") or \
            report["identification"].get("best_member")
        if standard is not None and standard != relation.spec:
            relations.insert(0, schemes.from_spec(standard))
        if not isinstance(relation, schemes.FiniteDifferences):
            relations.append(schemes.FiniteDifferences())
    masses = _mass_candidates(mass)
    order = _candidates(relations, masses, dampings)
    if len(order) > 1:
        errors, notes, factors = _compare(pieces, relations, masses, dampings, eps, ridge, holdout, dt)
        # the most standard scheme (on loads that cannot tell the schemes apart) against the
        # other schemes: kept unless one predicts REFINEMENT_GAIN better; differences compete
        # with it as with any relation (MARGIN, after it in the order)
        conservative = report["identification"].get("conservative_member")
        own = [c for c in order if c[2].spec == conservative]
        rivals = [c for c in order if c not in own and not isinstance(c[2], schemes.FiniteDifferences)]
        others = min((errors[c] for c in rivals), default=np.inf)
        kept = bool(own) and min(errors[c] for c in own) <= REFINEMENT_GAIN * others
        pool = [c for c in order if c not in rivals] if kept else order
        chosen = _preferred(errors, pool)
        report["candidate_errors"] = {_label(*c): e for c, e in errors.items()}
        if notes:
            report["candidate_notes"] = {_label(*c): n for c, n in notes.items()}
        report["why"] = (f"held-back prediction error {errors[chosen]:.3g} ({_label(*chosen)}); "
                         f"the simplest candidate within {MARGIN:g}x of the best "
                         f"({min(errors[c] for c in pool):.3g}) is kept")
        if kept:
            report["why"] += (f"; the most standard scheme the data allow ({conservative}), "
                              f"unless another predicts {REFINEMENT_GAIN:g}x better (best other "
                              f"{others:.3g}): the loads do not show where the loop samples them")
        unscored = not np.isfinite(min(errors.values()))  # every candidate failed: the final
        # fit below raises the reason (a warning about "the chosen model" first misled)
        if not errors[chosen] <= HELD_BACK_WARN and not unscored:
            _warn_poor_prediction(errors[chosen], _label(*chosen), len(order), holdout)
    else:
        chosen, factors, unscored = order[0], {}, False
        report["why"] = "mass, damping and scheme given: nothing to compare"
    mass, damping, relation = chosen
    relation = _with_recorded_kinematics(relation, pieces, report, explicit=requested != "auto")
    # the recipe that was scored: a learned mass certified with a raised ridge is refitted
    # from that ridge on (a first fit at the default ridge would stall again, at a full fit's cost)
    try:
        ops = _fit_relation(relation, pieces, damping, eps, ridge, strict, mass,
                            ridge_factor=factors.get(chosen, 1.0))
    except RankDeficientDataError as exc:
        if "'U[" not in str(exc):
            raise
        raise RankDeficientDataError(
            f"{exc}. Loads that are zero throughout (an unforced run recorded with "
            "inputs=[0.0]) cannot show how the loads enter: fit such a trajectory together "
            "with forced ones, or record it without inputs") from None
    if unscored:
        _warn_poor_prediction(float("inf"), _label(*chosen), len(order), holdout)
    E = None
    if trajs[0].Y is not None:
        E = infer_output(np.hstack([p[0] for p in pieces]), np.hstack([s.Y for s in trajs]))
    rom_scheme = schemes.rom_scheme(relation)
    report.update(scheme=relation.spec, rom_scheme=rom_scheme.spec, mass=mass, damping=damping,
                  certificate={k: v for k, v in ops.certificate.items()
                               if isinstance(v, (int, float, str, bool))})
    rom = LagrangianROM(K=ops.K, M=ops.M, C=ops.C, B=ops.B, E=E, scheme=rom_scheme,
                        meta={"method": "lopinf", "fit_scheme": relation.spec})
    return ReducedModel(rom, basis, relation, dt, report)


def _warn_poor_prediction(error, label, n_candidates, holdout) -> None:
    warn(f"lo.fit: the chosen model ({label}) predicts the held-back end of the training data "
         f"with relative error {error:.3g} (the best of {n_candidates} candidates: "
         "model.report['candidate_errors']), so the choice between them and the accuracy on "
         "new loads are in doubt. Usual causes: r too small for the dynamics (raise r); "
         "snapshots that are not consecutive steps of the loop (record every step); loads "
         "recorded at other times than the loop applied them (record the applied value, with "
         "input_time=); inputs that are not forces (a prescribed displacement: record the "
         "force it exerts instead); nonlinear dynamics; a record too short for its first "
         f"{1 - holdout:.0%} to determine the operators (record longer, or choose with "
         "mass= and damping=)", PoorPredictionWarning)


def _pieces(trajs, P, weight=None):
    """[(P Q, times, U, input_times, P V, P A)] per trajectory (P: (r, n) projection)."""
    def project(a):
        return None if a is None else P @ (a if weight is None else weight @ a)

    return [(project(s.Q), s.times, s.U, s.input_times, project(s.V), project(s.A)) for s in trajs]


def _leading_modes(Q, r, weight=None):
    """(U, s) of the snapshots: the leading max(r, ID_MAX_R) + LEADING_EXTRA singular
    triplets (:func:`~dolfinx_lopinf.core.basis.leading_svd`) when the data are at least
    LEADING_FROM times wider than that, else the full thin SVD; in the ``weight`` inner
    product when given (U W-orthonormal). Everything lo.fit decides (the rank check of r, the
    identification's coordinates) uses only these."""
    k = max(int(r), ID_MAX_R) + LEADING_EXTRA
    if min(Q.shape) >= LEADING_FROM * k:
        return leading_svd(Q, k, weight=weight)
    if weight is not None:
        return weighted_svd(Q, weight)
    return np.linalg.svd(Q, full_matrices=False)[:2]


def _identification_pieces(trajs, svd, r, weight=None):
    """(pieces, check_r): the trajectories in the leading POD coordinates the scheme is
    identified in - as many as the data resolve (singular values above ID_RANK_RTOL of the
    largest), so the truncated modes' closure error does not blur which relation holds, and
    at most ID_MAX_R and as many as keep ID_SAMPLES_PER_UNKNOWN samples per unknown of the
    free fit (2r + m per row) - and the number of them the held-back check uses (its free
    fit sees three quarters of the samples)."""
    U, s = svd
    n_sig = int((s > ID_RANK_RTOL * s[0]).sum()) if s[0] > 0 else 1
    m = 0 if trajs[0].U is None else trajs[0].U.shape[0]
    n_all = sum(len(t.times) for t in trajs)

    def cap(n):
        return max(1, min(ID_MAX_R, int((n / ID_SAMPLES_PER_UNKNOWN - m) / 2)))

    r_id = max(1, min(max(n_sig, min(r, cap(n_all))), cap(n_all), len(s)))
    return _pieces(trajs, U[:, :r_id].T, weight), min(r_id, cap(0.75 * n_all / 2))


def _relation_for(requested, pieces, check_r):
    """(the relation to fit, the identification report) for ``requested`` ("auto" or a scheme)."""
    if requested == "auto":
        members = standard_members() + [schemes.FiniteDifferences()]
        scheme, ident = identify(pieces, members=members, check_r=check_r)
        ident["coordinates"] = [int(pieces[0][0].shape[0]), int(check_r)]
        res = ident["residuals"]
        floor = max(min(res.values()), RESIDUAL_FLOOR)
        if scheme not in members:  # a refinement: the standard member nearest to it in the
            # residual (the first one within CLEAR_GAIN of the best came out as hht(0.15) on a
            # new user's generalised-alpha loop, 1.496x above the loop's own member: a choice
            # on the last digits, and a model 1,000x worse on an unseen load)
            ident["best_member"] = min(members, key=lambda m: res[m.spec]).spec
        if ident.get("loads") in ("none", "linear") and floor <= CLOSURE_LEVEL \
                and not isinstance(scheme, schemes.FiniteDifferences):
            # loads linear between bends (or none) do not show where a loop samples them, and
            # in the identification's coordinates the truncated modes' closure error can favour
            # a dissipative member over the loop's own (an average-acceleration loop of 1,575
            # dofs came out as generalised-alpha near alpha_m = alpha_f = 1/2, 190x worse on an
            # unseen smooth load): when a member's relation holds to the closure level, the
            # most standard member the residual cannot rule out (within SHORTLIST of the best)
            # is a candidate too, and the one kept unless another scheme predicts the held-back
            # end REFINEMENT_GAIN better (as in the identification: there the refinement
            # predicted 2-5x better in-sample at r = 12-20 and an unseen smooth load 1,400x
            # worse). Data no member's relation holds for (sub-sampled, nonlinear) and
            # differences are left as identified
            # at the best residual of its class: members the data cannot tell apart differ
            # only by closure (in a mass-orthonormal basis central differences came out 57x
            # below the loop's own Newmark(1/4), and linear acceleration was kept)
            by_member = {m: res[m.spec] for m in members}
            first = next(m for m in members
                         if _class_best(m, by_member, ident["loads"]) <= SHORTLIST * floor)
            if first != scheme:
                ident["conservative_member"] = first.spec
        return scheme, ident
    residual = Residual(pieces)
    try:
        named = residual(requested)
    except (ValueError, np.linalg.LinAlgError):
        named = float("inf")
    best, grid = identify(pieces, members=standard_members() + [schemes.FiniteDifferences()],
                          refine=False)
    grid = {best: grid["residual"]}
    ident = {"named": requested.spec, "residual": named, "best_member": best.spec,
             "best_residual": grid[best]}
    # only a relation that holds to the data's rounding contradicts the named one: where the
    # best holds to the truncated modes' closure only, another member can absorb that closure
    # better than the loop's own (exact Newmark recordings of a cantilever: 1.2e-7 named
    # against 1.8e-8 for a generalised-alpha member, whose model predicted an unseen load 15x
    # worse; a 13-sample record: 7.9e-3 against 2.0e-3 for continuous())
    if named > MISMATCH * grid[best] and named > MISMATCH_FLOOR and grid[best] <= RESIDUAL_FLOOR:
        warn(
            f"scheme={requested.spec}: the data obey its relation with relative residual "
            f"{named:.3g}, but {best.spec}'s with {grid[best]:.3g}: the data do not look like "
            f"a {requested.spec} loop; consider scheme={best.spec!r} or scheme='auto'",
            SchemeMismatchWarning)
    elif named > MISMATCH * grid[best] and named > MISMATCH_FLOOR \
            and not _equivalent(requested, best, _load_kind(pieces)):
        # truncated data (the best relation holds to the closure level only): the held-back
        # predictions of the two relations' free fits judge, at a factor closure does not
        # reach (a wrong member predicted in-sample 2-5x better at most on the identification's
        # data; a new user's generalised-alpha loop named Newmark: 1.7e-6 against 6.1e-8 in
        # the residual, a model 1e5 times worse on an unseen load, and no warning)
        e = held_back_errors(leading(pieces, check_r), [requested, best], HOLDOUT_CHECK)
        if e and e[requested] > PREDICTION_MISMATCH * max(e[best], PREDICTION_FLOOR):
            ident["held_back"] = {requested.spec: e[requested], best.spec: e[best]}
            warn(
                f"scheme={requested.spec}: its relation's free fit predicts the held-back end "
                f"of the data with relative error {e[requested]:.3g}, {best.spec}'s with "
                f"{e[best]:.3g} (relation residuals {named:.3g} and {grid[best]:.3g}): the data "
                f"do not look like a {requested.spec} loop. Check the scheme, and that the loads "
                f"were recorded when the loop applied them (input_time=); or pass "
                f"scheme={best.spec!r} or scheme='auto'", SchemeMismatchWarning)
    if pieces and pieces[0][2] is not None and np.isfinite(named):
        shift, shifted = _load_shift(requested, pieces, named)
        if shifted * LOAD_SHIFT_GAIN <= named and named > MISMATCH_FLOOR:
            ident["load_shift"] = {"steps": shift, "residual": shifted}
            af = getattr(requested, "alpha_f", 0.0)
            hint = (" - alpha_f dt: the applied value recorded without input_time=t - "
                    "alpha_f*dt?" if af > 0 and abs(shift + af) <= 0.02 else "")
            warn(
                f"scheme={requested.spec}: the data obey its relation {named / shifted:.3g}x "
                f"better (relative residual {shifted:.3g} against {named:.3g}) with the "
                f"recorded input times moved by {shift:+g} step(s){hint}: either the load values "
                f"act {abs(shift):g} step(s) {'later' if shift > 0 else 'earlier'} than the "
                "times they were recorded with (record the value the loop applied, with "
                "input_time= the time it acts at), or the snapshots are not consecutive steps "
                "of the loop (record every step)", SchemeMismatchWarning)
    return requested, ident


#: the load-time shifts (in steps) tried on a named scheme's relation (:func:`_load_shift`):
#: fractions of a step (a forgotten input_time= of a generalised-alpha loop is alpha_f dt)
#: and whole steps (a load recorded one step late)
LOAD_SHIFTS = (-5, -4, -3, -2, -1.5, -1, -0.75, -0.5, -0.25, 0.25, 0.5, 0.75, 1, 1.5, 2, 3, 4, 5)
#: a shift that makes the named relation hold this many times better is a timing error
LOAD_SHIFT_GAIN = 10.0


def _load_shift(scheme, pieces, named):
    """(shift, residual): the load-time shift among LOAD_SHIFTS (steps; the recorded input
    times moved by shift dt) with the least relation residual of ``scheme``. On a new user's generalised-alpha loop the
    residual 1.6e-7 fell to 5e-9 at +1 step for a load recorded one step late, at -5 for five
    steps, near -alpha_f for a forgotten input_time=; on correct recordings of the 14 held-out
    loops the best shift gains at most 2.1x (5.3x where the loads were recorded at the state
    times of an HHT loop). A gain of 3x is refined between the neighbouring shifts (bounded
    Brent: the residual is V-shaped in the shift, not parabolic)."""
    dt = float(np.mean(np.diff(pieces[0][1])))

    def residual(s):
        moved = [(p[0], p[1], p[2], (p[1] if p[3] is None else p[3]) + s * dt) + tuple(p[4:])
                 for p in pieces]
        try:
            return Residual(moved)(scheme)
        except (ValueError, np.linalg.LinAlgError, InputError):
            return float("inf")

    values = {s: residual(s) for s in LOAD_SHIFTS}
    values[0.0] = named
    best = min(values, key=values.get)
    if best != 0.0 and values[best] * 3.0 <= named:  # refine between the neighbours
        grid = sorted(values)
        i = grid.index(best)
        a, c = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
        sol = scipy.optimize.minimize_scalar(residual, bounds=(a, c), method="bounded",
                                             options={"xatol": 0.01})
        if sol.fun < values[best]:
            best = round(float(sol.x), 2)
            values[best] = float(sol.fun)
    return float(best), float(values[best])


#: recorded (u, v, a) whose Newmark updates hold to this (relative) fix beta and gamma
KINEMATICS_TOL = 1e-8


def _recorded_kinematics(pieces):
    """(beta, gamma, residual): the Newmark updates

        u_{n+1} = u_n + dt v_n + dt^2 ((1/2 - beta) a_n + beta a_{n+1}),
        v_{n+1} = v_n + dt ((1 - gamma) a_n + gamma a_{n+1}),

    fitted by least squares to the recorded (u, v, a) of every trajectory (exact in any
    linear projection of them), the residual the larger relative one; None without them."""
    du, eu, dv, ev, su, sv = [], [], [], [], [], []
    for Qh, times, _, _, Vh, Ah in pieces:
        if Vh is None or Ah is None or Qh.shape[1] < 3:
            return None
        dt = float(np.mean(np.diff(times)))
        da = Ah[:, 1:] - Ah[:, :-1]
        du.append((Qh[:, 1:] - Qh[:, :-1] - dt * Vh[:, :-1] - 0.5 * dt**2 * Ah[:, :-1]).ravel())
        eu.append((dt**2 * da).ravel())
        dv.append((Vh[:, 1:] - Vh[:, :-1] - dt * Ah[:, :-1]).ravel())
        ev.append((dt * da).ravel())
        su.append((Qh[:, 1:] - Qh[:, :-1]).ravel())
        sv.append((Vh[:, 1:] - Vh[:, :-1]).ravel())
    du, eu, dv, ev, su, sv = (np.concatenate(x) for x in (du, eu, dv, ev, su, sv))
    if not (eu @ eu > 0 and ev @ ev > 0):
        return None
    beta, gamma = float(du @ eu / (eu @ eu)), float(dv @ ev / (ev @ ev))
    tiny = np.finfo(float).tiny
    res = max(np.linalg.norm(du - beta * eu) / max(np.linalg.norm(su), tiny),
              np.linalg.norm(dv - gamma * ev) / max(np.linalg.norm(sv), tiny))
    return _simple(beta), _simple(gamma), float(res)


def _simple(x: float) -> float:
    """x as the nearest fraction with a denominator up to 12 where within 1e-9 of it."""
    for den in range(1, 13):
        k = round(x * den)
        if abs(x - k / den) <= 1e-9:
            return k / den
    return x


def _with_recorded_kinematics(relation, pieces, report, explicit: bool):
    """A Newmark-family relation with the beta, gamma that the recorded (u, v, a) obey (their
    updates hold to KINEMATICS_TOL): on (u, v, a) the balance alone is fitted, which holds no
    beta, gamma, so an explicit central-difference loop and average acceleration fit alike and
    the ROM's stepping came from the first of them in the list. A named scheme is kept, with a
    SchemeMismatchWarning when its beta, gamma contradict the records."""
    if not isinstance(relation, schemes.GeneralizedAlpha):
        return relation
    kin = _recorded_kinematics(pieces)
    if kin is None or not kin[2] <= KINEMATICS_TOL:
        return relation
    beta, gamma, res = kin
    report["identification"]["kinematics"] = {"beta": beta, "gamma": gamma, "residual": res}
    if abs(beta - relation.beta) <= 1e-9 and abs(gamma - relation.gamma) <= 1e-9:
        return relation
    am, af = relation.alpha_m, relation.alpha_f
    if am == 0.0 and af == 0.0:
        found = schemes.CentralDifference() if (beta, gamma) == (0.0, 0.5) else schemes.Newmark(beta, gamma)
    else:
        found = schemes.GeneralizedAlpha(am, af, beta, gamma)
    if explicit:
        warn(f"scheme={relation.spec}: the recorded velocities and accelerations follow the "
             f"Newmark updates with beta={beta:g}, gamma={gamma:g} (to {res:.1g}), not the named "
             f"scheme's beta={relation.beta:g}, gamma={relation.gamma:g}; consider "
             f"scheme={found.spec!r}", SchemeMismatchWarning)
        return relation
    note = (f"{relation.spec} -> {found.spec}: the recorded (u, v, a) obey the Newmark updates "
            f"with beta={beta:g}, gamma={gamma:g} to {res:.1g} (the balance fitted on them holds "
            "no beta, gamma)")
    report["identification"]["why_kinematics"] = note
    report["why"] = f"{report.get('why', '')}; {note}".lstrip("; ")
    return found


def _requested_scheme(trajs, scheme):
    """``"auto"`` or a Scheme: ``scheme``, or (None) the one the trajectories were recorded
    with, else ``"auto"``; a named InputError for mixed recordings or an unknown name."""
    if scheme is None:
        recorded = {getattr(s, "scheme", None) for s in trajs}
        if len(recorded) > 1:
            raise InputError(f"the trajectories were recorded with different schemes "
                             f"{sorted(map(str, recorded))}; pass scheme= explicitly")
        scheme = recorded.pop() or "auto"
    if isinstance(scheme, str) and scheme.strip().lower() == "auto":
        return "auto"
    return check_scheme(scheme, "scheme")
