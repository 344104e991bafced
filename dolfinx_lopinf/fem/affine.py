"""The affine parameter structure of a UFL Lagrangian, read by UFL algebra.

A parameter is a scalar ``dolfinx.fem.Constant`` of the forms (a Young's modulus, a damping
level, a wave-speed contrast). The system's forms - mass M = d^2 L / dq_t^2, stiffness
K = -d^2 L / dq^2, damping C = d^2 D / dq_t^2 of a Rayleigh dissipation function D(q_t), and
the input forms b_j (virtual work per unit input) - are split into

    F(c_1 .. c_p) = sum_S theta_S(c) F_S,   theta_S = prod_{k in S} c_k,   F_S = d_S F |_{c = 0},

where d_S differentiates once by every parameter of S (UFL: the Constant replaced by a
``ufl.variable``, ``ufl.diff``, derivatives expanded) and |_{c = 0} replaces every parameter
by zero (UFL simplifies the vanishing products away; an empty form is no term). This is
exact when F is affine in each parameter separately (multi-affine: E * zeta is one term);
that is checked: d^2 F / dc_k^2 must be the empty form, else the parameter enters
non-affinely and is named (:class:`~dolfinx_lopinf.errors.NonAffineParameterError`) - or,
with ``affine="auto"``, the system keeps no affine structure and a parametric fit uses the
interpolated model (:mod:`dolfinx_lopinf.core.interpolated`). No coefficient function is
asked of the user: the theta_S are the monomials of the parameters that the algebra finds.
:meth:`ParametricSystem.check_split` assembles F at random parameters and compares it with
sum_S theta_S F_S (the split reproduces the forms to rounding).

The full-order model at any mu is :func:`dolfinx_lopinf.fem.param_fom.simulate` (the forms
assembled with the Constants set to mu, not the sum of the terms).
"""

from __future__ import annotations

import itertools

import numpy as np

from ._dolfinx import PETSc, dolfinx, ufl
from ..core.basis import Basis
from ..core.parametric import OPERATORS, SYMBOLS, AffineStructure, ParametricModel, label
from ..errors import InputError, InputTypeError, NonAffineParameterError
from .state import StateMap, gather_states
from .intrusive import dense_state_matrix, reduced_matrix
from .lagrangian import LagrangianSystem

fpetsc = dolfinx.fem.petsc


def _expanded(form):
    from ufl.algorithms import expand_derivatives

    return expand_derivatives(form)


def _d(form, c):
    """d form / d c for a Constant c (expanded)."""
    var = ufl.variable(c)
    integrals = [itg.reconstruct(integrand=ufl.diff(ufl.replace(itg.integrand(), {c: var}), var))
                 for itg in form.integrals()]
    return _expanded(ufl.Form(integrals))


def _at_zero(form, constants):
    if form.empty():
        return form
    return _expanded(ufl.replace(form, {c: ufl.as_ufl(0.0) for c in constants}))


def split_form(form, parameters: dict, what: str = "form") -> list:
    """[(monomial, term form)] of ``form`` = sum theta_S(c) F_S in the scalar Constants
    ``parameters`` (name -> Constant); see the module docstring. Raises
    :class:`~dolfinx_lopinf.errors.NonAffineParameterError` when a parameter enters
    non-affinely."""
    if form is None:
        return []
    form = _expanded(form)
    if form.empty():
        return []
    present = {name: c for name, c in parameters.items() if c in form.constants()}
    for name, c in present.items():
        if not _d(_d(form, c), c).empty():
            raise NonAffineParameterError(
                f"the parameter {name!r} enters the {what} non-affinely (d^2/d{name}^2 of it is "
                f"not zero): it is not sum theta_i({name}) {SYMBOLS.get(what, what)}_i. Write it "
                f"with a Constant for the combination that enters linearly (e.g. c^2, 1/s), or "
                f"fit the interpolated model (ParametricSystem(..., affine='auto') / "
                f"dolfinx_lopinf.parametric.fit_interpolated)", name, what)
    terms = []
    names = sorted(present)
    for k in range(len(names) + 1):
        for subset in itertools.combinations(names, k):
            d = form
            for name in subset:
                d = _d(d, present[name])
                if d.empty():
                    break
            d = _at_zero(d, present.values())
            if not d.empty():
                terms.append((tuple(subset), d))
    return terms


