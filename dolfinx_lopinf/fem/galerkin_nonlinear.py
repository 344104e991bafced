"""Genuine Galerkin ROM of a nonlinear (hyperelastic) potential, and its ECSW hyper-reduction.

For an elastic energy U(u) = integral W(u) dx that is not a polynomial of u (neo-Hookean), the
intrusive Galerkin ROM on a basis V (state coordinates, u = u0 + V q) needs the full-order
internal force at every reduced Newton iterate:

    f_r(q) = V^T f(u0 + V q),     J_r(q) = V^T K_t(u0 + V q) V,     U_r(q) = U(u0 + V q),

f = dU/du and K_t = d^2U/du^2 assembled by DOLFINx from the UFL energy (:class:`GalerkinForce`;
any rank count, the r-vectors summed over ranks). With energy-conserving sampling and weighting
(ECSW, Farhat et al. 2015, the cell version of :mod:`dolfinx_lopinf.core.hyper`) the sums over
all cells become weighted sums over a few sampled cells S,

    f_r(q) ~ sum_{e in S} w_e V_e^T f_e(u0 + V q),   w_e >= 0,

which is still the gradient of the reduced potential sum_e w_e U_e (the ROM stays Lagrangian).
The weights fit the reduced force on training states (:func:`ecsw_sampling`):

    min_{w >= 0} || G w - b ||,   G[(k, a), e] = (V_a)^T f_e(u0 + V q_k),  b = G 1,

by the Lawson-Hanson NNLS of :func:`dolfinx_lopinf.core.hyper.nnls_tolerance`, stopped at
||G w - b|| <= tol ||b||. The column G[:, e] of a cell is assembled for all cells at once as a
DG0 vector: the linear form dU[phi] psi dx with psi the DG0 test function and phi = V_a.
Cells are numbered by their midpoints (x, then y, then z), so a sampling is the same on any
number of ranks.

Both objects expose ``r``, ``force_and_jacobian(q)`` and ``value(Q)``, so they drop into
:class:`dolfinx_lopinf.core.polynomial.PolynomialROM` (its numpy loop) as the reduced force.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ._dolfinx import MPI, dolfinx, ufl
from ..core._checks import check_positive
from ..core.hyper import nnls_tolerance
from ..errors import InputError
from .agreement import agree
from .state import StateMap, _map_key


@dataclass(frozen=True)
class CellSampling:
    """ECSW cells and weights. ``cells``: canonical cell numbers (midpoint order, see
    :func:`canonical_cells`), ``weights`` (same length, > 0), ``residual`` the relative
    reduced-force fit residual on the training states, ``n_cells`` the mesh's cell count."""

    cells: np.ndarray
    weights: np.ndarray
    residual: float
    n_cells: int
    seconds: float = 0.0

    def __post_init__(self):
        if len(self.cells) != len(self.weights):
            raise InputError(f"cells ({len(self.cells)}) and weights ({len(self.weights)}) differ "
                             "in length")
        if len(self.cells) and (np.min(self.cells) < 0 or np.max(self.cells) >= self.n_cells):
            raise InputError(f"cell numbers must lie in [0, {self.n_cells})")
        if np.any(~np.isfinite(self.weights)) or np.any(np.asarray(self.weights) <= 0):
            raise InputError("ECSW weights must be finite and positive")


def canonical_cells(msh) -> np.ndarray:
    """Canonical number of each owned cell of this rank: the rank of its midpoint in
    (x, y, z) lexicographic order over the whole mesh (the same for any partition)."""
    tdim = msh.topology.dim
    n_owned = msh.topology.index_map(tdim).size_local
    mid = dolfinx.mesh.compute_midpoints(msh, tdim, np.arange(n_owned, dtype=np.int32))
    pieces = msh.comm.allgather(mid)
    X = np.vstack(pieces)
    scale = max(np.abs(X).max(), 1e-300)
    key = np.round(X / scale, 10)
    perm = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))
    rank_of = np.empty(len(perm), dtype=np.int64)
    rank_of[perm] = np.arange(len(perm))
    start = sum(len(p) for p in pieces[:msh.comm.rank])
    return rank_of[start:start + n_owned]


