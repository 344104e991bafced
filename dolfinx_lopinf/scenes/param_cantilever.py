"""A design sweep of a 3D cantilever: Young's modulus and the Rayleigh damping level.

    L = integral( 1/2 rho q_t . q_t - 1/2 sigma_E(q) : eps(q) ) dx,
    D = integral( 1/2 zeta (a0 rho q_t . q_t + a1 sigma_E(q_t) : eps(q_t)) ) dx,

sigma_E = lambda(E) tr(eps) I + 2 mu(E) eps with lambda, mu linear in Young's modulus E (a
UFL Constant), zeta (a Constant) the damping level of the Rayleigh dissipation function D:
C = zeta (a0 M + a1 K(E)). The UFL split finds K(mu) = E K[E], C(mu) = zeta C[zeta] +
E zeta C[E*zeta] (a product of two parameters is one term), M and B parameter-free. The
geometry, load and Newmark scheme of :mod:`dolfinx_lopinf.scenes.cantilever`: [0, 1] x
[0, 0.1] x [0, 0.1] hexahedra, P1, clamped at x = 0, a vertical tip traction -p(t) e_z on
x = 1 (the input).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..fem._dolfinx import MPI, PETSc, dolfinx, ufl
from ..fem.affine import ParametricSystem
from .cantilever import ALPHA, BETA, HEIGHT, LENGTH, NU, RHO, WIDTH

E_REF = 1.0e4
SIZES = {
    "quick": {"cells": (12, 2, 2), "dt": 2e-3, "t_end": 0.6},
    "default": {"cells": (30, 4, 4), "dt": 1e-3, "t_end": 1.0},
}


def train_loads():
    """Two training tip loads per design: tones from 1.5 to 37 Hz (the first two bending modes
    sit near 5 and 30 Hz at E = 1e5 Pa), and a train of short pulses (broadband)."""
    def tones(t):
        return float(np.sin(2 * np.pi * 1.5 * t) + 0.6 * np.sin(2 * np.pi * 6.1 * t + 0.3)
                     + 0.5 * np.sin(2 * np.pi * 23.0 * t) + 0.4 * np.sin(2 * np.pi * 37.0 * t + 1.0))

    def pulses(t):
        s1, s2 = (t - 0.1) / 0.012, (t - 0.35) / 0.02
        return float(np.exp(-s1**2) - 0.8 * np.exp(-s2**2))

    return [tones, pulses]


def test_load(t):
    """Unseen: a ramp-and-hold (0 at t = 0) plus 9 and 29 Hz tones."""
    return float(min(t / 0.15, 1.0) + 0.5 * np.sin(2 * np.pi * 9.0 * t)
                 + 0.3 * np.sin(2 * np.pi * 29.0 * t))


@dataclass
class Cantilever:
    psys: ParametricSystem
    cells: tuple

    @property
    def V(self):
        return self.psys.V


def build(cells=(30, 4, 4), comm=MPI.COMM_WORLD, *, affine="auto") -> Cantilever:
    """The parametric cantilever (module docstring); parameters ``("E", "zeta")``."""
    msh = dolfinx.mesh.create_box(comm, [[0, 0, 0], [LENGTH, WIDTH, HEIGHT]], list(cells),
                                  dolfinx.mesh.CellType.hexahedron)
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1, (3,)))
    E = dolfinx.fem.Constant(msh, PETSc.ScalarType(E_REF))
    zeta = dolfinx.fem.Constant(msh, PETSc.ScalarType(1.0))
    lmbda = E * NU / ((1 + NU) * (1 - 2 * NU))
    mu = E / (2 * (1 + NU))

    def eps(w):
        return ufl.sym(ufl.grad(w))

    def sigma(w):
        return lmbda * ufl.tr(eps(w)) * ufl.Identity(3) + 2 * mu * eps(w)

    q, q_t = dolfinx.fem.Function(V, name="q"), dolfinx.fem.Function(V, name="q_t")
    # The whole physics: kinetic minus strain energy, and a Rayleigh dissipation function.
    lagrangian = (0.5 * RHO * ufl.inner(q_t, q_t) - 0.5 * ufl.inner(sigma(q), eps(q))) * ufl.dx
    dissipation = 0.5 * zeta * (ALPHA * RHO * ufl.inner(q_t, q_t)
                                + BETA * ufl.inner(sigma(q_t), eps(q_t))) * ufl.dx
    fdim = msh.topology.dim - 1
    clamped = dolfinx.mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[0], 0.0))
    bc = dolfinx.fem.dirichletbc(np.zeros(3, dtype=PETSc.ScalarType),
                                 dolfinx.fem.locate_dofs_topological(V, fdim, clamped), V)
    tip = dolfinx.mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[0], LENGTH))
    tags = dolfinx.mesh.meshtags(msh, fdim, tip, np.full(len(tip), 1, dtype=np.int32))
    ds = ufl.Measure("ds", domain=msh, subdomain_data=tags)
    v = ufl.TestFunction(V)
    traction = -v[2] * ds(1)  # virtual work of a unit downward tip traction
    psys = ParametricSystem(lagrangian, q, q_t, {"E": E, "zeta": zeta}, dissipation=dissipation,
                            input_forms=[traction], bcs=[bc], affine=affine)
    return Cantilever(psys, tuple(cells))
