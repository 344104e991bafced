"""Parametric L-OpInf: one reduced model for a family of designs (numpy only).

The full-order operators depend on parameters mu (p numbers) affinely,

    M(mu) = sum_i theta^M_i(mu) M_i,   C(mu) = sum_i theta^C_i(mu) C_i,
    K(mu) = sum_i theta^K_i(mu) K_i,   B(mu) = sum_i theta^B_i(mu) B_i,

with coefficients theta that are monomials of the parameters (``theta = E * zeta``, ``mu``,
``1``) - the terms :mod:`dolfinx_lopinf.fem.affine` reads from a UFL Lagrangian, or an
:class:`AffineStructure` written by hand. Every M_i, C_i, K_i of a mechanical system is
symmetric positive semidefinite (a kinetic energy, a dissipation, a strain energy).

The fit. From trajectories at training parameters mu_j (several per parameter allowed, each
with its own inputs), in one basis, the data relation of the integrator that produced them
(:meth:`dolfinx_lopinf.core.schemes.Scheme.relation`: M Qm + C Qc + K Qk = B Uf column by
column) becomes, with the operators expanded,

    Qm + sum_i Kh_i (theta^K_i(mu_j) Qk) + sum_i Ch_i (theta^C_i(mu_j) Qc)
       + sum_{i > 0} Mh_i (theta^M_i(mu_j) Qm) - sum_i Bh_i (theta^B_i(mu_j) Uf)  ~  0,

linear in all the reduced operators at once: one least-squares problem whose unknown
Theta = [Kh_1 .. Kh_a, Ch_1 .. Ch_c, Mh_1 .. Mh_d, -Bh_1 .. -Bh_f] has a + c + d symmetric
blocks constrained >= eps I and f m free columns - the certified engine's
:class:`~dolfinx_lopinf.core.lsq.Problem` with more PSD blocks (one QR compression of all
trajectories, then the interior point with its duality gap). The parameter-free mass term is
fixed to Mh_0 = I: exact in a basis orthonormal in M_0 (the mass-weighted POD); further mass
terms are learned as PSD blocks. Each coefficient is scaled by its largest training value
inside the fit (so E ~ 1e5 and zeta ~ 1 give blocks of one size), and undone afterwards.

The certificate. For every mu in the cone {mu : theta_i(mu) >= 0 for every term}, not only
at the training parameters,

    Kh(mu) = sum_i theta^K_i(mu) Kh_i >= eps (sum_i theta^K_i(mu)) I,   Ch(mu) >= 0,
    Mh(mu) = I + sum_i theta^M_i(mu) Mh_i >= I,

so the reduced model is the Euler-Lagrange equation of a Lagrangian with a non-negative
dissipation at every such mu, and the ROM stepped with an energy-stable scheme of the
Newmark family (average acceleration, generalised-alpha) or the midpoint rule keeps its
energy 1/2 v^T Mh v + 1/2 q^T Kh q non-increasing (unforced): stable at every parameter of
the cone. Outside it :meth:`ParametricModel.predict` refuses (or, asked to, checks the
operators at that mu alone).

The closure. A truncated basis leaks energy into the modes it drops; in a conservative
system's ROM that shows as a phase and amplitude error that grows with time. ``damping=
"closure"`` adds a PSD damping term for every stiffness monomial (Ch(mu) = sum theta_i Ch_i:
a Rayleigh dissipation, so the certificate and its cone are unchanged); ``"auto"`` keeps it
only when it predicts the training trajectories' held-back ends clearly better
(:func:`fit_affine`). The report says which was chosen.

Online cost. Kh(mu) is a sum of (r, r) matrices: forming the ROM at a new mu costs
O(terms r^2) and its steps cost what a fixed-parameter ROM's cost - independent of n.
"""

from __future__ import annotations

import itertools
import json
import time
from dataclasses import dataclass, field, replace

import numpy as np

from . import schemes
from ._checks import as_real_array, check_positive
from .basis import Basis, pod
from ._blas import serial_blas
from ._checks import pow2_scale
from .gram import RIDGE, MechanicalOperators, compress, psd_floor
from .rom import LagrangianROM, Trajectory
from .snapshots import Snapshots, check_scheme, common_weight
from . import lsq
from ..errors import FileFormatError, InputError, ParameterRangeWarning, SolverWarning, warn
from .io_atomic import atomic_savez_compressed, open_npz, plain

#: the operators of M a + C v + K u = B f that an affine structure lists terms of
OPERATORS = ("mass", "damping", "stiffness", "inputs")
#: ... and the symbols used in reports
SYMBOLS = {"mass": "M", "damping": "C", "stiffness": "K", "inputs": "B"}


def _monomial(term, parameters, where) -> tuple:
    """A term as a sorted tuple of parameter names (a name may repeat: mu^2 = (mu, mu))."""
    if isinstance(term, str):
        term = () if term.strip() in ("", "1") else tuple(t.strip() for t in term.split("*"))
    try:
        names = tuple(sorted(str(t) for t in term))
    except TypeError:
        raise InputError(f"{where}: a term must be a tuple of parameter names or a text such "
                         f"as 'E*zeta' or '1', got {term!r}") from None
    unknown = [t for t in names if t not in parameters]
    if unknown:
        raise InputError(f"{where}: term {'*'.join(names) or '1'} names {unknown}, which is not "
                         f"a parameter ({', '.join(parameters) or 'none'})")
    return names


