"""State coordinates of a DOLFINx space, gathering, and output matrices.

A state vector of the numpy core is one row per global dof in a layout that does not depend on
the number of MPI ranks: state[i] = scale[i] * dofs[order[i]] (:class:`StateMap`; for Hermite
beams the scales turn nodal slopes into rotations). Each rank touches only its owned dofs;
:func:`gather_states` assembles them in state coordinates on rank 0. A linear output
y = E_state state (point values: :func:`point_output_matrix`, any local linear functional
mapped by :func:`output_matrix_in_state`) is the same on every rank. :func:`state_gram` is an
inner product of the states (by default the L2 Gram matrix of the space) as a sparse matrix in
state coordinates on rank 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ._dolfinx import MPI, PETSc, dolfinx, ufl
from ..core._checks import check_weight
from ..errors import InputError, LOpInfWarning, warn
from .agreement import agree, check, together
from .lagrangian import _same_dofs


@dataclass(frozen=True)
class StateMap:
    """state[i] = scale[i] * dofs[order[i]] in global dof numbering.

    Attributes:
        order: (n,) global dof index of each state entry.
        scale: (n,) factor from dof to state value (1 for plain nodal values).
        blocks: name -> state rows of a physical block.
    """

    order: np.ndarray
    scale: np.ndarray
    blocks: dict = field(default_factory=dict)

    @classmethod
    def identity(cls, V) -> "StateMap":
        """Global dof order. Note: DOLFINx numbers dofs per partition, so this order (and
        thus the snapshot rows) changes with the number of ranks; see :meth:`from_coordinates`."""
        imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
        n = imap.size_global * bs
        return cls(np.arange(n), np.ones(n), {})

    @classmethod
    def from_coordinates(cls, V) -> "StateMap":
        """State rows ordered by dof coordinates (x, then y, then z; components of a vector
        field kept together), so the snapshots are the same for any number of ranks.

        Needs one coordinate per dof block (Lagrange-type elements); raises otherwise.
        """
        comm = V.mesh.comm
        imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
        n_owned = imap.size_local
        x = V.tabulate_dof_coordinates()[:n_owned]
        glob = imap.local_to_global(np.arange(n_owned, dtype=np.int32))
        pieces = comm.allgather((glob, x))
        G = np.concatenate([g for g, _ in pieces])
        X = np.vstack([c for _, c in pieces])
        scale = max(np.abs(X).max(), 1e-300)
        key = np.round(X / scale, 10)
        perm = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))
        if len(perm) > 1 and np.any(np.all(np.diff(key[perm], axis=0) == 0, axis=1)):
            raise InputError("several dofs share a coordinate (not a Lagrange-type space): pass "
                             "an explicit StateMap (see dolfinx_lopinf.scenes.beam for Hermite)")
        order = (G[perm][:, None] * bs + np.arange(bs)[None, :]).ravel()
        return cls(order, np.ones(len(order)), {})

    def to_dofs(self, states: np.ndarray) -> np.ndarray:
        """Global dof vectors (n, K) from states (n, K) (inverse map)."""
        dofs = np.zeros_like(states)
        dofs[self.order] = states / self.scale[:, None] if states.ndim == 2 else states / self.scale
        return dofs

    def to_local_dofs(self, V, states: np.ndarray) -> np.ndarray:
        """States (n, K) or (n,) as this rank's local dof rows of V: owned, then ghosts
        (the layout of ``Function.x.array``); ``states`` on every rank."""
        imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
        blocks = imap.local_to_global(np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32))
        return self.to_dofs(states)[(blocks.astype(np.int64)[:, None] * bs + np.arange(bs)[None, :]).ravel()]


def owned_global_dofs(V) -> np.ndarray:
    """Global indices of this rank's owned dofs (blocked spaces unrolled)."""
    imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
    start = imap.local_range[0]
    n_owned = imap.size_local
    return (np.repeat(np.arange(start, start + n_owned) * bs, bs)
            + np.tile(np.arange(bs), n_owned))