def _cell_integrals(energy):
    if not isinstance(energy, ufl.Form):
        raise InputError(f"energy must be a UFL form (the elastic energy, a scalar), got "
                         f"{type(energy).__name__}")
    if energy.arguments():
        raise InputError("energy must be a scalar form (no test or trial functions)")
    out = []
    for integral in energy.integrals():
        if integral.integral_type() != "cell" or integral.subdomain_id() not in ("everywhere", "otherwise"):
            raise InputError("energy must consist of cell integrals over the whole mesh (dx); got "
                             f"a {integral.integral_type()} integral on subdomain "
                             f"{integral.subdomain_id()!r}")
        out.append(integral)
    return out


def _rebuild(integrals, msh, transform, **measure):
    """The form sum_i transform(integrand_i) dx_i (each integral's metadata kept)."""
    form = None
    for i in integrals:
        term = transform(i.integrand()) * ufl.Measure("dx", domain=msh, metadata=i.metadata(),
                                                      **measure)
        form = term if form is None else form + term
    return form


class _Lift:
    """u = u0 + W q on this rank's local dofs (owned and ghost), W the basis in dofs."""

    def __init__(self, V, basis, state_map, u0):
        if not isinstance(state_map, StateMap):
            raise InputError(f"state_map must be a StateMap, got {type(state_map).__name__}")
        n = len(state_map.order)
        basis = np.asarray(basis, dtype=float)
        if basis.ndim != 2 or basis.shape[0] != n:
            raise InputError(f"basis must be a finite (n, r) array with n = {n} state rows (on "
                             f"every rank), got shape {basis.shape}")
        if not np.all(np.isfinite(basis)):
            bad = np.argwhere(~np.isfinite(basis))
            raise InputError(f"basis contains {len(bad)} NaN/inf entries (first at row "
                             f"{bad[0][0]}, column {bad[0][1]})")
        self.W = np.ascontiguousarray(state_map.to_local_dofs(V, basis))  # (local dofs, r)
        if u0 is None:
            self.u0 = np.zeros(len(self.W))
        else:
            u0 = np.asarray(u0, dtype=float).reshape(-1)
            if u0.shape != (n,) or not np.all(np.isfinite(u0)):
                raise InputError(f"u0 must be a finite state vector of length {n}, got shape {u0.shape}")
            self.u0 = state_map.to_local_dofs(V, u0)
        self.n_owned = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
        self.r = basis.shape[1]

    def set(self, fun, q, rows=None):
        if rows is None:
            fun.x.array[:] = self.u0 + self.W @ q
        else:
            fun.x.array[rows] = self.u0[rows] + self.W[rows] @ q


def _sampling_key(sampling):
    if isinstance(sampling, CellSampling):
        return (np.asarray(sampling.cells), np.asarray(sampling.weights, dtype=float),
                sampling.n_cells)
    return sampling


def _agreed_lift(where, energy, V, basis, state_map, u0, extra=None, **settings):
    """The energy's integrals and the lift u = u0 + W q, checked on this rank and then agreed
    on by every rank (the same error everywhere; the basis, u0 and ``settings`` equal on every
    rank). ``extra(r)``: a further check whose result is returned (and agreed on) too."""
    comm = V.mesh.comm
    out, problem = None, None
    try:
        integrals = _cell_integrals(energy)
        lift = _Lift(V, basis, state_map, u0)
        out = (integrals, lift) if extra is None else (integrals, lift, extra(lift.r))
    except Exception as exc:  # noqa: BLE001 - every rank must hear of it
        problem = exc
    if problem is None:
        settings.update(basis=np.asarray(basis, dtype=float), state_map=_map_key(state_map),
                        u0=None if u0 is None else np.asarray(u0, dtype=float))
        if extra is not None:
            settings["Qh"] = out[2]
    agree(comm, where, problem, **(settings if problem is None else {}))
    return out


