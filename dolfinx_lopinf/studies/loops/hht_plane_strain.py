"""User loop 2: a 2D plane-strain cantilever with a traction on its free end, HHT-alpha with
Rayleigh damping, written as the DOLFINx tutorials write a linear dynamics loop: a
``dolfinx.fem.petsc.LinearProblem`` (LU by MUMPS, the matrix reassembled every step) for the
new displacement, then the acceleration and velocity updated by interpolating
``dolfinx.fem.Expression``s of the Newmark formulas.

HHT-alpha (Hilber-Hughes-Taylor), written in the textbook form with alpha in (0, 1/3]:

    m(a_{n+1}, w) + (1 - alpha) c(v_{n+1}, w) + alpha c(v_n, w)
      + (1 - alpha) k(u_{n+1}, w) + alpha k(u_n, w) = <t(t_{n+1} - alpha dt), w>_{x = L},
    gamma = 1/2 + alpha,  beta = (1 + alpha)^2 / 4,

i.e. the generalised-alpha family with alpha_m = 0, alpha_f = alpha; c = eta_m m + eta_k k.
Beam L x H = 1 x 0.1 clamped at x = 0, Q1 quadrilaterals 48 x 15 (1,568 dofs; quick 24 x 4:
250 dofs), E = 1000, nu = 0.3, rho = 1, traction -p0 load(t) e_y on x = L.
"""

import time

import numpy as np

import dolfinx_solver  # noqa: F401  (the PyPI DOLFINx wheel: before dolfinx)
import dolfinx
import dolfinx.fem.petsc
import ufl
from mpi4py import MPI

NAME = "hht_plane_strain"

L, H = 1.0, 0.1
E, NU, RHO = 1000.0, 0.3, 1.0
P0 = 0.1
ETA_M, ETA_K = 0.02, 0.002
ALPHA = 0.1  # HHT: alpha_m = 0, alpha_f = alpha
GAMMA = 0.5 + ALPHA
BETA = (1 + ALPHA) ** 2 / 4

SIZES = {
    "quick": {"cells": (24, 4), "dt": 0.02, "t_train": 1.2, "t_test": 1.2},
    "default": {"cells": (48, 15), "dt": 0.01, "t_train": 3.0, "t_test": 3.0},
}
OUTPUT = {"points": [[L, H / 2, 0.0]], "component": 1}


def train_load(t):
    """Two tones that fade in."""
    return float((1 - np.exp(-t / 0.2)) * (np.sin(2 * np.pi * 0.6 * t) + 0.4 * np.sin(2 * np.pi * 2.2 * t)))


def test_load(t):
    """Unseen: two smooth pulses of opposite sign (zero at t = 0)."""
    pulse = np.sin(np.pi * np.clip(t / 0.8, 0, 1)) ** 2 - 0.6 * np.sin(np.pi * np.clip((t - 1.4) / 0.5, 0, 1)) ** 2
    return float(pulse)


mu = E / 2 / (1 + NU)
lmbda = E * NU / (1 + NU) / (1 - 2 * NU)  # plane strain


def epsilon(u):
    return ufl.sym(ufl.grad(u))


def sigma(u):
    return 2.0 * mu * epsilon(u) + lmbda * ufl.nabla_div(u) * ufl.Identity(len(u))


def m(u, w):
    return RHO * ufl.inner(u, w) * ufl.dx


def k(u, w):
    return ufl.inner(sigma(u), epsilon(w)) * ufl.dx


def c(u, w):
    return ETA_M * m(u, w) + ETA_K * k(u, w)


def free_end_ds(domain):
    fdim = domain.topology.dim - 1
    facets = dolfinx.mesh.locate_entities_boundary(domain, fdim, lambda x: np.isclose(x[0], L))
    facet_tag = dolfinx.mesh.meshtags(domain, fdim, facets, np.full(len(facets), 2, dtype=np.int32))
    return ufl.Measure("ds", domain=domain, subdomain_data=facet_tag)


