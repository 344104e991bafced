"""How the fishtail FOM's cost grows with the mesh: set-up phases, time per step, memory, ROM error.

    python -m dolfinx_lopinf.studies.scaling [--sizes 100k,200k,400k] [--ranks 1,2]
        [--solvers auto] [--steps 200] [--repeats 1] [--out results/scaling] [--max-gb 18]

For every (size, ranks, solver) the driver starts one worker,
``mpiexec -n <ranks> python -m dolfinx_lopinf.studies.scaling --case ...``, one at a time - a
fresh process, so its peak memory is the case's own - and stops a case whose resident memory
(all its processes) passes ``--max-gb``. Each worker writes ``cases/<size>_<ranks>_<solver>.json``
(``..._<k>.json`` for the k-th repeat); the driver gathers them into ``scaling.json`` and
``scaling.png``. With ``--repeats N`` every case runs N times (all sizes, then all sizes again)
and the table and the exponent take each case's fastest repeat: a small case's loop lasts a few
seconds, and a slow spell of a shared machine moved its time by 20 % between sweeps.

A worker, on the scene of :mod:`dolfinx_lopinf.scenes.fishtail` (P2, the paper's hull density):

* set-up phase by phase, each timed between barriers (the slowest rank): ``gmsh`` (meshing on
  rank 0), ``distribute`` (the dolfinx mesh from the gmsh model, partitioned), ``forms``
  (spaces, materials, Lagrangian forms, bc), ``output`` (the point output matrix), ``assemble``
  (M, K and A = M + dt/2 C + dt^2/4 K), ``solver`` (the factorisation or the preconditioner's
  set-up), ``integrator_other`` (input vectors, work vectors);
* ``steps`` Newmark steps of the sine input from its onset (u(t + 0.1 s): the scene's sine is
  zero before 0.1 s, which would make an iterative solver's first steps free), with the POI
  output and the states streamed into the mass-weighted POD (as the demo does); the time per
  step is the loop's wall time over the steps (slowest rank), beside the rank's CPU seconds
  (the machine may be shared: wall time then includes waiting for a core);
* the peak resident memory of every rank (``ru_maxrss``) after each phase;
* the ROM error: L-OpInf r = 2 (Newmark data relation) fitted to the run's POD coordinates,
  output error relative to the FOM over the run (a training error: the run is short).

The figure: time per step against dofs on log-log axes per (ranks, solver), with the exponent p
of the least-squares fit s/step ~ dofs^p; set-up time and peak memory per rank beside it.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

#: element sizes of the fishtail geometry and the P2 dofs they give (measured: the mesh is
#: unstructured, so other lc give other counts; the worker records the actual count)
SIZES = {"25k": 0.012, "50k": 0.007, "100k": 0.0047, "200k": 0.0035, "400k": 0.0026,
         "800k": 0.00195}
T_ONSET = 0.1  # the scene's sine input starts here


def _lc(size: str) -> float:
    if size in SIZES:
        return SIZES[size]
    try:
        lc = float(size)
    except ValueError:
        lc = float("nan")
    if not (np.isfinite(lc) and 0.0005 <= lc <= 0.05):
        from ..errors import InputError

        raise InputError(f"size {size!r}: one of {sorted(SIZES)} or an element size in metres "
                         "between 0.0005 and 0.05")
    return lc


# ----------------------------------------------------------------------------------------------
# worker (runs under mpiexec)
# ----------------------------------------------------------------------------------------------
def _peak_gb(comm) -> list[float]:
    """Peak resident memory of every rank in GB (ru_maxrss is in KiB on Linux)."""
    return comm.allgather(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9)


def _case_name(size: str, ranks: int, solver: str, repeat: int) -> str:
    """The case's file stem; repeats after the first carry their index."""
    return f"{size}_{ranks}_{solver}" + (f"_{repeat}" if repeat else "")


