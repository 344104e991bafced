"""The one-call pipeline: snapshots -> basis -> the data relation of the user's integrator ->
L-OpInf -> a reduced model that carries its basis, scheme and operators (numpy only).

    model = lo.fit(snapshots, r=4)                  # or a list of Snapshots (trajectories)
    traj = model.predict(n_steps=2000, inputs=u)    # from rest, or q0=/v0= full or reduced
    tip = traj.Y;  field = model.reconstruct(traj.Qh, rows=...)

Which data relation. A time loop's snapshots obey the relation of its integrator exactly,
and L-OpInf fitted to that relation identifies the operators of the *discrete* dynamics:

* ``"newmark"`` - average-acceleration Newmark (gamma = 1/2, beta = 1/4), which for a linear
  system is also the midpoint variational integrator; three-point relation
  D2 + Ch D1 + Kh Qbar = Bh Ubar (:func:`dolfinx_lopinf.core.ddt.newmark_data`); ROM: Newmark.
* ``"midpoint"`` - the same relation, the ROM integrated with the midpoint rule (inputs at
  the step midpoints), as our own FOM does.
* ``"continuous"`` - 8th-order finite differences (any integrator, an O((dt omega)^2) bias for
  modes the step does not resolve); ROM: Newmark at the data's dt.
* ``"auto"`` - each candidate is fitted on the first ``1 - holdout`` of every trajectory and
  predicts the held-back end by the Newmark recurrence its ROM runs, started from the two
  states there (relative error, the worst trajectory counts). ``model.report["why"]`` and
  ``["candidate_errors"]`` say what was compared.

Which reduced mass (``mass=``): Mh = I, or Mh learned (:mod:`dolfinx_lopinf.core.mass`), or
``"auto"`` (default): the candidates (mass model x relation) are compared on the held-back
end as above, and the simplest one - in the order Mh = I before learned, Newmark before
differences - whose error is within ``MARGIN`` = 1.5 of the best is kept. A near-tie (which
rounding or another BLAS could flip) is thus decided by that order, never by the last bits;
a learned mass must earn its place by a clear margin. An explicit scheme whose held-back
error is 3x worse than another relation's gets a warning naming both (the data contradict
the claim).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from . import ddt
from .basis import Basis, pod
from ..errors import InputError, LOpInfWarning
from .inference import RIDGE, infer_mechanical, infer_output
from .io_atomic import plain
from .rom import LagrangianROM, Trajectory, load_rom, save_rom
from .snapshots import Snapshots

SCHEMES = ("auto", "newmark", "midpoint", "continuous")
MASS_MODELS = ("auto", "identity", "learned")
_CANDIDATES = ("newmark", "continuous")  # "midpoint" has the same data relation as "newmark"
#: (mass model, relation) from the simplest: Mh = I before a learned Mh (an SDP, which can
#: switch modes off), the exact relation of the variational integrators before differences.
_PREFERENCE = (("identity", "newmark"), ("identity", "continuous"),
               ("learned", "newmark"), ("learned", "continuous"))
#: The first candidate of :data:`_PREFERENCE` whose held-back error is within this factor
#: of the best one wins.
MARGIN = 1.5


def _mass_candidates(mass):
    """The mass models ``mass`` allows; "auto" without cvxpy (the SDP's solver) is Mh = I."""
    if mass != "auto":
        return (mass,)
    try:
        import cvxpy  # noqa: F401
    except ImportError:
        return ("identity",)
    return ("identity", "learned")


class SchemeMismatchWarning(LOpInfWarning):
    """The scheme the caller named fits the data clearly worse than another relation."""


@dataclass(frozen=True)
class ReducedModel:
    """A fitted L-OpInf model with its basis: predict, reconstruct, save/load.

    Attributes:
        rom: the reduced operators (:class:`~dolfinx_lopinf.core.rom.LagrangianROM`).
        basis: the POD basis (``basis.V``: (n, r)).
        scheme: the data relation fitted (``"newmark"``, ``"midpoint"``, ``"continuous"``).
        dt: the time step of the snapshots (the ROM's default step).
        report: how the fit went - chosen scheme and held-back errors per candidate,
            the solver certificate, data sizes.
    """

    rom: LagrangianROM
    basis: Basis
    scheme: str
    dt: float
    report: dict = field(default_factory=dict)

    @property
    def r(self) -> int:
        return self.rom.r

    def _reduced(self, x, name):
        if x is None:
            return np.zeros(self.r)
        x = np.asarray(x, dtype=float)
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
            n_steps or t_end: how far (one of the two).
            inputs: for a forced model, u(t) -> (m,) or an (m, n_steps + 1) array (Newmark:
                at t_0 .. t_n; midpoint: (m, n_steps) at the step midpoints).
            dt: time step (default: the snapshots' dt); every: keep every ``every``-th step.
            backend: the time loop, as in :meth:`~dolfinx_lopinf.core.rom.LagrangianROM.simulate`
                (``"auto"``: compiled when numba is installed, else numpy).
        """
        dt = self.dt if dt is None else dt
        if (n_steps is None) == (t_end is None):
            raise InputError("give exactly one of n_steps and t_end")
        if n_steps is None:
            n_steps = int(round(t_end / dt))
        return self.rom.simulate(self._reduced(q0, "q0"), self._reduced(v0, "v0"), dt, n_steps,
                                 inputs=inputs, every=every, backend=backend)

    def reconstruct(self, Qh: np.ndarray, rows=None) -> np.ndarray:
        """Full states V Qh, or only the given ``rows`` (partial reconstruction)."""
        return self.basis.reconstruct(Qh, rows=rows)

    def save(self, path):
        """One ``.npz`` (operators, basis, scheme, report); returns the path written."""
        meta = dict(self.rom.meta, fit_scheme=self.scheme, fit_dt=self.dt,
                    fit_report=plain(self.report))
        rom = LagrangianROM(K=self.rom.K, M=self.rom.M, C=self.rom.C, B=self.rom.B, E=self.rom.E,
                            meta=meta, scheme=self.rom.scheme, lagrangian=self.rom.lagrangian)
        return save_rom(path, rom, basis_rows=self.basis.V, rows=np.arange(self.basis.n))

    @classmethod
    def load(cls, path) -> "ReducedModel":
        rom, extras = load_rom(path)
        if "basis_rows" not in extras or "fit_scheme" not in rom.meta:
            raise InputError(f"{path} holds a ROM without the basis and scheme of lo.fit; load it "
                             "with lo.load_rom")
        basis = Basis(extras["basis_rows"], {}, {})
        return cls(rom, basis, rom.meta["fit_scheme"], float(rom.meta["fit_dt"]),
                   rom.meta.get("fit_report", {}))


def _trajectories(snapshots) -> list[Snapshots]:
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
            raise InputError(f"snapshots[{i}] has dt = {s.dt:.6g}, snapshots[0] dt = {first.dt:.6g}:"
                             " the data relation and the ROM's scheme need one time step")
        if (s.U is None) != (first.U is None) or (s.U is not None and s.U.shape[0] != first.U.shape[0]):
            raise InputError(f"snapshots[{i}] and snapshots[0] differ in their inputs "
                             f"({'none' if s.U is None else s.U.shape[0]} vs "
                             f"{'none' if first.U is None else first.U.shape[0]}): give every "
                             "trajectory the same inputs, or none")
        if (s.Y is None) != (first.Y is None):
            raise InputError(f"snapshots[{i}] and snapshots[0] differ in having outputs Y")
    for i, s in enumerate(trajs):
        if s.Y is not None and s.output_times is not None and len(s.output_times) != len(s.times):
            raise InputError(f"snapshots[{i}] records outputs on their own time grid; fit needs "
                             "outputs at the state times (or none)")
    return trajs


def _relation(scheme, Qh, times, U):
    """(states, dQ, ddQ, inputs) of the data relation of ``scheme`` for one trajectory."""
    if scheme == "continuous":
        q, dq, ddq = ddt.derivatives(Qh, times)
        h = ddt.HALF_WIDTH
        return q, dq, ddq, None if U is None else U[:, h:-h]
    Qbar, D1, D2, Ubar = ddt.newmark_data(Qh, times, U)
    return Qbar, D1, D2, Ubar


def _fit_relation(scheme, pieces, damping, eps, ridge, strict, mass="identity"):
    """L-OpInf on the stacked relation data of several trajectories."""
    data = [_relation(scheme, *p) for p in pieces]
    Q, dQ, ddQ = (np.hstack([d[i] for d in data]) for i in range(3))
    U = None if data[0][3] is None else np.hstack([d[3] for d in data])
    return infer_mechanical(Q, dQ if damping else None, ddQ, U, damping=damping, eps=eps,
                            ridge=ridge, strict=strict, mass=mass)


def _recurrence_error(ops, Qh, U, dt):
    """Relative error of the Newmark three-point recurrence of ``ops`` over Qh (r, K), started
    from its first two columns (the prediction the ROM's scheme makes)."""
    r, K = Qh.shape
    I = np.eye(r) if ops.M is None else ops.M
    C = np.zeros((r, r)) if ops.C is None else ops.C
    Ap = I / dt**2 + C / (2 * dt) + ops.K / 4
    A0 = 2 * I / dt**2 - ops.K / 2
    Am = I / dt**2 - C / (2 * dt) + ops.K / 4
    Ubar = None if U is None else (U[:, 2:] + 2 * U[:, 1:-1] + U[:, :-2]) / 4
    forcing = np.zeros((r, K - 2)) if Ubar is None or ops.B is None else ops.B @ Ubar
    Ap_inv = np.linalg.inv(Ap)  # r x r, applied once per step
    pred = np.empty_like(Qh)
    pred[:, :2] = Qh[:, :2]
    for k in range(1, K - 1):
        pred[:, k + 1] = Ap_inv @ (forcing[:, k - 1] + A0 @ pred[:, k] - Am @ pred[:, k - 1])
    scale = np.linalg.norm(Qh[:, 2:])
    err = np.linalg.norm(pred[:, 2:] - Qh[:, 2:]) / max(scale, np.finfo(float).tiny)
    return float(err) if np.isfinite(err) else float("inf")


def _held_back_errors(pieces, damping, eps, ridge, holdout, dt, masses):
    """Held-back prediction error of every (mass model, relation) candidate (module docstring)."""
    fit_part, held = [], []
    for Qh, times, U in pieces:
        K = Qh.shape[1]
        k_cut = int(round((1 - holdout) * K))
        if k_cut < 2 * ddt.HALF_WIDTH + 3 or K - k_cut < 4:
            raise InputError(f"a trajectory of {K} samples is too short to compare schemes on a "
                             f"held-back {holdout:.0%}; record longer or name the scheme")
        fit_part.append((Qh[:, :k_cut], times[:k_cut], None if U is None else U[:, :k_cut]))
        # the held-back end, from the two samples before it so the recurrence starts there
        held.append((Qh[:, k_cut - 2:], None if U is None else U[:, k_cut - 2:]))
    errors = {}
    for mass in masses:
        for scheme in _CANDIDATES:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                try:
                    ops = _fit_relation(scheme, fit_part, damping, eps, ridge, False, mass)
                except (RuntimeError, np.linalg.LinAlgError):  # a failed candidate loses
                    errors[(mass, scheme)] = float("inf")
                    continue
            errors[(mass, scheme)] = max(_recurrence_error(ops, Qh, U, dt) for Qh, U in held)
    return errors


def _preferred(errors, allowed):
    """The first candidate of :data:`_PREFERENCE` among ``allowed`` whose held-back error is
    within :data:`MARGIN` of the smallest: a simpler model is only given up for a clear gain,
    so near-ties (which rounding could flip) are decided by the order, not by the last bits."""
    best = min(errors[c] for c in allowed)
    for cand in _PREFERENCE:
        if cand in allowed and errors[cand] <= MARGIN * best:
            return cand
    return allowed[0]


def fit(snapshots, r: int, *, scheme: str | None = None, damping: bool = True,
        mass: str = "auto", basis: Basis | None = None, eps: float = 1e-8,
        ridge: float = RIDGE, strict: bool = False, holdout: float = 0.25) -> ReducedModel:
    """Fit an L-OpInf reduced model to one or several recorded trajectories.

    Args:
        snapshots: a :class:`~dolfinx_lopinf.Snapshots` or a list of them (trajectories with
            different initial conditions or input histories, same system and dt).
        r: reduced dimension (ignored when ``basis`` is given: its r is used).
        scheme: ``"auto"``, ``"newmark"``, ``"midpoint"`` or ``"continuous"`` (module
            docstring); None: the scheme the snapshots were recorded with
            (``SnapshotRecorder(u, scheme=...)``), else ``"auto"``.
        damping: fit Ch >= eps I (False: conservative, no Ch).
        mass: ``"auto"`` (default), ``"identity"`` or ``"learned"``. ``"identity"``: Mh = I,
            exact in a mass-orthonormal basis, a model-form error in a Euclidean one (what a
            black box has). ``"learned"``: Mh fitted too, SPD, coordinate-invariant
            (:mod:`dolfinx_lopinf.core.mass`; beam block basis r = 20: 1.4e-5 vs 8e-4 with Mh = I),
            but its optimum can switch modes off. ``"auto"``: both, judged with the relations
            on the held-back end (module docstring); Mh = I unless the learned mass predicts
            it at least ``MARGIN`` times better. Without cvxpy, auto is Mh = I.
        basis: a :class:`~dolfinx_lopinf.core.basis.Basis` to use; default the POD of all
            trajectories' states (block-diagonal when the snapshots name blocks).
        eps, ridge, strict: as in :func:`~dolfinx_lopinf.infer_mechanical`.
        holdout: the fraction of every trajectory held back to choose the scheme.

    Returns:
        :class:`ReducedModel`.

    Example:
        >>> t = np.arange(0, 400) * 0.01
        >>> Q = np.vstack([np.cos(t), np.sin(t), np.cos(2 * t)])   # three coordinates
        >>> model = fit(Snapshots(t, Q), 3, damping=False)
        >>> model.scheme in ("newmark", "continuous")
        True
    """
    if mass not in MASS_MODELS:
        raise InputError(f"mass must be one of {MASS_MODELS}, got {mass!r}")
    trajs = _trajectories(snapshots)
    scheme = _requested_scheme(trajs, scheme)
    if not (isinstance(holdout, float) and 0.05 <= holdout <= 0.5):
        raise InputError(f"holdout must be a fraction in [0.05, 0.5], got {holdout!r}")
    dt = trajs[0].dt
    if basis is None:
        Q_all = np.hstack([s.Q for s in trajs])
        basis = pod(Q_all, r, blocks=trajs[0].blocks or None)
    elif not isinstance(basis, Basis) or basis.n != trajs[0].n_states:
        raise InputError(f"basis must be a Basis with {trajs[0].n_states} rows")
    pieces = [(basis.project(s.Q), s.times, s.U) for s in trajs]
    report = {"trajectories": len(trajs), "samples": [len(s.times) for s in trajs], "r": basis.r,
              "dt": dt, "requested_scheme": scheme}
    masses = _mass_candidates(mass)
    errors = _held_back_errors(pieces, damping, eps, ridge, holdout, dt, masses)
    report["candidate_errors"] = {f"{m}/{s}": e for (m, s), e in errors.items()}
    named = "newmark" if scheme == "midpoint" else scheme
    allowed = [c for c in errors if scheme == "auto" or c[1] == named]
    mass_chosen, fitted = _preferred(errors, allowed)
    chosen = fitted if scheme == "auto" else scheme
    # per relation, with the chosen mass model
    report["scheme_errors"] = {s: errors[(mass_chosen, s)] for s in _CANDIDATES}
    report["why"] = (f"held-back prediction error {errors[(mass_chosen, fitted)]:.3g} "
                     f"({mass_chosen} mass, {fitted} relation) vs "
                     + ", ".join(f"{e:.3g} ({m}/{s})" for (m, s), e in errors.items()
                                 if (m, s) != (mass_chosen, fitted))
                     + f"; a simpler candidate is kept unless another is {MARGIN:g}x better")
    if scheme != "auto":
        _warn_if_mismatched(scheme, named, {s: errors[(mass_chosen, s)] for s in _CANDIDATES})
    mass = mass_chosen
    ops = _fit_relation("newmark" if chosen == "midpoint" else chosen, pieces, damping, eps,
                        ridge, strict, mass)
    E = None
    if trajs[0].Y is not None:
        E = infer_output(np.hstack([p[0] for p in pieces]), np.hstack([s.Y for s in trajs]))
    report.update(scheme=chosen, mass=mass, certificate={k: v for k, v in ops.certificate.items()
                                              if isinstance(v, (int, float, str, bool))})
    rom = LagrangianROM(K=ops.K, M=ops.M, C=ops.C, B=ops.B, E=E,
                        scheme="midpoint" if chosen == "midpoint" else "newmark",
                        meta={"method": "lopinf", "fit_scheme": chosen})
    return ReducedModel(rom, basis, chosen, dt, report)


def _requested_scheme(trajs, scheme):
    """The scheme asked for: ``scheme``, or (None) the one the trajectories were recorded
    with, else ``"auto"``; a named InputError for mixed recordings or an unknown name."""
    if scheme is None:
        recorded = {getattr(s, "scheme", None) for s in trajs}
        if len(recorded) > 1:
            raise InputError(f"the trajectories were recorded with different schemes {sorted(map(str, recorded))}"
                             "; pass scheme= explicitly")
        scheme = recorded.pop() or "auto"
    if scheme not in SCHEMES:
        raise InputError(f"scheme must be one of {SCHEMES}, got {scheme!r}")
    return scheme


def _warn_if_mismatched(scheme, named, errors):
    """SchemeMismatchWarning when the requested relation ``named`` predicts the held-back data
    more than 3x worse than the best one (``errors``: relation -> held-back error)."""
    best = min(errors, key=errors.get)
    if errors[named] > 3 * errors[best]:
        warnings.warn(
            f"scheme={scheme!r}: its ROM predicts the held-back data with relative error "
            f"{errors[named]:.3g}, the {best!r} relation's with {errors[best]:.3g} (Newmark ROMs "
            f"at the data's dt): the data do not look like a {scheme!r} loop; consider "
            "scheme='auto'", SchemeMismatchWarning, stacklevel=3)