def gather_states(V, local: np.ndarray, state_map: StateMap) -> np.ndarray | None:
    """Gather owned rows (n_owned, K) of every rank into state coordinates on rank 0."""
    comm = V.mesh.comm
    pieces = comm.gather((owned_global_dofs(V), local), root=0)
    if comm.rank != 0:
        return None
    n_global = sum(len(g) for g, _ in pieces)
    dofs = np.empty((n_global,) + local.shape[1:])
    for g, values in pieces:
        dofs[g] = values
    scale = state_map.scale.reshape((-1,) + (1,) * (local.ndim - 1))
    return scale * dofs[state_map.order]


#: what :func:`state_gram` accepts as ``weight`` (for messages)
WEIGHTS = ('"l2" (the L2 Gram matrix of the space), a UFL bilinear form on V x V (e.g. '
           "rho * inner(u, v) * dx) or an assembled PETSc Mat in V's dof layout")
#: matrix types whose owned rows PETSc hands out directly (MatGetRow); others are converted
_ROW_TYPES = ("seqaij", "mpiaij", "seqbaij", "mpibaij")


def weight_kind(weight, V) -> str:
    """``"l2"``, ``"form"`` or ``"mat"``: what kind of :func:`state_gram` weight this is (this
    rank's verdict: the caller makes it collective), or an :class:`InputError` naming what is
    accepted."""
    n = V.dofmap.index_map.size_global * V.dofmap.index_map_bs
    if isinstance(weight, str):
        if weight == "l2":
            return "l2"
        raise InputError(f"weight must be {WEIGHTS}; got the string {weight!r}")
    if isinstance(weight, PETSc.Mat):
        if not weight.handle:  # PETSc.Mat() or destroyed (asking it anything would crash)
            raise InputError("weight is an empty or destroyed PETSc Mat: pass an assembled one, "
                             "e.g. dolfinx.fem.petsc.assemble_matrix(form) then A.assemble()")
        size, assembled = tuple(weight.getSize()), weight.assembled
        same_comm = MPI.Comm.Compare(weight.getComm().tompi4py(), V.mesh.comm) in (
            MPI.IDENT, MPI.CONGRUENT)
        if size != (n, n):
            raise InputError(f"weight is a PETSc Mat of global size {size}; the space has {n} dofs: "
                             f"pass the ({n}, {n}) matrix of a bilinear form on this space")
        if not assembled:
            raise InputError("weight is a PETSc Mat that is not assembled: call A.assemble() first")
        if not same_comm:
            raise InputError("weight is a PETSc Mat on another communicator than the space's mesh: "
                             "assemble it on the mesh's communicator")
        return "mat"
    if isinstance(weight, (ufl.Form, dolfinx.fem.Form)):
        if isinstance(weight, ufl.Form):
            args = sorted(weight.arguments(), key=lambda a: a.number())
            spaces = [a.ufl_function_space() for a in args]
            spaces = [s._cpp_object if isinstance(s, dolfinx.fem.FunctionSpace) else None
                      for s in spaces]
        else:
            spaces = list(weight.function_spaces) if weight.rank == 2 else [None] * weight.rank
        if len(spaces) != 2:
            what = {0: "a functional (no arguments)", 1: "a linear form"}.get(len(spaces),
                                                                              f"a form of rank {len(spaces)}")
            raise InputError(f"weight is {what}; it must be a bilinear form on V x V, e.g. "
                             "inner(TrialFunction(V), TestFunction(V)) * dx")
        if not all(s is not None and (s is V._cpp_object or _same_dofs(s, V)) for s in spaces):
            raise InputError("weight is a bilinear form on another function space than the "
                             "recorded one: build it from TrialFunction(V) and TestFunction(V) of "
                             "the recorded Function's space V")
        return "form"
    raise InputError(f"weight must be {WEIGHTS}; got {type(weight).__name__}")