def run_case(size: str, solver: str, steps: int, out: Path, *, r: int = 2,
             petsc_options: dict | None = None, repeat: int = 0) -> dict | None:
    """One case on MPI.COMM_WORLD (collective); rank 0 writes and returns the record."""
    from ..fem._dolfinx import MPI
    from ..fem.fom import run
    from ..fem.loop import OutputProbe
    from ..fem.streaming import StreamingPOD
    from ..scenes import fishtail as scene

    comm = MPI.COMM_WORLD
    phases, peaks, cpu = {}, {}, {}

    t_all, c_all = time.perf_counter(), time.process_time()
    timings = {}
    tail = scene.build(_lc(size), comm, timings=timings)
    comm.Barrier()
    for key in ("gmsh", "distribute", "forms", "output"):
        phases[key] = comm.allreduce(timings[f"{key}_seconds"], op=MPI.MAX)
    peaks["build"] = _peak_gb(comm)
    t0, c0 = time.perf_counter(), time.process_time()
    nm = scene.integrator(tail, scene.DT, solver=solver, petsc_options=petsc_options)
    comm.Barrier()
    integrator_s = time.perf_counter() - t0
    phases["assemble"] = comm.allreduce(nm.timings["assemble_seconds"], op=MPI.MAX)
    phases["solver"] = comm.allreduce(nm.timings["solver_setup_seconds"], op=MPI.MAX)
    phases["integrator_other"] = comm.allreduce(
        integrator_s - nm.timings["assemble_seconds"] - nm.timings["solver_setup_seconds"], op=MPI.MAX)
    cpu["integrator"] = comm.allreduce(time.process_time() - c0, op=MPI.MAX)
    peaks["integrator"] = _peak_gb(comm)
    setup_s = comm.allreduce(time.perf_counter() - t_all, op=MPI.MAX)
    cpu["setup"] = comm.allreduce(time.process_time() - c_all, op=MPI.MAX)
    n_dofs = tail.system.V.dofmap.index_map.size_global * tail.system.V.dofmap.index_map_bs

    def u(t):
        return float(scene.u_sine(t + T_ONSET))

    if comm.rank == 0:
        (out / "scratch").mkdir(parents=True, exist_ok=True)
    comm.Barrier()
    spod = StreamingPOD(tail.system.V, steps + 1, weight=nm.M, directory=out / "scratch")
    y = OutputProbe(tail.output_matrix)
    nm.initialize(tail.chamber_pressures(u(0.0)))
    c0 = time.process_time()
    loop = run(nm, steps, sinks=[y, spod.sink()], inputs=lambda t: tail.chamber_pressures(u(t)))
    cpu["steps"] = comm.allreduce(time.process_time() - c0, op=MPI.MAX)
    peaks["steps"] = _peak_gb(comm)
    Y = np.array([v[0] for v in y.values])
    stats = nm.solver.stats()
    nm_iterations = nm.solver.iteration_history
    t0 = time.perf_counter()
    _, Qh, _ = spod.compute(r)
    spod.close()
    rom_error = _rom_error(Qh, Y, u, scene.DT) if comm.rank == 0 else None
    rom_s = comm.allreduce(time.perf_counter() - t0, op=MPI.MAX)
    nm.close()
    peaks["end"] = _peak_gb(comm)
    if comm.rank != 0:
        return None
    record = {
        "size": size, "lc": _lc(size), "n_dofs": int(n_dofs), "ranks": comm.size,
        "solver": solver, "resolved_solver": stats["solver"], "steps": steps,
        "setup_seconds": setup_s, "phases_seconds": phases, "cpu_seconds_max_rank": cpu,
        "loop_seconds": loop["seconds"], "seconds_per_step": loop["seconds"] / steps,
        "cpu_seconds_per_step": cpu["steps"] / steps,
        "iterations_per_step": stats["iterations_per_solve"],
        "iterations_by_step": list(nm_iterations),
        "solver_stats": stats,
        "peak_gb_per_rank": max(peaks["end"]), "peak_gb_by_rank": peaks["end"],
        "peak_gb_after_phase": {k: max(v) for k, v in peaks.items()},
        "rom_r": r, "rom_output_error": rom_error, "rom_seconds": rom_s,
        "output": Y.tolist(), "load_average": os.getloadavg()[0],
        "petsc_options": petsc_options or {}, "repeat": repeat,
    }
    path = out / "cases" / f"{_case_name(size, comm.size, solver, repeat)}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record))
    return record


