"""Speed against error per scene, and the documentation's generated pages, from the demos'
metrics.json.

    python -m dolfinx_lopinf.studies.report [RESULTS_DIR ...]
    python -m dolfinx_lopinf.studies.report --docs docs/generated RESULTS_DIR ...

Each RESULTS_DIR is a demo's output folder (holding metrics.json) or a folder of them
(``results/*/metrics.json``). Without ``--docs`` it draws ``report_<scene>.png`` beside the
metrics of each scene - ROM wall time and inference time against test error for every method
and r, with the FOM time as a reference line - and prints a markdown table of the best test
error per method with what it cost (also written to the first RESULTS_DIR as report.md).

With ``--docs OUT`` it writes the generated part of the documentation instead
(:func:`write_docs`): ``OUT/<scene>.md`` per demo - the command and mode (quick or default)
that produced the metrics, the demo's tables, and every figure of its folder, copied to
``OUT/<scene>/`` - and ``OUT/benchmarks.md``, the speed-against-error table and figure of every
scene. Nothing in them is typed by hand; they are rewritten from the metrics whenever the
demos run again. When a scene appears in several folders, a default-mode run wins over a
quick one (and a later folder over an earlier one of the same mode).
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .report_tables import caption, error_kind, fmt, mode, n_dofs, provenance, scene_of, scene_tables



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
    for row in metrics.get("roms") or []:
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
    """The FOM's time over the ROMs' horizon (t_end); None where the metrics hold only a total
    over many runs (the parametric studies: every training and test parameter)."""
    seconds = metrics.get("fom_seconds_to_t_end", metrics.get("fom_seconds"))
    if "affine_terms" in metrics or not isinstance(seconds, (int, float)):
        return None
    return seconds


TABLE_HEADER = ["| scene | method | best r | test error | ROM s (loop) | ROM s, numpy loop | "
                "FOM / ROM | inference s | FOM s |",
                "|---|---|---|---|---|---|---|---|---|"]


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


# -- the documentation's generated pages ---------------------------------------------------------

class Run(NamedTuple):
    """One demo's output folder: its scene, metrics and the folder."""

    scene: str
    metrics: dict
    folder: Path


def find_runs(folders) -> dict[str, Run]:
    """scene -> the run the pages show: every ``metrics.json`` in ``folders`` (or one level
    below them); a default-mode run wins over a quick one, a later folder over an earlier one."""
    runs: dict[str, Run] = {}
    for folder in map(Path, folders):
        files = [folder / "metrics.json"] if (folder / "metrics.json").exists() \
            else sorted(folder.glob("*/metrics.json"))
        for f in files:
            metrics = json.loads(f.read_text())
            scene = scene_of(metrics, f.parent.name)
            old = runs.get(scene)
            if old is None or not (metrics.get("quick") and not old.metrics.get("quick")):
                runs[scene] = Run(scene, metrics, f.parent)
    return runs


def _copy_figures(run: Run, out: Path) -> list[Path]:
    """The run's PNG figures copied to ``out/<scene>/`` (emptied first); their new paths."""
    target = out / run.scene
    if target.exists():
        shutil.rmtree(target)
    target.mkdir(parents=True)
    copied = []
    for png in sorted(run.folder.glob("*.png")):
        if png.name.startswith("report_"):
            continue
        shutil.copy2(png, target / png.name)
        copied.append(target / png.name)
    return copied


def _boxed(lines: list[str]) -> list[str]:
    """Every markdown table of ``lines`` inside a ``{container} numbers`` block (the
    documentation's CSS keeps its numbers on one line)."""
    out, inside = [], False
    for line in lines + [""]:
        table = line.startswith("|")
        if table and not inside:
            out += ["```{container} numbers", ""]
        elif inside and not table:
            out += ["```"]
        out.append(line)
        inside = table
    return out[:-1]


