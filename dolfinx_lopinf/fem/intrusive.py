"""Intrusive Galerkin Lagrangian ROM from our own FOM operators - for comparison only.

With a basis V (n, r) in state coordinates (state = S dofs), the Galerkin ROM of
L = 1/2 q_t^T M q_t - 1/2 q^T K q is L_h = 1/2 qh_t^T Mh qh_t - 1/2 qh^T Kh qh with

    Mh = W^T M W,  Kh = W^T K W,  W = S^{-1} V  (the basis in dof coordinates).

It needs the FOM matrices, so it never feeds the non-intrusive (L-OpInf) path. The same
reduced matrices also give the FOM energy of reconstructed states,
E(V qh, V vh) = 1/2 vh^T Mh vh + 1/2 qh^T Kh qh, used to score every ROM.
"""

from __future__ import annotations

import numpy as np

from ._dolfinx import PETSc, dolfinx
from ..errors import InputError
from .agreement import agree
from .state import StateMap, _map_key, owned_global_dofs
from .lagrangian import LagrangianSystem
from ..core.rom import LagrangianROM


def reduced_matrix(A: "PETSc.Mat", V, basis: np.ndarray, state_map: StateMap) -> np.ndarray:
    """W^T A W for a PETSc matrix A on space V and a state-coordinate basis (n, r).

    Every rank uses only its owned rows of W; the r x r result is summed over ranks.
    ``basis`` must be available on every rank (it is small: n x r).
    """
    comm = V.mesh.comm
    problem = None
    try:
        basis = np.asarray(basis, dtype=float)
    except (TypeError, ValueError):
        problem, basis = f"basis must be an (n, r) array of numbers, got {type(basis).__name__}", None
    if problem is None and not isinstance(state_map, StateMap):
        problem = f"state_map must be a StateMap, got {type(state_map).__name__}"
    if problem is None:
        n = len(state_map.order)
        if basis.ndim != 2 or basis.shape[0] != n:
            problem = (f"basis must be a finite (n, r) array with n = {n} state rows (every rank), "
                       f"got shape {basis.shape}")
        elif not np.all(np.isfinite(basis)):
            problem = "basis contains NaN or inf"
    agree(comm, "reduced_matrix", problem,
          **({} if problem else {"basis": basis, "state_map": _map_key(state_map)}))
    return _reduced(A, V, basis, state_map)


def _reduced(A, V, basis, state_map) -> np.ndarray:
    """:func:`reduced_matrix` once the ranks agreed on the basis."""
    comm = V.mesh.comm
    W = state_map.to_dofs(basis)  # global dof coordinates
    owned = owned_global_dofs(V)
    x, y = A.createVecRight(), A.createVecLeft()
    AW = np.empty((len(owned), W.shape[1]))
    for j in range(W.shape[1]):
        x.array[:] = W[owned, j]
        A.mult(x, y)
        AW[:, j] = y.array
    local = W[owned].T @ AW
    return comm.allreduce(local)


def dense_state_matrix(form, V, state_map: StateMap) -> np.ndarray:
    """A bilinear form as a dense (n, n) matrix in state coordinates, on every rank.

    For small systems (a beam: n = 400) - e.g. the mass matrix as a POD weight. Cost: n
    matrix-vector products and n^2 memory, so not for 3D meshes.
    """
    if not isinstance(state_map, StateMap):
        raise InputError(f"state_map must be a StateMap, got {type(state_map).__name__}")
    n = len(state_map.order)
    if n > 20000:
        raise InputError(f"n = {n} is too large for a dense state matrix (limit 20,000): "
                         "project with the basis instead (dolfinx_lopinf.fem.intrusive)")
    agree(V.mesh.comm, "dense_state_matrix", None, state_map=_map_key(state_map))
    A = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(form))
    A.assemble()
    dense = _reduced(A, V, np.eye(n), state_map)
    A.destroy()
    return 0.5 * (dense + dense.T)


def galerkin_rom(system: LagrangianSystem, basis: np.ndarray, state_map: StateMap) -> LagrangianROM:
    """Galerkin ROM (Mh, Kh) of a quadratic Lagrangian in a state-coordinate basis (n, r)."""
    if not isinstance(system, LagrangianSystem):
        raise InputError(f"system must be a LagrangianSystem, got {type(system).__name__}")
    if not system.is_quadratic:
        raise InputError("the Galerkin ROM here is for quadratic Lagrangians (linear systems)")
    fem = dolfinx.fem
    mats = []
    for form in (system.mass_form, system.stiffness_form):
        A = dolfinx.fem.petsc.assemble_matrix(fem.form(form))
        A.assemble()
        mats.append(reduced_matrix(A, system.V, basis, state_map))
        A.destroy()
    Mh, Kh = (0.5 * (A + A.T) for A in mats)
    return LagrangianROM(K=Kh, M=Mh, meta={"method": "intrusive"})