def _rom_error(Qh_all, Y, u, dt) -> float:
    """L-OpInf (Newmark data relation, certified SPD K and C) on the POD coordinates of the
    run; relative output error of its simulation from rest against the FOM's."""
    from .. import core
    from ..core.metrics import relative_error

    times = dt * np.arange(Qh_all.shape[1])
    Qbar, D1, D2, Ubar = core.ddt.newmark_data(Qh_all, times, np.array([[u(t) for t in times]]))
    ops = core.infer_mechanical(Qbar, D1, D2, Ubar)
    Eh = core.infer_output(Qh_all, Y[None])
    rom = core.LagrangianROM(K=ops.K, C=ops.C, B=ops.B, E=Eh, scheme="newmark")
    r = Qh_all.shape[0]
    tr = rom.simulate(np.zeros(r), np.zeros(r), dt, len(Y) - 1,
                      inputs=lambda t: np.array([u(t)]))
    return float(relative_error(Y, tr.Y[0]))


# ----------------------------------------------------------------------------------------------
# driver
# ----------------------------------------------------------------------------------------------
def _tree_rss_gb(pid: int) -> float:
    """Resident memory of a process and all its descendants (GB), from /proc."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry))
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        todo.extend(children.get(p, []))
        try:
            with open(f"/proc/{p}/status") as f:
                for line in f:
                    if line.startswith("VmRSS:"):
                        total += int(line.split()[1]) * 1024
        except OSError:
            pass
    return total / 1e9


def _run_worker(size, ranks, solver, steps, out, max_gb, python, mpiexec, petsc_options,
                repeat=0) -> dict:
    """Start one case under mpiexec and watch its memory; the record, or why there is none."""
    cmd = [mpiexec, "-n", str(ranks), python, "-m", "dolfinx_lopinf.studies.scaling", "--case",
           "--sizes", size, "--solvers", solver, "--steps", str(steps), "--out", str(out),
           "--repeat-index", str(repeat)]
    if petsc_options:
        cmd += ["--petsc-options", json.dumps(petsc_options)]
    name = _case_name(size, ranks, solver, repeat)
    log = out / "logs" / f"{name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    t0, peak_tree = time.perf_counter(), 0.0
    with open(log, "w") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, start_new_session=True)
        while proc.poll() is None:
            peak_tree = max(peak_tree, _tree_rss_gb(proc.pid))
            if peak_tree > max_gb:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait()
                return {"size": size, "ranks": ranks, "solver": solver,
                        "stopped": f"resident memory {peak_tree:.1f} GB > --max-gb {max_gb}"}
            time.sleep(1.0)
    path = out / "cases" / f"{name}.json"
    if proc.returncode != 0 or not path.exists():
        return {"size": size, "ranks": ranks, "solver": solver,
                "stopped": f"exit code {proc.returncode}; see {log}"}
    record = json.loads(path.read_text())
    record["wall_seconds_process"] = time.perf_counter() - t0
    record["peak_gb_all_ranks_sampled"] = peak_tree
    return record


def fit_exponent(dofs, seconds) -> float | None:
    """p of the least-squares fit log(seconds) = c + p log(dofs) (None below two sizes)."""
    dofs, seconds = np.asarray(dofs, float), np.asarray(seconds, float)
    if len(np.unique(dofs)) < 2:
        return None
    return float(np.polyfit(np.log(dofs), np.log(seconds), 1)[0])


def fastest_repeats(records: list[dict]) -> list[dict]:
    """One record per case (size, ranks, solver asked for, steps): the repeat with the fewest
    seconds per step - the least disturbed by whatever else the machine ran - with every
    repeat's s/step in ``repeats_seconds_per_step`` (sorted)."""
    groups: dict[tuple, list[dict]] = {}
    for r in records:
        groups.setdefault((r["size"], r["ranks"], r["solver"], r["steps"]), []).append(r)
    best = []
    for group in groups.values():
        rec = dict(min(group, key=lambda r: r["seconds_per_step"]))
        rec["repeats_seconds_per_step"] = sorted(r["seconds_per_step"] for r in group)
        best.append(rec)
    return best


