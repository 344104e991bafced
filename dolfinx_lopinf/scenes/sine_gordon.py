"""Sine-Gordon on a periodic domain (docs/method.md#wave-and-sine-gordon).

    L = integral( 1/2 q_t^2 - 1/2 q_x^2 - (1 - cos q) ) dx   on [-20, 20), periodic,

with P1 elements and lumped mass (vertex quadrature for the kinetic term and the potential,
so M = h I and the nonlinear force is pointwise: q_tt = K q - sin(q)).

Periodicity, honestly: DOLFINx has no periodic constraint without dolfinx_mpc, so the mesh
itself is closed. The n vertices sit on a regular n-gon in the plane whose edges all have
length h = 40 / n, and the cells are the n edges (a 1D manifold mesh in 2D). On each straight
edge the tangential derivative of a P1 function is (q_j - q_i) / h, exactly the periodic 1D
stiffness; the mass and the potential only see vertex values. So the discrete equations are
those of the periodic interval, with x the arclength. States are ordered by x.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..fem._dolfinx import MPI, dolfinx, ufl
from ..fem.state import StateMap
from ..fem.lagrangian import LagrangianSystem

X_LEFT, X_RIGHT = -20.0, 20.0
N_POINTS = 2000
DT = 0.005
T_TRAIN, T_END, T_LONG = 5.0, 25.0, 105.0
VERTEX = {"quadrature_rule": "vertex", "quadrature_degree": 1}


def exact_kink_antikink(x, t):
    """q = 4 arctan(t / cosh x): the exact solution for q(x,0) = 0, q_t(x,0) = 4 / cosh x."""
    return 4.0 * np.arctan(t / np.cosh(x))


def exact_breather(x, t, w):
    """Breather of frequency w < 1: 4 arctan( sqrt(1-w^2)/w sin(w t) / cosh(sqrt(1-w^2) x) )."""
    k = np.sqrt(1.0 - w**2)
    return 4.0 * np.arctan(k / w * np.sin(w * t) / np.cosh(k * x))


def exact_kink(x, t, v):
    """Moving kink 4 arctan(exp((x - v t) / sqrt(1 - v^2)))."""
    return 4.0 * np.arctan(np.exp((x - v * t) / np.sqrt(1.0 - v**2)))


@dataclass
class SineGordon:
    system: LagrangianSystem
    state_map: StateMap
    x: np.ndarray  # (n,) arclength coordinate of the states, sorted
    x_local: np.ndarray  # arclength coordinate of the local dofs
    h: float


def closed_mesh(n: int, length: float, comm=MPI.COMM_WORLD):
    """A periodic 1D mesh of n equal cells: a regular n-gon of perimeter ``length``."""
    theta = 2 * np.pi * np.arange(n) / n
    radius = (length / n) / (2 * np.sin(np.pi / n))
    if comm.rank == 0:
        points = radius * np.column_stack([np.cos(theta), np.sin(theta)])
        cells = np.column_stack([np.arange(n), (np.arange(n) + 1) % n]).astype(np.int64)
    else:
        points, cells = np.zeros((0, 2)), np.zeros((0, 2), dtype=np.int64)
    element = ufl.Mesh(__import__("basix").ufl.element("Lagrange", "interval", 1, shape=(2,)))
    return dolfinx.mesh.create_mesh(comm, cells, element, points)


def build(n: int = N_POINTS, comm=MPI.COMM_WORLD, *, periodic: bool = True) -> SineGordon:
    """The sine-Gordon LagrangianSystem (periodic n-gon, or an interval with free ends)."""
    length = X_RIGHT - X_LEFT
    if periodic:
        msh = closed_mesh(n, length, comm)
    else:
        msh = dolfinx.mesh.create_interval(comm, n - 1, [X_LEFT, X_RIGHT])
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
    q, q_t = dolfinx.fem.Function(V, name="q"), dolfinx.fem.Function(V, name="q_t")
    dxv = ufl.dx(domain=msh, metadata=VERTEX)
    # The whole physics: 1/2 q_t^2 - 1/2 |grad q|^2 - (1 - cos q), lumped where pointwise.
    lagrangian = (0.5 * q_t**2 - (1 - ufl.cos(q))) * dxv - 0.5 * ufl.inner(ufl.grad(q), ufl.grad(q)) * ufl.dx
    system = LagrangianSystem(lagrangian, q, q_t)
    X = V.tabulate_dof_coordinates()
    if periodic:
        ang = np.mod(np.arctan2(X[:, 1], X[:, 0]), 2 * np.pi)
        x_local = X_LEFT + length * ang / (2 * np.pi)
        x_local[x_local > X_RIGHT - 0.5 * length / n] -= length  # wrap the seam
    else:
        x_local = X[:, 0]
    imap = V.dofmap.index_map
    n_owned = imap.size_local
    glob = imap.local_to_global(np.arange(n_owned, dtype=np.int32))
    pieces = comm.allgather((glob, x_local[:n_owned]))
    G = np.concatenate([g for g, _ in pieces])
    Xs = np.concatenate([c for _, c in pieces])
    perm = np.argsort(Xs)
    state_map = StateMap(G[perm], np.ones(len(G)), {})
    h = length / n if periodic else length / (n - 1)
    return SineGordon(system, state_map, Xs[perm], x_local, h)
