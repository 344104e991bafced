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
import datetime
import json
import re
import shutil
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
    """The FOM's time over the ROMs' horizon (t_end)."""
    return metrics.get("fom_seconds_to_t_end", metrics.get("fom_seconds"))


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

#: scene -> the demo that writes it (``python <demo> [--quick] --out DIR``)
DEMOS = {"beam": "demos/beam.py", "beam_unseen_ic": "demos/beam_unseen_ic.py",
         "sine_gordon": "demos/sine_gordon.py", "existing_code_cantilever": "demos/existing_code.py",
         "own_loop_cantilever": "demos/own_loop.py", "learned_mass": "demos/learned_mass.py",
         "svk_cantilever": "demos/svk_cantilever.py", "fishtail": "demos/fishtail.py",
         "parametric_membrane": "demos/parametric_membrane.py",
         "parametric_cantilever": "demos/parametric_cantilever.py"}

#: method -> its name in the tables
NAMES = {"lopinf": "L-OpInf", "lopinf_del": "L-OpInf, DEL data", "lopinf_fd": "L-OpInf, differences",
         "lopinf_mass_I": "L-OpInf, Mh = I", "lopinf_nsd": "L-OpInf, Kh <= 0",
         "lopinf_ecsw": "L-OpInf + ECSW", "opinf": "standard OpInf", "opinf_peer": "opinf (peer)",
         "intrusive": "intrusive", "projection": "projection"}


def scene_of(metrics: dict, folder_name: str) -> str:
    """The scene a metrics dict belongs to (the learned-mass study names it per row)."""
    if metrics.get("scene"):
        return metrics["scene"]
    return "learned_mass" if "rows" in metrics else folder_name


def mode(metrics: dict) -> str:
    return "quick" if metrics.get("quick") else "default"


def n_dofs(metrics: dict):
    """The FOM's state size (several: the largest)."""
    if "n_dofs" in metrics:
        return metrics["n_dofs"]
    sizes = [v.get("n_dofs") for key in ("materials", "loops") for v in metrics.get(key, {}).values()]
    sizes = [x for x in sizes if x]
    return max(sizes) if sizes else None


def error_kind(metrics: dict) -> str:
    if "error" in metrics:
        return metrics["error"]
    kinds = sorted({row.get("error") for row in metrics.get("rows", []) if row.get("error")})
    return " / ".join(kinds) or "-"


def fmt(value, kind: str = "") -> str:
    """A table cell: errors as 1.23e-04, seconds and other numbers to 3 digits."""
    if value is None:
        return "-"
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)):
        return f"{value:,}" if abs(value) >= 10_000 else str(value)
    if isinstance(value, str):
        return value
    if isinstance(value, (list, tuple)):
        return ", ".join(fmt(v, kind) for v in value)
    v = float(value)
    if not np.isfinite(v):
        return str(v)
    if kind == "error":
        return f"{v:.2e}"
    return f"{v:.3g}"


def md_table(header, rows) -> list[str]:
    """Markdown table lines."""
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + \
        ["| " + " | ".join(row) + " |" for row in rows]


def pivot(rows, index, column, value, *, kind="error", index_header=("r",), columns=None) -> list[str]:
    """One row per ``index(row)`` (a tuple), one column per ``column(row)``, cells
    ``row[value]`` (``fmt(kind)``); ``columns`` fixes their order."""
    cells, keys = {}, []
    for row in rows:
        k, c = index(row), column(row)
        if k not in keys:
            keys.append(k)
        cells[(k, c)] = row.get(value)
    cols = columns or list(dict.fromkeys(column(row) for row in rows))
    body = [[fmt(x) for x in k] + [fmt(cells.get((k, c)), kind) for c in cols] for k in keys]
    return md_table(list(index_header) + list(cols), body)


def listing(rows, columns) -> list[str]:
    """A table of ``rows`` with ``columns`` = (key, header, kind) - keys absent from every row
    are left out."""
    cols = [c for c in columns if any(c[0] in row for row in rows)]
    return md_table([h for _, h, _ in cols],
                    [[fmt(NAMES.get(row.get(k), row.get(k)) if k == "method" else row.get(k), kind)
                      for k, _, kind in cols] for row in rows])