def summarise(records: list[dict]) -> dict:
    """The table rows, the fitted exponents per (ranks, solver asked for), and each case's output
    deviation from the direct solver's at the same size and ranks.

    A case run several times (``--repeats``) enters the table and the exponent with its fastest
    repeat; ``exponent_median`` is the fit through the medians of the repeats."""
    done = [r for r in records if "stopped" not in r]

    def deviation(rec, ref):
        if ref is None or len(ref["output"]) != len(rec["output"]):
            return None
        a, b = np.array(rec["output"]), np.array(ref["output"])
        return float(np.abs(a - b).max() / np.abs(b).max())

    for rec in done:
        # other cases at this size: not the record itself, nor a repeat of it
        same = [d for d in done if d["size"] == rec["size"] and d["steps"] == rec["steps"]
                and (d["ranks"], d["solver"]) != (rec["ranks"], rec["solver"])]
        rec["output_deviation_vs_direct"] = deviation(rec, next(
            (d for d in same if d["ranks"] == rec["ranks"] and d["resolved_solver"] == "direct"), None))
        rec["output_deviation_vs_1_rank"] = deviation(rec, next(
            (d for d in same if d["ranks"] == 1 and d["resolved_solver"] == rec["resolved_solver"]), None))
    best = fastest_repeats(done)
    exponents = {}
    # grouped by the solver asked for: "auto" resolves to different solvers with the size
    for key in sorted({(r["ranks"], r["solver"]) for r in best}):
        group = sorted((r for r in best if (r["ranks"], r["solver"]) == key),
                       key=lambda r: r["n_dofs"])
        dofs = [r["n_dofs"] for r in group]
        exponents[f"{key[0]} ranks, {key[1]}"] = {
            "dofs": dofs,
            "seconds_per_step": [r["seconds_per_step"] for r in group],
            "repeats": [len(r["repeats_seconds_per_step"]) for r in group],
            "exponent": fit_exponent(dofs, [r["seconds_per_step"] for r in group]),
            "exponent_median": fit_exponent(
                dofs, [float(np.median(r["repeats_seconds_per_step"])) for r in group]),
            "exponent_cpu": fit_exponent(dofs, [r["cpu_seconds_per_step"] for r in group]),
        }
    table = [{k: r.get(k) for k in ("n_dofs", "ranks", "resolved_solver", "setup_seconds",
                                     "seconds_per_step", "repeats_seconds_per_step",
                                     "cpu_seconds_per_step", "iterations_per_step",
                                     "peak_gb_per_rank", "rom_output_error",
                                     "output_deviation_vs_direct", "output_deviation_vs_1_rank",
                                     "load_average")}
             for r in sorted(best, key=lambda r: (r["ranks"], r["solver"], r["n_dofs"]))]
    return {"table": table, "exponents": exponents,
            "stopped": [r for r in records if "stopped" in r]}