def state_gram(V, state_map: StateMap, weight="l2", *, strict: bool = True):
    """The inner product ``weight`` of V's functions in state coordinates: a symmetric
    ``scipy.sparse.csr_array`` (n, n) on rank 0, None on the other ranks (collective).
    A matrix that is not an inner product (not symmetric, a diagonal entry <= 0:
    :func:`~dolfinx_lopinf.core._checks.check_weight`) raises the same InputError on every
    rank; with ``strict=False`` it gives None on every rank and a warning instead (for the
    package's own runs, which must not fail at their end over an optional weight).

    W_state[i, j] = W_dofs[order[i], order[j]] / (scale[i] scale[j]), so that
    state_a^T W_state state_b = dofs_a^T W_dofs dofs_b. ``weight`` is

    * ``"l2"`` (default): the L2 Gram matrix, ``inner(u, v) * dx`` (unit density; scalar,
      vector and mixed spaces alike);
    * a UFL bilinear form on V x V (e.g. ``rho * inner(u, v) * dx``), assembled without
      boundary conditions;
    * an assembled PETSc Mat in V's dof layout (global dof numbering, as
      ``dolfinx.fem.petsc.assemble_matrix`` returns it; rows of Dirichlet dofs then have
      diagonal 1).

    Each rank reads its owned rows of the matrix; rank 0 gathers them (sparse: memory of the
    order of the matrix's nonzeros, never n x n).
    """
    if not isinstance(V, dolfinx.fem.FunctionSpace):
        raise InputError(f"V must be a dolfinx FunctionSpace, got {type(V).__name__}")
    comm = V.mesh.comm
    n = V.dofmap.index_map.size_global * V.dofmap.index_map_bs

    kind, problem = None, None
    try:
        _check_state_map(state_map, n)
        kind = weight_kind(weight, V)
    except Exception as exc:  # noqa: BLE001 - every rank must hear of it (agree)
        problem = exc
    agree(comm, "state_gram", problem, weight=kind, state_map=_map_key(state_map))
    with together(comm, "state_gram"):
        if kind == "mat":
            pieces = comm.gather(_owned_csr(weight), root=0)
        else:
            form = ufl.inner(ufl.TrialFunction(V), ufl.TestFunction(V)) * ufl.dx(domain=V.mesh) \
                if kind == "l2" else weight
            A = dolfinx.fem.petsc.assemble_matrix(
                form if isinstance(form, dolfinx.fem.Form) else dolfinx.fem.form(form))
            try:
                A.assemble()
                mine = _owned_csr(A)
            finally:
                A.destroy()
            pieces = comm.gather(mine, root=0)
    W, problem = None, None
    if comm.rank == 0:
        try:  # checked where it was gathered, the verdict sent to every rank
            W = check_weight(_to_state(pieces, n, state_map), n, "weight")
        except InputError as exc:
            problem = f"the assembled weight is not an inner product of the states: {exc}"
    problem = comm.bcast(problem, root=0)
    if problem is not None:
        if strict:
            raise InputError(problem)
        warn(f"{problem}; the snapshots carry no inner product (lo.fit: Euclidean POD)",
             LOpInfWarning)
        return None
    return W


def _owned_csr(A):
    """(global rows, global columns, values) of the nonzero entries of this rank's rows of the
    assembled Mat A (collective when A must be converted to AIJ first). Stored zeros are
    dropped here: the pattern of a vector or mixed space couples components that the form
    does not (two thirds of a 3D vector mass matrix's entries)."""
    B = A if A.getType() in _ROW_TYPES else A.convert(PETSc.Mat.Type.AIJ, out=PETSc.Mat())
    try:
        first, _ = B.getOwnershipRange()
        indptr, cols, vals = B.getValuesCSR()
    finally:
        if B is not A:
            B.destroy()
    rows = np.repeat(np.arange(first, first + len(indptr) - 1, dtype=np.int64), np.diff(indptr))
    keep = np.flatnonzero(vals)
    return rows[keep], np.asarray(cols, dtype=np.int64)[keep], np.asarray(vals, dtype=float)[keep]