def label(term: tuple) -> str:
    """``"E*zeta"`` for ("E", "zeta"), ``"1"`` for ()."""
    return "*".join(term) if term else "1"


@dataclass(frozen=True)
class AffineStructure:
    """Which affine terms each operator has: M(mu) = sum theta_i(mu) M_i, and likewise C, K
    and B (module docstring), theta_i a monomial of the parameters.

    Attributes:
        parameters: the parameter names, in the order of mu.
        mass, damping, stiffness, inputs: the terms of each operator, each a tuple of
            parameter names (its monomial: ``()`` is 1, ``("E", "zeta")`` is E * zeta) - or
            the text ``"E*zeta"``. ``mass`` must contain the parameter-free term ``()``
            (Mh_0 = I); ``damping`` and ``inputs`` may be empty (none).

    Example:
        >>> s = AffineStructure(("mu",), mass=[()], stiffness=["1", "mu"], inputs=["1"])
        >>> s.theta("stiffness", [2.5]).tolist()
        [1.0, 2.5]
    """

    parameters: tuple
    mass: tuple = ((),)
    damping: tuple = ()
    stiffness: tuple = ((),)
    inputs: tuple = ()

    def __post_init__(self):
        params = self.parameters
        if isinstance(params, str):
            params = (params,)
        params = tuple(str(p) for p in params)
        if len(set(params)) != len(params):
            raise InputError(f"parameters must be distinct names, got {params}")
        object.__setattr__(self, "parameters", params)
        for op in OPERATORS:
            value = getattr(self, op)
            terms = [] if value is None else list([value] if isinstance(value, str) else value)
            mono = tuple(_monomial(t, params, f"{op} terms") for t in terms)
            if len(set(mono)) != len(mono):
                raise InputError(f"{op} lists a term twice: {[label(t) for t in mono]}")
            object.__setattr__(self, op, mono)
        if () not in self.mass:
            raise InputError(
                f"the mass has no parameter-free term (terms {[label(t) for t in self.mass]}): "
                "the fit fixes that term to Mh_0 = I; write the density as a fixed number (or "
                "divide the Lagrangian by the parameter that scales it)")
        if not self.stiffness:
            raise InputError("the structure has no stiffness term")

    @property
    def p(self) -> int:
        return len(self.parameters)

    def check_mu(self, mu, name: str = "mu") -> np.ndarray:
        """mu as a (p,) float array: a number (p = 1), a sequence or a dict name -> value;
        an InputError naming what is wrong otherwise."""
        if isinstance(mu, dict):
            missing = [k for k in self.parameters if k not in mu]
            extra = [k for k in mu if k not in self.parameters]
            if missing or extra:
                raise InputError(f"{name} = {mu!r}: " + "; ".join(
                    ([f"missing {missing}"] if missing else []) + ([f"unknown {extra}"] if extra else []))
                    + f" (the parameters are {list(self.parameters)})")
            mu = [mu[k] for k in self.parameters]
        a = as_real_array(mu, name).reshape(-1)
        if a.shape != (self.p,):
            raise InputError(f"{name} = {mu!r} has {a.size} value(s); this model has {self.p} "
                             f"parameter(s) {list(self.parameters)}")
        if not np.all(np.isfinite(a)):
            raise InputError(f"{name} = {mu!r} is not finite")
        return a

    def theta(self, op: str, mu) -> np.ndarray:
        """(terms,) the coefficients theta_i(mu) of operator ``op``."""
        mu = self.check_mu(mu)
        index = {k: i for i, k in enumerate(self.parameters)}
        return np.array([np.prod([mu[index[k]] for k in t]) if t else 1.0
                         for t in getattr(self, op)], dtype=float)

    def cone_violations(self, mu) -> list:
        """[(operator, term, theta)] of the terms with theta_i(mu) < 0 (empty: mu in the cone)."""
        return [(op, label(t), float(v)) for op in ("mass", "damping", "stiffness")
                for t, v in zip(getattr(self, op), self.theta(op, mu)) if v < 0]

    @property
    def cone(self) -> str:
        """The cone where the certificate holds, in words."""
        terms = {t for op in ("mass", "damping", "stiffness") for t in getattr(self, op) if t}
        singles = {t[0] for t in terms if len(t) == 1}
        # a product of parameters each >= 0 (one term each) is >= 0: not listed again
        conds = sorted(label(t) for t in terms if len(t) == 1 or not set(t) <= singles)
        return ("every mu" if not conds else " and ".join(f"{c} >= 0" for c in conds))

    def describe(self) -> str:
        """The affine terms, one line per operator: ``K(mu) = 1 * K_1 + mu * K_mu``."""
        lines = []
        for op in OPERATORS:
            terms = getattr(self, op)
            s = SYMBOLS[op]
            lines.append(f"{s}(mu) = " + (" + ".join(f"{label(t)} * {s}[{label(t)}]" for t in terms)
                                          if terms else "0 (none)"))
        return "\n".join(lines)

    def as_dict(self) -> dict:
        return {"parameters": list(self.parameters),
                **{op: [label(t) for t in getattr(self, op)] for op in OPERATORS}}

    @classmethod
    def from_dict(cls, d: dict) -> "AffineStructure":
        return cls(tuple(d["parameters"]), **{op: d.get(op, ()) for op in OPERATORS})


