"""Snapshot data: the only thing the non-intrusive inference ever sees.

``Snapshots`` holds states Q (n, K) at uniform times (K,), optional velocities and
accelerations (n, K), inputs U (m, K_u) with the times at which they act, outputs Y (p, K)
and energies (K,), with named row blocks of Q (for the beam: ``{"w": ..., "theta": ...}``),
and optionally the integrator that produced them (``scheme``: a
:mod:`dolfinx_lopinf.core.schemes` object; None when unknown). It is a plain numpy object:
it can be saved to one ``.npz`` and loaded where there is no DOLFINx.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ._checks import (as_real_array, check_blocks, check_finite, check_matrix, check_uniform_times,
                      check_weight)
from ..errors import FileFormatError, InputError
from .io_atomic import atomic_savez_compressed, open_npz
from . import schemes as _schemes


def check_scheme(scheme, name: str = "scheme"):
    """``scheme`` as a :class:`~dolfinx_lopinf.core.schemes.Scheme` (from an object, its
    spec text or a name such as ``"newmark"``), or None; an
    :class:`~dolfinx_lopinf.errors.InputError` naming the bad value and the choices otherwise."""
    if scheme is None:
        return None
    if isinstance(scheme, str) and scheme.strip().lower() == "auto":
        raise InputError(f"{name}: 'auto' is not an integrator; for one you do not know pass "
                         "None (lo.fit then identifies it from the data)")
    try:
        return _schemes.from_spec(scheme)
    except InputError as exc:
        raise InputError(f"{name}: {exc}") from None


@dataclass(frozen=True)
class Snapshots:
    """Time samples of a full-order trajectory.

    Attributes:
        times: (K,) uniformly spaced sample times (times of a lower precision than float64
            are stored as the float64 grid t_0 + k dt they round).
        Q: (n, K) states; column k is the state at ``times[k]``.
        blocks: name -> row indices of Q for physically different parts of the state.
        V: (n, K) velocities, or None.
        U: (m, K_u) inputs ((K_u,): one input), or None.
        Y: (p, K) outputs, or None.
        energy: (K,) FOM energy, or None.
        output_times: (K_y,) times of ``Y`` when outputs are recorded on their own grid
            (e.g. a long run that keeps only outputs); None means ``times``.
        scheme: the integrator that produced the states (a
            :mod:`dolfinx_lopinf.core.schemes` object, or a name / spec text turned into
            one: ``"newmark"``, ``"midpoint"``, ``GeneralizedAlpha(rho_inf=0.8)``, ...), or
            None when unknown.
        A: (n, K) accelerations, or None (with V: the scheme's (u, v, a) relation is used).
        input_times: (K_u,) increasing times at which the columns of U act (a
            generalised-alpha loop applies its load at t_{n+1-alpha_f}); None: ``times``.
        weight: (n, n) inner product of the states - the mass matrix, or the L2 Gram matrix
            of the finite element space that :class:`~dolfinx_lopinf.SnapshotRecorder`
            assembles - as a ``scipy.sparse`` or dense symmetric positive definite matrix, or
            None (Euclidean). :func:`~dolfinx_lopinf.fit` builds its POD basis in it.
    """

    times: np.ndarray
    Q: np.ndarray
    blocks: dict = field(default_factory=dict)
    V: np.ndarray | None = None
    U: np.ndarray | None = None
    Y: np.ndarray | None = None
    energy: np.ndarray | None = None
    output_times: np.ndarray | None = None
    scheme: object = None
    A: np.ndarray | None = None
    input_times: np.ndarray | None = None
    weight: object = None

    def __post_init__(self):
        object.__setattr__(self, "scheme", check_scheme(self.scheme))
        dt = check_uniform_times(self.times)
        raw = np.asarray(self.times)
        times = as_real_array(self.times, "times")
        eps = np.finfo(raw.dtype).eps if raw.dtype.kind == "f" else np.finfo(float).eps
        if raw.dtype.kind == "f" and raw.dtype.itemsize < 8:
            # float32 (or coarser) times are a uniform grid rounded to their precision: keep
            # the grid itself, so every later check sees float64 times of that grid
            times = times[0] + dt * np.arange(len(times))
        object.__setattr__(self, "times", times)
        # how finely the caller's times are known (times given later, e.g. a window's
        # bounds, are compared to this rounding too)
        object.__setattr__(self, "_rounding", 2.0 * float(eps) * float(np.max(np.abs(times))))
        object.__setattr__(self, "_dt", dt)
        K = len(times)
        object.__setattr__(self, "Q", check_matrix(self.Q, "Q", cols=K))
        n = self.Q.shape[0]
        K_u = K
        if self.input_times is not None:
            if self.U is None:
                raise InputError("input_times given without inputs U; pass U too (or drop "
                                 "input_times)")
            ti = as_real_array(self.input_times, "input_times")
            if ti.ndim != 1 or len(ti) < 1:
                raise InputError(f"input_times must be a non-empty 1-D array, got shape {ti.shape}")
            check_finite(ti, "input_times")
            if len(ti) > 1 and np.min(np.diff(ti)) <= 0:
                k = int(np.argmin(np.diff(ti)))
                raise InputError(f"input_times must be strictly increasing; input_times[{k}] = "
                                 f"{float(ti[k])!r} is followed by {float(ti[k + 1])!r}")
            object.__setattr__(self, "input_times", ti)
            K_u = len(ti)
        for name in ("V", "A", "U", "energy"):
            value = getattr(self, name)
            if value is None:
                continue
            value = as_real_array(value, name)
            ok = {"V": value.shape == self.Q.shape, "A": value.shape == self.Q.shape,
                  "U": value.ndim in (1, 2), "energy": value.ndim == 1}[name] \
                and value.shape[-1] == (K_u if name == "U" else K)
            if not ok:
                want = {"V": f"{self.Q.shape} like Q", "A": f"{self.Q.shape} like Q",
                        "U": f"(m, {K_u})", "energy": f"({K},)"}[name]
                raise InputError(f"{name} has shape {value.shape}; it must be {want} (one "
                                 f"column per sample time)")
            check_finite(value, name)
            if name == "U" and value.ndim == 1:  # one input channel, as predict(inputs=) takes it
                value = value[None, :]
            object.__setattr__(self, name, value)
        ty = None
        if self.output_times is not None:
            if self.Y is None:
                raise InputError("output_times given without Y; pass the outputs Y too (or drop "
                                 "output_times)")
            ty = as_real_array(self.output_times, "output_times")
            if ty.ndim != 1 or len(ty) < 1:
                raise InputError(f"output_times must be a non-empty 1-D array, got shape {ty.shape}")
            check_finite(ty, "output_times")
            if len(ty) > 1 and np.min(np.diff(ty)) <= 0:
                k = int(np.argmin(np.diff(ty)))
                raise InputError(f"output_times must be strictly increasing; output_times[{k}] = "
                                 f"{float(ty[k])!r} is followed by {float(ty[k + 1])!r}")
            object.__setattr__(self, "output_times", ty)
        if self.Y is not None:
            Y = as_real_array(self.Y, "Y")
            Y = Y.reshape(1, -1) if Y.ndim == 1 else Y
            object.__setattr__(self, "Y", check_matrix(Y, "Y", cols=K if ty is None else len(ty)))
        object.__setattr__(self, "blocks", check_blocks(self.blocks, n))
        if self.weight is not None:
            object.__setattr__(self, "weight", check_weight(self.weight, n, "weight"))

    @property
    def dt(self) -> float:
        """The sample spacing (mean of the differences, exact to rounding even when the times
        carry a large offset)."""
        return self._dt

    @property
    def n_states(self) -> int:
        return self.Q.shape[0]

    def window(self, t_start: float, t_stop: float) -> "Snapshots":
        """The samples with ``t_start <= t <= t_stop`` (outputs on their own grid are cut too)."""
        for name, value in (("t_start", t_start), ("t_stop", t_stop)):
            try:
                bad = isinstance(value, (str, bytes, complex)) or np.isnan(float(value))
            except (TypeError, ValueError):
                bad = True
            if bad:
                raise InputError(f"{name} must be a real number (inf allowed), got {value!r}")
        tol = max(1e-9 * self.dt + 2 * np.finfo(float).eps * np.max(np.abs(self.times)),
                  getattr(self, "_rounding", 0.0))
        keep = (self.times >= t_start - tol) & (self.times <= t_stop + tol)
        if keep.sum() < 2:
            raise InputError(f"window [{t_start}, {t_stop}] holds fewer than 2 samples")

        def cut(a):
            return None if a is None else a[..., keep]

        Y, ty = self.Y, self.output_times
        if Y is not None and ty is None:
            Y = Y[:, keep]
        elif Y is not None:
            ykeep = (ty >= t_start - tol) & (ty <= t_stop + tol)
            Y, ty = Y[:, ykeep], ty[ykeep]
        U, ti = cut(self.U), None
        if self.input_times is not None:  # the inputs the window's steps need: one sample
            t0, t1 = self.times[keep][0], self.times[keep][-1]  # either side of it
            i0 = max(int(np.searchsorted(self.input_times, t0 - tol, side="right")) - 1, 0)
            i1 = min(int(np.searchsorted(self.input_times, t1 + tol, side="left")) + 1,
                     len(self.input_times))
            U, ti = self.U[:, i0:i1], self.input_times[i0:i1]
        return replace(self, times=self.times[keep], Q=self.Q[:, keep], V=cut(self.V),
                       A=cut(self.A), U=U, input_times=ti, energy=cut(self.energy), Y=Y,
                       output_times=ty)

    def save(self, path: str | Path) -> Path:
        """Write all arrays to one compressed ``.npz``, atomically (a temporary file in the
        same directory replaces ``path`` once complete; an interrupted save leaves the
        previous file intact). Returns the path written: ``.npz`` is appended unless
        ``path`` already ends in it."""
        arrays = {k: v for k, v in self.__dict__.items()
                  if isinstance(v, np.ndarray) and not k.startswith("_")}
        arrays.update({f"block__{k}": v for k, v in self.blocks.items()})
        if self.scheme is not None:
            arrays["scheme"] = np.array(self.scheme.spec)  # 0-d unicode: loads without pickle
        if self.weight is not None and not isinstance(self.weight, np.ndarray):  # sparse: CSR
            arrays.update(weight__data=self.weight.data, weight__indices=self.weight.indices,
                          weight__indptr=self.weight.indptr)
        return atomic_savez_compressed(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> "Snapshots":
        """Read a file written by :meth:`save`. Raises
        :class:`~dolfinx_lopinf.errors.FileFormatError` naming the file when it is not such
        a file (another format, truncated, missing or unknown entries), and
        ``FileNotFoundError`` when it does not exist."""
        fields = {"times", "Q", "V", "A", "U", "Y", "energy", "output_times", "scheme",
                  "input_times", "weight"}
        sparse_parts = ("weight__data", "weight__indices", "weight__indptr")
        with open_npz(path, "snapshots (Snapshots.save)") as (data, read):
            names = [k for k in data.files if not k.startswith("block__") and k not in sparse_parts]
            missing = [k for k in ("times", "Q") if k not in names]
            if missing:
                raise FileFormatError(f"{path}: lacks {', '.join(map(repr, missing))} "
                                      f"(entries found: {sorted(data.files)}); not a file "
                                      "written by Snapshots.save")
            unknown = sorted(set(names) - fields)
            if unknown:
                raise FileFormatError(f"{path}: unknown entries {unknown}; not a file written "
                                      "by Snapshots.save (a ROM? use load_rom)")
            kw = {k: read(k) for k in names}
            if "scheme" in kw:  # absent in files written before the field existed: None
                value = kw["scheme"]
                if value.ndim != 0 or value.dtype.kind != "U":
                    raise FileFormatError(f"{path}: entry 'scheme' must be one text value, got "
                                          f"dtype {value.dtype} shape {value.shape}")
                kw["scheme"] = str(value[()])
            kw["blocks"] = {k[7:]: read(k) for k in data.files if k.startswith("block__")}
            if any(k in data.files for k in sparse_parts):
                kw["weight"] = _sparse_weight(path, [read(k) if k in data.files else None
                                                     for k in sparse_parts], kw["Q"].shape[0])
        try:
            return cls(**kw)
        except InputError as exc:
            raise FileFormatError(f"{path}: the stored snapshots are invalid: {exc}") from exc


def _sparse_weight(path, parts, n):
    """The CSR weight stored by :meth:`Snapshots.save`, or a FileFormatError naming the file."""
    import scipy.sparse as sp

    data, indices, indptr = parts
    try:
        if data is None or indices is None or indptr is None:
            raise ValueError("part of the CSR arrays is missing")
        return sp.csr_array((data, indices, indptr), shape=(n, n))
    except (ValueError, TypeError) as exc:
        raise FileFormatError(f"{path}: the stored weight (CSR arrays weight__data, "
                              f"weight__indices, weight__indptr) is damaged: {exc}") from None


def common_weight(trajs, required: bool = True):
    """The inner product every trajectory (a list of :class:`Snapshots`) carries
    (``Snapshots.weight``; equal to 1e-12 of its largest entry, sparse or dense alike), or
    None when none does. When they carry different ones (or only some do): an InputError, or
    None when not ``required`` (the caller has a basis of its own)."""
    weights = [s.weight for s in trajs]
    if all(w is None for w in weights):
        return None
    first = weights[0]
    for k, w in enumerate(weights[1:], 1):
        if not _same_weight(first, w):
            if not required:
                return None
            raise InputError(
                f"the trajectories carry different inner products (Snapshots.weight of "
                f"trajectory 0 is {'None' if first is None else 'set'}, of trajectory {k} "
                f"{'None' if w is None else 'set' if first is None else 'different'}); record "
                "them with the same weight, or pass basis= (e.g. lo.pod(Q, r, weight=M))")
    return first


def _same_weight(a, b) -> bool:
    """Both None, or equal to 1e-12 of the largest entry (sparse or dense alike)."""
    if a is None or b is None:
        return a is b
    if a is b:
        return True
    import scipy.sparse as sp

    a = sp.csr_array(a)
    diff = abs(a - sp.csr_array(b))
    return bool(diff.max() <= 1e-12 * abs(a).max()) if diff.nnz else True