def _to_state(pieces, n: int, state_map: StateMap):
    """The gathered entries (global dof numbering) as a CSR array in state coordinates."""
    import scipy.sparse as sp

    rows, cols, vals = (np.concatenate(parts) for parts in zip(*pieces))
    inverse = np.empty(n, dtype=np.int64)
    inverse[np.asarray(state_map.order)] = np.arange(n)
    i, j = inverse[rows], inverse[cols]
    scale = np.asarray(state_map.scale, dtype=float)
    if not np.all(scale == 1.0):
        vals = vals / (scale[i] * scale[j])
    W = sp.csr_array((vals, (i, j)), shape=(n, n))
    W.sort_indices()
    return W


def output_matrix_in_state(V, E_local: np.ndarray, state_map: StateMap) -> np.ndarray:
    """The output matrix (p, n) acting on state coordinates, on every rank.

    ``E_local`` is (p, n_local) over local (owned + ghost) dofs as from
    :func:`point_output_matrix`; y = E_state @ state with state = scale * dofs[order].
    """
    comm = V.mesh.comm
    imap = V.dofmap.index_map
    bs = V.dofmap.index_map_bs
    n_local = (imap.size_local + imap.num_ghosts) * bs

    def local():
        E = np.asarray(E_local)
        if E.ndim != 2 or E.shape[1] != n_local or E.dtype.kind not in "fiu":
            raise InputError(f"E_local must be a real (p, n_local) array with n_local = {n_local} "
                             f"on this rank (from point_output_matrix), got shape {E.shape}")
        if not np.all(np.isfinite(E)):
            raise InputError("E_local contains NaN or inf")
        return E.shape[0]

    p = check(comm, "output_matrix_in_state", local, state_map=_map_key(state_map))
    agree(comm, "output_matrix_in_state", None, outputs=p)
    local_nodes = np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32)
    glob = np.repeat(imap.local_to_global(local_nodes) * bs, bs) + np.tile(np.arange(bs), len(local_nodes))
    n = imap.size_global * bs
    E_dofs = np.zeros((E_local.shape[0], n))
    np.add.at(E_dofs.T, glob, E_local.T)
    E_dofs = comm.allreduce(E_dofs)
    return E_dofs[:, state_map.order] / state_map.scale


def point_output_matrix(V, points: np.ndarray, component: int | None = None) -> np.ndarray:
    """(p, n_local) matrix E with y = sum over ranks of E @ u.x.array (owned + ghost dofs):
    the values at ``points`` (p, 3) of an FE function (one ``component`` of a vector field).
    Each point is handled by one rank. In a mixed space ``component`` counts through the
    sub-spaces' values in order (the mixed element's value: (w, theta) -> 0 is w, 1 is theta).

    Built from ``Function.eval`` on unit dof vectors (a mixed space's through its collapsed
    sub-space), so it is exact for any element.
    """
    if not isinstance(V, dolfinx.fem.FunctionSpace):
        raise InputError(f"V must be a dolfinx FunctionSpace, got {type(V).__name__}")
    msh = V.mesh
    comm = msh.comm
    bs = V.dofmap.index_map_bs
    problem, points, comp = None, _points(points, msh.geometry.dim), None
    if isinstance(points, str):
        problem, points = points, None
    value_size = int(np.prod(V.value_shape)) if len(V.value_shape) else 1
    if problem is None and value_size > 1 and component is None:
        problem = f"the space has {value_size} components: pass component=0..{value_size - 1}"
    elif problem is None:
        if component is not None and (isinstance(component, (bool, np.bool_))
                                      or not isinstance(component, (int, np.integer))):
            problem = f"component must be an integer in 0..{value_size - 1}, got {component!r}"
        else:
            comp = 0 if component is None else int(component)
            if not 0 <= comp < value_size:
                problem = f"component must be in 0..{value_size - 1}, got {component}"
    agree(comm, "point_output_matrix", problem, points=points, component=comp)
    if getattr(V.ufl_element(), "is_mixed", False):
        return _mixed_point_output_matrix(V, points, comp)
    tree = dolfinx.geometry.bb_tree(msh, msh.topology.dim)
    candidates = dolfinx.geometry.compute_collisions_points(tree, points)
    colliding = dolfinx.geometry.compute_colliding_cells(msh, candidates, points)
    n_local = (V.dofmap.index_map.size_local + V.dofmap.index_map.num_ghosts) * bs
    E = np.zeros((len(points), n_local))
    n_owned_cells = msh.topology.index_map(msh.topology.dim).size_local
    found = np.array([comm.rank if len(colliding.links(i)) and colliding.links(i)[0] < n_owned_cells
                      else comm.size for i in range(len(points))], dtype=np.int64)
    owner = np.empty_like(found)
    comm.Allreduce(found, owner, op=MPI.MIN)  # each point to the lowest rank owning its cell
    if np.any(owner == comm.size):
        raise InputError(f"points {points[owner == comm.size].tolist()} lie outside the mesh "
                         "(or on no owned cell of any rank): move them inside")
    probe = dolfinx.fem.Function(V)
    for i, point in enumerate(points):
        if owner[i] != comm.rank:
            continue
        cell = colliding.links(i)[0]
        for block in V.dofmap.cell_dofs(cell):
            for k in range(bs):
                dof = block * bs + k
                probe.x.array[:] = 0.0
                probe.x.array[dof] = 1.0
                E[i, dof] = probe.eval(point, np.array([cell], dtype=np.int32))[comp]
    return E


