"""User loop 5: a 3D cantilever with Newmark in acceleration form (Hughes, The Finite Element
Method, section 9.1) on assembled PETSc matrices, written as an engineer who knows the
textbook writes it: M, K assembled once, C = eta_m M + eta_k K, the effective matrix
A = M + gamma dt C + beta dt^2 K factorised once (KSP + LU), then predictor-corrector steps
on PETSc vectors. To save memory it keeps (records) only every RECORD_EVERY-th step.

    u~ = u_n + dt v_n + dt^2 (1/2 - beta) a_n,   v~ = v_n + dt (1 - gamma) a_n,
    A a_{n+1} = f(t_{n+1}) - C v~ - K u~,
    u_{n+1} = u~ + beta dt^2 a_{n+1},   v_{n+1} = v~ + gamma dt a_{n+1},

with gamma = 0.6, beta = (gamma + 1/2)^2 / 4 = 0.3025 (Newmark with numerical dissipation)
and Rayleigh damping. Body force rho g0 load(t) e_z; linear tetrahedra on the 1 x 0.1 x 0.1
bar clamped at x = 0 (20 x 4 x 4 cells: 1,575 dofs; quick 10 x 2 x 2: 297 dofs).
"""

import time

import numpy as np

import dolfinx_solver  # noqa: F401  (the PyPI DOLFINx wheel: before dolfinx)
import dolfinx
import dolfinx.fem.petsc
import ufl
from mpi4py import MPI
from petsc4py import PETSc

NAME = "newmark_every_k"

L, W = 1.0, 0.1
E, NU, RHO = 1000.0, 0.3, 1.0
G0 = 0.05
ETA_M, ETA_K = 0.1, 0.001
GAMMA = 0.6
BETA = (GAMMA + 0.5) ** 2 / 4
RECORD_EVERY = 5
SIZES = {
    "quick": {"cells": (10, 2, 2), "dt": 0.01, "t_train": 1.0, "t_test": 1.0},
    "default": {"cells": (20, 4, 4), "dt": 0.005, "t_train": 3.0, "t_test": 3.0},
}
OUTPUT = {"points": [[L, W / 2, W / 2]], "component": 2}


def train_load(t):
    """Weight switched on smoothly over 0.3, and reversed over [1.2, 1.5]."""
    on = np.sin(0.5 * np.pi * min(t / 0.3, 1.0)) ** 2
    flip = np.sin(0.5 * np.pi * np.clip((t - 1.2) / 0.3, 0, 1)) ** 2
    return float(on * (1 - 2 * flip))


def test_load(t):
    """Unseen: a 2 Hz shake that fades in."""
    return float((1 - np.exp(-(t / 0.3) ** 2)) * np.sin(2 * np.pi * 2.0 * t))


mu = E / 2 / (1 + NU)
lmbda = E * NU / (1 + NU) / (1 - 2 * NU)


def epsilon(u):
    return ufl.sym(ufl.grad(u))


def sigma(u):
    return lmbda * ufl.div(u) * ufl.Identity(3) + 2 * mu * epsilon(u)


def bc_clamped(V):
    dofs = dolfinx.fem.locate_dofs_geometrical(V, lambda x: np.isclose(x[0], 0.0))
    return [dolfinx.fem.dirichletbc(np.zeros(3), dofs, V)]