# -- training data ---------------------------------------------------------------------------
def _training(data, structure: AffineStructure | None, p: int | None = None):
    """[(mu (p,), Snapshots)] from ``data``: a list of (mu, Snapshots) pairs (several per mu
    allowed) or a dict mu -> Snapshots / list of Snapshots; the named checks."""
    if isinstance(data, dict):
        pairs = [(mu, s) for mu, ss in data.items()
                 for s in ([ss] if isinstance(ss, Snapshots) else ss)]
    else:
        try:
            pairs = [tuple(item) for item in data]
        except TypeError:
            raise InputError("data must be a list of (mu, Snapshots) pairs or a dict mu -> "
                             "Snapshots (or list of them)") from None
    if not pairs:
        raise InputError("data holds no trajectories")
    out = []
    for i, pair in enumerate(pairs):
        if len(pair) != 2 or not isinstance(pair[1], Snapshots):
            raise InputError(f"data[{i}] must be a pair (mu, Snapshots), got "
                             f"{type(pair).__name__} of {len(pair)} item(s)")
        mu = structure.check_mu(pair[0], f"the parameter of data[{i}]") if structure is not None \
            else as_real_array(pair[0], f"the parameter of data[{i}]").reshape(-1)
        out.append((mu, pair[1]))
    p = out[0][0].size if p is None else p
    first = out[0][1]
    for i, (mu, s) in enumerate(out):
        if mu.size != p:
            raise InputError(f"the parameter of data[{i}] has {mu.size} value(s), data[0]'s "
                             f"{p}: one parameter vector per trajectory, all of one length")
        if s.n_states != first.n_states:
            raise InputError(f"data[{i}] (mu = {mu.tolist()}) has {s.n_states} state rows, "
                             f"data[0] {first.n_states}: one system, one mesh")
        if abs(s.dt - first.dt) > 1e-9 * first.dt:
            raise InputError(f"data[{i}] (mu = {mu.tolist()}) has dt = {s.dt!r}, data[0] "
                             f"(mu = {out[0][0].tolist()}) dt = {first.dt!r}: the data relation "
                             "and the ROM's scheme need one time step for every parameter")
        if (s.U is None) != (first.U is None) or (s.U is not None and s.U.shape[0] != first.U.shape[0]):
            raise InputError(f"data[{i}] (mu = {mu.tolist()}) and data[0] differ in their inputs "
                             f"({'none' if s.U is None else s.U.shape[0]} vs "
                             f"{'none' if first.U is None else first.U.shape[0]} channels)")
    return out


def _scheme_of(pairs, scheme):
    if scheme is None:
        found = {s.scheme for _, s in pairs}
        if len(found) != 1 or None in found:
            raise InputError("pass scheme= (the integrator of the data; the trajectories do not "
                             "all carry the same recorded scheme)")
        return found.pop()
    return check_scheme(scheme, "scheme")


def _basis(pairs, r, basis, weight):
    if basis is not None:
        if not isinstance(basis, Basis) or basis.n != pairs[0][1].n_states:
            raise InputError(f"basis must be a Basis with {pairs[0][1].n_states} rows")
        return basis
    if r is None:
        raise InputError("give r (the reduced dimension) or a basis")
    if weight is None:  # the inner product the snapshots carry (lo.parametric.simulate's M_0)
        weight = common_weight([s for _, s in pairs])
    return pod(np.hstack([s.Q for _, s in pairs]), r, weight=weight)


def projector(basis: Basis) -> np.ndarray:
    """(r, n) P with P q = V^T W q (W the basis' weight, I when None; a loaded basis' stored
    W V), formed once."""
    return basis.projector()


def _relations(pairs, P, scheme):
    """Per trajectory: (mu, Qk, Qc, Qm, Uf) of the scheme's relation in reduced coordinates."""
    out = []
    for mu, s in pairs:
        Qk, Qc, Qm, Uf = scheme.relation(P @ s.Q, s.times, s.U, s.input_times)
        out.append((mu, Qk, Qc, Qm, Uf))
    return out