def provenance(run) -> str:
    """Which command, in which mode, wrote the metrics these tables show."""
    m = run.metrics
    demo = DEMOS.get(run.scene, "the study")
    args = " --quick" if m.get("quick") else ""
    if run.scene == "fishtail":
        args += f" --size {m.get('size')} --train {m.get('train_input')}"
    when = datetime.date.fromtimestamp((run.folder / "metrics.json").stat().st_mtime)
    return (f"*Generated by `python -m dolfinx_lopinf.studies.report --docs` from the metrics.json "
            f"of `python {demo}{args}` (**{mode(m)}** mode), written {when.isoformat()}. Times are "
            f"wall-clock seconds of that run on the machine it ran on.*")


# the tables of each scene ---------------------------------------------------------------------

def _by(rows, **where):
    return [r for r in rows if all(r.get(k) == v for k, v in where.items())]


def _method_basis(row) -> str:
    name = NAMES.get(row["method"], row["method"])
    return f"{name} ({row['basis']})" if row.get("basis") else name


def _tables_beam(m) -> list[str]:
    rows = m["roms"] + (m.get("peer_roms") or [])
    out = [f"State size n = {fmt(m['n_dofs'])}, midpoint rule dt = {fmt(m['dt'])} s, training window "
           f"[0, {fmt(m['t_train'])}] s, test window [{fmt(m['t_train'])}, {fmt(m['t_end'])}] s. "
           f"FOM: {fmt(m.get('fom_steps'))} steps in {fmt(m.get('fom_seconds'), 'seconds')} s, relative "
           f"energy drift {fmt(m.get('fom_energy_drift'), 'error')}.", ""]
    for basis in dict.fromkeys(r["basis"] for r in m["roms"]):
        sel = _by(rows, basis=basis)
        floor = [dict(r, method="projection", test_error=r["projection_error_test"])
                 for r in _by(sel, method="lopinf")]
        out += ["", f"### Test error against r, {basis} basis", ""]
        out += pivot(sel + floor, lambda r: (r["r"],), lambda r: NAMES.get(r["method"], r["method"]),
                     "test_error")
    r_max = max(r["r"] for r in m["roms"])
    out += ["", f"### Every ROM at r = {r_max}", ""]
    out += listing([r for r in rows if r["r"] == r_max], [
        ("basis", "basis", ""), ("method", "method", ""), ("train_error", "train error", "error"),
        ("test_error", "test error", "error"), ("projection_error_test", "projection (test)", "error"),
        ("max_energy_error", "max FOM energy error", "error"), ("infer_seconds", "inference s", "seconds"),
        ("rom_seconds", "ROM s", "seconds"), ("rom_backend", "loop", ""), ("stable", "stable", "")])
    return out


#: the unseen-IC demo's fits (demos/beam_unseen_ic.py: scheme and reduced mass of each)
UNSEEN_IC_NAMES = {"lopinf": "L-OpInf (auto, learned Mh)", "lopinf_fd": "L-OpInf (differences, learned Mh)",
                   "lopinf_mass_I": "L-OpInf (auto, Mh = I)", "intrusive": "intrusive"}


def _tables_beam_unseen_ic(m) -> list[str]:
    rows = m["roms"]
    out = [f"Training: initial conditions a = {fmt(m['train_a'])} on [0, {fmt(m['t_train'])}] s; test: "
           f"the unseen a = {fmt(m['test_a'])}. Errors are relative state errors of both test "
           "trajectories together: **train** = on the training time window, **test** = on the long "
           f"horizon [0, {fmt(m['t_end'])}] s.", ""]
    if m.get("paper_2r20"):
        out += ["Published at 2r = 20 (train window): " + ", ".join(
            f"{NAMES.get(k, k)} {fmt(v)}" for k, v in m["paper_2r20"].items()) + ".", ""]
    for basis in dict.fromkeys(r["basis"] for r in rows):
        sel = _by(rows, basis=basis)
        cells = []
        for key, floor, name in (("test_error_train_window", "projection_error_test_train_window",
                                  "train"), ("test_error", "projection_error_test", "test")):
            cells += [dict(r, value=r[key], column=f"{UNSEEN_IC_NAMES.get(r['method'], r['method'])}, {name}")
                      for r in sel]
            cells += [dict(r, value=r[floor], column=f"projection, {name}") for r in _by(sel, method="lopinf")]
        out += ["", f"### Unseen initial conditions, {basis} basis", ""]
        out += pivot(cells, lambda r: (r["r"],), lambda r: r["column"], "value")
    out += ["", "### The scheme `lo.fit(scheme=\"auto\")` chose", ""]
    out += pivot([dict(r, scheme=f"`{_short(r['scheme'])}`") for r in _by(rows, method="lopinf")],
                 lambda r: (r["r"],), lambda r: r["basis"], "scheme", kind="")
    return out


