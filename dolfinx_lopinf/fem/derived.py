"""Derived outputs: any UFL expression of the reconstructed field, at points or as a field.

    sigma_vm = von_mises(u)                             # a UFL expression of the Function u
    probe = DerivedOutput(sigma_vm, u, points=[[1.0, 0.05, 0.05]])
    s_rom = probe.from_reduced(model.basis, traj.Qh)    # (p, K): only the points' cells rebuilt
    s_fom = probe.from_states(snaps.Q)                  # the same expression of the FOM states
    W = dolfinx.fem.functionspace(mesh, ("DG", 0))
    field = DerivedOutput(sigma_vm, u, space=W).from_reduced(model.basis, traj.Qh)  # (n_W, K)

At points. Each point is located in one cell of one rank and pulled back to the reference
cell (x = F_c(X)); the expression is compiled once, for all the points' reference
coordinates, and evaluated on their cells. Inside a cell an expression of u depends only on
that cell's dofs, so only the state rows of those dofs are reconstructed from the reduced
coordinates (V[rows] Qh) - the cost does not grow with the mesh. The values are summed over
the ranks (each point has one owner) and returned on every rank.

As a field. The expression is interpolated into the space W at every time (the whole state
is reconstructed), and W's values are gathered on rank 0 in W's global dof order (None
elsewhere) - ready for :func:`dolfinx_lopinf.fem.vtx.write_vtx` with W.

States are in the rows of the snapshots (``state_map``: the recorder's, by default the dof
order). Collective over the mesh's communicator.
"""

from __future__ import annotations

import numpy as np

from ._dolfinx import MPI, dolfinx, ufl
from ..errors import InputError
from .state import StateMap, gather_states


def _inverse(state_map: StateMap, n: int) -> np.ndarray:
    inv = np.empty(n, dtype=np.int64)
    inv[state_map.order] = np.arange(len(state_map.order))
    return inv


