"""Gray-box nonlinearity: find the non-quadratic potential in the user's UFL Lagrangian.

For nonlinear waves the discrete equations are  q_tt = K q - f_nl(q)  with a pointwise
f_nl(q)_i = U_nl'(q_i) (docs/method.md#wave-and-sine-gordon). We identify U_nl from the form itself:

1. split every integral of L into additive terms;
2. a term is *non-quadratic* when its third derivative in q is not zero; such terms must
   depend on q only through q itself (no gradients, no q_t) - that is the potential
   -U_nl(q);
3. the pointwise derivative g(q) = U_nl'(q) is taken symbolically (``ufl.diff``) and
   compiled to a numpy function, together with g'(q) for Newton's method in the ROM.

Pointwise really means f_nl = M^-1 grad U_nl(q) equals g(q_i) dof by dof, which holds when
the kinetic term and the potential use the same vertex quadrature (lumped mass). This is
checked numerically on a random state; otherwise a clear error says what to change.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ._dolfinx import dolfinx, ufl
from ufl.corealg.traversal import unique_pre_traversal
from ..errors import InputError

_UNARY = {"Cos": np.cos, "Sin": np.sin, "Exp": np.exp, "Ln": np.log, "Sqrt": np.sqrt,
          "Abs": np.abs, "Cosh": np.cosh, "Sinh": np.sinh, "Tanh": np.tanh, "Atan": np.arctan}


def to_numpy(expr, q) -> Callable[[np.ndarray], np.ndarray]:
    """Compile a scalar UFL expression in the Function ``q`` (and constants) to numpy."""

    def build(e):
        name = type(e).__name__
        if e == q:
            return lambda x: x
        if name in ("IntValue", "FloatValue", "ScalarValue", "RealValue"):
            v = float(e)
            return lambda x: np.full_like(x, v)
        if name == "Zero":
            return lambda x: np.zeros_like(x)
        if name == "Variable":  # from ufl.diff: the labelled expression itself
            return build(e.ufl_operands[0])
        if isinstance(e, dolfinx.fem.Constant) or name == "Constant":
            v = float(np.asarray(e.value))
            return lambda x: np.full_like(x, v)
        ops = [build(o) for o in e.ufl_operands] if name not in ("Power",) else None
        if name == "Sum":
            a, b = ops
            return lambda x: a(x) + b(x)
        if name == "Product":
            a, b = ops
            return lambda x: a(x) * b(x)
        if name == "Division":
            a, b = ops
            return lambda x: a(x) / b(x)
        if name == "Power":
            a, b = (build(o) for o in e.ufl_operands)
            return lambda x: a(x) ** b(x)
        if name in _UNARY:
            f, (a,) = _UNARY[name], ops
            return lambda x: f(a(x))
        raise NotImplementedError(
            f"the nonlinear potential uses the UFL operator {name}, which the numpy translator "
            "does not know; supported: + - * / ** and " + ", ".join(sorted(_UNARY)))

    return build(expr)


def _additive_terms(e):
    """Split a UFL scalar expression into additive terms (through sums and constant factors)."""
    name = type(e).__name__
    if name == "Sum":
        return [t for o in e.ufl_operands for t in _additive_terms(o)]
    if name == "Product":
        a, b = e.ufl_operands
        for const, other in ((a, b), (b, a)):
            if not _coefficients(const) and type(other).__name__ == "Sum":
                return [const * t for t in _additive_terms(other)]
    return [e]


def _coefficients(e):
    return [t for t in unique_pre_traversal(e)
            if isinstance(t, ufl.Coefficient)]


@dataclass(frozen=True)
class PointwiseNonlinearity:
    """f_nl(q)_i = g(q_i) = U_nl'(q_i), identified from a Lagrangian.

    Attributes:
        potential: UFL density U_nl(q) (the negative of the non-quadratic terms of L).
        measure: the UFL measure it is integrated with (vertex quadrature).
        g, dg: numpy functions g = U_nl', g' = U_nl''.
        U: numpy function U_nl.
    """

    potential: object
    measure: object
    U: Callable
    g: Callable
    dg: Callable

    def __call__(self, Q: np.ndarray) -> np.ndarray:
        """f_nl applied column-wise to states Q (n, K) (or a vector)."""
        return self.g(np.asarray(Q, dtype=float))


def identify(system) -> PointwiseNonlinearity:
    """Find U_nl in ``system.lagrangian`` and compile g = U_nl' (see module docstring).

    Raises:
        ValueError: if L is quadratic, if a non-quadratic term involves gradients or q_t, or
            if f_nl is not pointwise for this discretisation (e.g. no vertex quadrature).
    """
    q, qt = system.q, system.q_t
    found, measures = [], []
    for integral in system.lagrangian.integrals():
        for term in _additive_terms(integral.integrand()):
            form = term * ufl.Measure(integral.integral_type(), domain=integral.ufl_domain(),
                                      metadata=integral.metadata())
            du = ufl.TrialFunction(system.V)
            third = ufl.derivative(ufl.derivative(ufl.derivative(form, q, du), q, du), q, du)
            if ufl.algorithms.expand_derivatives(third).empty():
                continue
            deps = {type(t).__name__ for t in unique_pre_traversal(term)}
            if "Grad" in deps or qt in _coefficients(term):
                raise InputError(
                    "a non-quadratic term of the Lagrangian involves derivatives of q or q_t; "
                    "the gray-box wave ROM needs the nonlinearity as a pointwise potential U(q)")
            found.append(-term)
            measures.append(form.integrals()[0])
    if not found:
        raise InputError("the Lagrangian is quadratic: there is no nonlinear potential to identify")
    metas = {str(m.metadata()) for m in measures}
    if len(metas) != 1:
        raise InputError("the non-quadratic terms use different measures; integrate them alike")
    density = found[0]
    for t in found[1:]:
        density = density + t
    qv = ufl.variable(q)
    dens_v = ufl.replace(density, {q: qv})
    g_expr = ufl.algorithms.expand_derivatives(ufl.diff(dens_v, qv))
    dg_expr = ufl.algorithms.expand_derivatives(ufl.diff(ufl.diff(dens_v, qv), qv))
    nl = PointwiseNonlinearity(density, measures[0].metadata(), to_numpy(density, q),
                               to_numpy(g_expr, q), to_numpy(dg_expr, q))
    _check_pointwise(system, nl, density, measures[0])
    return nl


def _check_pointwise(system, nl, density, integral):
    """f_nl = M^-1 grad U_nl(q) must equal g(q) dof by dof: M diagonal (lumped) and the
    potential integrated with the same vertex rule."""
    import dolfinx.fem.petsc
    from petsc4py import PETSc

    V = system.V
    M = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(system.mass_form))
    M.assemble()
    diag = M.getDiagonal()
    off = M.copy()
    off.setDiagonal(diag * 0.0)
    off_norm, m_norm = off.norm(PETSc.NormType.FROBENIUS), M.norm(PETSc.NormType.FROBENIUS)
    if off_norm > 1e-12 * m_norm:
        raise InputError(
            "the mass matrix is not diagonal, so f_nl = M^-1 grad U is not pointwise; integrate "
            "the kinetic term and the potential with vertex quadrature (ufl.dx(metadata="
            "{'quadrature_rule': 'vertex', 'quadrature_degree': 1}))")
    q = system.q
    saved = q.x.array.copy()
    q.x.array[:] = np.random.default_rng(0).uniform(-3, 3, q.x.array.shape)
    q.x.scatter_forward()  # ghosts take their owners' values
    measure = ufl.Measure(integral.integral_type(), domain=integral.ufl_domain(),
                          metadata=integral.metadata())
    v = ufl.TestFunction(V)
    grad_u = dolfinx.fem.petsc.assemble_vector(dolfinx.fem.form(ufl.derivative(density * measure, q, v)))
    grad_u.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    n = V.dofmap.index_map.size_local
    lhs = grad_u.array[:n] / diag.array[:n]
    rhs = nl.g(q.x.array[:n])
    q.x.array[:] = saved
    comm = V.mesh.comm
    err = comm.allreduce(np.abs(lhs - rhs).max(initial=0.0), op=__import__("mpi4py").MPI.MAX) / \
        max(comm.allreduce(np.abs(rhs).max(initial=0.0), op=__import__("mpi4py").MPI.MAX), 1e-300)
    if err > 1e-10:
        raise InputError(
            f"the nonlinear force is not pointwise for this discretisation (M^-1 grad U vs g(q): "
            f"relative mismatch {err:.1e}); integrate the potential with the same vertex "
            "quadrature as the kinetic term")