def scene_page(run: Run, out: Path) -> str:
    """The markdown of ``out/<scene>.md``: provenance, tables, figures (their paths relative to the
    documentation's source folder, ``/<out>/<scene>/...`` - OUT must be a folder directly in it,
    e.g. docs/generated - so the page can be included from any page)."""
    figures = _copy_figures(run, out)
    lines = [provenance(run), ""]
    lines += _boxed(scene_tables(run.scene, run.metrics))
    if figures:
        lines += ["", "### Figures", ""]
        for png in figures:
            text = caption(run.scene, png.name)
            lines += [f"```{{figure}} /{out.name}/{run.scene}/{png.name}", f":alt: {text}", ":width: 100%", "",
                      f"{text} (`{png.name}`)", "```", ""]
    return "\n".join(lines).rstrip() + "\n"


def benchmarks_page(runs: dict[str, Run], out: Path) -> str:
    """The markdown of ``out/benchmarks.md``: per scene the run's mode and size, the best test
    error of every method with what it cost, and the speed-against-error figure."""
    lines = ["| scene | mode | state size n | FOM s (ROMs' horizon) | error measured |",
             "|---|---|---|---|---|"]
    for scene, run in sorted(runs.items()):
        m = run.metrics
        fom = _fom_seconds(m)
        lines.append(f"| {scene} | {mode(m)} | {fmt(n_dofs(m))} | "
                     f"{fmt(fom, 'seconds')} | {error_kind(m)} |")
    lines += ["", "Best test error of every method (the smallest over r) and what it cost:", ""]
    lines += TABLE_HEADER
    figures = []
    for scene, run in sorted(runs.items()):
        if not _rows(run.metrics):
            continue
        png = out / scene / "speed_vs_error_report.png"
        png.parent.mkdir(parents=True, exist_ok=True)
        lines += [line.replace(f"| {run.metrics['scene']} |", f"| {scene} ({mode(run.metrics)}) |", 1)
                  for line in scene_report(run.metrics, png)]
        figures.append((scene, png))
    lines = _boxed(lines)
    for scene, png in figures:
        lines += ["", f"```{{figure}} /{out.name}/{scene}/{png.name}", f":alt: {scene}: speed against error",
                  ":width: 100%", "", f"{scene} ({mode(runs[scene].metrics)}): ROM and inference "
                  "wall time against test error, every method and r; the dashed line is the "
                  "FOM's time over the same horizon.", "```"]
    return "\n".join(lines) + "\n"


def write_docs(folders, out) -> list[Path]:
    """Write ``out/<scene>.md`` for every scene found in ``folders`` and ``out/benchmarks.md``
    (see the module docstring); returns the pages written. Pages and figure folders of scenes
    not found are left as they are (a partial run updates only what it ran)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    runs = find_runs(folders)
    if not runs:
        raise SystemExit(f"no metrics.json in {list(map(str, folders))} (or one level below): "
                         "run the demos first")
    written = []
    for scene, run in sorted(runs.items()):
        path = out / f"{scene}.md"
        path.write_text(scene_page(run, out))
        written.append(path)
    path = out / "benchmarks.md"
    path.write_text(benchmarks_page(runs, out))
    written.append(path)
    return written


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", nargs="*", default=["results"],
                        help="demo output folders, or folders of them (default: results)")
    parser.add_argument("--docs", default=None, metavar="OUT",
                        help="write the documentation's generated pages to OUT (e.g. docs/generated)")
    args = parser.parse_args(argv)
    if args.docs:
        for path in write_docs(args.results, args.docs):
            print(f"wrote {path}")
        return None
    runs = find_runs(args.results)
    if not runs:
        raise SystemExit(f"no metrics.json in {args.results} (or one level below): run the demos first")
    table = list(TABLE_HEADER)
    root = Path(args.results[0])
    for _scene, run in sorted(runs.items()):
        if not _rows(run.metrics):
            continue
        table += scene_report(run.metrics, run.folder.parent / f"report_{run.folder.name}.png")
    print("\n".join(table))
    (root / "report.md").write_text("\n".join(table) + "\n")
    return table


if __name__ == "__main__":
    main()
