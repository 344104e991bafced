"""From a continuous Lagrangian in UFL to every form the FOM needs (docs/method.md#discrete-euler-lagrange).

The user writes L(q, q_t) as a scalar UFL form in two dolfinx Functions on their own
function space (configuration ``q`` and velocity ``q_t``), optionally a nonconservative
force as a 1-form f(q, q_t; dq) (virtual work) and Dirichlet bcs. Everything else is UFL
calculus (``ufl.derivative``, ``ufl.replace``), never hand-assembled operators:

    mass       M(du, v)  =  d^2 L / dq_t^2 [du, v]          (must not depend on q, q_t)
    stiffness  K(du, v)  = -d^2 L / dq^2   [du, v]
    momentum   p(q, q_t) =  dL/dq_t                          (a 1-form)
    energy     E(q, q_t) =  dL/dq_t . q_t - L                (a 0-form)

Midpoint discrete Lagrangian and forces, step dt:

    L_d(q0, q1)   = dt L((q0+q1)/2, (q1-q0)/dt)
    f_d^+-(q0,q1) = dt/2 f((q0+q1)/2, (q1-q0)/dt; t + dt/2)

The integrator works in position-momentum form (equivalent to the discrete Euler-Lagrange
equations D2 L_d(q_{k-1}, q_k) + D1 L_d(q_k, q_{k+1}) + f_d^+ + f_d^- = 0):

    step residual   R(q1) = p0 + D1 L_d(q0, q1) + f_d^-(q0, q1)     (solve for q1)
    new momentum    p1    = D2 L_d(q0, q1) + f_d^+(q0, q1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._dolfinx import MPI, dolfinx, ufl
from ..errors import InputError, InputTypeError


def _as_function(obj, name):
    if not isinstance(obj, dolfinx.fem.Function):
        raise InputTypeError(f"{name} must be a dolfinx.fem.Function, got {type(obj).__name__}")
    return obj


def _on_space(f, V) -> bool:
    """Whether the Function ``f`` lives on V: the same space object, or one with provably the
    same dofs (:func:`_same_dofs`; this rank's verdict - the caller reduces over ranks)."""
    W = f.function_space._cpp_object
    return W is V._cpp_object or _same_dofs(W, V)


def _same_dofs(W, V) -> bool:
    """Whether the (whole) space W has provably the same dofs as V: same mesh object, same
    element, identical dof maps and index maps on this rank (the caller reduces over ranks)."""
    Wc, Vc = W, V._cpp_object
    if list(Wc.component()) or Wc.mesh is not Vc.mesh:
        return False
    if Wc.element.signature != Vc.element.signature:
        return False
    dw, dv = dolfinx.fem.DofMap(Wc.dofmap), dolfinx.fem.DofMap(Vc.dofmap)
    iw, iv = dw.index_map, dv.index_map
    return (dw.index_map_bs == dv.index_map_bs and iw.size_local == iv.size_local
            and iw.size_global == iv.size_global and np.array_equal(iw.ghosts, iv.ghosts)
            and np.array_equal(dw.list, dv.list))


def _describe_space(W) -> str:
    comp = list(W.component())
    sub = f", sub-space {comp}" if comp else ""
    try:
        e = W.element.basix_element
        name = f"{'Lagrange' if e.family.name == 'P' else e.family.name} degree {e.degree}"
    except (AttributeError, RuntimeError):  # a mixed or blocked element without one basix element
        name = W.element.signature
    return f"{name}{sub}, {dolfinx.fem.DofMap(W.dofmap).index_map.size_global} dof blocks"


def check_bcs(bcs, V) -> tuple:
    """The Dirichlet conditions ``bcs`` as conditions on V (collective over V's communicator).

    Every bc must be a ``dolfinx.fem.DirichletBC`` on V or on a sub-space of V (``V.sub(i)``).
    A bc on a separately created space with provably the same dofs (same mesh object, same
    element, identical dof map on every rank) and a Constant or Function value is rebuilt on V.
    Anything else (another mesh, another element such as P2 for a P1 or Hermite system, a
    collapsed sub-space) is refused: its dof numbers mean other dofs of V, and the matrix
    assembly would silently drop it while the vector updates applied it.
    """
    if isinstance(bcs, dolfinx.fem.DirichletBC):
        bcs = (bcs,)
    try:
        bcs = tuple(bcs)
    except TypeError:
        raise InputError(f"bcs must be a sequence of dolfinx.fem.DirichletBC, got "
                         f"{type(bcs).__name__}") from None
    comm = V.mesh.comm
    out = []
    for i, bc in enumerate(bcs):
        if not isinstance(bc, dolfinx.fem.DirichletBC):
            raise InputError(f"bcs[{i}] must be a dolfinx.fem.DirichletBC (from "
                             f"dolfinx.fem.dirichletbc), got {type(bc).__name__}")
        W = bc.function_space
        if V._cpp_object.contains(W):
            out.append(bc)
            continue
        same = bool(comm.allreduce(_same_dofs(W, V), op=MPI.LAND))
        value = bc.g
        dofs = np.asarray(bc.dof_indices()[0], dtype=np.int32)
        bs = V.dofmap.index_map_bs
        if bs > 1:  # dof_indices() are unrolled; a whole-space bc is built from dof blocks
            dofs = np.unique(dofs // bs).astype(np.int32)
        if same and hasattr(value, "value") and not hasattr(value, "x"):  # a Constant
            val = np.asarray(value.value, dtype=dolfinx.default_scalar_type)
            out.append(dolfinx.fem.dirichletbc(val if val.ndim else val[()], dofs, V))
            continue
        if same and hasattr(value, "x") and value.function_space == W:  # a Function on W
            g = dolfinx.fem.Function(V)
            g.x.array[:] = value.x.array
            out.append(dolfinx.fem.dirichletbc(g, dofs))
            continue
        where = "another mesh" if W.mesh is not V._cpp_object.mesh else "another function space"
        raise InputError(
            f"bcs[{i}] is defined on {where} ({_describe_space(W)}) than the system's space "
            f"({_describe_space(V._cpp_object)}): its dof numbers would constrain other dofs, "
            "and the matrix assembly would drop it while the vector updates applied it. Build it "
            "on the space of q: dolfinx.fem.dirichletbc(value, dofs, q.function_space) with dofs "
            "from dolfinx.fem.locate_dofs_topological/geometrical(q.function_space, ...)")
    return tuple(out)


def _depends_on(form, functions) -> bool:
    """Whether a form (after expanding derivatives) still contains any of ``functions``."""
    expanded = ufl.algorithms.expand_derivatives(form)
    if expanded.empty():
        return False
    coefficients = set(expanded.coefficients())
    return any(f in coefficients for f in functions)


@dataclass(frozen=True)
class StepForms:
    """UFL forms of one midpoint step from (q0, p0) to (q1, p1); see the module docstring.

    ``residual`` and ``momentum`` are 1-forms in the system's test function; the
    Jacobians are bilinear forms in (trial, test).
    """

    q0: "dolfinx.fem.Function"
    q1: "dolfinx.fem.Function"
    residual: ufl.Form  # D1 L_d(q0, q1) + f_d^-   (p0 is added as a vector)
    momentum: ufl.Form  # D2 L_d(q0, q1) + f_d^+
    d_residual_d_q1: ufl.Form
    d_residual_d_q0: ufl.Form
    d_momentum_d_q1: ufl.Form
    d_momentum_d_q0: ufl.Form


class LagrangianSystem:
    """A Lagrangian system L(q, q_t) (+ forcing f) on a dolfinx function space.

    Args:
        lagrangian: scalar UFL form L(q, q_t) (no test or trial functions).
        q, q_t: the dolfinx Functions L is written in (same space).
        bcs: homogeneous Dirichlet conditions on q (and so on q_t), built on the space of q
            or a sub-space of it (see :func:`check_bcs`; a bc on another space is refused).
        forcing: optional nonconservative virtual work f(q, q_t; dq): a UFL 1-form whose
            single argument is a test function on the same space.
        time: optional ``dolfinx.fem.Constant`` that the forcing depends on; the integrator
            sets it to the step midpoint t + dt/2 before assembling forces.

    Example:
        >>> V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1))       # doctest: +SKIP
        >>> q, q_t = dolfinx.fem.Function(V), dolfinx.fem.Function(V)  # doctest: +SKIP
        >>> L = (0.5 * q_t**2 - 0.5 * q.dx(0)**2) * ufl.dx             # doctest: +SKIP
        >>> system = LagrangianSystem(L, q, q_t)                        # doctest: +SKIP
    """

    def __init__(self, lagrangian, q, q_t, *, bcs=(), forcing=None, time=None):
        self.q = _as_function(q, "q")
        self.q_t = _as_function(q_t, "q_t")
        if q.function_space != q_t.function_space:
            raise InputError("q and q_t must live on the same function space")
        if not isinstance(lagrangian, ufl.Form):
            raise InputTypeError(
                "the Lagrangian must be a UFL Form, e.g. (0.5*q_t**2 - 0.5*q.dx(0)**2)*ufl.dx; "
                f"got {type(lagrangian).__name__}"
            )
        if lagrangian.arguments():
            raise InputError(
                "the Lagrangian must be a scalar form (a functional of q and q_t) without test "
                f"or trial functions; it has arguments {lagrangian.arguments()}"
            )
        coefficients = set(lagrangian.coefficients())
        if q not in coefficients or q_t not in coefficients:
            missing = [n for n, f in (("q", q), ("q_t", q_t)) if f not in coefficients]
            raise InputError(f"the Lagrangian does not depend on {', '.join(missing)}")
        self.lagrangian = lagrangian
        self.V = q.function_space
        self.bcs = check_bcs(bcs, self.V)
        self.time = time
        self.test = ufl.TestFunction(self.V)
        self.trial = ufl.TrialFunction(self.V)
        self.forcing = None
        if forcing is not None:
            args = forcing.arguments() if isinstance(forcing, ufl.Form) else ()
            if len(args) != 1 or args[0].number() != 0:
                raise InputError("forcing must be a UFL 1-form f(q, q_t; dq) with one test function")
            if args[0].ufl_function_space() != self.V:
                raise InputError("the forcing's test function must be on the space of q")
            self.forcing = ufl.replace(forcing, {args[0]: self.test})

        v, du = self.test, self.trial
        self.momentum_form = ufl.derivative(lagrangian, q_t, v)
        self.mass_form = ufl.derivative(self.momentum_form, q_t, du)
        self.stiffness_form = -ufl.derivative(ufl.derivative(lagrangian, q, v), q, du)
        self.energy_form = ufl.derivative(lagrangian, q_t, q_t) - lagrangian
        if ufl.algorithms.expand_derivatives(self.mass_form).empty():
            raise InputError(
                "the Lagrangian has no kinetic energy: d^2 L / dq_t^2 = 0 (L is at most linear in "
                "q_t), so the mass matrix is zero and the velocity cannot be determined; add the "
                "kinetic term, e.g. 0.5 * rho * q_t**2 * ufl.dx")
        if _depends_on(self.mass_form, (q, q_t)):
            raise NotImplementedError(
                "the kinetic energy must be quadratic in q_t with a mass that does not depend on "
                "q or q_t (T = 1/2 q_t.M q_t); configuration-dependent mass is not supported"
            )
        gyro = ufl.derivative(self.momentum_form, q, du)
        self.is_quadratic = not (
            _depends_on(self.stiffness_form, (q, q_t)) or _depends_on(gyro, (q, q_t))
            or (self.forcing is not None and _depends_on(
                ufl.derivative(self.forcing, q, du) + ufl.derivative(self.forcing, q_t, du), (q, q_t)))
        )

    def discrete_lagrangian(self, q0, q1, dt) -> ufl.Form:
        """L_d(q0, q1) = dt L((q0+q1)/2, (q1-q0)/dt)."""
        return dt * ufl.replace(self.lagrangian, {self.q: 0.5 * (q0 + q1), self.q_t: (q1 - q0) / dt})

    def discrete_force(self, q0, q1, dt):
        """f_d^+ = f_d^- = dt/2 f((q0+q1)/2, (q1-q0)/dt), or None without forcing."""
        if self.forcing is None:
            return None
        return 0.5 * dt * ufl.replace(self.forcing, {self.q: 0.5 * (q0 + q1), self.q_t: (q1 - q0) / dt})

    def step_forms(self, dt: float) -> StepForms:
        """All forms of one midpoint step (Functions q0, q1 are created here and owned by it)."""
        q0 = dolfinx.fem.Function(self.V, name="q_k")
        q1 = dolfinx.fem.Function(self.V, name="q_k+1")
        dt_c = dolfinx.fem.Constant(self.V.mesh, dolfinx.default_scalar_type(dt))
        Ld = self.discrete_lagrangian(q0, q1, dt_c)
        residual = ufl.derivative(Ld, q0, self.test)
        momentum = ufl.derivative(Ld, q1, self.test)
        fd = self.discrete_force(q0, q1, dt_c)
        if fd is not None:
            residual, momentum = residual + fd, momentum + fd
        du = self.trial
        return StepForms(
            q0, q1, residual, momentum,
            ufl.derivative(residual, q1, du), ufl.derivative(residual, q0, du),
            ufl.derivative(momentum, q1, du), ufl.derivative(momentum, q0, du),
        )
