"""Speed against error, per scene, from the demos' metrics.json.

    python -m dolfinx_lopinf.studies.report [RESULTS_DIR]

For every ``RESULTS_DIR/*/metrics.json`` it draws ``RESULTS_DIR/report_<scene>.png``: ROM
wall time and inference time against test error for every method and r, with the FOM time
as a reference line, and prints a markdown table of the best test error per method with what
it cost. A user sees at a glance what a given error costs.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import NamedTuple

import numpy as np


class Point(NamedTuple):
    """One ROM row of a scene, as the report plots and tabulates it."""

    label: str
    r: int
    error: float
    rom_seconds: float
    infer_seconds: float
    rom_seconds_numpy: float | None  # the same run on the numpy reference loop
    backend: str  # the loop rom_seconds was measured with


def _rows(metrics: dict):
    """A :class:`Point` for every ROM row. Every demo
    writes the harness's vocabulary (:mod:`dolfinx_lopinf.studies.harness`): ``test_error`` of
    the scene's error kind, times as plain numbers."""
    out = []
    for row in metrics.get("roms", []):
        err, rom_s = row.get("test_error"), row.get("rom_seconds")
        if err is None or rom_s is None or not np.isfinite(err):
            continue
        label = row["method"] + (f" ({row['basis']})" if "basis" in row else "")
        numpy_s = row.get("rom_seconds_numpy")
        out.append(Point(label, row["r"], float(err), float(rom_s),
                         float(row.get("infer_seconds", 0.0)),
                         None if numpy_s is None else float(numpy_s), row.get("rom_backend", "numpy")))
    return out


def _fom_seconds(metrics: dict) -> float | None:
    """The FOM's time over the ROMs' horizon (t_end)."""
    return metrics.get("fom_seconds_to_t_end", metrics.get("fom_seconds"))


def scene_report(metrics: dict, path: Path) -> list[str]:
    """Draw the speed-vs-error front of one scene; return markdown table lines."""
    from ..viz.render import _finish, _pyplot

    plt = _pyplot()
    rows = _rows(metrics)
    fig, ax = plt.subplots(figsize=(10.5, 4.6))
    labels = sorted({p.label for p in rows})
    for i, label in enumerate(labels):
        sel = sorted((p for p in rows if p.label == label and p.error <= 1.0), key=lambda p: p.r)
        failed = sum(1 for p in rows if p.label == label and p.error > 1.0)
        note = f" ({failed} with error > 1 omitted)" if failed else ""
        ax.loglog([p.rom_seconds for p in sel], [p.error for p in sel], "o", color=f"C{i}", alpha=0.8,
                  label=f"{label}: ROM{note}")
        if any(p.infer_seconds > 0 for p in sel):
            ax.loglog([max(p.infer_seconds, 1e-6) for p in sel], [p.error for p in sel], "x", color=f"C{i}",
                      label=f"{label}: inference")
    fom = _fom_seconds(metrics)
    if fom:
        ax.axvline(fom, color="k", ls="--", label=f"FOM {fom:.3g} s (same horizon as the ROMs)")
    _finish(fig, ax, path, xlabel="wall time [s]", ylabel="relative test error",
            title=f"{metrics['scene']}: speed against {metrics.get('error', 'state')} error "
                  f"(n = {metrics.get('n_dofs')})",
            legend={"loc": "upper left", "bbox_to_anchor": (1.01, 1.0)})  # beside the data
    lines = []
    for label in labels:
        best = min((p for p in rows if p.label == label), key=lambda p: p.error)
        numpy_s = "-" if best.rom_seconds_numpy is None else f"{best.rom_seconds_numpy:.3g}"
        speedup = "-" if not fom else f"{fom / best.rom_seconds:.3g}x"
        lines.append(f"| {metrics['scene']} | {label} | {best.r} | {best.error:.2e} | "
                     f"{best.rom_seconds:.3g} ({best.backend}) | {numpy_s} | {speedup} | "
                     f"{best.infer_seconds:.3g} | "
                     f"{fom if fom is None else f'{fom:.3g}'} |")
    return lines


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", nargs="?", default="results")
    args = parser.parse_args(argv)
    root = Path(args.results)
    files = sorted(root.glob("*/metrics.json"))
    if not files:
        raise SystemExit(f"no */metrics.json under {root}: run the demos first")
    table = ["| scene | method | best r | test error | ROM s (loop) | ROM s, numpy loop | "
             "FOM / ROM | inference s | FOM s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for f in files:
        metrics = json.loads(f.read_text())
        if not metrics.get("roms"):
            continue
        table += scene_report(metrics, root / f"report_{f.parent.name}.png")
    print("\n".join(table))
    (root / "report.md").write_text("\n".join(table) + "\n")
    return table


if __name__ == "__main__":
    main()
