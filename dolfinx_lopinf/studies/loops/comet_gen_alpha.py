"""User loop 1: a 3D cantilever under an end traction, generalised-alpha with Rayleigh damping,
written the way the COMET / FEniCS "elastodynamics" numerical tour (J. Bleyer) writes it.

The tour's structure, ported to DOLFINx 0.11 as a user would: module-level ``m``, ``k``, ``c``
and ``Wext`` forms; ``update_a``, ``update_v`` (usable on UFL objects and on arrays, the
``ufl=`` switch), ``avg``; the residual written in the unknown displacement ``du``,
``a_form = lhs(res)``, ``L_form = rhs(res)``; the matrix assembled once and factorised by LU,
the right-hand side assembled every step with the traction evaluated at t_{n+1-alpha_f}; then
``update_fields(u, u_old, v_old, a_old)`` on the dof arrays.

Scheme (Chung-Hulbert family, the tour's parameters): alpha_m = 0.2, alpha_f = 0.4,
gamma = 1/2 + alpha_f - alpha_m = 0.7, beta = (gamma + 1/2)^2 / 4 = 0.36;

    m(a_{n+1-am}, w) + c(v_{n+1-af}, w) + k(u_{n+1-af}, w) = Wext(t_{n+1-af}; w),
    x_{n+1-alpha} = alpha x_n + (1 - alpha) x_{n+1}  (the tour's ``avg``),

with Rayleigh damping c = eta_m m + eta_k k. Beam L x B x H = 1 x 0.1 x 0.04 clamped at
x = 0, Q1 hexahedra (24 x 4 x 2 cells: 1,125 dofs; quick 12 x 2 x 1: 234 dofs), E = 1000,
nu = 0.3, rho = 1, traction p0 load(t) e_y on the end x = L. The training load is the tour's:
ramped over [0, 0.8] and then released at once (a jump to zero); the test load is smooth.
"""

import time

import numpy as np

import dolfinx_solver  # noqa: F401  (the PyPI DOLFINx wheel: before dolfinx)
import dolfinx
import dolfinx.fem.petsc  # noqa: F401  (makes fem.petsc available)
from dolfinx import fem, mesh
import ufl
from mpi4py import MPI
from petsc4py import PETSc

NAME = "comet_gen_alpha"

# Geometry, material, loading (the tour's values; Rayleigh damping switched on)
L, B, H = 1.0, 0.1, 0.04
E, NU, RHO = 1000.0, 0.3, 1.0
LMBDA = E * NU / (1 + NU) / (1 - 2 * NU)
MU = E / 2 / (1 + NU)
ETA_M, ETA_K = 0.05, 0.005
P0 = 1.0
CUTOFF_TC = 0.8

# Generalized-alpha method parameters
ALPHA_M = 0.2
ALPHA_F = 0.4
GAMMA = 0.5 + ALPHA_F - ALPHA_M
BETA = (GAMMA + 0.5) ** 2 / 4.0

SIZES = {
    "quick": {"cells": (12, 2, 1), "dt": 0.04, "t_train": 1.6, "t_test": 1.6},
    "default": {"cells": (24, 4, 2), "dt": 0.02, "t_train": 4.0, "t_test": 4.0},
}
#: where the study reads its output: the tip deflection u_y at the end's centre
OUTPUT = {"points": [[L, B / 2, H / 2]], "component": 1}


def train_load(t):
    """The tour's load: ramped up to 1 over CUTOFF_TC, then released at once."""
    return t / CUTOFF_TC if t <= CUTOFF_TC else 0.0


def test_load(t):
    """Unseen: a smooth push-pull (zero value and slope at t = 0)."""
    return float(0.8 * np.sin(np.pi * t / 1.5) ** 2 * np.cos(2 * np.pi * t / 3.0))


def epsilon(v):
    return ufl.sym(ufl.grad(v))


def sigma(v):
    return LMBDA * ufl.tr(epsilon(v)) * ufl.Identity(3) + 2.0 * MU * epsilon(v)


# Mass form
def m(u, u_):
    return RHO * ufl.inner(u, u_) * ufl.dx


# Elastic stiffness form
def k(u, u_):
    return ufl.inner(sigma(u), epsilon(u_)) * ufl.dx


# Rayleigh damping form
def c(u, u_):
    return ETA_M * m(u, u_) + ETA_K * k(u, u_)


def clamped(x):
    return np.isclose(x[0], 0.0)


def right(x):
    return np.isclose(x[0], L)


def end_measure(domain):
    """ds(1): the loaded end x = L."""
    fdim = domain.topology.dim - 1
    facets = mesh.locate_entities_boundary(domain, fdim, right)
    tags = mesh.meshtags(domain, fdim, facets, np.full_like(facets, 1))
    return ufl.Measure("ds", domain=domain, subdomain_data=tags)


def build(size="default"):
    cells = SIZES[size]["cells"]
    domain = mesh.create_box(MPI.COMM_WORLD, [[0.0, 0.0, 0.0], [L, B, H]], list(cells),
                             mesh.CellType.hexahedron)
    V = fem.functionspace(domain, ("Lagrange", 1, (3,)))
    return domain, V


