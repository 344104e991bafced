"""A soft 3D cantilever in large deformation: St. Venant-Kirchhoff (or neo-Hookean) elasticity.

    L = integral( 1/2 rho u_t . u_t - W(E(u)) ) dx,   E = 1/2 (F^T F - I),  F = I + grad u,
    SVK:          W = lambda/2 (tr E)^2 + mu tr(E E)                       (quartic in grad u)
    neo-Hookean:  W = mu/2 (tr F^T F - 3) - mu ln J + lambda/2 (ln J)^2   (not polynomial)
    linear:       W = lambda/2 (tr eps)^2 + mu tr(eps eps)                 (the small-strain model)
    virtual work  f(u, u_t; v) = a s(t) b . v  -  alpha rho u_t . v  -  beta sigma_lin(u_t) : eps(v)

on the beam [0, 1] x [0, 0.1] x [0, 0.1] clamped at x = 0, under a dead (follower-free)
vertical body load b = -e_z of amplitude a with the time profile s(t): a smooth ramp to 1
over [0, T_RAMP], held to T_HOLD, smoothly released over T_RELEASE, then free vibration with
light Rayleigh damping (alpha M + beta K_0, K_0 the stiffness at u = 0). The load is an input
u(t) = a s(t) of the reduced model (one channel); the potential of the elastic energy is all
that is nonlinear.

Discretisation: Q2 hexahedra (27-node Lagrange), default 10 x 1 x 1 cells (567 dofs, 540
free). Q2 is chosen over P1/Q1 because linear elements lock in bending: one Q2 cell through
the thickness represents the linear bending stress exactly, so a coarse, fast mesh still bends
correctly (the first bending frequency is within 1 % of the Euler-Bernoulli value 5.10 Hz).
Quadrature: degree 4 (3 x 3 x 3 Gauss points): the mass is exact and the potential is still
an exact quartic polynomial of the nodal values under any fixed rule - which is all the
polynomial reduced model needs.

Time integration: the package's midpoint variational integrator (:class:`MidpointIntegrator`,
PETSc SNES Newton with LU at every step for the nonlinear materials, one factorisation for the
linear one), dt = 2e-3 s. Its snapshots obey the discrete forced Euler-Lagrange relation

    M D2_k + C D1_k + 1/2 (F(q_{k-1/2}) + F(q_{k+1/2})) = B Ubar_k,
    q_{k+-1/2} = (q_k + q_{k+-1}) / 2,  Ubar_k = (u(t_{k-1/2}) + u(t_{k+1/2})) / 2,

with F = grad U the internal force - the relation :mod:`dolfinx_lopinf.core.polynomial` fits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..fem._dolfinx import MPI, dolfinx, ufl
from ..fem.state import StateMap, owned_global_dofs, point_output_matrix
from ..fem.lagrangian import LagrangianSystem
from ..errors import InputError

LENGTH, WIDTH, HEIGHT = 1.0, 0.1, 0.1
E_MOD, NU, RHO = 1.0e5, 0.3, 1.0
LAMBDA = E_MOD * NU / ((1 + NU) * (1 - 2 * NU))
MU = E_MOD / (2 * (1 + NU))
RAYLEIGH = (0.2, 2e-4)  # alpha [1/s], beta [s]: ~1.5 % of critical on the first mode
DT = 2e-3
T_RAMP, T_HOLD, T_RELEASE = 0.3, 0.5, 0.05
QUADRATURE_DEGREE = 4
TIP = (LENGTH, 0.5 * WIDTH, 0.5 * HEIGHT)
MATERIALS = ("svk", "neo-hookean", "linear")


def profile(t):
    """s(t): 0 -> 1 by (1 - cos)/2 over [0, T_RAMP], 1 to T_HOLD, back to 0 over T_RELEASE."""
    t = np.asarray(t, dtype=float)
    up = 0.5 * (1 - np.cos(np.pi * np.clip(t / T_RAMP, 0, 1)))
    down = 0.5 * (1 + np.cos(np.pi * np.clip((t - T_HOLD) / T_RELEASE, 0, 1)))
    return np.where(t < T_HOLD, up, down)


def _profile_ufl(t):
    up = 0.5 * (1 - ufl.cos(np.pi * ufl.min_value(t / T_RAMP, 1.0)))
    tau = ufl.min_value(ufl.max_value((t - T_HOLD) / T_RELEASE, 0.0), 1.0)
    down = 0.5 * (1 + ufl.cos(np.pi * tau))
    return ufl.conditional(ufl.lt(t, T_HOLD), up, down)


def strain_energy_density(u, material: str):
    """W(u) of one of :data:`MATERIALS` (a UFL scalar)."""
    d = len(u)
    I = ufl.Identity(d)
    if material == "linear":
        eps = ufl.sym(ufl.grad(u))
        return 0.5 * LAMBDA * ufl.tr(eps) ** 2 + MU * ufl.inner(eps, eps)
    F = I + ufl.grad(u)
    if material == "svk":
        E = 0.5 * (F.T * F - I)
        return 0.5 * LAMBDA * ufl.tr(E) ** 2 + MU * ufl.inner(E, E)
    if material == "neo-hookean":
        J = ufl.det(F)
        return 0.5 * MU * (ufl.tr(F.T * F) - d) - MU * ufl.ln(J) + 0.5 * LAMBDA * ufl.ln(J) ** 2
    raise InputError(f"material must be one of {MATERIALS}, got {material!r}")


@dataclass
class Cantilever:
    """The scene: system, state map, output, and what the demo needs to score ROMs."""

    system: LagrangianSystem
    material: str
    amplitude: "dolfinx.fem.Constant"  # a in the load a s(t) b
    state_map: StateMap
    output_matrix: np.ndarray  # (2, n_local): tip x- and z-displacement
    energy_form: object  # the elastic energy (scalar form in system.q)
    force_form: object  # dU/du (1-form in system.q)
    load_form: object  # b . v, the load per unit input (1-form)

    @property
    def V(self):
        return self.system.V

    @property
    def comm(self):
        return self.V.mesh.comm

    def _set_q(self, state: np.ndarray):
        """system.q = the state (global state coordinates, the same on every rank)."""
        q = self.system.q
        q.x.array[:] = self.state_map.to_local_dofs(self.V, state)
        q.x.scatter_forward()

    def _to_state(self, owned: np.ndarray) -> np.ndarray:
        """Owned rows (n_owned, ...) of every rank -> state coordinates (n, ...) on every rank
        (each global dof has one owner: the sum over ranks adds zeros to it, exactly)."""
        dofs = np.zeros((len(self.state_map.order),) + owned.shape[1:])
        dofs[owned_global_dofs(self.V)] = owned
        if self.comm.size > 1:
            dofs = self.comm.allreduce(dofs)
        scale = self.state_map.scale.reshape((-1,) + (1,) * (owned.ndim - 1))
        return dofs[self.state_map.order] / scale

    def _n_owned(self) -> int:
        return self.V.dofmap.index_map.size_local * self.V.dofmap.index_map_bs

    def internal_force(self, states: np.ndarray) -> np.ndarray:
        """grad U at states (n, k) (state coordinates, the same on every rank; collective),
        the Dirichlet rows zero; on every rank."""
        states = np.atleast_2d(np.asarray(states, dtype=float).T).T
        n_owned = self._n_owned()
        owned = np.empty((n_owned, states.shape[1]))
        form = dolfinx.fem.form(self.force_form) if not hasattr(self, "_force_c") else self._force_c
        self._force_c = form
        saved = self.system.q.x.array.copy()
        for j in range(states.shape[1]):
            self._set_q(states[:, j])
            b = dolfinx.fem.assemble_vector(form)
            b.scatter_reverse(dolfinx.la.InsertMode.add)
            owned[:, j] = b.array[:n_owned]
        self.system.q.x.array[:] = saved
        out = self._to_state(owned)
        out[self.clamped_rows] = 0.0
        return out

    def potential(self, states: np.ndarray) -> np.ndarray:
        """U at states (n, k) (state coordinates, the same on every rank; collective); on
        every rank."""
        states = np.atleast_2d(np.asarray(states, dtype=float).T).T
        form = dolfinx.fem.form(self.energy_form) if not hasattr(self, "_energy_c") else self._energy_c
        self._energy_c = form
        saved = self.system.q.x.array.copy()
        out = np.empty(states.shape[1])
        for j in range(states.shape[1]):
            self._set_q(states[:, j])
            out[j] = dolfinx.fem.assemble_scalar(form)
        self.system.q.x.array[:] = saved
        return self.comm.allreduce(out) if self.comm.size > 1 else out

    def load_vector(self) -> np.ndarray:
        """b in state coordinates (the full-order input vector per unit input), on every rank
        (collective)."""
        b = dolfinx.fem.assemble_vector(dolfinx.fem.form(self.load_form))
        b.scatter_reverse(dolfinx.la.InsertMode.add)
        out = self._to_state(b.array[:self._n_owned()])
        out[self.clamped_rows] = 0.0
        return out

    @property
    def clamped_rows(self) -> np.ndarray:
        """State rows of the clamped (Dirichlet) dofs, on every rank (collective on first use)."""
        if not hasattr(self, "_clamped"):
            n_owned = self._n_owned()
            owned = np.zeros(n_owned, dtype=bool)
            for bc in self.system.bcs:
                dofs = bc.dof_indices()[0]  # local, unrolled (blocked space): owned, then ghosts
                owned[dofs[dofs < n_owned]] = True
            mask = np.zeros(len(self.state_map.order), dtype=bool)
            mask[owned_global_dofs(self.V)] = owned
            if self.comm.size > 1:
                mask = self.comm.allreduce(mask.astype(np.int8)) > 0
            self._clamped = np.flatnonzero(mask[self.state_map.order])
        return self._clamped

    def initial_state(self):
        """Rest: zero configuration and velocity as this rank's local dof arrays (owned +
        ghosts), the form :func:`dolfinx_lopinf.run` takes."""
        n = len(self.system.q.x.array)
        return np.zeros(n), np.zeros(n)

    def set_probe_input(self, integrator, u) -> None:
        """Make ``integrator``'s next step carry the load u[0] b (the input of the reduced
        model; 0 when u is empty): amplitude u[0] at a time in the hold phase, where s = 1.
        The ``set_input`` of :func:`dolfinx_lopinf.fem.probes.probe`."""
        u = np.atleast_1d(np.asarray(u, dtype=float))
        self.amplitude.value = float(u[0]) if u.size else 0.0
        integrator.t = 0.5 * (T_RAMP + T_HOLD)


def build(material: str = "svk", cells=(10, 1, 1), comm=MPI.COMM_WORLD,
          damping: bool = True) -> Cantilever:
    """The cantilever with ``material`` in :data:`MATERIALS` on ``cells`` Q2 hexahedra."""
    msh = dolfinx.mesh.create_box(comm, [[0, 0, 0], [LENGTH, WIDTH, HEIGHT]], list(cells),
                                  dolfinx.mesh.CellType.hexahedron)
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 2, (3,)))
    u, u_t = dolfinx.fem.Function(V, name="u"), dolfinx.fem.Function(V, name="u_t")
    v = ufl.TestFunction(V)
    dx = ufl.Measure("dx", domain=msh, metadata={"quadrature_degree": QUADRATURE_DEGREE})
    W = strain_energy_density(u, material)
    energy = W * dx
    L = 0.5 * RHO * ufl.inner(u_t, u_t) * dx - energy
    t = dolfinx.fem.Constant(msh, 0.0)
    amp = dolfinx.fem.Constant(msh, 0.0)
    b = ufl.as_vector((0.0, 0.0, -1.0))
    load = ufl.inner(b, v) * dx
    forcing = amp * _profile_ufl(t) * load
    if damping:
        alpha, beta = RAYLEIGH
        eps = lambda w: ufl.sym(ufl.grad(w))  # noqa: E731
        sig = lambda w: LAMBDA * ufl.tr(eps(w)) * ufl.Identity(3) + 2 * MU * eps(w)  # noqa: E731
        forcing = forcing - alpha * RHO * ufl.inner(u_t, v) * dx - beta * ufl.inner(sig(u_t), eps(v)) * dx
    fdim = msh.topology.dim - 1
    clamped = dolfinx.mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[0], 0.0))
    bc = dolfinx.fem.dirichletbc(np.zeros(3), dolfinx.fem.locate_dofs_topological(V, fdim, clamped), V)
    system = LagrangianSystem(L, u, u_t, bcs=[bc], forcing=forcing, time=t)
    E_out = np.vstack([point_output_matrix(V, [TIP], component=c) for c in (0, 2)])
    return Cantilever(system, material, amp, StateMap.from_coordinates(V), E_out, energy,
                      ufl.derivative(energy, u, v), load)