# -- the model -------------------------------------------------------------------------------
@dataclass(frozen=True)
class ParametricModel:
    """A reduced model for every parameter of the cone: operators(mu) = sum theta_i(mu) Op_i.

    Attributes:
        structure: the :class:`AffineStructure` (parameters and terms).
        terms: operator name -> list of (r, r) (or (r, m) for ``inputs``) matrices, one per
            term of the structure (``mass``: the terms other than the parameter-free one,
            whose matrix is I).
        basis: the reduced basis (``basis.V``: (n, r)).
        scheme: the data relation fitted (the ROM steps :func:`schemes.rom_scheme` of it).
        dt: the training time step.
        mu_train: (n_train, p) the training parameters (the range a prediction is inside).
        report: how the fit went: certificate, cone, fit seconds, data sizes.
    """

    structure: AffineStructure
    terms: dict
    basis: Basis
    scheme: schemes.Scheme
    dt: float
    mu_train: np.ndarray
    report: dict = field(default_factory=dict)

    @property
    def r(self) -> int:
        return self.basis.r

    def operators(self, mu):
        """(M, C, K, B) at mu: sums of (r, r) terms (M None when it is I, C / B None when the
        structure has none)."""
        s = self.structure

        def combine(op, first=None):
            mats = self.terms.get(op, [])
            if not mats:
                return first
            theta = s.theta(op, mu)
            out = sum(t * A for t, A in zip(theta, mats))
            return out if first is None else first + out

        M = None
        if len(s.mass) > 1:
            theta = s.theta("mass", mu)
            M = np.eye(self.r) + sum(t * A for t, A, term in zip(theta, self._mass_full(), s.mass) if term)
        return M, combine("damping"), combine("stiffness"), combine("inputs")

    def _mass_full(self):
        """The mass terms aligned with structure.mass (I for the parameter-free one)."""
        it = iter(self.terms.get("mass", []))
        return [np.eye(self.r) if not t else next(it) for t in self.structure.mass]

    def check_parameter(self, mu, outside_cone: str = "error") -> np.ndarray:
        """mu checked: its length, inside the certified cone (``outside_cone="check"``:
        outside it, the operators at mu checked instead), inside the training range (a
        :class:`~dolfinx_lopinf.errors.ParameterRangeWarning` when not)."""
        s = self.structure
        mu = s.check_mu(mu)
        if outside_cone not in ("error", "check"):
            raise InputError(f"outside_cone must be 'error' or 'check', got {outside_cone!r}")
        bad = s.cone_violations(mu)
        if bad:
            where = ", ".join(f"theta_{SYMBOLS[op]}[{t}] = {v:.4g}" for op, t, v in bad)
            if outside_cone == "error":
                raise InputError(
                    f"mu = {dict(zip(s.parameters, mu.tolist()))} is outside the cone "
                    f"{s.cone} where the stability certificate holds ({where} < 0: a sum of "
                    "PSD terms with a negative weight need not be PSD); pass "
                    "outside_cone='check' to predict there after checking the operators at "
                    "this mu alone")
            self._check_at(mu)
        lo, hi = self.mu_train.min(axis=0), self.mu_train.max(axis=0)
        out = (mu < lo) | (mu > hi)
        if out.any():
            names = [f"{n} = {v:.4g} (trained on [{a:.4g}, {b:.4g}])"
                     for n, v, a, b, o in zip(s.parameters, mu, lo, hi, out) if o]
            warn(f"predicting outside the training range: {', '.join(names)}; stability is "
                 f"certified in the cone {s.cone}, accuracy is not", ParameterRangeWarning)
        return mu

    def _check_at(self, mu):
        M, C, K, _ = self.operators(mu)
        problems = []
        for name, A, strict in (("K", K, True), ("C", C, False), ("M", M, True)):
            if A is None:
                continue
            w = np.linalg.eigvalsh(0.5 * (A + A.T))
            if w[0] < 0 or (strict and w[0] == 0):
                problems.append(f"{name}h(mu) has eigenvalue {w[0]:.4g}")
        if problems:
            raise InputError(f"mu = {mu.tolist()} is outside the certified cone and there "
                             + "; ".join(problems) + ": the ROM is not stable at this mu")

    def rom(self, mu, *, outside_cone: str = "error") -> LagrangianROM:
        """The fixed-parameter ROM at mu (checked as :meth:`check_parameter`)."""
        mu = self.check_parameter(mu, outside_cone)
        M, C, K, B = self.operators(mu)
        return LagrangianROM(K=K, M=M, C=C, B=B, scheme=schemes.rom_scheme(self.scheme),
                             meta={"method": self.report.get("method", "parametric-lopinf"),
                                   "mu": mu.tolist()})

    def predict(self, mu, n_steps: int | None = None, *, t_end: float | None = None, q0=None,
                v0=None, inputs=None, dt: float | None = None, every: int = 1,
                backend: str = "auto", outside_cone: str = "error") -> Trajectory:
        """Integrate the ROM at parameter ``mu`` with the scheme of the data from (q0, v0)
        (full or reduced states; rest by default); ``inputs`` as in
        :meth:`dolfinx_lopinf.core.rom.LagrangianROM.simulate`."""
        rom = self.rom(mu, outside_cone=outside_cone)
        return _run(rom, self.basis, self.dt if dt is None else dt, n_steps, t_end, q0, v0, inputs,
                    every, backend)

    def reconstruct(self, Qh, rows=None) -> np.ndarray:
        return self.basis.reconstruct(Qh, rows=rows)

    def save(self, path):
        """One ``.npz``, written atomically: the structure, every term, the basis (V, and the
        W V that projects full states when the basis is weighted), the scheme, dt, the
        training parameters and the report. :meth:`load` reads it with numpy alone. Returns
        the path written (``.npz`` appended unless ``path`` ends in it)."""
        b = self.basis
        arrays = {"parametric_structure": np.array(json.dumps(self.structure.as_dict())),
                  "scheme": np.array(self.scheme.spec), "dt": np.array(float(self.dt)),
                  "mu_train": np.asarray(self.mu_train, dtype=float), "V": b.V,
                  "report": np.array(json.dumps(plain(self.report)))}
        dual = b.saved_dual()
        if dual is not None:
            arrays["dual"] = dual
        for op in OPERATORS:
            for i, A in enumerate(self.terms.get(op, [])):
                arrays[f"term__{op}__{i}"] = np.asarray(A, dtype=float)
        return atomic_savez_compressed(path, **arrays)

    @classmethod
    def load(cls, path) -> "ParametricModel":
        """Read a file written by :meth:`save`. Raises
        :class:`~dolfinx_lopinf.errors.FileFormatError` naming the file when it is not such a
        file (another kind of file, missing or damaged entries, terms that do not fit the
        structure), and ``FileNotFoundError`` when it does not exist."""
        with open_npz(path, "parametric model (ParametricModel.save)") as (data, read):
            missing = [k for k in ("parametric_structure", "scheme", "dt", "mu_train", "V")
                       if k not in data.files]
            if missing:
                raise FileFormatError(f"{path}: lacks {missing} (entries found: "
                                      f"{sorted(data.files)}); not a file written by "
                                      "ParametricModel.save (a lo.fit model? use "
                                      "lo.ReducedModel.load)")
            entries = {k: read(k) for k in data.files}
        try:
            structure = AffineStructure.from_dict(json.loads(str(entries["parametric_structure"])))
            report = json.loads(str(entries["report"])) if "report" in entries else {}
            V = entries["V"]
            dual = entries.get("dual")
            if V.ndim != 2 or not np.all(np.isfinite(V)) or (
                    dual is not None and (dual.shape != V.shape or not np.all(np.isfinite(dual)))):
                raise InputError(f"the basis V {V.shape} (and its W V) must be a finite (n, r) "
                                 "array")
            basis = Basis(V, {}, {"all": (np.arange(V.shape[0]), np.arange(V.shape[1]))},
                          None, dual)
            terms = {op: [entries[k] for k in sorted(
                (k for k in entries if k.startswith(f"term__{op}__")),
                key=lambda k: int(k.rsplit("__", 1)[1]))] for op in OPERATORS}
            for op, mats in terms.items():
                for A in mats:
                    if A.ndim != 2 or A.shape[0] != V.shape[1] or not np.all(np.isfinite(A)):
                        raise InputError(f"a {op} term of shape {A.shape} does not fit r = "
                                         f"{V.shape[1]} (or is not finite)")
            dt = float(entries["dt"])
            if not (np.isfinite(dt) and dt > 0):
                raise InputError(f"dt must be a positive number, got {dt}")
            return cls.from_operators(structure, basis, str(entries["scheme"]), dt, terms,
                                      entries["mu_train"], report)
        except (InputError, ValueError, KeyError, TypeError) as exc:
            raise FileFormatError(f"{path}: the stored parametric model is invalid: {exc}") from None

    @classmethod
    def from_operators(cls, structure, basis, scheme, dt, terms: dict, mu_train=None,
                       report=None) -> "ParametricModel":
        """A model from given terms (e.g. the intrusive Galerkin projections V^T K_i V)."""
        s = structure
        for op in OPERATORS:
            want = len(getattr(s, op)) - (1 if op == "mass" else 0)
            if len(terms.get(op, [])) != want:
                raise InputError(f"terms[{op!r}] must hold {want} matrices (the structure's "
                                 f"{op} terms{' other than 1' if op == 'mass' else ''})")
        mu_train = np.zeros((1, s.p)) if mu_train is None else np.atleast_2d(mu_train)
        return cls(s, {op: [np.asarray(A, float) for A in terms.get(op, [])] for op in OPERATORS},
                   basis, check_scheme(scheme), float(dt), mu_train, dict(report or {}))


