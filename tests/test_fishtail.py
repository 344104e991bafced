"""Fishtail scene (work in progress for the full demo): geometry, two materials, chamber
pressure inputs, Newmark FOM."""

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf._dolfinx")

from dolfinx_lopinf._dolfinx import MPI  # noqa: E402
from dolfinx_lopinf.integrators import NewmarkIntegrator  # noqa: E402
from dolfinx_lopinf.scenes import fishtail as ft  # noqa: E402


@pytest.fixture(scope="module")
def small():
    return ft.build(0.012)


def _tip_history(f, nm, u, steps=40):
    nm.initialize(f.chamber_pressures(0.0))
    ys, energies = [], []
    for k in range(1, steps + 1):
        nm.step(f.chamber_pressures(u))
        ys.append(MPI.COMM_WORLD.allreduce(f.output_matrix @ nm.q.x.array)[0])
        energies.append(nm.energy())
    return np.array(ys), np.array(energies)


def test_geometry_tags_and_materials(small):
    tags = small.cell_tags
    assert len(tags.find(1)) > 0 and len(tags.find(2)) > 0  # hull and beam cells
    for tag in (11, 12, 20):
        n = MPI.COMM_WORLD.allreduce(len(small.facet_tags.find(tag)))
        assert n > 0, tag
    assert small.system.is_quadratic


def test_chamber_pressure_bends_the_tail_antisymmetrically(small):
    """Mirror-symmetric geometry: swapping the chamber pressures (u -> -u) mirrors the
    lateral tip displacement (up to the asymmetry of the unstructured mesh)."""
    nm = NewmarkIntegrator(small.system, ft.DT, rayleigh=ft.RAYLEIGH, input_forms=small.input_forms,
                           prefix="ft_test_")
    y_plus, e_plus = _tip_history(small, nm, 5000.0)
    y_minus, _ = _tip_history(small, nm, -5000.0)
    assert np.all(np.isfinite(y_plus)) and np.abs(y_plus).max() > 1e-5
    assert np.abs(y_plus + y_minus).max() < 0.05 * np.abs(y_plus).max()
    assert e_plus[-1] > 0


def test_fishtail_demo_quick(tmp_path):
    import json
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "demos" / "fishtail.py"
    proc = subprocess.run([sys.executable, str(script), "--quick", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    m = json.loads((tmp_path / "metrics.json").read_text())
    lop = [r for r in m["roms"] if r["method"] == "lopinf"]
    assert all(r["min_eig_K"] > 0 and r["min_eig_C"] > 0 and r["stable"] for r in lop)
    best = min(r["output_errors"]["sine"] for r in lop)
    assert best < 2e-2  # training input, short horizon
    assert (tmp_path / "poi_step.png").stat().st_size > 10_000
