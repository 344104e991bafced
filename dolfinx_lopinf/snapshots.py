"""Snapshot data: the only thing the non-intrusive inference ever sees.

``Snapshots`` holds states Q (n, K) at uniform times (K,), optional velocities (n, K),
inputs U (m, K), outputs Y (p, K) and energies (K,), with named row blocks of Q (for
the beam: ``{"w": ..., "theta": ...}``). It is a plain numpy object: it can be saved to one
``.npz`` and loaded where there is no DOLFINx.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ._checks import check_finite, check_matrix, check_uniform_times


@dataclass(frozen=True)
class Snapshots:
    """Time samples of a full-order trajectory.

    Attributes:
        times: (K,) uniformly spaced sample times.
        Q: (n, K) states; column k is the state at ``times[k]``.
        blocks: name -> row indices of Q for physically different parts of the state.
        V: (n, K) velocities, or None.
        U: (m, K) inputs, or None.
        Y: (p, K) outputs, or None.
        energy: (K,) FOM energy, or None.
        output_times: (K_y,) times of ``Y`` when outputs are recorded on their own grid
            (e.g. a long run that keeps only outputs); None means ``times``.
    """

    times: np.ndarray
    Q: np.ndarray
    blocks: dict = field(default_factory=dict)
    V: np.ndarray | None = None
    U: np.ndarray | None = None
    Y: np.ndarray | None = None
    energy: np.ndarray | None = None
    output_times: np.ndarray | None = None

    def __post_init__(self):
        times = np.asarray(self.times, dtype=float)
        check_uniform_times(times)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "Q", check_matrix(self.Q, "Q", cols=len(times)))
        n = self.Q.shape[0]
        for name in ("V", "U", "energy"):
            value = getattr(self, name)
            if value is None:
                continue
            value = np.asarray(value, dtype=float)
            if value.shape[-1] != len(times) or (name == "V" and value.shape != self.Q.shape):
                raise ValueError(f"{name} has shape {value.shape}, incompatible with Q {self.Q.shape}")
            check_finite(value, name)
            object.__setattr__(self, name, value)
        if self.Y is not None:
            ty = times if self.output_times is None else np.asarray(self.output_times, float)
            object.__setattr__(self, "Y", check_matrix(np.atleast_2d(self.Y), "Y", cols=len(ty)))
        blocks = {str(k): np.asarray(v, dtype=np.int64) for k, v in self.blocks.items()}
        for name, rows in blocks.items():
            if rows.size and (rows.min() < 0 or rows.max() >= n):
                raise ValueError(f"block {name!r} indexes rows outside 0..{n - 1}")
        object.__setattr__(self, "blocks", blocks)

    @property
    def dt(self) -> float:
        return float(self.times[1] - self.times[0])

    @property
    def n_states(self) -> int:
        return self.Q.shape[0]

    def window(self, t_start: float, t_stop: float) -> "Snapshots":
        """The samples with ``t_start <= t <= t_stop`` (outputs on their own grid are cut too)."""
        tol = 1e-9 * self.dt
        keep = (self.times >= t_start - tol) & (self.times <= t_stop + tol)
        if keep.sum() < 2:
            raise ValueError(f"window [{t_start}, {t_stop}] holds fewer than 2 samples")

        def cut(a):
            return None if a is None else a[..., keep]

        Y, ty = self.Y, self.output_times
        if Y is not None and ty is None:
            Y = Y[:, keep]
        elif Y is not None:
            ykeep = (ty >= t_start - tol) & (ty <= t_stop + tol)
            Y, ty = Y[:, ykeep], ty[ykeep]
        return replace(self, times=self.times[keep], Q=self.Q[:, keep], V=cut(self.V),
                       U=cut(self.U), energy=cut(self.energy), Y=Y, output_times=ty)

    def save(self, path: str | Path) -> Path:
        """Write all arrays to one compressed ``.npz``."""
        path = Path(path)
        arrays = {k: v for k, v in self.__dict__.items() if isinstance(v, np.ndarray)}
        arrays.update({f"block__{k}": v for k, v in self.blocks.items()})
        np.savez_compressed(path, **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "Snapshots":
        with np.load(path) as data:
            kw = {k: data[k] for k in data.files if not k.startswith("block__")}
            kw["blocks"] = {k[7:]: data[k] for k in data.files if k.startswith("block__")}
        return cls(**kw)