def _mixed_point_output_matrix(V, points, comp: int) -> np.ndarray:
    """:func:`point_output_matrix` of a mixed space (``Function.eval`` does not evaluate mixed
    elements): flat component ``comp`` of the mixed value lies in one sub-space; its matrix
    on the collapsed sub-space, scattered into V's dofs (``collapse()``'s map)."""
    for s in range(V.element.num_sub_elements):
        sub = V.sub(s)
        size = int(np.prod(sub.value_shape)) if len(sub.value_shape) else 1
        if comp < size:
            W, parent = sub.collapse()
            E_sub = point_output_matrix(W, points, component=comp if size > 1 else None)
            bs = V.dofmap.index_map_bs
            E = np.zeros((len(points), (V.dofmap.index_map.size_local + V.dofmap.index_map.num_ghosts) * bs))
            E[:, np.ravel(np.asarray(parent, dtype=np.int64))] = E_sub
            return E
        comp -= size
    raise AssertionError("component checked against the value size")  # pragma: no cover


def _points(points, gdim: int):
    """Points as a finite (p, 3) array (columns beyond those given are 0), or a message."""
    try:
        P = np.asarray(points, dtype=float)
    except (TypeError, ValueError):
        return (f"points must be an array of coordinates (p, {gdim}) or (p, 3), got "
                f"{type(points).__name__} {str(points)[:60]}")
    if P.ndim == 1:
        P = P[None, :]
    if P.ndim != 2 or P.shape[0] == 0 or not gdim <= P.shape[1] <= 3:
        return (f"points must have shape (p, {gdim}) or (p, 3) - one row of coordinates per "
                f"point on this {gdim}-D mesh - got shape {np.shape(points)}")
    if not np.all(np.isfinite(P)):
        return f"points contain NaN or inf (rows {np.flatnonzero(~np.all(np.isfinite(P), axis=1)).tolist()})"
    return np.hstack([P, np.zeros((P.shape[0], 3 - P.shape[1]))])


def _map_key(state_map):
    """What identifies a state map across ranks (for :func:`agree`): its dof order (exactly)
    and its scales."""
    if not isinstance(state_map, StateMap):
        return state_map
    return (np.asarray(state_map.order), np.asarray(state_map.scale, dtype=float))


def _check_state_map(state_map, n_global: int) -> None:
    if not isinstance(state_map, StateMap):
        raise InputError(f"state_map must be a StateMap, got {type(state_map).__name__}")
    order = np.asarray(state_map.order)
    scale = np.asarray(state_map.scale, dtype=float)
    if order.shape != (n_global,) or scale.shape != (n_global,):
        raise InputError(f"state_map has {order.shape} rows and {scale.shape} scales; the "
                         f"space has {n_global} dofs")
    if not np.array_equal(np.sort(order), np.arange(n_global)):
        raise InputError("state_map.order is not a permutation of the global dofs 0..n-1")
    if not np.all(np.isfinite(scale) & (scale != 0)):
        raise InputError("state_map.scale must be finite and nonzero")