def _run(rom, basis, dt, n_steps, t_end, q0, v0, inputs, every, backend):
    dt = check_positive(dt, "dt")
    if (n_steps is None) == (t_end is None):
        raise InputError("give exactly one of n_steps and t_end")
    if n_steps is None:
        n = float(t_end) / dt
        if abs(n - round(n)) > 1e-6 * max(n, 1.0) or round(n) < 1:
            raise InputError(f"t_end = {t_end!r} is not a whole number of steps dt = {dt:.6g}")
        n_steps = int(round(n))

    def reduced(x, name):
        if x is None:
            return np.zeros(basis.r)
        x = as_real_array(x, name)
        if x.shape == (basis.r,):
            return x
        if x.shape == (basis.n,):
            return basis.project(x)
        raise InputError(f"{name} must be a reduced ({basis.r},) or a full ({basis.n},) state, "
                         f"got shape {x.shape}")

    return rom.simulate(reduced(q0, "q0"), reduced(v0, "v0"), dt, n_steps, inputs=inputs,
                        every=every, backend=backend)


# -- the fit ---------------------------------------------------------------------------------
@serial_blas
def _solve(relations, structure, eps, ridge, strict, solver, quiet=False):
    """The joint fit on the relation data (module docstring): (terms, certificate)."""
    s = structure
    r = relations[0][1].shape[0]
    m = 0 if relations[0][4] is None else relations[0][4].shape[0]
    mus = np.array([rel[0] for rel in relations])
    blocks = ([("stiffness", t, 1) for t in s.stiffness] + [("damping", t, 2) for t in s.damping]
              + [("mass", t, 3) for t in s.mass if t])
    free = [("inputs", t, 4) for t in s.inputs] if m else []
    if s.inputs and not m:
        raise InputError(f"the structure has input terms {[label(t) for t in s.inputs]} but the "
                         "trajectories carry no inputs U")
    if m and not s.inputs:
        raise InputError("the trajectories carry inputs U but the structure has no input term")
    # theta of every term at every trajectory, scaled by its largest training value
    scale = {}
    for op, t, _ in blocks + free:
        th = np.array([s.theta(op, mu)[getattr(s, op).index(t)] for mu in mus])
        top = float(np.max(np.abs(th)))
        if top == 0:
            raise InputError(f"the term {label(t)} of {SYMBOLS[op]} is zero at every training "
                             f"parameter: the data cannot determine {SYMBOLS[op]}[{label(t)}]; "
                             "train at parameters where it acts")
        scale[(op, t)] = (th / top, top)
    Qm_all = [rel[3] for rel in relations]
    c_state = pow2_scale(*Qm_all, *[rel[1] for rel in relations])
    c_input = pow2_scale(*[rel[4] for rel in relations]) if m else 1.0
    rows, names = [], []
    for op, t, k in blocks + free:
        w, _ = scale[(op, t)]
        data = [rel[k] / (c_input if op == "inputs" else c_state) for rel in relations]
        rows.append(np.hstack([wj * d for wj, d in zip(w, data)]))
        sym = SYMBOLS[op]
        names += [f"{sym}[{label(t)}]*row{i}" for i in range(rows[-1].shape[0])]
    target = np.hstack(Qm_all) / c_state
    L, Z, cond, rank, _ = compress(rows, target, names, ridge, strict,
                                    "[theta Qk; theta Qc; theta Qm; theta U]")
    problem = lsq.Problem(L, Z, len(blocks), eps, len(free) * m)
    t0 = time.perf_counter()
    theta, cert = (solver or lsq.Auto()).solve(problem)
    solve_seconds = time.perf_counter() - t0
    nb = len(blocks)
    S = np.stack([theta[:, i * r:(i + 1) * r] for i in range(nb)])
    S = psd_floor(S, eps)
    theta = np.hstack(list(S) + [theta[:, nb * r:]])
    D = np.vstack(rows)
    resid = float(np.linalg.norm(theta @ D + target) / max(np.linalg.norm(target), 1e-300))
    terms = {op: [] for op in OPERATORS}
    for i, (op, t, _) in enumerate(blocks):
        terms[op].append(S[i] / scale[(op, t)][1])
    for j, (op, t, _) in enumerate(free):
        Bj = -theta[:, nb * r + j * m: nb * r + (j + 1) * m]
        terms[op].append(Bj * (c_state / c_input) / scale[(op, t)][1])
    certificate = {k: v for k, v in cert.as_dict().items() if isinstance(v, (int, float, str, bool))}
    certificate.update(problem.kkt(theta))
    certificate.update(solver=cert.solver, converged=bool(cert.converged),
                       solve_seconds=solve_seconds, relative_residual=resid, data_rank=rank,
                       data_rows=int(L.shape[0]), data_condition=cond, eps=eps,
                       psd_blocks=nb, free_columns=len(free) * m,
                       min_eig={f"{SYMBOLS[op]}[{label(t)}]": float(np.linalg.eigvalsh(S[i])[0]
                                                                  / scale[(op, t)][1])
                                for i, (op, t, _) in enumerate(blocks)})
    if not cert.converged and not quiet:
        warn(f"{cert.solver} stopped without meeting its tolerance (duality gap "
             f"{cert.duality_gap}); see the certificate", SolverWarning)
    return terms, certificate