def figure(path: Path, records: list[dict], exponents: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    done = fastest_repeats([r for r in records if "stopped" not in r])
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    for i, (label, e) in enumerate(sorted(exponents.items())):
        group = sorted((r for r in done if f"{r['ranks']} ranks, {r['solver']}" == label),
                       key=lambda r: r["n_dofs"])
        n = np.array([r["n_dofs"] for r in group], float)
        colour = f"C{i}"
        s = np.array([r["seconds_per_step"] for r in group])
        name = label if e["exponent"] is None else f"{label}: p = {e['exponent']:.2f}"
        axes[0].loglog(n, s, "o", color=colour, label=name)
        every = [(r["n_dofs"], t) for r in group for t in r["repeats_seconds_per_step"][1:]]
        if every:
            axes[0].loglog(*zip(*every), ".", color=colour, alpha=0.5, ms=4)
        if e["exponent"] is not None:
            c = np.polyfit(np.log(n), np.log(s), 1)
            grid = np.geomspace(n.min(), n.max(), 20)
            axes[0].loglog(grid, np.exp(np.polyval(c, np.log(grid))), "-", color=colour, lw=1)
        cpu = np.array([r["cpu_seconds_per_step"] for r in group])
        axes[0].loglog(n, cpu, "x--", color=colour, lw=0.8,
                       label=f"{label} (CPU s of the busiest rank)" + (
                           "" if e["exponent_cpu"] is None else f": p = {e['exponent_cpu']:.2f}"))
        axes[1].loglog(n, [r["setup_seconds"] for r in group], "o-", color=colour, label=label)
        axes[2].loglog(n, [r["peak_gb_per_rank"] for r in group], "o-", color=colour, label=label)
    if done:
        n = np.array(sorted({r["n_dofs"] for r in done}), float)
        s0 = min(r["seconds_per_step"] for r in done if r["n_dofs"] == n[0])
        axes[0].loglog(n, s0 * n / n[0], "k:", lw=1, label="slope 1")
    axes[0].set(xlabel="dofs", ylabel="seconds per Newmark step",
                title="time per step (o wall: fastest run, line fitted; . other runs; x CPU)")
    axes[1].set(xlabel="dofs", ylabel="seconds", title="set-up (mesh to factorisation)")
    axes[2].set(xlabel="dofs", ylabel="GB", title="peak resident memory per rank")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        if done:
            ax.legend(fontsize=8)
    steps = sorted({r["steps"] for r in done})
    fig.suptitle(f"fishtail FOM scaling ({', '.join(map(str, steps))} steps per case; shared machine)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _repeats(seconds: list[float]) -> str:
    """'-' for one run, else 'n: min-max' of the repeats' s/step."""
    return "-" if len(seconds) < 2 else f"{len(seconds)}: {min(seconds):.3f}-{max(seconds):.3f}"


def _table(summary: dict) -> str:
    head = ("dofs", "ranks", "solver", "setup s", "s/step", "repeats", "cpu s/step", "its",
            "GB/rank", "ROM err", "dev vs direct", "dev vs 1 rank", "load")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in summary["table"]:
        dev, dev1 = r["output_deviation_vs_direct"], r["output_deviation_vs_1_rank"]
        lines.append(" | ".join([
            f"{r['n_dofs']:,}", str(r["ranks"]), r["resolved_solver"], f"{r['setup_seconds']:.1f}",
            f"{r['seconds_per_step']:.3f}", _repeats(r.get("repeats_seconds_per_step") or []),
            f"{r['cpu_seconds_per_step']:.3f}",
            f"{r['iterations_per_step']:.1f}", f"{r['peak_gb_per_rank']:.2f}",
            f"{r['rom_output_error']:.2e}", "-" if dev is None else f"{dev:.1e}",
            "-" if dev1 is None else f"{dev1:.1e}", f"{r['load_average']:.1f}"]).join(["| ", " |"]))
    lines.append("")
    for label, e in summary["exponents"].items():
        if e["exponent"] is not None:
            several = max(e.get("repeats") or [1]) > 1
            lines.append(f"* exponent of s/step in the dofs, {label}: {e['exponent']:.2f}"
                         + (" (fastest repeats; through the medians: "
                            f"{e['exponent_median']:.2f})" if several else "")
                         + f"; CPU seconds: {e['exponent_cpu']:.2f}")
    for r in summary["stopped"]:
        lines.append(f"* stopped {r['size']} {r['ranks']} ranks {r['solver']}: {r['stopped']}")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="100k,200k,400k",
                        help=f"comma-separated: {', '.join(SIZES)} or element sizes in metres")
    parser.add_argument("--ranks", default="1,2", help="comma-separated MPI rank counts")
    parser.add_argument("--solvers", default="auto", help="comma-separated solver names "
                        "(dolfinx_lopinf.fem.linsolve.SOLVERS)")
    parser.add_argument("--steps", type=int, default=200, help="Newmark steps per case")
    parser.add_argument("--repeats", type=int, default=1,
                        help="run every case this many times (the sizes in turn, then again), and "
                        "fit the exponent through each case's fastest repeat")
    parser.add_argument("--out", default="results/scaling")
    parser.add_argument("--max-gb", type=float, default=18.0,
                        help="stop a case whose processes hold more resident memory than this")
    parser.add_argument("--petsc-options", default=None, help="JSON dict of PETSc options")
    parser.add_argument("--collect", action="store_true",
                        help="run nothing: gather every case already in --out/cases into the JSON and figure")
    parser.add_argument("--case", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--repeat-index", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    from ..errors import InputError
    from ..fem.linsolve import check_solver

    sizes = [s.strip() for s in args.sizes.split(",") if s.strip()]
    solvers = [s.strip() for s in args.solvers.split(",") if s.strip()]
    try:
        ranks = [int(x) for x in args.ranks.split(",") if x.strip()]
        options = json.loads(args.petsc_options) if args.petsc_options else None
    except ValueError as exc:
        raise InputError(f"--ranks must be integers and --petsc-options a JSON dict: {exc}") from None
    for s in sizes:
        _lc(s)
    for s in solvers:
        check_solver(s)
    if args.steps < 4 or not ranks or min(ranks) < 1 or args.repeats < 1:
        raise InputError("--steps must be >= 4, --ranks positive integers and --repeats >= 1")
    out = Path(args.out)
    if args.case:
        return run_case(sizes[0], solvers[0], args.steps, out, petsc_options=options,
                        repeat=args.repeat_index)
    out.mkdir(parents=True, exist_ok=True)
    summary_path = out / "scaling.json"
    if args.collect:
        records = [json.loads(p.read_text()) for p in sorted((out / "cases").glob("*.json"))]
        return _write(out, records)
    bindir = Path(sys.executable).parent
    mpiexec = str(bindir / "mpiexec") if (bindir / "mpiexec").exists() else "mpiexec"
    records, stopped = [], set()
    # the sizes in turn, then again: a slow spell of the machine then touches one repeat of
    # several sizes rather than every repeat of one; a case stopped once is not run again
    for repeat, size, n, solver in itertools.product(range(args.repeats), sizes, ranks, solvers):
        if (size, n, solver) in stopped:
            continue
        rec = _run_worker(size, n, solver, args.steps, out, args.max_gb, sys.executable, mpiexec,
                          options, repeat)
        records.append(rec)
        if "stopped" in rec:
            stopped.add((size, n, solver))
        print(f"{size} {n} ranks {solver}" + (f" (repeat {repeat + 1})" if repeat else "") + ": "
              + (rec["stopped"] if "stopped" in rec else
                 f"{rec['n_dofs']:,} dofs, set-up {rec['setup_seconds']:.1f} s, "
                 f"{rec['seconds_per_step']:.3f} s/step, {rec['peak_gb_per_rank']:.2f} GB/rank, "
                 f"ROM r=2 error {rec['rom_output_error']:.2e}"), flush=True)
        summary = summarise(records)
        summary_path.write_text(json.dumps({"cases": records, **summary}, indent=1))
    return _write(out, records)


def _write(out: Path, records: list[dict]) -> dict:
    """scaling.json, scaling.png, and the table (markdown) in scaling.md and on stdout."""
    summary = summarise(records)
    (out / "scaling.json").write_text(json.dumps({"cases": records, **summary}, indent=1))
    figure(out / "scaling.png", records, summary["exponents"])
    steps = sorted({r["steps"] for r in records if "stopped" not in r})
    (out / "scaling.md").write_text(
        f"*Generated by `python -m dolfinx_lopinf.studies.scaling` ({', '.join(map(str, steps))} "
        "Newmark steps per case, sine input from its onset). s/step: wall seconds per step of the "
        "slowest rank; cpu s/step: that rank's CPU seconds; its: iterations per step (a "
        "factor's substitutions count 1, a step the recycled subspace answered 0); load: the machine's load average "
        "during the case; dev: the largest output difference, relative, against the direct "
        "solver / one rank at the same size.*\n\n" + _table(summary) + "\n")
    print(_table(summary))
    return summary


if __name__ == "__main__":
    main()