def simulate(load, t_end, *, size="default", on_step=None, dt=None, record_every=RECORD_EVERY):
    """The user's program; ``on_step(t, u, v, a, applied_load, applied_time)`` at t = 0 and
    after every ``record_every``-th step only."""
    dt = SIZES[size]["dt"] if dt is None else dt
    domain = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [L, W, W]], list(SIZES[size]["cells"]),
                                     dolfinx.mesh.CellType.tetrahedron)
    V = dolfinx.fem.functionspace(domain, ("Lagrange", 1, (3,)))
    bcs = bc_clamped(V)
    du, w = ufl.TrialFunction(V), ufl.TestFunction(V)
    b_z = dolfinx.fem.Constant(domain, np.zeros(3))

    M = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(RHO * ufl.inner(du, w) * ufl.dx), bcs=bcs)
    M.assemble()
    K = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(ufl.inner(sigma(du), epsilon(w)) * ufl.dx), bcs=bcs)
    K.assemble()
    C = M.copy()
    C.scale(ETA_M)
    C.axpy(ETA_K, K)
    A = M.copy()
    A.axpy(GAMMA * dt, C)
    A.axpy(BETA * dt**2, K)
    f_form = dolfinx.fem.form(RHO * ufl.inner(b_z, w) * ufl.dx)

    ksp = PETSc.KSP().create(domain.comm)
    ksp.setOperators(A)
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    ksp.getPC().setFactorSolverType("mumps")

    u = dolfinx.fem.Function(V, name="u")
    v = dolfinx.fem.Function(V, name="v")
    a = dolfinx.fem.Function(V, name="a")
    u_p, v_p = u.x.petsc_vec.duplicate(), v.x.petsc_vec.duplicate()
    rhs, tmp = u.x.petsc_vec.duplicate(), u.x.petsc_vec.duplicate()

    if on_step is not None:
        on_step(0.0, u, v, a, load(0.0), 0.0)
    num_steps = int(round(t_end / dt))
    start = time.perf_counter()
    for n in range(num_steps):
        t = (n + 1) * dt
        # predictors
        u.x.petsc_vec.copy(u_p)
        u_p.axpy(dt, v.x.petsc_vec)
        u_p.axpy(dt**2 * (0.5 - BETA), a.x.petsc_vec)
        v.x.petsc_vec.copy(v_p)
        v_p.axpy(dt * (1 - GAMMA), a.x.petsc_vec)
        # right-hand side f(t_{n+1}) - C v~ - K u~
        b_z.value[2] = -G0 * load(t)
        with rhs.localForm() as loc:
            loc.set(0.0)
        dolfinx.fem.petsc.assemble_vector(rhs, f_form)
        rhs.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        C.mult(v_p, tmp)
        rhs.axpy(-1.0, tmp)
        K.mult(u_p, tmp)
        rhs.axpy(-1.0, tmp)
        dolfinx.fem.petsc.set_bc(rhs, bcs)
        ksp.solve(rhs, a.x.petsc_vec)
        # correctors
        u_p.axpy(BETA * dt**2, a.x.petsc_vec)
        u_p.copy(u.x.petsc_vec)
        v_p.axpy(GAMMA * dt, a.x.petsc_vec)
        v_p.copy(v.x.petsc_vec)
        for f in (u, v, a):
            f.x.scatter_forward()
        if on_step is not None and (n + 1) % record_every == 0:
            on_step(t, u, v, a, load(t), t)
    seconds = time.perf_counter() - start
    for obj in (ksp, A, C, K, M, u_p, v_p, rhs, tmp):
        obj.destroy()
    return {"V": V, "dt": dt, "n_steps": num_steps, "seconds": seconds,
            "scheme": dict(scheme(), record_every=record_every)}


def scheme():
    return {"name": "Newmark (gamma = 0.6)", "alpha_m": 0.0, "alpha_f": 0.0, "beta": BETA,
            "gamma": GAMMA, "record_every": RECORD_EVERY}


def fe_forms(V):
    du, w = ufl.TrialFunction(V), ufl.TestFunction(V)
    mass = RHO * ufl.inner(du, w) * ufl.dx
    stiffness = ufl.inner(sigma(du), epsilon(w)) * ufl.dx
    return {"mass": mass, "damping": ETA_M * mass + ETA_K * stiffness, "stiffness": stiffness,
            "inputs": [RHO * ufl.inner(ufl.as_vector([0.0, 0.0, -G0]), w) * ufl.dx],
            "bcs": bc_clamped(V)}
