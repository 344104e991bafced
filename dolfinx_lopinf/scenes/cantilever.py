"""A 3D cantilever under a time-dependent vertical tip traction, in plain dolfinx.

The model of ``demos/existing_code.py`` (which stays a self-contained "user's own code"
example), kept here so that the package - the stability suite's forced case - does not
depend on the source tree: linear elasticity on [0, 1] x [0, 0.1] x [0, 0.1] hexahedra,
clamped at x = 0, a vertical traction -p(t) e_z on x = 1, Rayleigh damping
C = alpha M + beta K, Newmark average acceleration (gamma = 1/2, beta = 1/4), MUMPS LU.
Same constants, mesh, load and loop as the demo; change both together.
"""

from __future__ import annotations

import time

import numpy as np

from ..fem._dolfinx import MPI, PETSc, dolfinx, ufl

LENGTH, WIDTH, HEIGHT = 1.0, 0.1, 0.1
E_MOD, NU, RHO = 1.0e5, 0.3, 1.0
ALPHA, BETA = 0.5, 2e-4  # Rayleigh damping
DT = 1e-3


def train_load(t):
    """A multi-frequency load that excites the first bending modes (0.5 - 9 Hz)."""
    return (np.sin(2 * np.pi * 0.5 * t) + 0.6 * np.sin(2 * np.pi * 3.1 * t + 0.3)
            + 0.4 * np.sin(2 * np.pi * 5.3 * t) + 0.3 * np.sin(2 * np.pi * 8.9 * t + 1.0))


def simulate(load, t_end, n_cells=(30, 4, 4), recorder_factory=None, comm=MPI.COMM_WORLD):
    """Run the cantilever from rest under the tip load ``load(t)`` up to ``t_end``.

    ``recorder_factory(q)`` (optional) returns an object with ``record(t, q, inputs=[p])``,
    e.g. a :class:`dolfinx_lopinf.SnapshotRecorder`; it is called at t = 0 and every step.

    Returns:
        (V, recorder, seconds): the function space, the recorder (or None) and the wall time
        of the time loop (max over ranks).
    """
    msh = dolfinx.mesh.create_box(comm, [[0, 0, 0], [LENGTH, WIDTH, HEIGHT]], list(n_cells),
                                  dolfinx.mesh.CellType.hexahedron)
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1, (3,)))
    lmbda = E_MOD * NU / ((1 + NU) * (1 - 2 * NU))
    mu = E_MOD / (2 * (1 + NU))

    def sigma(w):
        eps = ufl.sym(ufl.grad(w))
        return lmbda * ufl.tr(eps) * ufl.Identity(3) + 2 * mu * eps

    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    fdim = msh.topology.dim - 1
    clamped = dolfinx.mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[0], 0.0))
    bc = dolfinx.fem.dirichletbc(np.zeros(3), dolfinx.fem.locate_dofs_topological(V, fdim, clamped), V)
    tip = dolfinx.mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[0], LENGTH))
    tags = dolfinx.mesh.meshtags(msh, fdim, tip, np.full(len(tip), 1, dtype=np.int32))
    ds = ufl.Measure("ds", domain=msh, subdomain_data=tags)
    p = dolfinx.fem.Constant(msh, 0.0)
    traction = ufl.as_vector((0.0, 0.0, -p))

    m_form = dolfinx.fem.form(RHO * ufl.inner(u, v) * ufl.dx)
    k_form = dolfinx.fem.form(ufl.inner(sigma(u), ufl.sym(ufl.grad(v))) * ufl.dx)
    f_form = dolfinx.fem.form(ufl.inner(traction, v) * ds(1))
    M = dolfinx.fem.petsc.assemble_matrix(m_form, bcs=[bc])
    M.assemble()
    K = dolfinx.fem.petsc.assemble_matrix(k_form, bcs=[bc])
    K.assemble()
    C = M.copy()
    C.scale(ALPHA)
    C.axpy(BETA, K)
    A = M.copy()
    A.axpy(0.5 * DT, C)
    A.axpy(0.25 * DT**2, K)
    solver = PETSc.KSP().create(comm)
    solver.setOperators(A)
    solver.setType("preonly")
    solver.getPC().setType("lu")
    solver.getPC().setFactorSolverType("mumps")

    q, vel, acc = (dolfinx.fem.Function(V) for _ in range(3))
    q_star, v_star = q.x.petsc_vec.duplicate(), q.x.petsc_vec.duplicate()
    rhs, tmp = q.x.petsc_vec.duplicate(), q.x.petsc_vec.duplicate()
    recorder = recorder_factory(q) if recorder_factory else None

    n_steps = int(round(t_end / DT))
    t0 = time.perf_counter()
    if recorder is not None:
        recorder.record(0.0, q, inputs=[load(0.0)])
    for n in range(1, n_steps + 1):
        t = n * DT
        q.x.petsc_vec.copy(q_star)
        q_star.axpy(DT, vel.x.petsc_vec)
        q_star.axpy(0.25 * DT**2, acc.x.petsc_vec)
        vel.x.petsc_vec.copy(v_star)
        v_star.axpy(0.5 * DT, acc.x.petsc_vec)
        p.value = load(t)
        with rhs.localForm() as loc:
            loc.set(0.0)
        dolfinx.fem.petsc.assemble_vector(rhs, f_form)
        rhs.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        C.mult(v_star, tmp)
        rhs.axpy(-1.0, tmp)
        K.mult(q_star, tmp)
        rhs.axpy(-1.0, tmp)
        dolfinx.fem.petsc.set_bc(rhs, [bc])
        solver.solve(rhs, acc.x.petsc_vec)
        q_star.copy(q.x.petsc_vec)
        q.x.petsc_vec.axpy(0.25 * DT**2, acc.x.petsc_vec)
        v_star.copy(vel.x.petsc_vec)
        vel.x.petsc_vec.axpy(0.5 * DT, acc.x.petsc_vec)
        for f in (q, vel, acc):
            f.x.scatter_forward()
        if recorder is not None:
            recorder.record(t, q, inputs=[load(t)])
    seconds = comm.allreduce(time.perf_counter() - t0, op=MPI.MAX)
    return V, recorder, seconds