def clamp(V):
    domain = V.mesh
    fdim = domain.topology.dim - 1
    left = dolfinx.mesh.locate_entities_boundary(domain, fdim, lambda x: np.isclose(x[0], 0.0))
    dofs = dolfinx.fem.locate_dofs_topological(V, fdim, left)
    return [dolfinx.fem.dirichletbc(np.zeros(2), dofs, V)]


def simulate(load, t_end, *, size="default", on_step=None, dt=None):
    """The user's program; ``on_step(t, u, v, a, applied_load, applied_time)`` at t = 0 and
    after each step."""
    dt = SIZES[size]["dt"] if dt is None else dt
    nx, ny = SIZES[size]["cells"]
    domain = dolfinx.mesh.create_rectangle(MPI.COMM_WORLD, [[0.0, 0.0], [L, H]], [nx, ny],
                                           cell_type=dolfinx.mesh.CellType.quadrilateral)
    V = dolfinx.fem.functionspace(domain, ("Lagrange", 1, (2,)))
    bcs = clamp(V)
    ds = free_end_ds(domain)

    u = dolfinx.fem.Function(V, name="u")
    u_n = dolfinx.fem.Function(V)
    v_n = dolfinx.fem.Function(V)
    a_n = dolfinx.fem.Function(V)
    v = dolfinx.fem.Function(V, name="v")
    a = dolfinx.fem.Function(V, name="a")
    T = dolfinx.fem.Constant(domain, np.zeros(2))

    w = ufl.TestFunction(V)
    du = ufl.TrialFunction(V)

    def newmark_a(u):
        return (u - u_n - dt * v_n) / (BETA * dt**2) - (1 - 2 * BETA) / (2 * BETA) * a_n

    def newmark_v(a):
        return v_n + dt * ((1 - GAMMA) * a_n + GAMMA * a)

    F = (m(newmark_a(du), w)
         + (1 - ALPHA) * c(newmark_v(newmark_a(du)), w) + ALPHA * c(v_n, w)
         + (1 - ALPHA) * k(du, w) + ALPHA * k(u_n, w)
         - ufl.inner(T, w) * ds(2))
    problem = dolfinx.fem.petsc.LinearProblem(
        ufl.lhs(F), ufl.rhs(F), u=u, bcs=bcs, petsc_options_prefix="hht_",
        petsc_options={"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"})
    a_expr = dolfinx.fem.Expression(newmark_a(u), V.element.interpolation_points)
    v_expr = dolfinx.fem.Expression(newmark_v(a), V.element.interpolation_points)

    if on_step is not None:
        on_step(0.0, u, v, a, load(0.0), 0.0)
    num_steps = int(round(t_end / dt))
    start = time.perf_counter()
    for n in range(num_steps):
        t = (n + 1) * dt
        t_alpha = t - ALPHA * dt
        T.value[1] = -P0 * load(t_alpha)
        problem.solve()
        a.interpolate(a_expr)
        v.interpolate(v_expr)
        u_n.x.array[:] = u.x.array
        v_n.x.array[:] = v.x.array
        a_n.x.array[:] = a.x.array
        if on_step is not None:
            on_step(t, u, v, a, load(t_alpha), t_alpha)
    seconds = time.perf_counter() - start
    return {"V": V, "dt": dt, "n_steps": num_steps, "seconds": seconds, "scheme": scheme()}


def scheme():
    return {"name": "HHT-alpha", "alpha_m": 0.0, "alpha_f": ALPHA, "beta": BETA, "gamma": GAMMA,
            "record_every": 1}


def fe_forms(V):
    du, w = ufl.TrialFunction(V), ufl.TestFunction(V)
    ds = free_end_ds(V.mesh)
    return {"mass": m(du, w), "damping": c(du, w), "stiffness": k(du, w),
            "inputs": [ufl.inner(ufl.as_vector([0.0, -P0]), w) * ds(2)], "bcs": clamp(V)}