#: damping= choices of :func:`fit_affine`
DAMPING = ("structure", "closure", "auto")
#: with damping="auto" the closure damping is kept only when its worst held-back error is below
#: CLOSURE_GAIN times the structure's (a richer model must earn its place)
CLOSURE_GAIN = 0.98


def with_closure(structure: AffineStructure) -> AffineStructure:
    """The structure plus a damping term for every stiffness monomial it lacks: Ch(mu) >= 0
    for the energy the truncated modes carry away (a Rayleigh dissipation, certificate and
    cone unchanged)."""
    extra = [t for t in structure.stiffness if t not in structure.damping]
    return AffineStructure(structure.parameters, mass=structure.mass,
                           damping=tuple(structure.damping) + tuple(extra),
                           stiffness=structure.stiffness, inputs=structure.inputs)


def _held_back_choice(pairs, scheme, structure, eps, ridge, solver, holdout):
    """{"structure": worst held-back error, "closure": ...} (module docstring of fit_affine)."""
    from . import compiled
    from .holdout import prediction_error, split
    backend = compiled.resolve_backend("auto")

    pieces = [(s.Q, s.times, s.U, s.input_times, None, None) for _, s in pairs]
    fit_part, _ = split(pieces, holdout)
    # each candidate runs every whole trajectory from its first samples (the scheme's
    # recurrence, no velocities needed): the error a prediction from the start makes, over
    # the fitted part and on into the held-back end
    held = [(s.Q, s.times, s.U, s.input_times) for _, s in pairs]
    errors = {}
    for name, st in (("structure", structure), ("closure", with_closure(structure))):
        rels = [(mu,) + tuple(scheme.relation(Qh, t, U, ti)) for (mu, _), (Qh, t, U, ti, _, _)
                in zip(pairs, fit_part)]
        try:
            terms, _ = _solve(rels, st, eps, ridge, False, solver, quiet=True)
        except (InputError, np.linalg.LinAlgError, ValueError):
            errors[name] = float("inf")
            continue
        model = ParametricModel(st, terms, Basis(np.eye(pieces[0][0].shape[0]), {}, {}), scheme, 1.0,
                                np.zeros((1, st.p)))
        worst = 0.0
        for (mu, s), h in zip(pairs, held):
            M, C, K, B = model.operators(mu)
            worst = max(worst, prediction_error(MechanicalOperators(K, C, B, M=M), scheme, h,
                                                s.dt, backend))
        errors[name] = worst
    return errors


