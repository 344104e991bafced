"""Snapshot POD whose memory does not grow with n x K: snapshots go to disk as they come.

    pod = StreamingPOD(V, capacity=401, weight=M)    # M: PETSc matrix (mass), or None
    for k in range(...):
        ... one FOM step ...
        pod.append(q)                                 # dolfinx Function or owned array
    basis_local, Qh, lam = pod.compute(r)             # collective

or, in the one time loop, as a sink: ``fom.run(integrator, n, sinks=[pod.sink(until_step=400)])``.

The method of snapshots in the W inner product (W = M gives a mass-orthonormal basis, the
reduced mass is then exactly I):

    G = Q^T W Q = Psi diag(lam) Psi^T   (K x K),
    V = Q Psi_r diag(lam_r)^-1/2        (V^T W V = I),
    Qh = V^T W Q = diag(lam_r)^1/2 Psi_r^T.

Each rank appends its owned dofs q_k and w_k = W q_k (one mat-vec) to two on-disk arrays
(``.npy`` files, one row per snapshot), written with plain file writes: the rows go to the
page cache and the disk, never into the process's memory (a writable memory map of the
files would count every written page in the process's resident memory - 2.3 GB per rank
over the 795k-dof fishtail's training run). G is summed over column chunks of the stored
rows (read back row by row into one reused buffer, no memory map either) and all-reduced; V
is formed chunk by chunk too. A chunk holds ``chunk`` columns of all K rows; by default as
many as fit :data:`CHUNK_BYTES` per array. Peak memory per rank: O(K^2 + chunk K + n_local r)
for any number of snapshots; disk: 2 n K doubles (deleted by :meth:`close`). Qh and lam are
identical on every rank; V is returned as this rank's owned rows.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from ._dolfinx import MPI, dolfinx
from ..core._blas import share_cores_among_ranks
from ..errors import InputError
from .agreement import agree
from .lagrangian import _on_space


#: bytes of one column chunk of one stored array (K rows x chunk columns) when ``chunk`` is
#: not given: the reading buffers of :meth:`StreamingPOD.gram` and ``compute``
CHUNK_BYTES = 32 * 2**20


def _positive(x) -> bool:
    try:
        return bool(np.isfinite(float(x)) and float(x) > 0)
    except (TypeError, ValueError):
        return False


class StreamingPOD:
    """Out-of-core method-of-snapshots POD of the states of a dolfinx function space.

    Args:
        V: the FunctionSpace of the recorded states.
        capacity: the most snapshots that will be appended (sizes the disk arrays).
        weight: PETSc matrix W of the inner product (e.g. the mass matrix), or None for the
            Euclidean one.
        directory: where the per-rank arrays go (default: a fresh temporary directory).
        chunk: number of state rows (columns of the stored arrays) handled at once in
            :meth:`gram` and :meth:`compute`; default: as many as fit :data:`CHUNK_BYTES`.
    """

    def __init__(self, V, capacity: int, *, weight=None, directory=None, chunk: int | None = None):
        if not isinstance(V, dolfinx.fem.FunctionSpace):
            raise InputError(f"V must be a dolfinx FunctionSpace, got {type(V).__name__}")
        problem = None
        for name, value, low in (("capacity", capacity, 2), ("chunk", 1 if chunk is None else chunk, 1)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                problem = problem or f"{name} must be an integer >= {low}, got {value!r}"
        if weight is not None and not hasattr(weight, "mult"):
            problem = problem or f"weight must be a PETSc matrix (or None), got {type(weight).__name__}"
        # the directory may differ between ranks (node-local disks); the sizes may not
        agree(V.mesh.comm, "StreamingPOD", problem, capacity=capacity, weight=weight is not None)
        self.V, self.comm = V, V.mesh.comm
        share_cores_among_ranks(self.comm)  # the Gram updates' dense work: a rank's share
        self.n_owned = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
        self.capacity, self.weight = int(capacity), weight
        self.chunk = int(chunk) if chunk is not None else \
            max(1, min(max(self.n_owned, 1), CHUNK_BYTES // (8 * self.capacity)))
        base = tempfile.mkdtemp(prefix="lopinf_pod_", dir=directory)
        self._dir = Path(base)
        name = f"rank{self.comm.rank}"
        self._files = {}  # "q", "wq" -> (path, open file, offset of the data)
        for key in ("q", "wq") if weight is not None else ("q",):
            path = self._dir / f"{name}_{key}.npy"
            header = np.lib.format.open_memmap(path, mode="w+", dtype=float,
                                               shape=(self.capacity, self.n_owned))
            offset = header.offset
            del header  # the file exists at full size; rows are written through the file
            self._files[key] = (path, open(path, "r+b"), offset)
        self._x = weight.createVecRight() if weight is not None else None
        self._y = weight.createVecLeft() if weight is not None else None
        self.count = 0
        self._eig = None

    def append(self, q) -> None:
        """Store one snapshot: a dolfinx Function on V or this rank's owned values."""
        problem = None
        if isinstance(q, dolfinx.fem.Function):
            if not _on_space(q, self.V):
                problem = "the snapshot is a Function on another mesh or function space than V"
            q = q.x.array[: self.n_owned]
        q = np.asarray(q, dtype=float)
        if problem is not None:
            pass
        elif q.shape != (self.n_owned,):
            problem = f"snapshot has shape {q.shape}; this rank owns {self.n_owned} dofs"
        elif self.count >= self.capacity:
            problem = f"StreamingPOD is full ({self.capacity} snapshots); raise capacity"
        elif not np.all(np.isfinite(q)):
            problem = f"snapshot {self.count} contains NaN or inf"
        # collective verdict: a rank that refuses does not leave the others appending
        agree(self.comm, "StreamingPOD.append", problem)
        self._write("q", q)
        if self.weight is not None:
            self._x.array[:] = q
            self.weight.mult(self._x, self._y)
            self._write("wq", self._y.array)
        self.count += 1

    def _write(self, key, row) -> None:
        _, f, offset = self._files[key]
        f.seek(offset + self.count * self.n_owned * 8)
        f.write(np.ascontiguousarray(row, dtype=float).tobytes())

    def _columns(self, key, cols, buffer) -> np.ndarray:
        """The stored rows' columns ``cols`` (count x width), read row by row into the front
        of ``buffer`` (count x chunk, reused across chunks; no memory map: the file's pages
        stay out of the process's resident memory)."""
        path, f, offset = self._files[key]
        f.flush()
        out = buffer[:, : cols.stop - cols.start]  # each row a contiguous prefix
        width = out.shape[1] * 8
        for k in range(self.count):
            start = offset + (k * self.n_owned + cols.start) * 8
            got = os.preadv(f.fileno(), [memoryview(out[k]).cast("B")], start)
            if got != width:
                raise OSError(f"StreamingPOD: short read of snapshot {k} ({got} of {width} bytes) "
                              f"from {path}")
        return out

    def _chunks(self):
        """(a reading buffer of count x chunk, the column slices of the chunks)."""
        buffer = np.empty((self.count, min(self.chunk, self.n_owned)))
        return buffer, [slice(start, min(start + self.chunk, self.n_owned))
                        for start in range(0, self.n_owned, self.chunk)]

    def gram(self) -> np.ndarray:
        """G = Q^T W Q over the appended snapshots (collective; identical on every rank)."""
        K = self.count
        G = np.zeros((K, K))
        bq, chunks = self._chunks()
        bw = np.empty_like(bq) if self.weight is not None else None
        for cols in chunks:
            Q = self._columns("q", cols, bq)
            W = self._columns("wq", cols, bw) if self.weight is not None else Q
            G += Q @ W.T
        G = self.comm.allreduce(G, op=MPI.SUM)
        return 0.5 * (G + G.T)

    def compute(self, r: int, *, rank_rtol: float = 1e-7):
        """The rank-r POD (collective). Singular values sqrt(lam) below ``rank_rtol`` times the
        largest count as zero: the Gram matrix resolves lam to ~1e-16 lam_max, so singular
        values below ~1e-8 of the largest are not known.

        Returns:
            ``(basis_local, Qh, lam)``: this rank's owned rows of V (n_owned, r), the reduced
            coordinates Qh = V^T W Q (r, K) and all eigenvalues of G (descending).
        """
        problem = None
        if isinstance(r, (bool, np.bool_)) or not isinstance(r, (int, np.integer)) or r < 1:
            problem = f"r must be an integer >= 1, got {r!r}"
        elif not _positive(rank_rtol):
            problem = f"rank_rtol must be a positive finite number, got {rank_rtol!r}"
        agree(self.comm, "StreamingPOD.compute", problem, r=r, rank_rtol=rank_rtol)
        lam, Psi = self._eigen()
        sv = np.sqrt(np.maximum(lam, 0.0))
        rank = self.numerical_rank(rank_rtol)
        if r > rank:
            raise InputError(f"asked for r = {r} but the {self.count} snapshots have numerical rank "
                             f"{rank} (singular values {sv[: r + 1]}); lower r or record richer data")
        coef = Psi[:, :r] / np.sqrt(lam[:r])  # V = Q coef
        basis = np.empty((self.n_owned, r))
        bq, chunks = self._chunks()
        for cols in chunks:
            basis[cols] = self._columns("q", cols, bq).T @ coef
        Qh = np.sqrt(lam[:r])[:, None] * Psi[:, :r].T
        return basis, Qh, lam

    def _eigen(self):
        """Eigenpairs of G, descending, cached until the next append (collective)."""
        if self.count < 2:
            raise InputError(f"POD needs at least 2 snapshots, {self.count} appended")
        if self._eig is None or self._eig[0] != self.count:
            lam, Psi = np.linalg.eigh(self.gram())
            order = np.argsort(lam)[::-1]
            lam, Psi = lam[order], Psi[:, order]
            # sign convention (so 1 and N ranks agree): the largest entry of each column is > 0
            Psi *= np.sign(Psi[np.argmax(np.abs(Psi), axis=0), np.arange(Psi.shape[1])])
            self._eig = (self.count, lam, Psi)
        return self._eig[1], self._eig[2]

    def numerical_rank(self, rank_rtol: float = 1e-7) -> int:
        """Number of singular values sqrt(lam) above ``rank_rtol`` times the largest (collective)."""
        sv = np.sqrt(np.maximum(self._eigen()[0], 0.0))
        return int(np.sum(sv > rank_rtol * max(sv[0], np.finfo(float).tiny)))

    def sink(self, *, every: int = 1, until_step: int | None = None):
        """A sink of :func:`dolfinx_lopinf.fem.loop.run_loop` that appends the integrator's state
        at every ``every``-th step up to ``until_step`` (step 0 included)."""
        from .loop import Every

        return Every(lambda s: self.append(s.q), every=every, until_step=until_step)

    @property
    def disk_bytes(self) -> int:
        return len(self._files) * self.count * self.n_owned * 8

    def close(self) -> None:
        """Delete the on-disk arrays."""
        for _, f, _ in self._files.values():
            f.close()
        self._files = {}
        shutil.rmtree(self._dir, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