def _tables_sine_gordon(m) -> list[str]:
    out = [f"State size n = {fmt(m['n_dofs'])}, midpoint rule with Newton, dt = {fmt(m['dt'])}; training "
           f"[0, {fmt(m['t_train'])}], test [{fmt(m['t_train'])}, {fmt(m['t_end'])}], energy to "
           f"t = {fmt(m.get('t_long'))}. FOM against the exact kink-antikink solution at "
           f"t = {fmt(m['t_end'])}: max error {fmt(m.get('fom_error_vs_exact'), 'error')}; its energy "
           f"drift {fmt(m.get('fom_energy_drift'), 'error')}.", ""]
    out += listing(m["roms"], [
        ("method", "method", ""), ("r", "r", ""), ("train_error", "train error", "error"),
        ("test_error", "test error", "error"), ("projection_error_test", "projection (test)", "error"),
        ("max_energy_error", "max FOM energy error", "error"), ("rom_seconds", "ROM s", "seconds"),
        ("rom_seconds_numpy", "ROM s, numpy loop", "seconds"), ("stable", "stable", "")])
    return out


def _short(spec) -> str:
    """A scheme's spec for a table: average-acceleration Newmark's parameters left out, the
    others to four digits."""
    if not spec:
        return "-"
    text = re.sub(r"\(beta=0\.25, gamma=0\.5\)", "", str(spec))
    return re.sub(r"-?\d+\.\d+(e-?\d+)?", lambda x: f"{float(x.group()):.4g}", text)


def _tables_existing_code(m) -> list[str]:
    out = [f"State size n = {fmt(m['n_dofs'])}, the user's Newmark loop with dt = {fmt(m['dt'])} s; "
           f"trained on one load history over [0, {fmt(m['t_train'])}] s, tested on an unseen one over "
           f"[0, {fmt(m['t_end'])}] s. Error: the tip displacement (output), relative. FOM "
           f"{fmt(m['fom_seconds'], 'seconds')} s for the test run.", ""]
    rows = [dict(r, scheme=_short(r.get("scheme"))) for r in m["roms"] + (m.get("peer_roms") or [])]
    out += listing(rows, [
        ("method", "method", ""), ("r", "r", ""), ("scheme", "data relation", ""),
        ("mass", "Mh", ""), ("test_error", "unseen-load error", "error"),
        ("train_error", "training-load error", "error"),
        ("projection_error_test", "projection (test)", "error"), ("infer_seconds", "fit s", "seconds"),
        ("rom_seconds", "ROM s", "seconds"), ("stable", "stable", "")])
    return out


