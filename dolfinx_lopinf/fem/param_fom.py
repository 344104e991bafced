"""The full-order model of a :class:`~dolfinx_lopinf.fem.affine.ParametricSystem` at any mu.

The forms are assembled with the parameter Constants set to mu (the full forms, not the
sum of the affine terms) and stepped with a scheme of the generalised-alpha family
(:mod:`dolfinx_lopinf.core.schemes`: Newmark average acceleration by default, HHT,
generalised-alpha), on the state (u, v, a):

    u* = u_n + dt v_n + dt^2 (1/2 - beta) a_n,     v* = v_n + dt (1 - gamma) a_n,
    [(1 - am) M + (1 - af) gamma dt C + (1 - af) beta dt^2 K] a_{n+1}
        = f(t_{n+1-af}) - am M a_n - C ((1 - af) v* + af v_n) - K ((1 - af) u* + af u_n),
    u_{n+1} = u* + beta dt^2 a_{n+1},               v_{n+1} = v* + gamma dt a_{n+1},

f(t) = sum_j u_j(t) b_j(mu), the matrix factored once (MUMPS Cholesky), a_0 from
M a_0 = f(t_0) - C v_0 - K u_0. The recorded :class:`~dolfinx_lopinf.Snapshots` carry the
states at every step, the inputs at the times the scheme applied them (``input_times``:
t_0, then t_n + (1 - af) dt) and the scheme - exactly what its data relation needs - and
the mechanical energy 1/2 v^T M v + 1/2 u^T K u at every step (M, K at mu: the bc rows
carry zeros, so they add nothing).
"""

from __future__ import annotations

import time

import numpy as np

from ._dolfinx import MPI, dolfinx
from ..core import schemes
from ..core.snapshots import Snapshots
from ..errors import InputError, ParameterRangeWarning, warn
from .state import gather_states, state_gram
from .integrators import _check_dt, _check_homogeneous, _destroy, _direct_solver, _unique_prefix

fpetsc = dolfinx.fem.petsc


def _input_values(inputs, m, t):
    if inputs is None:
        return np.zeros(m)
    u = np.atleast_1d(np.asarray(inputs(t) if callable(inputs) else inputs, dtype=float)).reshape(-1)
    if u.shape != (m,) or not np.all(np.isfinite(u)):
        raise InputError(f"inputs(t) must return {m} finite value(s) (one per input form), got "
                         f"{u.tolist()} at t = {t:.6g}")
    return u


