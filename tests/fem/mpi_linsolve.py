"""A small P2 elastic bar stepped by Newmark and by the linear midpoint rule with every linear
solver of :mod:`dolfinx_lopinf.fem.linsolve`; test_linsolve.py imports it, and runs it under
1 and 2 ranks (``python mpi_linsolve.py OUT.npz``: the gathered tip histories and final
states, sorted by dof coordinates)."""
import sys

import numpy as np

from dolfinx_lopinf.fem._dolfinx import MPI, PETSc, dolfinx, ufl
from dolfinx_lopinf.fem.fom import run
from dolfinx_lopinf.fem.loop import OutputProbe
from dolfinx_lopinf.fem.state import StateMap, gather_states, point_output_matrix
from dolfinx_lopinf.fem.integrators import MidpointIntegrator
from dolfinx_lopinf.fem.newmark import NewmarkIntegrator, rigid_body_modes
from dolfinx_lopinf.fem.lagrangian import LagrangianSystem

# A stiffness-dominated step matrix, as in the fishtail: dt^2/4 K / M ~ 1e3 per element
E_MOD, NU, RHO, DT = 1.0e5, 0.45, 1.0, 1e-2
RAYLEIGH = (1e-2, 1e-4)
ITERATIVE = ("cg+gamg", "cg+pmg", "cg+jacobi", "chebyshev")
SUBSPACE = ("direct+subspace", "direct+blr+subspace")


def build(comm=MPI.COMM_WORLD, degree=2, n=(8, 2, 2)):
    msh = dolfinx.mesh.create_box(comm, [[0, 0, 0], [1.0, 0.2, 0.2]], list(n),
                                  dolfinx.mesh.CellType.tetrahedron)
    V = dolfinx.fem.functionspace(msh, ("Lagrange", degree, (3,)))
    lam = E_MOD * NU / ((1 + NU) * (1 - 2 * NU))
    mu = E_MOD / (2 * (1 + NU))
    q, q_t = dolfinx.fem.Function(V), dolfinx.fem.Function(V)
    eps = ufl.sym(ufl.grad(q))
    lagrangian = (0.5 * RHO * ufl.inner(q_t, q_t)
                  - 0.5 * (lam * ufl.tr(eps) ** 2 + 2 * mu * ufl.inner(eps, eps))) * ufl.dx
    fdim = msh.topology.dim - 1
    root = dolfinx.mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[0], 0.0))
    bc = dolfinx.fem.dirichletbc(np.zeros(3, dtype=PETSc.ScalarType),
                                 dolfinx.fem.locate_dofs_topological(V, fdim, root), V)
    system = LagrangianSystem(lagrangian, q, q_t, bcs=[bc])
    tip = dolfinx.mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[0], 1.0))
    tags = dolfinx.mesh.meshtags(msh, fdim, np.sort(tip), np.ones(len(tip), dtype=np.int32))
    v = ufl.TestFunction(V)
    load = [v[2] * ufl.ds(domain=msh, subdomain_data=tags, subdomain_id=1)]
    E = point_output_matrix(V, np.array([[1.0, 0.1, 0.1]]), component=2)
    return system, load, E


def newmark(system, load, E, solver, steps=40, options=None, dt=DT):
    """The tip history and the final state of Newmark under u(t) = 50 sin(2 pi t)^2."""
    V = system.V
    gamg = solver == "cg+gamg"
    with NewmarkIntegrator(system, dt, rayleigh=RAYLEIGH, input_forms=load, solver=solver,
                           petsc_options=options,
                           near_nullspace=rigid_body_modes(V) if gamg else None) as nm:
        nm.initialize([0.0])
        y = OutputProbe(E)
        run(nm, steps, sinks=[y], inputs=lambda t: [50.0 * np.sin(2 * np.pi * t) ** 2])
        n_own = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
        return np.array([v[0] for v in y.values]), nm.q.x.array[:n_own].copy(), nm.solver.stats()


def midpoint(system, solver, steps=30, options=None, dt=DT):
    """The states (owned dofs, one column per step) of the linear midpoint rule from a bending
    velocity."""
    V = system.V
    v0 = dolfinx.fem.Function(V)
    v0.interpolate(lambda x: np.vstack([0 * x[0], 0 * x[0], x[0] ** 2]))
    n_own = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
    states = []
    with MidpointIntegrator(system, dt, solver=solver, petsc_options=options) as it:
        it.initialize(np.zeros_like(v0.x.array), v0)
        for _ in range(steps):
            states.append(it.step().x.array[:n_own].copy())
    return np.array(states).T


if __name__ == "__main__":
    comm = MPI.COMM_WORLD
    system, load, E = build(comm)
    smap = StateMap.from_coordinates(system.V)
    out = {}
    for solver in ("direct", "direct+blr") + SUBSPACE + ITERATIVE:
        Y, q, _ = newmark(system, load, E, solver)
        out[f"newmark_Y_{solver}"] = Y
        out[f"newmark_q_{solver}"] = gather_states(system.V, q[:, None], smap)
    for solver in ("direct", "cg+pmg", "direct+subspace"):
        out[f"midpoint_q_{solver}"] = gather_states(system.V, midpoint(system, solver), smap)
    # how far halving dt moves each scheme's answer (the size of its truncation error)
    Y_half, _, _ = newmark(system, load, E, "direct", steps=80, dt=DT / 2)
    q_half = gather_states(system.V, midpoint(system, "direct", steps=60, dt=DT / 2)[:, 1::2], smap)
    if comm.rank == 0:
        out["newmark_time_error"] = np.abs(out["newmark_Y_direct"] - Y_half[::2]).max() / np.abs(Y_half).max()
        q_ref = out["midpoint_q_direct"]
        out["midpoint_time_error"] = np.abs(q_ref - q_half).max() / np.abs(q_half).max()
    if comm.rank == 0:
        np.savez(sys.argv[1], **{k: np.asarray(v) for k, v in out.items()})