def fit_affine(data, structure: AffineStructure, r: int | None = None, *,
               basis: Basis | None = None, weight=None, scheme=None, damping: str = "auto",
               eps: float = 1e-8, ridge: float = RIDGE, strict: bool = False, solver=None,
               holdout: float = 0.25) -> ParametricModel:
    """Parametric L-OpInf: every affine term fitted jointly, each symmetric PSD (module
    docstring), one convex problem on the certified engine.

    Args:
        data: a list of (mu, :class:`~dolfinx_lopinf.Snapshots`) pairs - several per
            parameter allowed, each with its own inputs - or a dict mu -> Snapshots / list.
            One state dimension, one dt, the same number of inputs for all.
        structure: the :class:`AffineStructure` (from the UFL forms:
            ``ParametricSystem.structure``).
        r, basis, weight: the reduced basis: ``basis``, or the POD of all trajectories with r
            vectors (``weight``: the inner product, e.g. the parameter-free mass matrix - then
            Mh_0 = I is exact; default the one the snapshots carry, ``Snapshots.weight``,
            which :func:`dolfinx_lopinf.parametric.simulate` records, else Euclidean).
        scheme: the integrator of the data (a :mod:`~dolfinx_lopinf.core.schemes` object or
            name); None: the one the snapshots carry.
        damping: ``"structure"`` - the damping terms of the structure (none for a
            conservative system); ``"closure"`` - plus a PSD damping term for each stiffness
            monomial (:func:`with_closure`): a truncated basis leaks energy to the modes it
            drops, a Rayleigh dissipation models that and keeps the certificate;
            ``"auto"`` (default) - both fitted on the first ``1 - holdout`` of every
            trajectory, each then predicts every whole trajectory from its first samples
            (the scheme's recurrence, on into the held-back end); the closure is kept when
            its worst relative error is below CLOSURE_GAIN times the other's.
        eps: every PSD block is >= eps I (in the units of the scaled coefficient).
        ridge, strict: as in :func:`~dolfinx_lopinf.infer_mechanical`.
        solver: a :mod:`~dolfinx_lopinf.core.lsq` strategy (default ``lsq.Auto()``).

    Returns:
        :class:`ParametricModel`; ``report["certificate"]`` holds the duality gap and the
        cone where stability is certified, ``report["fit_seconds"]`` the time from the
        reduced data to the operators, wall clock (``fit_cpu_seconds``: the process's CPU
        time, which a shared machine disturbs less; ``choice_seconds``: the held-back choice,
        ``project_seconds``: projecting the snapshots).
    """
    if not isinstance(structure, AffineStructure):
        raise InputError(f"structure must be an AffineStructure, got {type(structure).__name__}")
    if not (np.isfinite(eps) and eps >= 0):
        raise InputError(f"eps must be a finite number >= 0, got {eps!r}")
    if damping not in DAMPING:
        raise InputError(f"damping must be one of {DAMPING}, got {damping!r}")
    pairs = _training(data, structure)
    scheme = _scheme_of(pairs, scheme)
    outside = [mu.tolist() for mu, _ in pairs if structure.cone_violations(mu)]
    if outside:
        warn(f"training parameters {outside} lie outside the cone {structure.cone} where the "
             "certificate holds: the model fits them but will predict there only with "
             "outside_cone='check'", ParameterRangeWarning)
    t0 = time.perf_counter()
    basis_given = basis is not None
    basis = _basis(pairs, r, basis, weight)
    t1 = time.perf_counter()
    P = projector(basis)
    reduced = [(mu, replace(s, Q=P @ s.Q, V=None, A=None, weight=None)) for mu, s in pairs]
    t2 = time.perf_counter()
    choice = None
    if damping == "auto" and with_closure(structure) != structure:
        choice = _held_back_choice(reduced, scheme, structure, eps, ridge, solver, holdout)
        damping = "closure" if choice["closure"] < CLOSURE_GAIN * choice["structure"] else "structure"
    fitted = with_closure(structure) if damping == "closure" else structure
    t3, c3 = time.perf_counter(), time.process_time()
    relations = _relations(reduced, np.eye(basis.r), scheme)
    terms, cert = _solve(relations, fitted, eps, ridge, strict, solver)
    t4, c4 = time.perf_counter(), time.process_time()
    mus = np.array([mu for mu, _ in pairs])
    cert["stable_for"] = (f"every mu with {fitted.cone} (not only the {len(np.unique(mus, axis=0))}"
                          " training parameters): Kh(mu) = sum theta_i Kh_i, each Kh_i >= eps I"
                          + (", Ch_i >= eps I" if fitted.damping else "")
                          + (", Mh_i >= eps I" if len(fitted.mass) > 1 else "")
                          + f"; the ROM steps {schemes.rom_scheme(scheme).spec}")
    cert["cone"] = fitted.cone
    report = {"method": "parametric-lopinf", "structure": fitted.as_dict(),
              "damping": damping, "held_back_errors": choice,
              "trajectories": len(pairs), "parameters_trained": len(np.unique(mus, axis=0)),
              "samples": int(sum(len(s.times) for _, s in pairs)), "r": basis.r,
              "basis": ("given" if basis_given else "POD in the snapshots' inner product"
                        if basis.weight is not None else "POD"),
              "mass": ("Mh = I (parameter-free mass; exact in a basis orthonormal in it"
                       + ("" if basis.weight is not None or basis_given else
                          " - this Euclidean POD is not: record the snapshots with their mass "
                          "(lo.parametric.simulate does) or pass weight=") + ")"
                       if len(fitted.mass) == 1 else
                       "Mh(mu) = I + sum theta_i Mh_i, Mh_i learned PSD"),
              "certificate": cert, "basis_seconds": t1 - t0, "project_seconds": t2 - t1,
              "choice_seconds": t3 - t2, "fit_seconds": t4 - t3, "fit_cpu_seconds": c4 - c3,
              "scheme": scheme.spec}
    return ParametricModel(fitted, terms, basis, scheme, pairs[0][1].dt, mus, report)