def _tables_own_loop(m) -> list[str]:
    out = [f"The tutorial-style cantilever on {fmt(m.get('ranks', 1))} rank(s). Error: the tip "
           "deflection under the unseen body force, relative. Rows: the basis and the reduced mass "
           "asked for, and the data relation asked for (`auto`: identified; `named`: the loop's own "
           "scheme; `continuous`: eighth-order differences); the last column says what `lo.fit` "
           "chose at the largest r.", ""]
    for integrator, loop in m.get("loops", {}).items():
        rows = loop["roms"]
        r_max = max(r["r"] for r in rows)
        out += ["", f"### The {integrator} loop", "",
                f"State size n = {fmt(loop['n_dofs'])}, dt = {fmt(loop['dt'])} s, trained on "
                f"[0, {fmt(loop['t_train'])}] s, tested on [0, {fmt(loop['t_end'])}] s; FOM "
                f"{fmt(loop['fom_seconds'], 'seconds')} s for the test run.", ""]
        chose = {(r["basis"], r["mass"], r["requested"]): f"`{_short(r['scheme'])}`, Mh {r['mass_chosen']}"
                 for r in rows if r["r"] == r_max}
        cells = [dict(r, column=f"r = {r['r']}") for r in rows]
        table = pivot(cells, lambda r: (r["basis"], r["mass"], r["requested"]), lambda r: r["column"],
                      "test_error", index_header=("basis", "Mh", "relation asked"))
        header, rule, body = table[0], table[1], table[2:]
        keys = list(dict.fromkeys((r["basis"], r["mass"], r["requested"]) for r in rows))
        out += [header + f" chose at r = {r_max} |", rule + "---|"]
        out += [line + f" {chose.get(k, '-')} |" for line, k in zip(body, keys)]
        floors = {r["r"]: r["projection_error_test"] for r in rows if r["basis"] == "euclidean"}
        out += ["", "Projection floor of the Euclidean POD on the test data: " + ", ".join(
            f"r = {k}: {fmt(v, 'error')}" for k, v in sorted(floors.items())) + "."]
    return out


def _tables_learned_mass(m) -> list[str]:
    out = []
    names = {"lopinf_mass_identity": "Mh = I", "lopinf_mass_learned": "learned Mh", "intrusive": "intrusive"}
    for scene, what in (("beam", "state error on the test window (block POD, the midpoint DEL relation)"),
                        ("cantilever", "tip error under the unseen load (Euclidean POD, the Newmark "
                                       "relation)")):
        rows = [r for r in m["rows"] if r["scene"] == scene]
        if not rows:
            continue
        floor = [dict(r, method="projection", test_error=r["projection_error_test"])
                 for r in rows if r["method"] == "lopinf_mass_identity"]
        out += ["", f"### {scene}: {what}", ""]
        out += pivot(rows + floor, lambda r: (r["r"],), lambda r: names.get(r["method"], r["method"]),
                     "test_error")
        learned = [r for r in rows if r["method"] == "lopinf_mass_learned"]
        out += ["", "The learned-mass fits:", ""]
        out += listing(learned, [("r", "r", ""), ("solver", "solver", ""),
                                 ("certified_gap", "duality gap", "error"),
                                 ("infer_seconds", "fit s", "seconds")])
    return out


def _tables_svk(m) -> list[str]:
    out = [f"Trained at amplitudes {fmt(m['train_amplitudes'])}, tested at {fmt(m['test_amplitudes'])}; "
           f"midpoint rule dt = {fmt(m['dt'])} s to t = {fmt(m['t_end'])} s. Error: the tip "
           "displacement, relative, at each unseen amplitude.", ""]
    for material, mm in m.get("materials", {}).items():
        rows = mm["rows"]
        out += ["", f"### {material} (n = {fmt(mm['n_dofs'])}, {fmt(mm['n_cells'])} cells)", "",
                f"The linear (small-strain) model at the largest amplitude is off by "
                f"{fmt(mm.get('linear_vs_nonlinear_tip_difference'), 'error')} (relative tip "
                "difference to the nonlinear one).", ""]
        out += pivot(rows, lambda r: (r["method"], r["r"]), lambda r: f"a = {fmt(r['amplitude'])}",
                     "tip_error", index_header=("method", "r"))
        longs = mm.get("long_runs") or []
        if longs:
            out += ["", "Undamped, unforced runs, five times the training length:", ""]
            out += listing(longs, [(k, h, kind) for k, h, kind in (
                ("method", "method", ""), ("r", "r", ""), ("scheme", "scheme", ""),
                ("energy_error_rom", "ROM energy error", "error"),
                ("energy_error_fom", "FOM energy error", "error"), ("stable", "stable", ""))])
    return out