def _check_parameters(parameters) -> dict:
    if not isinstance(parameters, dict) or not parameters:
        raise InputError("parameters must be a dict name -> dolfinx.fem.Constant (at least one)")
    out = {}
    for name, c in parameters.items():
        if not isinstance(c, dolfinx.fem.Constant):
            raise InputTypeError(
                f"parameter {name!r} is a {type(c).__name__}, not a dolfinx.fem.Constant: a "
                "parameter must be a scalar Constant of the forms (a field parameter - a "
                "Function - is not supported; scale a fixed field by a Constant instead)")
        if np.asarray(c.value).shape != ():
            raise InputError(f"parameter {name!r} is a Constant of shape "
                             f"{np.asarray(c.value).shape}; a parameter must be a scalar Constant")
        out[str(name)] = c
    return out


class ParametricSystem:
    """A linear mechanical system whose forms depend on scalar Constants (the parameters).

    Args:
        lagrangian: the scalar UFL Lagrangian L(q, q_t) (quadratic), in the parameters.
        q, q_t: the Functions L is written in.
        parameters: name -> scalar ``dolfinx.fem.Constant`` used in the forms (the order is
            the order of mu).
        dissipation: optional Rayleigh dissipation function D(q_t), a scalar form quadratic in
            q_t (damping C = d^2 D / dq_t^2), e.g. ``0.5 * zeta * a0 * rho * q_t**2 * dx``.
        input_forms: the virtual work per unit input b_j(v), 1-forms with a test function on
            the space of q (one per input channel); may depend on the parameters.
        bcs: homogeneous Dirichlet conditions.
        state_map: dof -> state rows (default: by dof coordinates, rank independent).
        affine: True - split every form (an error names a non-affine parameter); "auto" -
            the same, but a non-affine parameter leaves ``structure`` None (the interpolated
            fit) and ``nonaffine`` says why; False - no split.

    Attributes:
        structure: the :class:`~dolfinx_lopinf.core.parametric.AffineStructure` found (or None).
        term_forms: operator -> list of term forms aligned with the structure (``inputs``:
            per term, one form or None per input channel).
    """

    def __init__(self, lagrangian, q, q_t, parameters: dict, *, dissipation=None, input_forms=(),
                 bcs=(), state_map: StateMap | None = None, affine="auto"):
        if affine not in (True, False, "auto"):
            raise InputError(f"affine must be True, False or 'auto', got {affine!r}")
        self.parameters = _check_parameters(parameters)
        self.system = LagrangianSystem(lagrangian, q, q_t, bcs=bcs)
        if not self.system.is_quadratic:
            raise InputError("a ParametricSystem is linear: the Lagrangian must be quadratic in "
                             "(q, q_t)")
        V = self.system.V
        self.V, self.bcs = V, self.system.bcs
        v, du = self.system.test, self.system.trial
        self.forms = {"mass": self.system.mass_form, "stiffness": self.system.stiffness_form,
                      "damping": None}
        if dissipation is not None:
            if not isinstance(dissipation, ufl.Form) or dissipation.arguments():
                raise InputError("dissipation must be a scalar UFL form D(q_t) (no test or trial "
                                 "functions), e.g. 0.5 * c * q_t**2 * ufl.dx")
            C = ufl.derivative(ufl.derivative(dissipation, q_t, v), q_t, du)
            if _expanded(C).empty():
                raise InputError("the dissipation function does not depend on q_t (its second "
                                 "derivative in q_t is zero)")
            coeffs = set(_expanded(C).coefficients())
            if q in coeffs or q_t in coeffs:
                raise InputError("the dissipation function must be quadratic in q_t alone "
                                 "(a constant damping matrix)")
            self.forms["damping"] = C
        self.input_forms = []
        for j, form in enumerate(input_forms):
            args = form.arguments() if isinstance(form, ufl.Form) else ()
            if len(args) != 1 or args[0].ufl_function_space() != V:
                raise InputError(f"input_forms[{j}] must be a UFL 1-form whose test function is on "
                                 "the space of q")
            self.input_forms.append(ufl.replace(form, {args[0]: v}))
        self.state_map = StateMap.from_coordinates(V) if state_map is None else state_map
        used = set()
        for form in [f for f in self.forms.values() if f is not None] + self.input_forms:
            used |= set(_expanded(form).constants())
        unused = [n for n, c in self.parameters.items() if c not in used]
        if unused:
            raise InputError(f"parameter(s) {unused} are not Constants of the forms (they appear in "
                             "none of the mass, stiffness, damping or input forms); pass the "
                             "Constant objects the Lagrangian is written with")
        self.nonaffine = None
        self.structure, self.term_forms = None, None
        if affine is not False:
            try:
                self._split()
            except NonAffineParameterError as exc:
                if affine is True:
                    raise
                self.nonaffine = {"parameter": exc.parameter, "operator": exc.operator,
                                  "why": str(exc)}

    @property
    def names(self) -> tuple:
        return tuple(self.parameters)

    @property
    def m(self) -> int:
        return len(self.input_forms)

    def _split(self):
        params = self.parameters
        found = {op: split_form(self.forms[op], params, op) for op in ("mass", "damping", "stiffness")}
        per_input = [split_form(b, params, "inputs") for b in self.input_forms]
        monos = sorted({t for terms in per_input for t, _ in terms}, key=lambda t: (len(t), t))
        inputs = [[dict(terms).get(t) for terms in per_input] for t in monos]
        self.structure = AffineStructure(self.names, mass=[t for t, _ in found["mass"]],
                                         damping=[t for t, _ in found["damping"]],
                                         stiffness=[t for t, _ in found["stiffness"]], inputs=monos)
        self.term_forms = {op: [f for _, f in found[op]] for op in ("mass", "damping", "stiffness")}
        self.term_forms["inputs"] = inputs

    def describe(self) -> str:
        """The affine terms found (or why there are none)."""
        if self.structure is None:
            return ("no affine structure: " + self.nonaffine["why"]) if self.nonaffine else \
                "no affine structure (affine=False)"
        return self.structure.describe()

    # -- parameters and assembly -------------------------------------------------------------
    def check_mu(self, mu) -> np.ndarray:
        if self.structure is not None:
            return self.structure.check_mu(mu)
        return AffineStructure(self.names).check_mu(mu)

    def set(self, mu) -> np.ndarray:
        """Set the parameter Constants to mu (checked); returns mu as an array."""
        mu = self.check_mu(mu)
        for c, value in zip(self.parameters.values(), mu):
            c.value = value
        return mu

    def _matrix(self, form, bcs=True, diag=1.0):
        A = fpetsc.assemble_matrix(dolfinx.fem.form(form), bcs=list(self.bcs) if bcs else [],
                                   diag=diag)
        A.assemble()
        return A

    def _vector(self, form, bcs=True):
        b = fpetsc.assemble_vector(dolfinx.fem.form(form))
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        if bcs:
            fpetsc.set_bc(b, list(self.bcs))
        return b

    def assemble(self, mu) -> dict:
        """The FOM at mu, assembled from the full forms with the Constants set (PETSc, with
        the Dirichlet conditions: M diag 1, K and C diag 0): {"M", "K", "C" (or None),
        "b": [input vectors]}; the caller destroys them."""
        self.set(mu)
        out = {"M": self._matrix(self.forms["mass"]),
               "K": self._matrix(self.forms["stiffness"], diag=0.0),
               "C": None if self.forms["damping"] is None else
               self._matrix(self.forms["damping"], diag=0.0),
               "b": [self._vector(b) for b in self.input_forms]}
        return out

    def check_split(self, mus=None, seed: int = 0) -> dict:
        """max over ``mus`` (default: 3 random parameters in [0.5, 2]^p) of the relative
        Frobenius difference between each form assembled at mu and sum_S theta_S(mu) F_S."""
        if self.structure is None:
            raise InputError("this system has no affine structure to check: " + self.describe())
        rng = np.random.default_rng(seed)
        mus = rng.uniform(0.5, 2.0, (3, len(self.names))) if mus is None else mus
        worst = {}
        terms = {op: [self._matrix(f, bcs=False) for f in self.term_forms[op]]
                 for op in ("mass", "damping", "stiffness")}
        for mu in mus:
            mu = self.set(mu)
            for op in ("mass", "damping", "stiffness"):
                if self.forms[op] is None:
                    continue
                full = self._matrix(self.forms[op], bcs=False)
                norm = full.norm(PETSc.NormType.FROBENIUS)
                for th, A in zip(self.structure.theta(op, mu), terms[op]):
                    full.axpy(-th, A, PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
                worst[op] = max(worst.get(op, 0.0), full.norm(PETSc.NormType.FROBENIUS) / norm)
                full.destroy()
            th = self.structure.theta("inputs", mu)
            for j, form in enumerate(self.input_forms):
                full = self._vector(form, bcs=False)
                norm = full.norm()
                for t, forms in zip(th, self.term_forms["inputs"]):
                    if forms[j] is not None:
                        b = self._vector(forms[j], bcs=False)
                        full.axpy(-t, b)
                        b.destroy()
                worst["inputs"] = max(worst.get("inputs", 0.0), full.norm() / max(norm, 1e-300))
                full.destroy()
        for mats in terms.values():
            for A in mats:
                A.destroy()
        return worst

    # -- bases and the intrusive model -------------------------------------------------------
    def mass_form(self):
        """The parameter-free mass term's bilinear form (the whole mass form when it does not
        depend on mu), or None when every mass term carries a parameter."""
        if self.structure is None:
            return self.forms["mass"]
        if () not in self.structure.mass:
            return None
        return self.term_forms["mass"][self.structure.mass.index(())]

    def mass_matrix(self) -> np.ndarray:
        """The parameter-free mass term (the whole mass when it does not depend on mu) as a
        dense (n, n) state matrix on every rank: the POD weight that makes Mh_0 = I."""
        form = self.mass_form()
        if form is None:
            raise InputError("every mass term of this system carries a parameter: there is no "
                             "parameter-free mass to make a basis orthonormal in")
        return dense_state_matrix(form, self.V, self.state_map)

    def _state_vector(self, b) -> np.ndarray:
        """A PETSc vector of V in state coordinates on every rank."""
        n_owned = self.V.dofmap.index_map.size_local * self.V.dofmap.index_map_bs
        full = gather_states(self.V, b.array_r[:n_owned].copy(), self.state_map)
        return self.V.mesh.comm.bcast(full, root=0)

    def intrusive(self, basis: Basis, scheme, dt: float, mu_train=None) -> ParametricModel:
        """The intrusive parametric Galerkin ROM: every term projected on ``basis`` (V^T K_S V,
        V^T b_S); the basis must be orthonormal in the parameter-free mass."""
        if self.structure is None:
            raise InputError("the intrusive parametric ROM needs the affine structure: "
                             + self.describe())
        W = basis.V
        terms = {}
        for op in ("mass", "damping", "stiffness"):
            red = []
            for f in self.term_forms[op]:
                A = self._matrix(f, bcs=False)
                R = reduced_matrix(A, self.V, W, self.state_map)
                A.destroy()
                red.append(0.5 * (R + R.T))
            terms[op] = red
        M0 = terms["mass"][self.structure.mass.index(())]
        dev = float(np.abs(M0 - np.eye(basis.r)).max())
        if dev > 1e-8:
            raise InputError(f"the basis is not orthonormal in the parameter-free mass (max "
                             f"|V^T M_0 V - I| = {dev:.3g}); build it with weight=mass_matrix()")
        terms["mass"] = [A for A, t in zip(terms["mass"], self.structure.mass) if t]
        terms["inputs"] = []
        for forms in self.term_forms["inputs"]:
            cols = []
            for f in forms:
                if f is None:
                    cols.append(np.zeros(basis.r))
                    continue
                b = self._vector(f, bcs=False)
                cols.append(W.T @ self._state_vector(b))
                b.destroy()
            terms["inputs"].append(np.column_stack(cols))
        return ParametricModel.from_operators(self.structure, basis, scheme, dt, terms, mu_train,
                                              {"method": "intrusive"})

    def terms_table(self) -> list:
        """[{operator, term, theta}] rows of the affine terms (for reports)."""
        if self.structure is None:
            return []
        return [{"operator": SYMBOLS[op], "theta": label(t)}
                for op in OPERATORS for t in getattr(self.structure, op)]


__all__ = ["ParametricSystem", "split_form"]
