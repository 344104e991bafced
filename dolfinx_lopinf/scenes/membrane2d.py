"""A 2D membrane with a variable wave speed and a forced source - a family of designs.

    L = integral( 1/2 q_t^2 - 1/2 c(x; mu)^2 |grad q|^2 ) dx   on the unit square,  q = 0
    on the boundary, forced by u(t) g(x) (virtual work u(t) g v dx),

with a stiff inclusion: c(x; mu)^2 = c0^2 + mu c1(x)^2, c1^2 a smoothed disk indicator
(centre INCLUSION_AT, radius R, edge width INCLUSION_EDGE) - the contrast mu is the
parameter (study ``"contrast"``: affine, K(mu) = K[1] + mu K[mu] read from the UFL), or the
inclusion's radius R with a fixed contrast (study ``"radius"``: R sits inside the tanh of
the indicator, so it enters non-affinely - the interpolated model's case). The source g is
a Gaussian at SOURCE_AT. P1 triangles, Newmark average acceleration (the FOM of
:mod:`dolfinx_lopinf.fem.param_fom`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..fem._dolfinx import MPI, PETSc, dolfinx, ufl
from ..fem.affine import ParametricSystem

C0 = 1.0
INCLUSION_AT, INCLUSION_RADIUS, INCLUSION_EDGE = (0.62, 0.56), 0.2, 0.03
#: the fixed contrast of the radius study
RADIUS_CONTRAST = 3.0
SOURCE_AT, SOURCE_WIDTH = (0.3, 0.35), 0.07
STUDIES = ("contrast", "radius")
SIZES = {
    "quick": {"cells": 24, "dt": 0.01, "t_end": 1.2},
    "default": {"cells": 48, "dt": 0.005, "t_end": 2.0},
}


def train_loads():
    """Two training inputs per parameter: a tone under a slow envelope plus a lower one, and
    a train of two smooth pulses."""
    def tones(t):
        return float(np.sin(np.pi * min(t / 0.6, 1.0)) * np.sin(2 * np.pi * 2.2 * t)
                     + 0.5 * np.sin(2 * np.pi * 0.9 * t))

    def pulses(t):
        s1, s2 = (t - 0.25) / 0.08, (t - 0.8) / 0.12
        return float(np.exp(-s1**2) - 0.7 * np.exp(-s2**2))

    return [tones, pulses]


def test_load(t):
    """Unseen: a Ricker wavelet then a 1.6 Hz tone (0 at t = 0)."""
    s = (t - 0.35) / 0.1
    return float((1 - 2 * s**2) * np.exp(-s**2) + 0.6 * np.sin(2 * np.pi * 1.6 * t)
                 * min(t / 0.3, 1.0))


@dataclass
class Membrane:
    psys: ParametricSystem
    study: str
    cells: int

    @property
    def V(self):
        return self.psys.V


def inclusion_indicator(x, radius):
    """c1(x)^2: 1 inside the disk, 0 outside, a tanh edge of width INCLUSION_EDGE."""
    r = ufl.sqrt((x[0] - INCLUSION_AT[0]) ** 2 + (x[1] - INCLUSION_AT[1]) ** 2)
    return 0.5 * (1 - ufl.tanh((r - radius) / INCLUSION_EDGE))


def build(cells: int = 48, *, study: str = "contrast", comm=MPI.COMM_WORLD,
          affine="auto") -> Membrane:
    """The membrane on a cells x cells triangle grid; ``study`` picks the parameter."""
    if study not in STUDIES:
        raise ValueError(f"study must be one of {STUDIES}, got {study!r}")
    msh = dolfinx.mesh.create_unit_square(comm, cells, cells)
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
    q, q_t = dolfinx.fem.Function(V, name="q"), dolfinx.fem.Function(V, name="q_t")
    x = ufl.SpatialCoordinate(msh)
    if study == "contrast":
        param = dolfinx.fem.Constant(msh, PETSc.ScalarType(1.0))
        c2 = C0**2 + param * inclusion_indicator(x, INCLUSION_RADIUS)
        parameters = {"mu": param}
    else:
        param = dolfinx.fem.Constant(msh, PETSc.ScalarType(INCLUSION_RADIUS))
        c2 = C0**2 + RADIUS_CONTRAST * inclusion_indicator(x, param)
        parameters = {"R": param}
    # The whole physics: kinetic minus strain energy density.
    lagrangian = (0.5 * q_t**2 - 0.5 * c2 * ufl.inner(ufl.grad(q), ufl.grad(q))) * ufl.dx
    r2 = (x[0] - SOURCE_AT[0]) ** 2 + (x[1] - SOURCE_AT[1]) ** 2
    v = ufl.TestFunction(V)
    source = 10.0 * ufl.exp(-r2 / SOURCE_WIDTH**2) * v * ufl.dx
    tdim = msh.topology.dim
    msh.topology.create_connectivity(tdim - 1, tdim)
    facets = dolfinx.mesh.exterior_facet_indices(msh.topology)
    bc = dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0),
                                 dolfinx.fem.locate_dofs_topological(V, tdim - 1, facets), V)
    psys = ParametricSystem(lagrangian, q, q_t, parameters, input_forms=[source], bcs=[bc],
                            affine=affine)
    return Membrane(psys, study, cells)