# -- intrusive ------------------------------------------------------------------------------
def intrusive(structure: AffineStructure, full_terms: dict, basis: Basis, scheme, dt,
              mu_train=None) -> ParametricModel:
    """The intrusive parametric Galerkin ROM: every term projected, Op_i -> V^T Op_i V
    (inputs V^T B_i). ``full_terms``: operator -> list of full (n, n) / (n, m) arrays (or
    objects with ``@``) aligned with the structure's terms (the mass list includes the
    parameter-free term, whose projection must be I: the basis orthonormal in it)."""
    V = basis.V
    terms = {}
    for op in OPERATORS:
        mats = list(full_terms.get(op, []))
        if len(mats) != len(getattr(structure, op)):
            raise InputError(f"full_terms[{op!r}] must hold one matrix per {op} term "
                             f"({len(getattr(structure, op))})")
        red = [V.T @ A if op == "inputs" else V.T @ (A @ V) for A in mats]
        if op == "mass":
            M0 = red[structure.mass.index(())]
            dev = float(np.abs(M0 - np.eye(basis.r)).max())
            if dev > 1e-8:
                raise InputError(f"the basis is not orthonormal in the parameter-free mass "
                                 f"(max |V^T M_0 V - I| = {dev:.3g}); build it with weight=M_0")
            red = [A for A, t in zip(red, structure.mass) if t]
        terms[op] = [0.5 * (A + A.T) if op != "inputs" else A for A in red]
    return ParametricModel.from_operators(structure, basis, scheme, dt, terms, mu_train,
                                          {"method": "intrusive"})


def sample_design(bounds, n: int, seed: int = 0) -> np.ndarray:
    """n parameter points spread over the box ``bounds`` [(lo, hi)] * p: the corners first
    (for p <= 3), then a seeded Latin hypercube - a small training design."""
    bounds = np.asarray(bounds, dtype=float).reshape(-1, 2)
    p = len(bounds)
    pts = []
    if p <= 3:
        pts = [list(c) for c in itertools.product(*[(a, b) for a, b in bounds])][:n]
    rng = np.random.default_rng(seed)
    k = n - len(pts)
    if k > 0:
        u = (np.argsort(rng.random((p, k)), axis=1).T + rng.random((k, p))) / k
        pts += list(bounds[:, 0] + u * (bounds[:, 1] - bounds[:, 0]))
    return np.array(pts, dtype=float)