def simulate(psys, mu, dt: float, n_steps: int, *, inputs=None, scheme="newmark", q0=None,
             v0=None, petsc_options: dict | None = None) -> tuple:
    """Run the FOM at parameter ``mu`` for ``n_steps`` steps of ``dt`` (module docstring).

    Args:
        psys: the :class:`~dolfinx_lopinf.fem.affine.ParametricSystem`.
        mu: the parameters (checked: length, finite).
        inputs: u(t) -> (m,) values of the input channels (None: unforced).
        scheme: a generalised-alpha-family scheme or its name.
        q0, v0: initial state / velocity as (n,) state-coordinate arrays (every rank); rest
            by default.

    Returns:
        ``(snapshots, seconds)``: the Snapshots on rank 0 (None on the others; their
        ``weight`` is the parameter-free mass, so ``lo.parametric.fit``'s POD makes Mh_0 = I,
        when the system has one) and the wall time of the time loop (max over ranks).
    """
    scheme = schemes.from_spec(scheme)
    if not isinstance(scheme, schemes.GeneralizedAlpha):
        raise InputError(f"the parametric FOM steps the generalised-alpha family (Newmark, HHT, "
                         f"generalised-alpha), not {scheme.spec}")
    dt = _check_dt(dt)
    n_steps = int(n_steps)
    if n_steps < 1:
        raise InputError(f"n_steps must be >= 1, got {n_steps}")
    m = psys.m
    if inputs is not None and m == 0:
        raise InputError("this system has no input forms; pass inputs=None")
    V, comm = psys.V, psys.V.mesh.comm
    _check_homogeneous(psys.bcs, V)
    mu = psys.check_mu(mu)
    outside = [] if psys.structure is None else psys.structure.cone_violations(mu)
    if outside:  # a reduced model refuses such a mu (ParametricModel.check_parameter)
        warn(f"simulate: mu = {np.asarray(mu).tolist()} lies outside the cone "
             f"{psys.structure.cone}: " + ", ".join(f"{op} term {t} has coefficient {v:.4g}"
                                                      for op, t, v in outside)
             + " - that operator may be indefinite (e.g. a negative stiffness), and the full "
             "model runs as asked", ParameterRangeWarning)
    ops = psys.assemble(mu)
    M, K, C, bs = ops["M"], ops["K"], ops["C"], ops["b"]
    am, af, beta, gamma = (scheme.alpha_m, scheme.alpha_f, scheme.beta, scheme.gamma)
    A = M.copy()
    A.scale(1 - am)
    if C is not None:
        A.axpy((1 - af) * gamma * dt, C)
    A.axpy((1 - af) * beta * dt**2, K)
    prefix = _unique_prefix("param_fom")
    ksp = _direct_solver(A, comm, prefix, petsc_options, spd=True)
    ksp_m = _direct_solver(M, comm, prefix + "m_", None, spd=True)
    n_owned = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
    u, v, a = (fpetsc.create_vector(V) for _ in range(3))
    us, vs, rhs, tmp = (fpetsc.create_vector(V) for _ in range(4))
    for vec, x in ((u, q0), (v, v0)):
        vec.set(0.0)
        if x is not None:
            x = np.asarray(x, dtype=float)
            if x.shape != (len(psys.state_map.order),):
                raise InputError(f"q0 / v0 must be ({len(psys.state_map.order)},) state arrays")
            with vec.localForm() as loc:
                loc.array[:] = psys.state_map.to_local_dofs(V, x)
            fpetsc.set_bc(vec, list(psys.bcs), alpha=0.0)

    def load(t, out):
        out.set(0.0)
        values = _input_values(inputs, m, t)
        for b, uj in zip(bs, values):
            out.axpy(float(uj), b)
        return values

    def apply(Mat, x, y, scale):
        Mat.mult(x, tmp)
        y.axpy(-scale, tmp)

    U = np.zeros((m, n_steps + 1))
    input_times = np.concatenate([[0.0], (np.arange(n_steps) + 1 - af) * dt])
    U[:, 0] = load(0.0, rhs)
    apply(K, u, rhs, 1.0)
    if C is not None:
        apply(C, v, rhs, 1.0)
    fpetsc.set_bc(rhs, list(psys.bcs), alpha=0.0)
    ksp_m.solve(rhs, a)
    Q = np.empty((n_owned, n_steps + 1))
    Q[:, 0] = u.array_r[:n_owned]
    energy = np.empty(n_steps + 1)

    def mech_energy():
        M.mult(v, tmp)
        e = 0.5 * v.dot(tmp)
        K.mult(u, tmp)
        return float(e + 0.5 * u.dot(tmp))

    energy[0] = mech_energy()
    t0 = time.perf_counter()
    for k in range(n_steps):
        u.copy(us)
        us.axpy(dt, v)
        us.axpy(dt**2 * (0.5 - beta), a)
        v.copy(vs)
        vs.axpy(dt * (1 - gamma), a)
        U[:, k + 1] = load(input_times[k + 1], rhs)
        if am:
            apply(M, a, rhs, am)
        if C is not None:
            apply(C, vs, rhs, 1 - af)
            if af:
                apply(C, v, rhs, af)
        apply(K, us, rhs, 1 - af)
        if af:
            apply(K, u, rhs, af)
        fpetsc.set_bc(rhs, list(psys.bcs), alpha=0.0)
        ksp.solve(rhs, a)
        us.copy(u)
        u.axpy(beta * dt**2, a)
        vs.copy(v)
        v.axpy(gamma * dt, a)
        Q[:, k + 1] = u.array_r[:n_owned]
        energy[k + 1] = mech_energy()
    seconds = comm.allreduce(time.perf_counter() - t0, op=MPI.MAX)
    _destroy(ksp, ksp_m, A, M, K, C, u, v, a, us, vs, rhs, tmp, *bs)
    states = gather_states(V, Q, psys.state_map)
    mass0 = psys.mass_form()
    weight = None if mass0 is None else state_gram(V, psys.state_map, mass0, strict=False)
    if comm.rank != 0:
        return None, seconds
    times = dt * np.arange(n_steps + 1)
    snap = Snapshots(times, states, U=U if m else None, input_times=input_times if m else None,
                     scheme=scheme, energy=energy, weight=weight)
    return snap, seconds


__all__ = ["simulate"]