def _tables_fishtail(m) -> list[str]:
    rows = m["roms"]
    inputs = list(rows[0]["output_errors"]) if rows else []
    out = [f"Mesh `{m.get('size')}`: n = {fmt(m['n_dofs'])} on {fmt(m.get('n_ranks'))} rank(s), "
           f"Newmark dt = {fmt(m['dt'])} s to t = {fmt(m['t_end'])} s; trained on the "
           f"{m.get('train_input')} input over [0, {fmt(m['t_train'])}] s, data relation: "
           f"{m.get('data')}; hull density {fmt(m.get('hull_density'))} kg/m^3. FOM "
           f"{fmt(m.get('fom_seconds'), 'seconds')} s per input (the slowest), training snapshots "
           f"on disk {fmt((m.get('snapshot_disk_bytes') or 0) / 1e6)} MB.", "",
           "Relative tip-output error over the whole run, per input:", ""]
    cells = [dict(r, value=r["output_errors"][i], column=i + (" (training)" if i == m.get("train_input")
                                                             else ""))
             for r in rows for i in inputs]
    out += pivot(cells, lambda r: (NAMES.get(r["method"], r["method"]), r["r"]), lambda r: r["column"],
                 "value", index_header=("method", "r"))
    out += ["", "Time and fit:", ""]
    out += listing(rows, [("method", "method", ""), ("r", "r", ""), ("infer_seconds", "fit s", "seconds"),
                          ("rom_seconds", "ROM s (slowest input)", "seconds"),
                          ("min_eig_K", "min eig Kh", ""), ("min_eig_C", "min eig Ch", "")])
    return out


def _mu(row) -> str:
    mu = row.get("mu")
    where = "inside" if row.get("inside") else "outside"
    return f"{fmt(mu)} ({row.get('split')}, {where})"


def _tables_parametric(m) -> list[str]:
    out = [f"n = {fmt(m.get('n_dofs'))}, Newmark dt = {fmt(m.get('dt'))} s to t = {fmt(m.get('t_end'))} s. "
           "Rows: each test parameter (inside or outside the training range), columns: the "
           "models; the relative state error under an input no training run saw (the worst of "
           "the parameter's test runs).", ""]
    for study, text in (m.get("affine_terms") or {}).items():
        out += [f"Affine terms read from the UFL ({study}):", "", "```text", str(text).strip(), "```", ""]
    studies = list(dict.fromkeys(r.get("study", "") for r in m["roms"]))
    for study in studies:
        for r_value in sorted({r["r"] for r in m["roms"] if r.get("study", "") == study}):
            rows = [r for r in m["roms"] if r.get("study", "") == study and r["r"] == r_value
                    and r.get("split") == "test"]
            out += ["", f"### {study + ', ' if study else ''}r = {r_value}", ""]
            out += pivot(rows, lambda r: (_mu(r),), lambda r: NAMES.get(r["method"], r["method"]),
                         "test_error", index_header=("parameter",))
            unstable = [r for r in rows if not r.get("stable", True)]
            if unstable:
                out += ["", "Unstable: " + "; ".join(f"{NAMES.get(r['method'], r['method'])} at {_mu(r)}"
                                                   for r in unstable) + "."]
    fits = [f for f in m.get("fits", []) if f.get("method") == "lopinf"]
    if fits:
        out += ["", "### The L-OpInf fits", ""]
        out += listing([dict(f, gap=(f.get("report") or {}).get("certificate", {}).get("duality_gap"),
                             damping=(f.get("report") or {}).get("damping")) for f in fits],
                       [("study", "study", ""), ("r", "r", ""), ("fit_seconds", "fit s", "seconds"),
                        ("gap", "duality gap", "error"), ("damping", "damping", "")])
    return out


def _tables_generic(m) -> list[str]:
    rows = m.get("roms") or []
    if not rows:
        return ["(no ROM rows in this metrics.json)"]
    return listing(rows, [("basis", "basis", ""), ("method", "method", ""), ("r", "r", ""),
                          ("train_error", "train error", "error"), ("test_error", "test error", "error"),
                          ("projection_error_test", "projection (test)", "error"),
                          ("infer_seconds", "inference s", "seconds"), ("rom_seconds", "ROM s", "seconds"),
                          ("stable", "stable", "")])


