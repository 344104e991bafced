"""Euler-Bernoulli beam, simply supported (docs/method.md#beam).

    L = integral( 1/2 mu w_t^2 - 1/2 EI w_xx^2 ) dx   on [0, l],  w(0) = w(l) = 0,

discretised with cubic Hermite (C1) elements on a uniform mesh of ``n_nodes`` nodes; the
state is [w; theta] in R^(2 n_nodes): nodal deflections then nodal rotations, sorted by x.

What the Hermite derivative dofs mean: basix defines them on the reference interval
X in [0, 1], so a derivative dof is dw/dX = J w'(x) with J = x(vertex 1) - x(vertex 0)
of the cell. The state map divides by J, so theta = w' in physical units. That is only
one number per node when every cell touching a node has the same J - true on a uniform,
consistently oriented mesh, which :func:`build` checks (a non-uniform mesh would make the
shared derivative dof mean different slopes in its two cells, i.e. not C1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..fem._dolfinx import MPI, PETSc, dolfinx, ufl
from ..fem.state import StateMap, point_output_matrix
from ..fem.lagrangian import LagrangianSystem
from ..errors import InputError

LENGTH = 1.0  # m
MU = 6.28e-3  # kg/m
EI = 9.81e-3  # N m^2
DT = 1e-5  # s
T_TRAIN = 0.03  # s
T_END = 0.18  # s


def initial_deflection(x: np.ndarray, a: float | None = None, l: float = LENGTH):
    """(w, w') of the paper's initial condition.

    ``a=None``: w = 0.001 (x^4 - 2 l x^3 + l^3 x); otherwise the unseen-IC family
    w = 0.001 (a x^5 - 2 l x^4 + (10a/3 - 4) l^2 x^3 + (6 - 10a/3 - a) l^4 x).
    """
    if a is None:
        return 1e-3 * (x**4 - 2 * l * x**3 + l**3 * x), 1e-3 * (4 * x**3 - 6 * l * x**2 + l**3)
    c3, c1 = (10 * a / 3 - 4) * l**2, (6 - 10 * a / 3 - a) * l**4
    w = 1e-3 * (a * x**5 - 2 * l * x**4 + c3 * x**3 + c1 * x)
    dw = 1e-3 * (5 * a * x**4 - 8 * l * x**3 + 3 * c3 * x**2 + c1)
    return w, dw


def analytic_frequencies(k: np.ndarray, l: float = LENGTH, mu: float = MU, ei: float = EI):
    """Simply supported beam: omega_k = (k pi / l)^2 sqrt(EI / mu)  [rad/s]."""
    return (np.asarray(k) * np.pi / l) ** 2 * np.sqrt(ei / mu)


@dataclass
class Beam:
    """Everything a demo or test needs about the discretised beam."""

    system: LagrangianSystem
    state_map: StateMap
    x_nodes: np.ndarray  # (n_nodes,) sorted node coordinates
    value_dofs: np.ndarray  # local dof index of w at each owned/ghost node (local numbering)
    slope_dofs: np.ndarray
    jacobian: np.ndarray  # dw/dX = J w' for the local derivative dofs
    x_local: np.ndarray  # coordinates of the local nodes
    output_matrix: np.ndarray  # (1, n_local): deflection at x = l/2

    def initial_state(self, a: float | None = None):
        """Local dof arrays (q0, v0) of the (Hermite-interpolated) initial condition."""
        q0 = np.zeros(self.system.V.dofmap.index_map.size_local
                      + self.system.V.dofmap.index_map.num_ghosts)
        w, dw = initial_deflection(self.x_local, a)
        q0[self.value_dofs] = w
        q0[self.slope_dofs] = self.jacobian * dw
        return q0, np.zeros_like(q0)


def _hermite_nodes(V):
    """Per local vertex: (value dof, derivative dof, x, J); checks J is unique per node."""
    msh = V.mesh
    tdim = msh.topology.dim
    n_cells = msh.topology.index_map(tdim).size_local + msh.topology.index_map(tdim).num_ghosts
    x = msh.geometry.x[:, 0]
    geo = msh.geometry.dofmaps[0]
    value, slope, xs, jac = {}, {}, {}, {}
    for c in range(n_cells):
        dofs = V.dofmap.cell_dofs(c)
        x0, x1 = x[geo[c, 0]], x[geo[c, 1]]
        J = x1 - x0
        for local_vertex, xv in ((0, x0), (1, x1)):
            vd, sd = dofs[2 * local_vertex], dofs[2 * local_vertex + 1]
            if sd in jac and not np.isclose(jac[sd], J, rtol=1e-10, atol=0):
                raise InputError(
                    f"Hermite derivative dof at x = {xv:.6g} is shared by cells of different "
                    f"length/orientation (J = {jac[sd]:.6g} vs {J:.6g}): on such a mesh the "
                    "derivative dofs do not represent one slope. Use a uniform mesh."
                )
            value[sd], slope[sd], xs[sd], jac[sd] = vd, sd, xv, J
    keys = sorted(jac)
    return (np.array([value[k] for k in keys]), np.array(keys), np.array([xs[k] for k in keys]),
            np.array([jac[k] for k in keys]))


def build(n_nodes: int = 200, comm=MPI.COMM_WORLD, *, length: float = LENGTH, mu: float = MU,
          ei: float = EI) -> Beam:
    """The beam's LagrangianSystem on a uniform Hermite mesh, with its state map and output."""
    import basix.ufl

    if n_nodes < 3:
        raise InputError("the beam needs at least 3 nodes")
    msh = dolfinx.mesh.create_interval(comm, n_nodes - 1, [0.0, length])
    V = dolfinx.fem.functionspace(msh, basix.ufl.element(basix.ElementFamily.Hermite, "interval", 3))
    w, w_t = dolfinx.fem.Function(V, name="w"), dolfinx.fem.Function(V, name="w_t")
    mu_c = dolfinx.fem.Constant(msh, PETSc.ScalarType(mu))
    ei_c = dolfinx.fem.Constant(msh, PETSc.ScalarType(ei))
    # The whole physics: the continuous Lagrangian density.
    lagrangian = (0.5 * mu_c * w_t**2 - 0.5 * ei_c * w.dx(0).dx(0) ** 2) * ufl.dx

    value_dofs, slope_dofs, x_local, jac = _hermite_nodes(V)
    ends = value_dofs[np.isclose(x_local, 0.0) | np.isclose(x_local, length)]
    bc = dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), ends.astype(np.int32), V)
    system = LagrangianSystem(lagrangian, w, w_t, bcs=[bc])

    # State map: global numbering, gathered on every rank (n is small for a beam).
    imap = V.dofmap.index_map
    n_owned = imap.size_local
    owned = value_dofs < n_owned  # value and slope dofs of a node share an owner
    to_global = imap.local_to_global
    rows = comm.allgather((to_global(value_dofs[owned].astype(np.int32)),
                           to_global(slope_dofs[owned].astype(np.int32)),
                           x_local[owned], jac[owned]))
    gv, gs, gx, gj = (np.concatenate([r[i] for r in rows]) for i in range(4))
    order = np.argsort(gx)
    n = len(gx)
    state_map = StateMap(
        order=np.concatenate([gv[order], gs[order]]),
        scale=np.concatenate([np.ones(n), 1.0 / gj[order]]),
        blocks={"w": np.arange(n), "theta": np.arange(n, 2 * n)},
    )
    E = point_output_matrix(V, np.array([[0.5 * length, 0.0, 0.0]]))
    return Beam(system, state_map, gx[order], value_dofs, slope_dofs, jac, x_local, E)