class GalerkinForce:
    """f_r(q) = V^T f(u0 + V q), J_r(q) = V^T K_t V, U_r(q) = U(u0 + V q) assembled by DOLFINx
    (see the module docstring); with ``sampling`` the ECSW-weighted sums over its cells.

    Args:
        energy: the elastic energy, a scalar UFL form of cell integrals in the Function ``u``.
        u: the Function ``energy`` is written in (not modified: a private copy is used).
        basis: (n, r) basis in state coordinates (every rank).  state_map: the snapshots' map.
        u0: optional offset state (n,).  sampling: a :class:`CellSampling`, or None (all cells).
    """

    def __init__(self, energy, u, basis, state_map: StateMap, *, u0=None, sampling=None):
        if not isinstance(u, dolfinx.fem.Function):
            raise InputError(f"u must be a dolfinx Function, got {type(u).__name__}")
        V = u.function_space
        msh = V.mesh
        self.comm = msh.comm
        integrals, self._lift = _agreed_lift("GalerkinForce", energy, V, basis, state_map, u0,
                                             sampling=_sampling_key(sampling))
        self.r = self._lift.r
        self._u = dolfinx.fem.Function(V)
        self.sampling = sampling
        tdim = msh.topology.dim
        n_cells = msh.topology.index_map(tdim).size_global
        if sampling is None:
            energy_r = _rebuild(integrals, msh, lambda e: ufl.replace(e, {u: self._u}))
            self._rows_set = None  # every local dof
            self.n_cells_used = n_cells
        else:
            if not isinstance(sampling, CellSampling):
                raise InputError(f"sampling must be a CellSampling, got {type(sampling).__name__}")
            if sampling.n_cells != n_cells:
                raise InputError(f"the sampling is for a mesh of {sampling.n_cells} cells, this one "
                                 f"has {n_cells}")
            canon = canonical_cells(msh)
            pos = {int(c): j for j, c in enumerate(sampling.cells)}
            local = np.array([i for i, c in enumerate(canon) if int(c) in pos], dtype=np.int32)
            weights = np.array([sampling.weights[pos[int(canon[i])]] for i in local])
            D = dolfinx.fem.functionspace(msh, ("DG", 0))
            w = dolfinx.fem.Function(D)
            w.x.array[D.dofmap.list[local, 0]] = weights
            w.x.scatter_forward()
            tags = dolfinx.mesh.meshtags(msh, tdim, local, np.ones(len(local), dtype=np.int32))
            energy_r = _rebuild(integrals, msh, lambda e: ufl.replace(e, {u: self._u}) * w,
                                subdomain_data=tags, subdomain_id=1)
            self._w = w
            bs = V.dofmap.index_map_bs
            blocks = np.unique(V.dofmap.list[local].ravel()) if len(local) else np.zeros(0, np.int32)
            self._rows_set = (blocks[:, None] * bs + np.arange(bs)[None, :]).ravel()
            self.n_cells_used = len(sampling.cells)
        v = ufl.TestFunction(V)
        force = ufl.derivative(energy_r, self._u, v)
        # K_t phi for one direction phi (a vector form): J_r column by column costs r vector
        # assemblies, far cheaper than the full element matrices of K_t (81 x 81 per Q2 cell)
        self._dir = dolfinx.fem.Function(V)
        self._energy = dolfinx.fem.form(energy_r)
        self._force = dolfinx.fem.form(force)
        self._tangent_dir = dolfinx.fem.form(ufl.derivative(force, self._u, self._dir))
        self._b = dolfinx.la.vector(V.dofmap.index_map, V.dofmap.index_map_bs)
        # owned rows that receive a contribution (on any rank): all owned rows without sampling
        n_owned = self._lift.n_owned
        if self._rows_set is None:
            self._rows = np.arange(n_owned)
        else:
            mark = dolfinx.la.vector(V.dofmap.index_map, V.dofmap.index_map_bs)
            mark.array[self._rows_set] = 1.0
            mark.scatter_reverse(dolfinx.la.InsertMode.add)
            self._rows = np.flatnonzero(mark.array[:n_owned] > 0)
        self._W_rows = np.ascontiguousarray(self._lift.W[self._rows])
        self.evaluations = 0
        self.seconds = 0.0

    def _sum(self, local):
        out = np.empty_like(local)
        self.comm.Allreduce(np.ascontiguousarray(local), out, op=MPI.SUM)
        return out

    def _project(self, form):
        """W_rows^T (assembled vector of ``form``) on this rank (owned rows)."""
        b = self._b
        b.array[:] = 0.0
        dolfinx.fem.assemble_vector(b.array, form)
        b.scatter_reverse(dolfinx.la.InsertMode.add)
        return self._W_rows.T @ b.array[self._rows]

    def force(self, q) -> np.ndarray:
        """f_r(q) (r,)."""
        q = self._check(q)
        self._lift.set(self._u, q, self._rows_set)
        return self._sum(self._project(self._force))

    def force_and_jacobian(self, q):
        """(f_r(q), J_r(q)): one force assembly and r assemblies of K_t V_a."""
        t0 = time.perf_counter()
        q = self._check(q)
        self._lift.set(self._u, q, self._rows_set)
        out = np.empty((self.r, self.r + 1))
        out[:, 0] = self._project(self._force)
        W = self._lift.W
        rows = slice(None) if self._rows_set is None else self._rows_set
        for a in range(self.r):
            self._dir.x.array[rows] = W[rows, a]
            out[:, a + 1] = self._project(self._tangent_dir)
        out = self._sum(out)
        J = out[:, 1:]
        self.evaluations += 1
        self.seconds += time.perf_counter() - t0
        return out[:, 0], 0.5 * (J + J.T)

    def value(self, Q) -> np.ndarray:
        """U_r at the columns of Q (r, N) (or one q: a float)."""
        problem = None
        try:
            Q = np.asarray(Q, dtype=float)
            one = Q.ndim == 1
            Q = Q.reshape(self.r, -1)
        except (TypeError, ValueError):
            problem, Q, one = f"Q must be an (r = {self.r}, N) array of numbers", None, False
        agree(self.comm, "GalerkinForce.value", problem, **({} if problem else {"Q": Q}))
        out = np.empty(Q.shape[1])
        for j in range(Q.shape[1]):
            if not np.all(np.isfinite(Q[:, j])):
                out[j] = np.nan
                continue
            self._lift.set(self._u, Q[:, j], self._rows_set)
            out[j] = dolfinx.fem.assemble_scalar(self._energy)
        out = self._sum(out)
        return float(out[0]) if one else out

    def gradient(self, Q) -> np.ndarray:
        """f_r at the columns of Q (r, N) (or one q)."""
        problem = None
        try:
            Q = np.asarray(Q, dtype=float)
        except (TypeError, ValueError):
            problem = f"Q must be an (r = {self.r}, N) array of numbers or one q (r,)"
        if problem is None and (Q.ndim not in (1, 2) or Q.shape[0] != self.r):
            problem = f"Q must be an (r = {self.r}, N) array or one q (r,), got shape {Q.shape}"
        agree(self.comm, "GalerkinForce.gradient", problem, **({} if problem else {"Q": Q}))
        if Q.ndim == 1:
            return self.force(Q)
        if Q.shape[1] == 0:
            return np.zeros((self.r, 0))
        return np.column_stack([self.force(Q[:, j]) for j in range(Q.shape[1])])

    def _check(self, q):
        """q as (r,) floats, the same on every rank (else the same error on every rank: each
        rank assembles its part at its own q)."""
        problem = None
        try:
            q = np.asarray(q, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            problem, q = f"q must be r = {self.r} numbers, got {type(q).__name__}", None
        if problem is None and q.shape != (self.r,):
            problem = f"q must have r = {self.r} entries, got shape {q.shape}"
        agree(self.comm, "GalerkinForce", problem, **({} if problem else {"q": q}))
        return q


def cell_force_matrix(energy, u, basis, state_map: StateMap, Qh, *, u0=None):
    """G[(k, a), e] = V_a^T f_e(u0 + V q_k) for the owned cells of this rank: returns
    (G_local (K r, n_owned_cells), canonical numbers of those cells)."""
    if not isinstance(u, dolfinx.fem.Function):
        raise InputError(f"u must be a dolfinx Function, got {type(u).__name__}")
    V = u.function_space
    msh = V.mesh

    def training(r):
        Q = np.asarray(Qh, dtype=float)
        if Q.ndim != 2 or Q.shape[0] != r or not np.all(np.isfinite(Q)):
            raise InputError(f"Qh must be a finite (r = {r}, K) array of reduced training "
                             f"states, got shape {Q.shape}")
        return Q

    integrals, lift, Qh = _agreed_lift("cell_force_matrix", energy, V, basis, state_map, u0,
                                       extra=training)
    uw, phi = dolfinx.fem.Function(V), dolfinx.fem.Function(V)
    D = dolfinx.fem.functionspace(msh, ("DG", 0))
    psi = ufl.TestFunction(D)
    L = _rebuild(integrals, msh, lambda e: ufl.derivative(ufl.replace(e, {u: uw}), uw, phi) * psi)
    form = dolfinx.fem.form(L)
    tdim = msh.topology.dim
    n_owned = msh.topology.index_map(tdim).size_local
    dofs = D.dofmap.list[:n_owned, 0]
    r, K = Qh.shape
    G = np.empty((K * r, n_owned))
    c = dolfinx.la.vector(D.dofmap.index_map, 1)
    for k in range(K):
        lift.set(uw, Qh[:, k])
        for a in range(r):
            phi.x.array[:] = lift.W[:, a]
            c.array[:] = 0.0
            dolfinx.fem.assemble_vector(c.array, form)
            G[k * r + a] = c.array[dofs]
    return G, canonical_cells(msh)


def ecsw_sampling(energy, u, basis, state_map: StateMap, Qh, *, u0=None, tol: float = 1e-3,
                  max_cells: int | None = None) -> CellSampling:
    """ECSW cells and weights fitting the reduced force at the training states Qh (r, K)
    to relative residual ``tol`` (see the module docstring). Collective; the same sampling
    (canonical cell numbers) on every rank and for any number of ranks."""
    problem = None
    try:
        tol = check_positive(tol, "tol")
        if max_cells is not None and (isinstance(max_cells, bool) or not isinstance(max_cells, (int, np.integer))
                                      or max_cells < 1):
            raise InputError(f"max_cells must be an integer >= 1 or None, got {max_cells!r}")
    except InputError as exc:
        problem = exc
    if isinstance(u, dolfinx.fem.Function):
        agree(u.function_space.mesh.comm, "ecsw_sampling", problem, tol=tol, max_cells=max_cells)
    elif problem is not None:
        raise problem
    t0 = time.perf_counter()
    G_local, canon = cell_force_matrix(energy, u, basis, state_map, Qh, u0=u0)
    comm = u.function_space.mesh.comm
    pieces = comm.gather((G_local, canon), root=0)
    n_cells = u.function_space.mesh.topology.index_map(u.function_space.mesh.topology.dim).size_global
    result = None
    if comm.rank == 0:
        G = np.empty((G_local.shape[0], n_cells))
        for Gp, cp in pieces:
            G[:, cp] = Gp
        b = G.sum(axis=1)
        bad = np.flatnonzero(~np.all(np.isfinite(G), axis=1))
        if len(bad):
            result = ("nonfinite", int(bad[0]) // np.shape(Qh)[0], None)
        elif not np.any(b):
            result = ("zero", None, None)
        else:
            w, residual = nnls_tolerance(G, b, tol, max_cells)
            cells = np.flatnonzero(w > 0)
            result = ("ok", cells, w[cells], residual)
    result = comm.bcast(result, root=0)
    if result[0] == "nonfinite":
        raise InputError(f"the cell forces are not finite at training state {result[1]} (column "
                         "of Qh): an inverted element (det F <= 0) for this material? Train on "
                         "states the FOM actually reached")
    if result[0] == "zero":
        raise InputError("the reduced force is zero at every training state: nothing to fit "
                         "(pass deformed training states Qh)")
    _, cells, weights, residual = result
    return CellSampling(np.asarray(cells, dtype=np.int64), np.asarray(weights, dtype=float),
                        float(residual), int(n_cells), time.perf_counter() - t0)