class DerivedOutput:
    """A UFL expression of the Function ``u``, evaluated from states or reduced trajectories.

    Args:
        expr: a UFL expression whose only unknown coefficient is ``u`` (constants allowed).
        u: the dolfinx Function the snapshots record.
        points: (p, 3) or (p, gdim) physical points; or
        space: a FunctionSpace to interpolate the expression into (a field).
        state_map: the snapshots' map (default: dof order, as SnapshotRecorder records).
    """

    def __init__(self, expr, u, *, points=None, space=None, state_map: StateMap | None = None):
        if not isinstance(u, dolfinx.fem.Function):
            raise InputError(f"u must be the dolfinx Function the expression is written in, got "
                             f"{type(u).__name__}")
        if (points is None) == (space is None):
            raise InputError("give exactly one of points= (values at points) and space= (a field)")
        self.u, self.V = u, u.function_space
        self.comm = self.V.mesh.comm
        self.state_map = StateMap.identity(self.V) if state_map is None else state_map
        imap, bs = self.V.dofmap.index_map, self.V.dofmap.index_map_bs
        self._n = imap.size_global * bs
        if len(self.state_map.order) != self._n:
            raise InputError(f"state_map has {len(self.state_map.order)} rows, the space of u "
                             f"{self._n} dofs")
        self._work = dolfinx.fem.Function(self.V)
        expr = ufl.replace(expr, {u: self._work})
        if points is not None:
            self._setup_points(expr, points)
        else:
            self._setup_field(expr, space)

    # -- set-up ---------------------------------------------------------------------------
    def _setup_points(self, expr, points):
        msh = self.V.mesh
        gdim = msh.geometry.dim
        try:
            P = np.atleast_2d(np.asarray(points, dtype=float))
        except (TypeError, ValueError):
            raise InputError(f"points must be a (p, {gdim}) or (p, 3) array of numbers (one row "
                             f"per point, all of one length), got {points!r}") from None
        if P.ndim != 2 or P.shape[1] not in (gdim, 3) or not np.all(np.isfinite(P)):
            raise InputError(f"points must be a finite (p, {gdim}) or (p, 3) array, got shape "
                             f"{np.shape(points)}")
        P3 = np.zeros((len(P), 3))
        P3[:, :P.shape[1]] = P
        tree = dolfinx.geometry.bb_tree(msh, msh.topology.dim)
        colliding = dolfinx.geometry.compute_colliding_cells(
            msh, dolfinx.geometry.compute_collisions_points(tree, P3), P3)
        n_owned = msh.topology.index_map(msh.topology.dim).size_local
        mine = np.array([len(colliding.links(i)) > 0 and colliding.links(i)[0] < n_owned
                         for i in range(len(P3))])
        owner = self.comm.allreduce(np.where(mine, self.comm.rank, self.comm.size), op=MPI.MIN)
        if np.any(owner == self.comm.size):
            raise InputError(f"points {P[owner == self.comm.size].tolist()} lie outside the mesh")
        self._mine = np.flatnonzero(owner == self.comm.rank)
        self._cells = np.array([colliding.links(i)[0] for i in self._mine], dtype=np.int32)
        geom = msh.geometry
        X = np.zeros((max(len(self._mine), 1), msh.topology.dim))
        for j, (i, c) in enumerate(zip(self._mine, self._cells)):
            coords = geom.x[geom.dofmaps[0][c]][:, :gdim]
            X[j] = geom.cmaps[0].pull_back(P3[i:i + 1, :gdim], coords)[0]
        self._expr = dolfinx.fem.Expression(expr, X, comm=MPI.COMM_SELF)
        self.shape = tuple(self._expr.value_shape)
        self._p = len(P3)
        # the local dofs of the points' cells, and their state rows
        bs = self.V.dofmap.index_map_bs
        blocks = np.unique(np.concatenate([self.V.dofmap.cell_dofs(c) for c in self._cells])
                           if len(self._cells) else np.zeros(0, dtype=np.int32))
        self._local = (blocks[:, None] * bs + np.arange(bs)).ravel()
        imap = self.V.dofmap.index_map
        glob = np.repeat(imap.local_to_global(blocks.astype(np.int32)) * bs, bs) \
            + np.tile(np.arange(bs), len(blocks))
        self._rows = _inverse(self.state_map, self._n)[glob]
        self._scale = self.state_map.scale[self._rows]
        self.field = None

    def _setup_field(self, expr, space):
        if not isinstance(space, dolfinx.fem.FunctionSpace):
            raise InputError(f"space must be a dolfinx FunctionSpace, got {type(space).__name__}")
        if space.mesh._cpp_object is not self.V.mesh._cpp_object:
            raise InputError("space must be on the mesh of u")
        self.field = dolfinx.fem.Function(space)
        try:
            self._expr = dolfinx.fem.Expression(expr, space.element.interpolation_points)
        except Exception as exc:  # a UFL/FFCx error: the expression does not fit the space
            raise InputError(f"the expression cannot be interpolated into the space: {exc}") from exc
        W = space
        self._field_map = StateMap.identity(W)
        self.shape = tuple(self._expr.value_shape)

    # -- evaluation -----------------------------------------------------------------------
    def rows(self) -> np.ndarray:
        """The state rows the point values depend on (this rank's points)."""
        if self.field is not None:
            raise InputError("a field depends on every state row")
        return self._rows

    def from_reduced(self, basis, Qh):
        """Values from reduced coordinates Qh (r, K) and their basis (``.V``: (n, r)):
        points -> ``(p, *shape, K)`` on every rank; field -> (n_W, K) on rank 0."""
        Qh = np.asarray(Qh, dtype=float)
        Qh = Qh.reshape(-1, 1) if Qh.ndim == 1 else Qh
        V = np.asarray(basis.V if hasattr(basis, "V") else basis, dtype=float)
        if V.ndim != 2 or V.shape[0] != self._n or Qh.shape[0] != V.shape[1]:
            raise InputError(f"basis must be (n, r) with n = {self._n} and Qh (r, K), got "
                             f"{V.shape} and {Qh.shape}")
        if self.field is None:
            return self._points(V[self._rows] @ Qh)
        return self._field(V @ Qh)

    def from_states(self, Q):
        """Values from full states Q (n, K) in the snapshots' rows (on every rank)."""
        Q = np.asarray(Q, dtype=float)
        Q = Q.reshape(-1, 1) if Q.ndim == 1 else Q
        if Q.shape[0] != self._n:
            raise InputError(f"states must have {self._n} rows (the snapshots'), got {Q.shape[0]}")
        if self.field is None:
            return self._points(Q[self._rows])
        return self._field(Q)

    def _points(self, S):
        """S: (len(rows), K) states on the rows of the points' cells."""
        K = S.shape[1]
        out = np.zeros((self._p,) + self.shape + (K,))
        if len(self._mine):
            arr = self._work.x.array
            for k in range(K):
                arr[:] = 0.0
                arr[self._local] = S[:, k] / self._scale
                values = self._expr.eval(self.V.mesh, self._cells)  # (cells, points, *shape)
                idx = np.arange(len(self._mine))
                out[self._mine, ..., k] = values[idx, idx]
        return self.comm.allreduce(out, op=MPI.SUM) if self.comm.size > 1 else out

    def _field(self, Q):
        W = self.field.function_space
        n_owned = W.dofmap.index_map.size_local * W.dofmap.index_map_bs
        local = np.empty((n_owned, Q.shape[1]))
        imap, bs = self.V.dofmap.index_map, self.V.dofmap.index_map_bs
        nodes = np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32)
        glob = np.repeat(imap.local_to_global(nodes) * bs, bs) + np.tile(np.arange(bs), len(nodes))
        rows = _inverse(self.state_map, self._n)[glob]
        for k in range(Q.shape[1]):
            self._work.x.array[:] = Q[rows, k] / self.state_map.scale[rows]
            self.field.interpolate(self._expr)
            local[:, k] = self.field.x.array[:n_owned]
        return gather_states(W, local, self._field_map)