def simulate(load, t_end, *, size="default", on_step=None, dt=None):
    """The user's program; ``on_step(t, u, v, a, applied_load, applied_time)`` at t = 0 and
    after each step. Returns V, dt, the scheme and the wall time of the loop."""
    dt_ = SIZES[size]["dt"] if dt is None else dt
    domain, V = build(size)
    bcs = [fem.dirichletbc(np.zeros(3), fem.locate_dofs_geometrical(V, clamped), V)]
    ds = end_measure(domain)

    u_ = ufl.TestFunction(V)
    du = ufl.TrialFunction(V)
    u = fem.Function(V, name="Displacement")
    u_old = fem.Function(V)
    v_old = fem.Function(V)
    a_old = fem.Function(V)
    p = fem.Constant(domain, np.zeros(3))
    dt = fem.Constant(domain, dt_)

    # Work of external forces
    def Wext(u_):
        return ufl.dot(u_, p) * ds(1)

    # Update formula for acceleration
    # a = 1/(2*beta)*((u - u0 - v0*dt)/(0.5*dt*dt) - (1-2*beta)*a0)
    def update_a(u, u_old, v_old, a_old, ufl=True):
        dt__ = dt if ufl else float(dt.value)
        return (u - u_old - dt__ * v_old) / BETA / dt__**2 - (1 - 2 * BETA) / 2 / BETA * a_old

    # Update formula for velocity
    # v = dt * ((1-gamma)*a0 + gamma*a) + v0
    def update_v(a, u_old, v_old, a_old, ufl=True):
        dt__ = dt if ufl else float(dt.value)
        return v_old + dt__ * ((1 - GAMMA) * a_old + GAMMA * a)

    def update_fields(u, u_old, v_old, a_old):
        """Update fields at the end of each time step."""
        u_vec, u0_vec = u.x.array, u_old.x.array
        v0_vec, a0_vec = v_old.x.array, a_old.x.array
        a_vec = update_a(u_vec, u0_vec, v0_vec, a0_vec, ufl=False)
        v_vec = update_v(a_vec, u0_vec, v0_vec, a0_vec, ufl=False)
        v_old.x.array[:], a_old.x.array[:] = v_vec, a_vec
        u_old.x.array[:] = u.x.array

    def avg(x_old, x_new, alpha):
        return alpha * x_old + (1 - alpha) * x_new

    # Residual
    a_new = update_a(du, u_old, v_old, a_old, ufl=True)
    v_new = update_v(a_new, u_old, v_old, a_old, ufl=True)
    res = (m(avg(a_old, a_new, ALPHA_M), u_) + c(avg(v_old, v_new, ALPHA_F), u_)
           + k(avg(u_old, du, ALPHA_F), u_) - Wext(u_))
    a_form = fem.form(ufl.lhs(res))
    L_form = fem.form(ufl.rhs(res))

    # Define solver for reusing factorization
    K = fem.petsc.assemble_matrix(a_form, bcs=bcs)
    K.assemble()
    solver = PETSc.KSP().create(domain.comm)
    solver.setOperators(K)
    solver.setType(PETSc.KSP.Type.PREONLY)
    solver.getPC().setType(PETSc.PC.Type.LU)
    solver.getPC().setFactorSolverType("mumps")
    b = fem.petsc.create_vector(V)

    num_steps = int(round(t_end / dt_))
    time_ = np.linspace(0, num_steps * dt_, num_steps + 1)
    if on_step is not None:
        on_step(0.0, u, v_old, a_old, load(0.0), 0.0)
    start = time.perf_counter()
    for i, dti in enumerate(np.diff(time_)):
        t = time_[i + 1]
        t_load = t - float(ALPHA_F * dti)
        p.value[1] = P0 * load(t_load)

        # Solve for new displacement
        with b.localForm() as b_local:
            b_local.set(0.0)
        fem.petsc.assemble_vector(b, L_form)
        fem.petsc.apply_lifting(b, [a_form], [bcs])
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        fem.petsc.set_bc(b, bcs)
        solver.solve(b, u.x.petsc_vec)
        u.x.scatter_forward()

        # Update old fields with new quantities
        update_fields(u, u_old, v_old, a_old)
        if on_step is not None:
            on_step(t, u, v_old, a_old, load(t_load), t_load)
    seconds = time.perf_counter() - start
    solver.destroy(), K.destroy(), b.destroy()
    return {"V": V, "dt": dt_, "n_steps": num_steps, "seconds": seconds, "bcs": bcs,
            "scheme": scheme()}


def scheme():
    return {"name": "generalised-alpha", "alpha_m": ALPHA_M, "alpha_f": ALPHA_F, "beta": BETA,
            "gamma": GAMMA, "record_every": 1}


def fe_forms(V):
    """The loop's own forms, for the intrusive reference: mass, damping, stiffness (bilinear),
    the input form for a unit load amplitude (linear) and the Dirichlet conditions."""
    domain = V.mesh
    du, u_ = ufl.TrialFunction(V), ufl.TestFunction(V)
    ds = end_measure(domain)
    e_y = ufl.as_vector([0.0, P0, 0.0])
    bcs = [fem.dirichletbc(np.zeros(3), fem.locate_dofs_geometrical(V, clamped), V)]
    return {"mass": m(du, u_), "damping": c(du, u_), "stiffness": k(du, u_),
            "inputs": [ufl.dot(u_, e_y) * ds(1)], "bcs": bcs}
