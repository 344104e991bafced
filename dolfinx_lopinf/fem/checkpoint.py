"""Checkpoints of :func:`dolfinx_lopinf.fem.fom.run`: the files, the run's fingerprint, resuming,
and the sink of the time loop that writes them (:class:`CheckpointSink`).

Per rank r and prefix P: two head files P.rank<r>.npz and P.rank<r>.b.npz written in turn
(the previous head stays valid while the next one is written, so the ranks can always agree
on a step all of them have), and append-only chunk files P.rank<r>.part<c>.npz holding what
was recorded between checkpoint c-1 and c (state and velocity columns, energies, outputs).
A head holds the integrator state (q, p, t, k), the run's fingerprint and a CRC of every
chunk it refers to. Each checkpoint writes one chunk and one head, each atomically
(:class:`CheckpointSink`).

The fingerprint is everything that determines the trajectory: the settings (exact) and
sketches (random projections) of the assembled forms at probe states; a checkpoint resumes
only when its fingerprint equals the run's (:func:`_resume`, collective).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import time
import zlib
from pathlib import Path

import numpy as np

from ._dolfinx import PETSc, dolfinx
from ..core.io_atomic import atomic_savez
from ..errors import CheckpointMismatchError, FileFormatError, InputError
from .agreement import agree
from .loop import OutputProbe, Sink

fpetsc = dolfinx.fem.petsc


def _collective(comm, problem, cls=InputError, where="run"):
    """Raise ``cls(problem)`` on every rank when any rank has a problem (same verdict
    everywhere; one allgather, see :func:`~dolfinx_lopinf.fem.agreement.agree`)."""
    agree(comm, where, None if problem is None else cls(problem))


_FORMAT = "dolfinx_lopinf checkpoint 2"
_CHUNK_KEYS = ("Q", "Vel", "energies", "energy_times", "ys", "y_times")


def _crc(arrays: dict) -> int:
    crc = 0
    for key in _CHUNK_KEYS:
        a = np.ascontiguousarray(arrays[key])
        crc = zlib.crc32(repr((key, a.dtype.str, a.shape)).encode(), crc)
        crc = zlib.crc32(a.view(np.uint8).reshape(-1) if a.size else b"", crc)
    return crc


class _CheckpointFiles:
    """The files of one rank's checkpoint under a prefix."""

    def __init__(self, prefix, rank: int):
        prefix = Path(prefix)
        self.dir = prefix.parent
        self.base = f"{prefix.name}.rank{rank}"
        self.heads = (self.dir / f"{self.base}.npz", self.dir / f"{self.base}.b.npz")

    def chunk(self, c: int) -> Path:
        return self.dir / f"{self.base}.part{c:05d}.npz"

    def remedy(self) -> str:
        return (f"delete the files {self.dir / self.base}*.npz, use another checkpoint prefix, "
                "or pass checkpoint_restart=True to start the run over")

    def existing(self) -> list[Path]:
        pattern = re.compile(rf"^\.?{re.escape(self.base)}\.(npz|b\.npz|part\d+\.npz)(\..*\.tmp)?$")
        try:
            return [self.dir / n for n in os.listdir(self.dir) if pattern.match(n)]
        except OSError:
            return []

    def remove_all(self):
        for path in self.existing():
            try:
                path.unlink()
            except OSError:
                pass


def _load_npz(path: Path, remedy: str) -> dict:
    """Every array of an .npz, or FileFormatError naming the file and the remedy."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except Exception as exc:  # BadZipFile, EOFError, zlib.error, ValueError, OSError, ...
        raise FileFormatError(f"checkpoint file {path} is truncated or corrupt "
                              f"({type(exc).__name__}: {exc}); {remedy}") from None


def _probe_vectors(V):
    """Two deterministic probe states (local arrays, owned + ghosts) that depend only on the
    global dof numbers, and the owned rows' global numbers."""
    imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
    nodes = np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32)
    g = (np.repeat(imap.local_to_global(nodes) * bs, bs) + np.tile(np.arange(bs), len(nodes))) \
        .astype(float)
    return 1e-3 * np.sin(1.3 * g + 0.1), 1e-3 * np.cos(0.77 * g + 0.2), g[: imap.size_local * bs]


