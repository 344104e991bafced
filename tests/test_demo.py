"""The beam demo end to end in quick mode: it runs, writes the shared metrics schema and
figures, and its ROMs carry the structure they promise."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf._dolfinx")

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("beam")
    proc = subprocess.run([sys.executable, str(ROOT / "demos" / "beam.py"), "--quick", "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, json.loads((out / "metrics.json").read_text())


def test_metrics_schema(quick_run):
    _, m = quick_run
    for key in ("scene", "n_dofs", "dt", "t_train", "t_end", "fom_seconds", "fom_energy_drift", "roms"):
        assert key in m
    assert m["scene"] == "beam" and m["n_dofs"] == 400 and m["dt"] == 1e-5
    assert {row["method"] for row in m["roms"]} == {"lopinf", "opinf", "intrusive"}
    for row in m["roms"]:
        for key in ("method", "r", "train_error", "test_error", "projection_error_test",
                    "max_energy_error", "infer_seconds", "rom_seconds", "stable"):
            assert key in row, key
        assert isinstance(row["stable"], bool)


def test_fom_and_roms_are_physical(quick_run):
    _, m = quick_run
    assert m["fom_energy_drift"] < 1e-9
    for row in m["roms"]:
        if row["method"] == "lopinf":
            assert row["symmetry_error"] == 0.0
            assert row["min_eig_K"] >= 1e-8
            assert row["stable"]
        # no ROM can beat the projection error of its basis on the test window by much
        assert row["test_error"] >= 0.5 * row["projection_error_test"]
    best = min(r["test_error"] for r in m["roms"]
               if r["method"] == "lopinf" and r["basis"] == "mass-orthonormal")
    assert best < 1e-3


def test_figures_written(quick_run):
    out, _ = quick_run
    for name in ("beam_shapes", "error_vs_r_euclidean-block", "error_vs_r_mass-orthonormal",
                 "energy_error", "midpoint_deflection", "midpoint_deflection_error"):
        png = out / f"{name}.png"
        assert png.exists() and png.stat().st_size > 10_000, name
        with open(png, "rb") as f:
            assert f.read(8) == b"\x89PNG\r\n\x1a\n"