TABLES = {"beam": _tables_beam, "beam_unseen_ic": _tables_beam_unseen_ic,
          "sine_gordon": _tables_sine_gordon, "existing_code_cantilever": _tables_existing_code,
          "own_loop_cantilever": _tables_own_loop, "learned_mass": _tables_learned_mass,
          "svk_cantilever": _tables_svk, "fishtail": _tables_fishtail,
          "parametric_membrane": _tables_parametric, "parametric_cantilever": _tables_parametric}


def scene_tables(scene: str, metrics: dict) -> list[str]:
    """The markdown tables of one scene's metrics."""
    lines = TABLES.get(scene, _tables_generic)(metrics)
    definition = metrics.get("error_definition")
    if definition:
        lines += ["", f"Error measured: {definition}."]
    return lines


#: figure file name (a regular expression) -> caption, per scene ("*": any scene)
CAPTIONS = {
    "beam": {"beam_shapes.png": "Deflection of the FOM and of L-OpInf in both bases at three times",
             r"error_vs_r_(.*)\.png": "Training- and test-window state error against r, {0} basis",
             "energy_error.png": "Relative FOM energy error of the reconstructed ROM states",
             "midpoint_deflection.png": "Midpoint deflection of the FOM and the ROMs, long run",
             "midpoint_deflection_error.png": "Midpoint deflection error of the ROMs, long run",
             "peer_error_vs_r.png": "Test error against r: L-OpInf, standard OpInf, intrusive and "
                                    "opinf's first-order model (peer)",
             "peer_energy_error.png": "FOM energy error of L-OpInf and of the opinf peer"},
    "beam_unseen_ic": {"error_vs_r.png": "Error on the unseen initial conditions against r, block "
                                         "POD: train window (solid) and test horizon (dashed)",
                       "error_vs_r_mass_orthonormal.png": "The same in the mass-orthonormal basis"},
    "sine_gordon": {"error_vs_r.png": "Training and test state error against r",
                    "wave_shapes.png": "The wave of the FOM and of L-OpInf at three times",
                    "energy_error.png": "Relative FOM energy error of the reconstructed ROM states",
                    "speed_vs_error.png": "ROM wall time against test error"},
    "existing_code_cantilever": {"tip_displacement.png": "Tip displacement under the unseen load: "
                                                         "FOM and ROMs"},
    "own_loop_cantilever": {r"tip_error_(.*)\.png": "Tip error under the unseen body force, {0} loop",
                            r"tip_(.*)\.png": "Tip deflection under the unseen body force, {0} loop: "
                                              "the loop and the fitted models"},
    "svk_cantilever": {r"tip_(.*)\.png": "Tip displacement at the largest unseen amplitude, {0}: "
                                         "the nonlinear and the linear FOM, the ROMs",
                       r"error_vs_r_(.*)\.png": "Tip error against r at the largest unseen amplitude, {0}",
                       r"energy_(.*)\.png": "Energy of undamped, unforced runs, five times the "
                                            "training length, {0}",
                       r"deformed_(.*)\.png": "Deformed cantilever at true scale, {0}: FOM and ROMs"},
    "fishtail": {r"poi_(.*)\.png": "Tip displacement, its error and the energy of the reconstructed "
                                   "state, {0} input",
                 r"deformed_(.*)\.png": "The deformed tail, FOM and L-OpInf side by side, {0} input"},
    "parametric_membrane": {r"error_vs_mu_(.*)\.png": "Error at unseen parameters, {0} study "
                                                      "(shaded: the training range)",
                            r"fields_(.*)\.png": "Fields at an unseen parameter, {0} study: FOM and ROMs"},
    "parametric_cantilever": {r"error_vs_(E|zeta)\.png": "Error at unseen designs against {0}",
                              "deformed.png": "The cantilever at an unseen design: FOM and ROMs"},
}


def caption(scene: str, name: str) -> str:
    """The caption of figure ``name`` of ``scene`` (its file name if none is known)."""
    for pattern, text in {**CAPTIONS.get(scene, {}), **CAPTIONS.get("*", {})}.items():
        match = re.fullmatch(pattern, name)
        if match:
            return text.format(*(g.replace("_", " ") for g in match.groups()))
    return name.removesuffix(".png").replace("_", " ")


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
