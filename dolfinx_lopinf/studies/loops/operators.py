"""The study's side of a user loop: its FE operators in snapshot row order, and a collector of
the loop's own (u, v, a) trajectory - for the intrusive reference, never for the fit.

For a loop module with ``fe_forms(V)`` (mass, damping, stiffness bilinear forms, input linear
forms for unit load amplitudes, Dirichlet conditions) and a state map state = S dofs
(``SnapshotRecorder.state_map``):

    M = S^-T M_dofs S^-1 (dense, n x n),  likewise C and K;  B[:, j] = S b_j  (b_j assembled),
    fixed = the state rows of Dirichlet dofs (zero in every snapshot).

The Dirichlet rows are left as assembled (no bcs in the assembly); the reference works on the
free rows (a POD basis of the snapshots is zero there, and the full basis is I[:, free]).
"""

from __future__ import annotations

import numpy as np

from dolfinx_lopinf.fem._dolfinx import PETSc, dolfinx
from dolfinx_lopinf.fem.state import gather_states, output_matrix_in_state, point_output_matrix
from dolfinx_lopinf.fem.intrusive import dense_state_matrix


def _owned_to_state(V, local_owned: np.ndarray, state_map) -> np.ndarray:
    """Owned dof rows (n_owned,) or (n_owned, K) of every rank -> state rows, on every rank."""
    x = gather_states(V, local_owned, state_map)
    return V.mesh.comm.bcast(x, root=0)


def state_vector(form, V, state_map) -> np.ndarray:
    """An assembled linear form in state coordinates (n,), on every rank."""
    b = dolfinx.fem.petsc.assemble_vector(dolfinx.fem.form(form))
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    n_owned = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
    out = _owned_to_state(V, b.array[:n_owned].copy(), state_map)
    b.destroy()
    return out


def fixed_rows(bcs, V, state_map) -> np.ndarray:
    """Boolean (n,): the state rows of the Dirichlet dofs of ``bcs``."""
    n_owned = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
    mark = np.zeros(n_owned)
    for bc in bcs:
        dofs, first_ghost = bc.dof_indices()
        mark[dofs[:first_ghost]] = 1.0
    return _owned_to_state(V, mark, state_map) > 0.5


def fe_operators(loop, V, state_map) -> dict:
    """M, C (None if undamped), K (n, n), B (n, m), fixed (n,) bool and free (indices) of a
    loop module's forms, in snapshot row order (dense: small systems only)."""
    forms = loop.fe_forms(V)
    ops = {"M": dense_state_matrix(forms["mass"], V, state_map),
           "K": dense_state_matrix(forms["stiffness"], V, state_map),
           "C": None if forms.get("damping") is None
           else dense_state_matrix(forms["damping"], V, state_map),
           "B": np.column_stack([state_vector(f, V, state_map) for f in forms["inputs"]])}
    ops["fixed"] = fixed_rows(forms["bcs"], V, state_map)
    ops["free"] = np.flatnonzero(~ops["fixed"])
    return ops


def output_matrix(loop, V, state_map):
    """(E_local for the recorder, E_state (p, n) acting on snapshot rows) of loop.OUTPUT."""
    E_local = point_output_matrix(V, np.array(loop.OUTPUT["points"], dtype=float),
                                  component=loop.OUTPUT.get("component"))
    return E_local, output_matrix_in_state(V, E_local, state_map)


class Collector:
    """Keeps the loop's own u (and v, a when the loop has them) at every ``on_step`` call, in
    state coordinates - what the reference must reproduce."""

    def __init__(self):
        self.times, self.u, self.v, self.a, self.loads, self.load_times = [], [], [], [], [], []
        self.V = None

    def __call__(self, t, u, v, a, applied_load, applied_time):
        self.V = u.function_space
        n_owned = self.V.dofmap.index_map.size_local * self.V.dofmap.index_map_bs
        self.times.append(float(t))
        self.u.append(u.x.array[:n_owned].copy())
        self.v.append(None if v is None else v.x.array[:n_owned].copy())
        self.a.append(None if a is None else a.x.array[:n_owned].copy())
        self.loads.append(np.atleast_1d(np.asarray(applied_load, dtype=float)))
        self.load_times.append(float(applied_time))

    def arrays(self, state_map) -> dict:
        """times, U (inputs), load_times and Q, V, A (n, K) in state rows (V, A None if absent)."""
        out = {"times": np.array(self.times), "U": np.column_stack(self.loads),
               "load_times": np.array(self.load_times)}
        for key in ("u", "v", "a"):
            cols = getattr(self, key)
            out[{"u": "Q", "v": "V", "a": "A"}[key]] = None if cols[0] is None else \
                _owned_to_state(self.V, np.column_stack(cols), state_map)
        return out