def _sketch(comm, owned: np.ndarray, g: np.ndarray) -> list:
    """Four random projections and the squared norm of a distributed vector (allreduced):
    equal vectors give equal sketches; any real change of the vector changes them."""
    R = np.cos(np.outer(g, [0.7548776662, 0.5698402910, 0.3247179572, 0.2207440846]) + np.arange(4))
    local = np.append(owned @ R, owned @ owned)
    return [float(x) for x in comm.allreduce(local)]


def _fingerprint(stepper, settings: dict, output_matrix, probe_times) -> dict:
    """Everything that determines the trajectory: settings (exact), and sketches of the
    assembled forms at probe states (mass/momentum, step residual and momentum, forcing at
    two times, energy), the bcs' global dofs, the output matrix (compared with a tolerance)."""
    system = stepper.system
    V, comm = system.V, system.V.mesh.comm
    fp = dict(settings)
    a, b, g = _probe_vectors(V)
    n_owned = len(g)
    f = stepper.forms
    saved = [(fn, fn.x.array.copy()) for fn in (f.q0, f.q1, system.q, system.q_t)]
    saved_time = None if system.time is None else np.array(system.time.value, copy=True)
    vec = fpetsc.create_vector(V)

    def assembled(form):
        with vec.localForm() as loc:
            loc.set(0.0)
        fpetsc.assemble_vector(vec, form)
        vec.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return _sketch(comm, vec.array[:n_owned], g)

    try:
        for fn, x in ((f.q0, a), (f.q1, b), (system.q, a), (system.q_t, b)):
            fn.x.array[:] = x
        fp["mass and momentum dL/dq_t at a probe state"] = assembled(stepper._momentum_at)
        fp["energy at a probe state"] = [float(comm.allreduce(
            dolfinx.fem.assemble_scalar(stepper._energy)))]
        for t in probe_times:
            stepper._set_time(t)
            tag = f" (t = {t:.6g})" if system.time is not None else ""
            fp[f"step residual at a probe state{tag} (stiffness, potential, forcing)"] = \
                assembled(stepper._residual)
            fp[f"step momentum at a probe state{tag}"] = assembled(stepper._momentum)
            if system.forcing is not None:
                fp[f"forcing at a probe state{tag}"] = assembled(dolfinx.fem.form(system.forcing))
            if system.time is None:
                break
    finally:
        for fn, x in saved:
            fn.x.array[:] = x
        if saved_time is not None:
            system.time.value = saved_time
        vec.destroy()
    # Dirichlet conditions: the sorted global numbers of the constrained dofs
    bs = V.dofmap.index_map_bs
    owned_bc = stepper._bc_dofs[stepper._bc_dofs_owned_mask]
    glob = V.dofmap.index_map.local_to_global((owned_bc // bs).astype(np.int32)) * bs + owned_bc % bs
    all_bc = np.sort(np.concatenate(comm.allgather(np.asarray(glob, dtype=np.int64))))
    fp["Dirichlet dofs (global numbers)"] = f"{len(all_bc)} dofs, sha256 " + \
        hashlib.sha256(all_bc.tobytes()).hexdigest()[:16]
    if output_matrix is not None:
        E = np.asarray(output_matrix, dtype=float)
        fp["output matrix"] = [float(x) for x in comm.allreduce(
            np.concatenate([E @ a, E @ b]))] + [float(E.shape[0])]
    return fp


def _add_state_sketches(fp: dict, stepper) -> None:
    system = stepper.system
    comm = system.V.mesh.comm
    g = _probe_vectors(system.V)[2]
    n_owned = len(g)
    fp["initial state q0 (after the bcs)"] = _sketch(comm, stepper.q.x.array[:n_owned], g)
    fp["initial velocity v0 (after the bcs)"] = _sketch(comm, system.q_t.x.array[:n_owned], g)


def _differences(stored: dict, current: dict, n_global: int) -> list[str]:
    out = []
    for key in sorted(set(stored) | set(current)):
        old, new = stored.get(key), current.get(key)
        if key not in stored or key not in current:
            out.append(f"{key}: {'absent' if old is None else old!r} in the checkpoint, "
                       f"{'absent' if new is None else new!r} in this run")
        elif isinstance(old, list) and isinstance(new, list) and len(old) == len(new):
            o, n = np.array(old, dtype=float), np.array(new, dtype=float)
            # sketch entries: equal up to rounding (the same run reproduces them bit for bit;
            # the tolerance only keeps a harmless last-bit difference from refusing a resume)
            scale = np.sqrt(abs(o[-1])) + np.sqrt(abs(n[-1])) if len(o) == 5 else np.abs(o).max()
            tol = 1e-9 * max(scale * np.sqrt(max(n_global, 1)), np.abs(o).max(initial=0.0), 1e-300)
            same = np.all((np.abs(o - n) <= tol) | (np.isnan(o) & np.isnan(n)))
            if not same:
                rel = float(np.nanmax(np.abs(o - n)) / max(np.nanmax(np.abs(o)), 1e-300))
                out.append(f"{key} (differs by {rel:.2g} relative)")
        elif old != new:
            out.append(f"{key}: {old!r} in the checkpoint, {new!r} in this run")
    return out


def _resume(files: _CheckpointFiles, comm, fingerprint: dict, n_global: int):
    """Read this rank's newest head that every rank has, check its fingerprint, load its
    chunks. Collective: every rank returns the same kind of answer or raises the same error.
    Returns None (no checkpoint: start from step 0) or (head, chunks)."""
    heads, problem = {}, None
    for path in files.heads:
        if path.exists():
            try:
                data = _load_npz(path, files.remedy())
                if str(data.get("format", "")) != _FORMAT or "k" not in data:
                    raise FileFormatError(f"{path} is not a checkpoint of this version of "
                                          f"dolfinx_lopinf (no '{_FORMAT}' header); "
                                          f"{files.remedy()}")
                heads[int(data["k"])] = (path, data)
            except FileFormatError as exc:
                problem = problem or str(exc)
    _collective(comm, problem, FileFormatError)
    steps = comm.allgather(sorted(heads))
    if not any(steps):
        return None
    common = set(steps[0]).intersection(*map(set, steps[1:]))
    if not common:
        missing = [r for r, s in enumerate(steps) if not s]
        raise CheckpointMismatchError(
            f"the checkpoint under prefix {files.dir / files.base.rsplit('.rank', 1)[0]} is "
            f"incomplete: ranks {missing or 'all'} have no head at a step the others have "
            f"(steps per rank: {steps}); it comes from a run on another number of ranks or was "
            f"left by another run. {files.remedy()}")
    k = max(common)
    path, head = heads[k]
    try:
        stored = json.loads(str(head["fingerprint"]))
    except (KeyError, ValueError) as exc:
        stored, problem = {}, f"checkpoint file {path} has no readable fingerprint ({exc})"
    _collective(comm, problem, FileFormatError)
    diffs = _differences(stored, fingerprint, n_global)
    all_diffs = comm.allgather(diffs) if comm.size > 1 else [diffs]
    union = list(dict.fromkeys(d for ds in all_diffs for d in ds))
    if union:
        raise CheckpointMismatchError(
            f"checkpoint {path} belongs to another run, so resuming it would silently continue "
            "that run's trajectory. What differs: " + "; ".join(union) + f". {files.remedy()}")
    chunks, problem = [], None
    crcs = np.asarray(head["chunk_crc"], dtype=np.int64)
    for c in range(int(head["n_chunks"])):
        try:
            data = _load_npz(files.chunk(c), files.remedy())
            if any(key not in data for key in _CHUNK_KEYS) or _crc(data) != int(crcs[c]):
                raise FileFormatError(f"checkpoint chunk {files.chunk(c)} does not match its head "
                                      f"{path} (checksum); {files.remedy()}")
            chunks.append(data)
        except FileNotFoundError:
            problem = problem or f"checkpoint chunk {files.chunk(c)} is missing; {files.remedy()}"
            break
        except FileFormatError as exc:
            problem = problem or str(exc)
            break
    _collective(comm, problem, FileFormatError)
    return head, chunks


def _checkpoint_files(checkpoint, rank: int) -> _CheckpointFiles:
    """This rank's checkpoint files under the prefix (its directory checked on this rank)."""
    try:
        prefix = Path(checkpoint)
    except TypeError:
        raise InputError(f"checkpoint must be a path prefix (str or Path), got "
                         f"{type(checkpoint).__name__}") from None
    directory = prefix.parent
    if not directory.is_dir():
        raise InputError(f"checkpoint = {str(checkpoint)!r}: the directory {directory} does not "
                         "exist (create it first)")
    if not os.access(directory, os.W_OK | os.X_OK):
        raise InputError(f"checkpoint = {str(checkpoint)!r}: the directory {directory} is not "
                         "writable")
    return _CheckpointFiles(prefix, rank)


class CheckpointSink(Sink):
    """Every ``every`` steps (not at the last one) append what ``recorder`` and ``probe``
    recorded since the previous checkpoint to a chunk file and write the integrator state to
    a head file (each atomically); see the format notes above :func:`_crc`. ``recorder``: the
    run's :class:`~dolfinx_lopinf.fem.fom.StateRecorder`."""

    def __init__(self, files: _CheckpointFiles, fingerprint: dict, recorder,
                 probe: OutputProbe | None, *, every: int):
        self.files, self.fingerprint, self.every = files, fingerprint, every
        self.recorder, self.probe = recorder, probe
        self.j = self.ne = self.ny = 0
        self.crc, self.bytes, self.seconds = [], 0, 0.0

    def after(self, s):
        if s.k % self.every == 0 and s.k < s.n_steps:
            self.save(s)

    def save(self, s):
        t_save = time.perf_counter()
        rec, probe, it = self.recorder, self.probe, s.integrator
        c = len(self.crc)
        p_out = probe.E.shape[0] if probe is not None else 0
        ys = probe.values if probe is not None else []
        y_times = probe.times if probe is not None else []
        chunk = {"Q": rec.Q[:, self.j:rec.filled],
                 "Vel": rec.Vel[:, self.j:rec.filled] if rec.Vel is not None else np.zeros((0, 0)),
                 "energies": np.array(rec.energies[self.ne:], dtype=float),
                 "energy_times": np.array(rec.energy_times[self.ne:], dtype=float),
                 "ys": (np.array(ys[self.ny:], dtype=float).reshape(-1, p_out) if p_out
                        else np.zeros((0, 0))),
                 "y_times": np.array(y_times[self.ny:], dtype=float)}
        atomic_savez(self.files.chunk(c), **chunk)
        crcs = self.crc + [_crc(chunk)]
        head = self.files.heads[len(crcs) % 2]
        atomic_savez(head, format=np.array(_FORMAT),
                     fingerprint=np.array(json.dumps(self.fingerprint)), k=np.array(s.k),
                     q=it.q.x.array, p=it.p.array, t=np.array(it.t),
                     n_chunks=np.array(len(crcs)), chunk_crc=np.array(crcs, dtype=np.int64),
                     filled=np.array(rec.filled))
        self.j, self.ne, self.ny, self.crc = rec.filled, len(rec.energies), len(ys), crcs
        self.bytes += self.files.chunk(c).stat().st_size + head.stat().st_size
        self.seconds += time.perf_counter() - t_save

    def restore(self, integrator, head, chunks) -> int:
        """Put a resumed checkpoint back into the integrator, recorder and probe; return the
        first step still to take."""
        rec, probe = self.recorder, self.probe
        k_start = int(head["k"]) + 1
        integrator.q.x.array[:] = head["q"]
        integrator.p.array[:] = head["p"]
        integrator.t = float(head["t"])
        integrator.steps_taken = k_start - 1
        j0 = 0
        for data in chunks:
            j1 = j0 + data["Q"].shape[1]
            rec.Q[:, j0:j1] = data["Q"]
            if rec.Vel is not None:
                rec.Vel[:, j0:j1] = data["Vel"]
            j0 = j1
            rec.energies.extend(data["energies"].tolist())
            rec.energy_times.extend(data["energy_times"].tolist())
            if probe is not None:
                probe.values.extend(list(data["ys"]))
                probe.times.extend(data["y_times"].tolist())
        rec.filled = j0
        self.j, self.ne = rec.filled, len(rec.energies)
        self.ny = len(probe.values) if probe is not None else 0
        self.crc = [int(c) for c in head["chunk_crc"]]
        return k_start

    def finish(self, s):
        self.files.remove_all()
