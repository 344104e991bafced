"""The scaling study's pieces: the exponent fit, the summary, the command line's refusals, and
one tiny case end to end (slow: it meshes and runs the fishtail under mpiexec)."""

import json

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

from dolfinx_lopinf.errors import InputError  # noqa: E402
from dolfinx_lopinf.studies import scaling  # noqa: E402


def test_fit_exponent():
    n = np.array([1e5, 2e5, 4e5, 8e5])
    assert scaling.fit_exponent(n, 3e-6 * n**1.33) == pytest.approx(1.33)
    assert scaling.fit_exponent([1e5, 1e5], [1.0, 1.1]) is None


def test_summary_compares_with_direct():
    def rec(n, solver, y, s):
        return {"size": str(n), "n_dofs": n, "ranks": 1, "solver": solver, "resolved_solver": solver,
                "output": y, "seconds_per_step": s, "cpu_seconds_per_step": s, "setup_seconds": 1.0,
                "iterations_per_step": 1.0, "peak_gb_per_rank": 1.0, "rom_output_error": 1e-3,
                "load_average": 0.1, "steps": 10}
    records = [rec(100, "direct", [0.0, 1.0, 2.0], 1.0), rec(100, "cg+pmg", [0.0, 1.0, 2.002], 3.0),
               rec(200, "direct", [0.0, 1.0], 2.0), {"size": "800k", "ranks": 2, "solver": "auto",
                                                     "stopped": "memory"}]
    out = scaling.summarise(records)
    assert records[1]["output_deviation_vs_direct"] == pytest.approx(1e-3)
    assert out["exponents"]["1 ranks, direct"]["exponent"] == pytest.approx(1.0)
    assert out["exponents"]["1 ranks, cg+pmg"]["exponent"] is None
    assert len(out["table"]) == 3 and out["stopped"][0]["stopped"] == "memory"
    # "auto" resolves to another solver with the size: one exponent for what was asked
    auto = [rec(100, "auto", [0.0, 1.0], 1.0), rec(400, "auto", [0.0, 1.0], 4.0)]
    auto[1]["resolved_solver"] = "direct+blr+subspace"
    assert scaling.summarise(auto)["exponents"]["1 ranks, auto"]["exponent"] == pytest.approx(1.0)
    table = scaling._table(out)
    assert "stopped 800k" in table
    head, rule, *rows = table.splitlines()[:5]  # a markdown table: header, rule, one line per case
    assert head.startswith("| dofs") and rule.count("---|") == head.count("|") - 1
    assert sum(line.startswith("| ") for line in table.splitlines()) == 1 + len(out["table"])


@pytest.mark.parametrize("argv, match", [
    (["--solvers", "mumps"], "solver must be one of"),
    (["--sizes", "huge"], "size 'huge'"),
    (["--ranks", "two"], "--ranks must be integers"),
    (["--steps", "2"], "--steps must be >= 4"),
    (["--repeats", "0"], "--repeats >= 1"),
])
def test_bad_command_lines_are_refused(argv, match, tmp_path):
    with pytest.raises(InputError, match=match):
        scaling.main(argv + ["--out", str(tmp_path)])


@pytest.mark.slow
def test_tiny_case_end_to_end(tmp_path):
    summary = scaling.main(["--sizes", "25k", "--ranks", "1", "--steps", "8", "--out", str(tmp_path)])
    (row,) = summary["table"]
    assert row["resolved_solver"] == "direct" and row["n_dofs"] > 20_000
    assert row["seconds_per_step"] > 0 and row["peak_gb_per_rank"] > 0.1
    assert np.isfinite(row["rom_output_error"])
    data = json.loads((tmp_path / "scaling.json").read_text())
    assert set(data["cases"][0]["phases_seconds"]) >= {"gmsh", "distribute", "forms", "assemble", "solver"}
    assert (tmp_path / "scaling.png").stat().st_size > 10_000
    assert "| dofs | ranks |" in (tmp_path / "scaling.md").read_text()


def test_repeats_enter_with_their_fastest_run():
    def rec(n, s, repeat):
        return {"size": str(n), "n_dofs": n, "ranks": 2, "solver": "auto", "resolved_solver": "x",
                "output": [0.0, 1.0], "seconds_per_step": s, "cpu_seconds_per_step": s,
                "setup_seconds": 1.0, "iterations_per_step": 0.1, "peak_gb_per_rank": 1.0,
                "rom_output_error": 1e-3, "load_average": 0.1, "steps": 10, "repeat": repeat}
    # a slow spell (x1.3) hit the first repeat of the small case and the second of the large
    records = [rec(100, 1.3, 0), rec(800, 8.0, 0), rec(100, 1.0, 1), rec(800, 10.4, 1),
               rec(100, 1.1, 2), rec(800, 8.8, 2)]
    out = scaling.summarise(records)
    e = out["exponents"]["2 ranks, auto"]
    assert e["exponent"] == pytest.approx(1.0) and e["repeats"] == [3, 3]
    assert e["exponent_median"] == pytest.approx(np.log(8.8 / 1.1) / np.log(8))
    assert len(out["table"]) == 2 and out["table"][0]["repeats_seconds_per_step"] == [1.0, 1.1, 1.3]
    table = scaling._table(out)
    assert "3: 1.000-1.300" in table and "through the medians: 1.00" in table
    assert scaling._case_name("100k", 2, "auto", 0) == "100k_2_auto"
    assert scaling._case_name("100k", 2, "auto", 2) == "100k_2_auto_2"
    # a repeat is not a reference for its own case: a direct case has no deviation from direct
    direct = [dict(rec(100, 1.0, k), solver="direct", resolved_solver="direct") for k in (0, 1)]
    direct[1]["output"] = [0.0, 1.5]
    assert scaling.summarise(direct)["table"][0]["output_deviation_vs_direct"] is None
