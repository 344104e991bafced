"""User loop 4: linear elastodynamics with average-acceleration Newmark written as a residual in
the unknown displacement and solved by ``dolfinx.fem.petsc.NonlinearProblem`` (SNES) every
step - what users do when they start from the hyperelasticity demo and keep the loop when the
material is linear (Newton converges in one iteration).

    F(u_{n+1}; w) = (rho a_{n+1}(u_{n+1}), w) + (sigma(u_{n+1}), eps(w)) - (q(t_{n+1}), w)_top = 0,
    a_{n+1} = (u_{n+1} - u_n - dt v_n) / (beta dt^2) - (1 / (2 beta) - 1) a_n,
    v_{n+1} = v_n + dt ((1 - gamma) a_n + gamma a_{n+1}),   beta = 1/4, gamma = 1/2, no damping.

A clamped-clamped plane-stress beam 2 x 0.2 under a pressure q = -p0 load(t) e_y on its top
face, P2 triangles 40 x 4 ("right" diagonals: 1,458 dofs; quick 16 x 2: 330 dofs), E = 1000,
nu = 0.3, rho = 1. This loop is the positive control: average-acceleration Newmark is the
relation lo.fit knows exactly today.
"""

import time

import numpy as np

import dolfinx_solver  # noqa: F401  (the PyPI DOLFINx wheel: before dolfinx)
import dolfinx
from dolfinx import fem, mesh
from dolfinx.fem.petsc import NonlinearProblem
import ufl
from mpi4py import MPI

NAME = "newmark_nonlinear_problem"

LX, LY = 2.0, 0.2
E, NU, RHO = 1000.0, 0.3, 1.0
P0 = 0.2
BETA, GAMMA = 0.25, 0.5
SIZES = {
    "quick": {"cells": (16, 2), "dt": 0.01, "t_train": 0.6, "t_test": 0.6},
    "default": {"cells": (40, 4), "dt": 0.005, "t_train": 1.5, "t_test": 1.5},
}
OUTPUT = {"points": [[LX / 2, LY / 2, 0.0]], "component": 1}  # mid-span deflection


def train_load(t):
    """Ramp to 1 over 0.2, hold, switch off at 0.5, then a 3 Hz shake from 0.9."""
    base = min(t / 0.2, 1.0) if t < 0.5 else 0.0
    return float(base + (0.5 * np.sin(2 * np.pi * 3.0 * (t - 0.9)) if t > 0.9 else 0.0))


def test_load(t):
    """Unseen: a smooth pulse and a slower reversed one."""
    return float(np.sin(np.pi * min(t / 0.4, 1.0)) ** 2 - 0.7 * np.sin(np.pi * np.clip((t - 0.6) / 0.7, 0, 1)) ** 2)


def eps(u):
    return ufl.sym(ufl.grad(u))


mu = E / (2 * (1 + NU))
lmbda = E * NU / ((1 + NU) * (1 - 2 * NU))
lmbda = 2 * mu * lmbda / (lmbda + 2 * mu)  # plane stress


def sigma(u):
    return lmbda * ufl.tr(eps(u)) * ufl.Identity(2) + 2 * mu * eps(u)


def top_ds(domain):
    fdim = domain.topology.dim - 1
    top = mesh.locate_entities_boundary(domain, fdim, lambda x: np.isclose(x[1], LY))
    tags = mesh.meshtags(domain, fdim, top, np.full(len(top), 1, dtype=np.int32))
    return ufl.Measure("ds", domain=domain, subdomain_data=tags)


def clamped_ends(V):
    dofs = fem.locate_dofs_geometrical(V, lambda x: np.isclose(x[0], 0.0) | np.isclose(x[0], LX))
    return [fem.dirichletbc(np.zeros(2, dtype=dolfinx.default_scalar_type), dofs, V)]


def simulate(load, t_end, *, size="default", on_step=None, dt=None):
    """The user's program; ``on_step(t, u, v, a, applied_load, applied_time)`` at t = 0 and
    after each step. Returns also the SNES iteration counts."""
    dt_ = SIZES[size]["dt"] if dt is None else dt
    nx, ny = SIZES[size]["cells"]
    domain = mesh.create_rectangle(MPI.COMM_WORLD, [np.array([0.0, 0.0]), np.array([LX, LY])],
                                   [nx, ny], mesh.CellType.triangle)
    V = fem.functionspace(domain, ("Lagrange", 2, (domain.geometry.dim,)))
    bcs = clamped_ends(V)
    ds = top_ds(domain)

    u = fem.Function(V, name="displacement")   # unknown u_{n+1}
    u_n = fem.Function(V)
    v_n = fem.Function(V, name="velocity")
    a_n = fem.Function(V, name="acceleration")
    w = ufl.TestFunction(V)
    dt = fem.Constant(domain, dt_)
    q = fem.Constant(domain, np.zeros(2))

    a_new = (u - u_n - dt * v_n) / (BETA * dt**2) - (1 / (2 * BETA) - 1) * a_n
    F = (RHO * ufl.inner(a_new, w) * ufl.dx + ufl.inner(sigma(u), eps(w)) * ufl.dx
         - ufl.inner(q, w) * ds(1))

    petsc_options = {"snes_type": "newtonls", "snes_linesearch_type": "none",
                     "snes_atol": 1e-10, "snes_rtol": 1e-10, "snes_error_if_not_converged": True,
                     "ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"}
    problem = NonlinearProblem(F, u, bcs=bcs, petsc_options=petsc_options,
                               petsc_options_prefix="elastodynamics_")

    if on_step is not None:
        on_step(0.0, u, v_n, a_n, load(0.0), 0.0)
    num_steps = int(round(t_end / dt_))
    iterations = []
    start = time.perf_counter()
    for n in range(num_steps):
        t = (n + 1) * dt_
        q.value[1] = -P0 * load(t)
        problem.solve()
        assert problem.solver.getConvergedReason() > 0
        iterations.append(problem.solver.getIterationNumber())
        u.x.scatter_forward()
        # Newmark updates of the acceleration and velocity, on the dof arrays
        a_new_ = (u.x.array - u_n.x.array - dt_ * v_n.x.array) / (BETA * dt_**2) \
            - (1 / (2 * BETA) - 1) * a_n.x.array
        v_n.x.array[:] += dt_ * ((1 - GAMMA) * a_n.x.array + GAMMA * a_new_)
        a_n.x.array[:] = a_new_
        u_n.x.array[:] = u.x.array
        if on_step is not None:
            on_step(t, u, v_n, a_n, load(t), t)
    seconds = time.perf_counter() - start
    return {"V": V, "dt": dt_, "n_steps": num_steps, "seconds": seconds, "scheme": scheme(),
            "snes_iterations": iterations}


def scheme():
    return {"name": "Newmark (average acceleration)", "alpha_m": 0.0, "alpha_f": 0.0, "beta": BETA,
            "gamma": GAMMA, "record_every": 1}


def fe_forms(V):
    du, w = ufl.TrialFunction(V), ufl.TestFunction(V)
    return {"mass": RHO * ufl.inner(du, w) * ufl.dx, "damping": None,
            "stiffness": ufl.inner(sigma(du), eps(w)) * ufl.dx,
            "inputs": [ufl.inner(ufl.as_vector([0.0, -P0]), w) * top_ds(V.mesh)(1)],
            "bcs": clamped_ends(V)}
