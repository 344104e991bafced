"""User loop 3: a vibrating membrane, u_tt = c^2 Laplace(u) + f(t) g(x) on the unit square,
u = 0 on the boundary, explicit central differences with a lumped mass - the way an explicit
wave solver is written in DOLFINx: the lumped mass from vertex quadrature (diagonal for P1),
the right-hand side f g - c^2 grad u . grad v assembled every step (matrix-free), then a
pointwise update of the dof arrays:

    m_L (u^{n+1} - 2 u^n + u^{n-1}) / dt^2 = b(t_n; u^n) = (f(t_n) g, v) - c^2 (grad u^n, grad v),
    u^{n+1} = 0 on the boundary;  first step from u^{-1} = u^0 - dt v^0 + dt^2/2 a^0.

This is Newmark with beta = 0, gamma = 1/2 (no damping): the step to t_{n+1} uses the load at
t_n, so ``applied_time`` = t_n for the state at t_{n+1}. P1 triangles on a 44 x 44 grid
(2,025 dofs, 1,849 free; quick 16 x 16: 289 dofs), c = 1, dt = 0.01 below the CFL limit
(lumped P1: dt < 2 / sqrt(lambda_max(M_L^-1 K)) = 0.01608 here, 0.0444 quick; the rule of thumb
h / (c sqrt 2) = 0.0161). The source g is a Gaussian of width 0.15 at (0.3, 0.4).
"""

import time

import numpy as np

import dolfinx_solver  # noqa: F401  (the PyPI DOLFINx wheel: before dolfinx)
import dolfinx
import dolfinx.fem.petsc
import ufl
from mpi4py import MPI
from petsc4py import PETSc

NAME = "membrane_central_difference"

C_WAVE = 1.0
SOURCE_AT, SOURCE_WIDTH = (0.3, 0.4), 0.15
SIZES = {
    "quick": {"cells": 16, "dt": 0.02, "t_train": 1.0, "t_test": 1.0, "t_free": 4.0},
    "default": {"cells": 44, "dt": 0.01, "t_train": 2.0, "t_test": 2.0, "t_free": 20.0,
                "extra_r": (16,)},  # the study adds this r: a wave needs more modes
}
OUTPUT = {"points": [[0.7, 0.6, 0.0]], "component": None}


def train_load(t):
    """A forced source: a 1.5 Hz tone under a slow envelope, plus a 0.6 Hz one."""
    return float(np.sin(np.pi * min(t / 1.5, 1.0)) * np.sin(2 * np.pi * 1.5 * t)
                 + 0.5 * np.sin(2 * np.pi * 0.6 * t))


def test_load(t):
    """Unseen: a Ricker-like pulse and a 1 Hz tone (value 0 at t = 0)."""
    s = (t - 0.5) / 0.24
    return float((1 - 2 * s**2) * np.exp(-s**2) * min(t / 0.1, 1.0) - 0.5 * np.sin(2 * np.pi * 1.0 * t))


def free_load(t):
    """For the long free run: a smooth pulse over [0, 0.5], then nothing."""
    return float(np.sin(np.pi * t / 0.5) ** 2) if t < 0.5 else 0.0


def source_shape(domain):
    x = ufl.SpatialCoordinate(domain)
    r2 = (x[0] - SOURCE_AT[0]) ** 2 + (x[1] - SOURCE_AT[1]) ** 2
    return 10.0 * ufl.exp(-r2 / SOURCE_WIDTH**2)


def lumped_dx(domain):
    return ufl.Measure("dx", domain=domain, metadata={"quadrature_rule": "vertex", "quadrature_degree": 1})


def boundary_bc(V):
    domain = V.mesh
    tdim = domain.topology.dim
    domain.topology.create_connectivity(tdim - 1, tdim)
    facets = dolfinx.mesh.exterior_facet_indices(domain.topology)
    dofs = dolfinx.fem.locate_dofs_topological(V, tdim - 1, facets)
    return dolfinx.fem.dirichletbc(0.0, dofs, V)


def simulate(load, t_end, *, size="default", on_step=None, dt=None, u0=None):
    """The user's program; ``on_step(t, u, None, None, applied_load, applied_time)`` at t = 0
    and after each step. ``u0``: optional initial displacement, a callable x -> values
    (interpolated); the initial velocity is zero."""
    dt = SIZES[size]["dt"] if dt is None else dt
    n = SIZES[size]["cells"]
    domain = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, n, n, dolfinx.mesh.CellType.triangle)
    V = dolfinx.fem.functionspace(domain, ("Lagrange", 1))
    bc = boundary_bc(V)
    bdofs = bc.dof_indices()[0]

    u_n = dolfinx.fem.Function(V, name="u")  # u^n
    u_nm1 = dolfinx.fem.Function(V)          # u^{n-1}
    u_np1 = dolfinx.fem.Function(V)          # u^{n+1}
    if u0 is not None:
        u_n.interpolate(u0)
        u_n.x.array[bdofs] = 0.0
    f = dolfinx.fem.Constant(domain, 0.0)
    v = ufl.TestFunction(V)
    g = source_shape(domain)

    # lumped mass: vertex quadrature makes the P1 mass matrix diagonal
    M = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(ufl.TrialFunction(V) * v * lumped_dx(domain)))
    M.assemble()
    m_lumped = M.getDiagonal()
    m_inv = 1.0 / m_lumped.array.copy()

    rhs = dolfinx.fem.form(f * g * v * ufl.dx - C_WAVE**2 * ufl.inner(ufl.grad(u_n), ufl.grad(v)) * ufl.dx)
    b = dolfinx.fem.petsc.create_vector(V)
    n_owned = V.dofmap.index_map.size_local

    def accel():
        with b.localForm() as loc:
            loc.set(0.0)
        dolfinx.fem.petsc.assemble_vector(b, rhs)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return b.array[:n_owned] * m_inv

    # start: u^{-1} = u^0 - dt v^0 + dt^2/2 a^0 (v^0 = 0)
    f.value = load(0.0)
    u_nm1.x.array[:n_owned] = u_n.x.array[:n_owned] + 0.5 * dt**2 * accel()
    if on_step is not None:
        on_step(0.0, u_n, None, None, load(0.0), 0.0)
    num_steps = int(round(t_end / dt))
    start = time.perf_counter()
    for k in range(num_steps):
        t = k * dt
        f.value = load(t)
        u_np1.x.array[:n_owned] = 2 * u_n.x.array[:n_owned] - u_nm1.x.array[:n_owned] + dt**2 * accel()
        u_np1.x.array[bdofs] = 0.0
        u_np1.x.scatter_forward()
        u_nm1.x.array[:] = u_n.x.array
        u_n.x.array[:] = u_np1.x.array
        if on_step is not None:
            on_step(t + dt, u_n, None, None, load(t), t)
    seconds = time.perf_counter() - start
    M.destroy(), b.destroy(), m_lumped.destroy()
    return {"V": V, "dt": dt, "n_steps": num_steps, "seconds": seconds, "scheme": scheme()}


def scheme():
    return {"name": "central-differences", "alpha_m": 0.0, "alpha_f": 0.0, "beta": 0.0, "gamma": 0.5,
            "record_every": 1}


def fe_forms(V):
    domain = V.mesh
    du, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    return {"mass": du * v * lumped_dx(domain), "damping": None,
            "stiffness": C_WAVE**2 * ufl.inner(ufl.grad(du), ufl.grad(v)) * ufl.dx,
            "inputs": [source_shape(domain) * v * ufl.dx], "bcs": [boundary_bc(V)]}
