"""The demos' shared harness: command line, rank-0 gating, one metrics vocabulary, the JSON
writer and the summary table. A demo keeps only what is specific to its scene::

    from dolfinx_lopinf.studies import harness

    def main(argv=None):
        args = harness.parse(__doc__, argv, out="results/beam", quick="short windows")
        ...                                                  # the scene: FOM, fits, scores
        rows.append(harness.rom_row("lopinf", r, train_error=..., test_error=...,
                                    stable=harness.stable(Qh, energy_error), ...))
        metrics = harness.metrics("beam", error="state", quick=args.quick, roms=rows, ...)
        harness.write_metrics(args.out, metrics)             # rank 0, atomic
        harness.summary(rows, ["method", "r", "train_error", "test_error", "stable"])
        return metrics                                       # tests call main() in-process

One vocabulary for every scene:

* ``train_error`` / ``test_error`` in every ROM row: relative errors on the training and test
  windows (or inputs) of the quantity named by the metrics' ``error`` (``"state"``: the
  reconstructed state, ``"output"``: the output y = E q); other errors keep explicit names
  (``projection_error_test``, ``max_energy_error``, ``output_errors`` per input, ...).
* ``stable``: :func:`stable` - one definition (:data:`STABLE_DEFINITION`).
* times in seconds, plain numbers (the slowest input when a row runs several; the per-input
  times under ``*_by_input``).

Why here (``dolfinx_lopinf/studies``) and not in ``demos/``: the vocabulary is read back by
:mod:`dolfinx_lopinf.studies.report` and by the tests, and an installed package cannot import
``demos/``; ``studies`` keeps it apart from the library's numerical layers.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..core.io_atomic import atomic_write_text, plain

#: the error vocabulary: what ``train_error`` / ``test_error`` of a row measure
ERRORS = {
    "state": "relative Frobenius error of the reconstructed states, ||Q - V Qh|| / ||Q||",
    "output": "relative error of the output, ||Y - Y_rom|| / ||Y||",
}

#: a run whose relative train or test error is above this has grown far past the truth: not
#: stable, even when its states stay finite (a model that grows by 1e12 over the test window)
DIVERGED_ERROR = 10.0
#: the one definition of a stable ROM run
STABLE_DEFINITION = ("states finite, relative train and test errors <= 10 and, where the FOM "
                     "energy of the reconstructed state is scored, relative FOM energy error "
                     "finite and <= 1")


def stable(states, energy_error=None, *, bound: float = 1.0) -> bool:
    """:data:`STABLE_DEFINITION`: ``states`` (any array, e.g. Qh or outputs) all finite and,
    when ``energy_error`` is given, it is finite and never above ``bound``."""
    ok = bool(np.all(np.isfinite(states)))
    if energy_error is not None:
        e = np.asarray(energy_error, dtype=float)
        ok = ok and bool(np.all(np.isfinite(e)) and (e.size == 0 or np.max(e) <= bound))
    return ok


def parse(doc: str, argv=None, *, out: str, quick: str = "short runs", extra=None):
    """The shared command line: ``--quick`` and ``--out`` (default ``out``); ``extra(parser)``
    adds a demo's own options. Returns the parsed namespace (``args.out`` a Path)."""
    parser = argparse.ArgumentParser(description=doc,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help=quick)
    parser.add_argument("--out", default=out, help="output directory")
    if extra is not None:
        extra(parser)
    args = parser.parse_args(argv)
    args.out = Path(args.out)
    args.parser = parser
    return args


def is_root(comm=None) -> bool:
    """True on the rank that writes files and prints (rank 0)."""
    if comm is None:
        from ..fem._dolfinx import MPI

        comm = MPI.COMM_WORLD
    return comm.rank == 0


def rom_row(method: str, r: int, *, train_error, test_error, stable: bool, **fields) -> dict:
    """One ROM row of metrics.json: method, r, the two errors of the scene's kind, stable
    (the caller's verdict, and no error above :data:`DIVERGED_ERROR`), and the scene's own
    fields (times, certificates, other errors)."""
    grown = any(e is not None and np.isfinite(e) and e > DIVERGED_ERROR
                for e in (train_error, test_error))
    return {"method": str(method), "r": int(r), "train_error": train_error,
            "test_error": test_error, **fields, "stable": bool(stable) and not grown}


def metrics(scene: str, *, error: str, quick: bool, roms: list | None, **fields) -> dict:
    """The metrics dict of one demo run: scene, error kind and its definition, the stable
    definition, quick flag, the scene's fields and its ROM rows (``roms=None``: the scene
    keeps its rows elsewhere, e.g. one table per loop)."""
    if error not in ERRORS:
        raise ValueError(f"error must be one of {sorted(ERRORS)}, got {error!r}")
    out = {"scene": scene, **fields, "quick": bool(quick), "error": error,
           "error_definition": ERRORS[error], "stable_definition": STABLE_DEFINITION}
    if roms is not None:
        out["roms"] = roms
    return out


def write_metrics(out, metrics: dict, name: str = "metrics.json") -> Path:
    """Write ``out/name`` atomically (rank 0 only; creates ``out``); numpy values become
    plain JSON numbers. Returns the path."""
    path = Path(out) / name
    if is_root():
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(plain(metrics), indent=1))
    return path


def _cell(value, width):
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return f"{str(value):>{width}}"
    if isinstance(value, (int, np.integer)):
        return f"{value:>{width}d}"
    return f"{value:{width}.2e}"


def summary(rows: list[dict], columns, *, widths=None, print_it: bool = True) -> str:
    """The summary table of ``rows`` (``columns``: keys, or (key, header) pairs); printed on
    rank 0 and returned."""
    cols = [(c, c) if isinstance(c, str) else tuple(c) for c in columns]
    widths = widths or [max(len(h), 9 if k not in ("method", "basis", "r") else len(h)) for k, h in cols]
    lines = [" ".join(f"{h:>{w}}" for (_, h), w in zip(cols, widths))]
    for row in rows:
        lines.append(" ".join(_cell(row.get(k), w) for (k, _), w in zip(cols, widths)))
    text = "\n".join(lines)
    if print_it and is_root():
        print(text)
    return text
