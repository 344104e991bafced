"""Record snapshots from an existing dolfinx time loop (no need for our FOM).

    recorder = SnapshotRecorder(u)                  # u: the dolfinx Function your loop updates
    for n in range(num_steps):
        ...  your solve ...
        recorder.record(t, u, inputs=[load(t)])     # once per step (or every k-th step)
    snaps = recorder.snapshots()                    # Snapshots on rank 0, None elsewhere

Each rank stores only its owned dofs; :meth:`SnapshotRecorder.snapshots` gathers them once
into global dof order, so the arrays are identical for any number of ranks.
"""

from __future__ import annotations

import numpy as np

from ._dolfinx import MPI, dolfinx
from .fom import StateMap, gather_states
from .snapshots import Snapshots


class SnapshotRecorder:
    """Collects states (and optional velocities, inputs, outputs) of a dolfinx Function.

    Args:
        u: the Function (or its FunctionSpace) whose values are recorded.
        state_map: dof -> state coordinates (default: ordered by dof coordinates, identical
            for any number of ranks; Lagrange-type spaces).
        output_matrix: optional (p, n_local) local output matrix, e.g. from
            :func:`dolfinx_lopinf.point_output_matrix`; y = sum over ranks of E u_local.
        blocks: optional name -> state rows (for block-diagonal POD).

    Example:
        >>> rec = SnapshotRecorder(u)                                   # doctest: +SKIP
        >>> rec.record(0.0, u, inputs=[0.0])                            # doctest: +SKIP
    """

    def __init__(self, u, *, state_map: StateMap | None = None, output_matrix=None,
                 blocks: dict | None = None):
        V = u.function_space if isinstance(u, dolfinx.fem.Function) else u
        if not hasattr(V, "dofmap"):
            raise TypeError("SnapshotRecorder needs a dolfinx Function or FunctionSpace")
        self.V = V
        self.state_map = StateMap.from_coordinates(V) if state_map is None else state_map
        if blocks:
            self.state_map = StateMap(self.state_map.order, self.state_map.scale, blocks)
        self.output_matrix = output_matrix
        self._n_owned = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
        self._n_local = (V.dofmap.index_map.size_local + V.dofmap.index_map.num_ghosts) \
            * V.dofmap.index_map_bs
        self._times, self._states, self._velocities, self._inputs, self._outputs = [], [], [], [], []

    def __len__(self) -> int:
        return len(self._times)

    def _local(self, f, name):
        if isinstance(f, dolfinx.fem.Function):
            if f.function_space.dofmap.index_map.size_global != self.V.dofmap.index_map.size_global:
                raise ValueError(f"{name} lives on a different function space than the recorder's")
            arr = f.x.array
        else:
            arr = np.asarray(f, dtype=float)
        if arr.shape[0] not in (self._n_owned, self._n_local):
            raise ValueError(f"{name} has {arr.shape[0]} local entries; expected {self._n_owned} "
                             f"(owned) or {self._n_local} (owned + ghosts)")
        return arr

    def record(self, t: float, u, *, velocity=None, inputs=None) -> None:
        """Store the state at time t (times must be increasing and uniformly spaced).

        Args:
            t: time of this state.
            u: Function or local dof array (owned, or owned + ghosts).
            velocity: optional Function/array of the velocity at t.
            inputs: optional sequence of m input values at t (same m every call).
        """
        t = float(t)
        comm = self.V.mesh.comm
        arr = self._local(u, "u")
        # collective check, so every rank raises together (no rank left waiting)
        if comm.allreduce(not np.all(np.isfinite(arr[: self._n_owned])), op=MPI.LOR):
            raise ValueError(f"the state recorded at t = {t} contains NaN or inf")
        if self._times:
            if t <= self._times[-1]:
                raise ValueError(f"times must increase: got t = {t} after {self._times[-1]}")
            if len(self._times) >= 2:
                dt = self._times[1] - self._times[0]
                if abs((t - self._times[-1]) - dt) > 1e-6 * dt:
                    raise ValueError(f"record at a uniform spacing: dt was {dt}, now "
                                     f"{t - self._times[-1]} at t = {t}")
        if inputs is not None:
            inputs = np.atleast_1d(np.asarray(inputs, dtype=float)).ravel()
            if self._inputs and len(inputs) != len(self._inputs[0]):
                raise ValueError(f"inputs had {len(self._inputs[0])} entries, now {len(inputs)}")
        if (inputs is None) != (not self._inputs) and self._times:
            raise ValueError("pass inputs at every record() call or at none")
        if (velocity is None) != (not self._velocities) and self._times:
            raise ValueError("pass velocity at every record() call or at none")
        self._times.append(t)
        self._states.append(arr[: self._n_owned].copy())
        if velocity is not None:
            self._velocities.append(self._local(velocity, "velocity")[: self._n_owned].copy())
        if inputs is not None:
            self._inputs.append(inputs)
        if self.output_matrix is not None:
            full = arr if arr.shape[0] == self._n_local else None
            if full is None:
                raise ValueError("outputs need the ghosted array: pass the Function itself")
            self._outputs.append(comm.allreduce(self.output_matrix @ full))

    def snapshots(self) -> Snapshots | None:
        """Gather everything to rank 0 as :class:`Snapshots` (None on the other ranks)."""
        if len(self._times) < 2:
            raise ValueError("record at least two time steps before asking for snapshots")
        Q = gather_states(self.V, np.column_stack(self._states), self.state_map)
        Vel = gather_states(self.V, np.column_stack(self._velocities), self.state_map) \
            if self._velocities else None
        if self.V.mesh.comm.rank != 0:
            return None
        U = np.column_stack(self._inputs) if self._inputs else None
        Y = np.column_stack(self._outputs) if self._outputs else None
        return Snapshots(times=np.array(self._times), Q=Q, blocks=self.state_map.blocks, V=Vel,
                         U=U, Y=Y)
