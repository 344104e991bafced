"""The beam demo end to end in quick mode: it runs, writes the shared metrics schema and
figures, and its ROMs carry the structure they promise."""

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def quick_run(quick_demo):
    return quick_demo("beam")


def test_metrics_schema(quick_run):
    _, m = quick_run
    for key in ("scene", "n_dofs", "dt", "t_train", "t_end", "fom_seconds", "fom_energy_drift", "roms"):
        assert key in m
    assert m["scene"] == "beam" and m["n_dofs"] == 400 and m["dt"] == 1e-5
    assert {row["method"] for row in m["roms"]} == {"lopinf", "lopinf_del", "opinf", "intrusive"}
    for row in m["roms"]:
        for key in ("method", "r", "train_error", "test_error", "projection_error_test",
                    "max_energy_error", "infer_seconds", "rom_seconds", "stable"):
            assert key in row, key
        assert isinstance(row["stable"], bool)


def test_fom_and_roms_are_physical(quick_run):
    _, m = quick_run
    assert m["fom_energy_drift"] < 1e-9
    for row in m["roms"]:
        if row["method"].startswith("lopinf"):
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


def test_existing_code_demo_quick(quick_demo):
    """An ordinary dolfinx cantilever loop + SnapshotRecorder -> forced L-OpInf ROM that
    predicts the tip displacement for an unseen load."""
    tmp_path, m = quick_demo("existing_code")
    assert m["error"] == "output"  # train_error / test_error are tip (output) errors
    rows = {(x["method"], x["r"]): x for x in m["roms"]}
    for r in (2, 4):
        auto, fd = rows[("lopinf", r)], rows[("lopinf_fd", r)]
        # the loop is Newmark: lo.fit(scheme="auto") must find its relation, and that beats
        # finite differences on the unseen load (1.6e-3 vs 2.0e-3 measured on this mesh)
        assert auto["scheme"] == "newmark(beta=0.25, gamma=0.5)", auto["identification"]
        assert auto["test_error"] < min(5e-3, fd["test_error"])  # output error (m["error"])
        assert auto["min_eig_K"] > 0 and auto["min_eig_C"] > 0
    model = __import__("dolfinx_lopinf").ReducedModel.load(tmp_path / "cantilever_rom.npz")
    assert model.scheme == "newmark" and model.rom.scheme == "newmark"
    assert model.rom.B.shape == (m["saved_rom_r"], 1) and model.basis.n == m["n_dofs"]
    assert (tmp_path / "tip_displacement.png").stat().st_size > 10_000


def test_recorder_rejects_bad_records():
    import dolfinx_lopinf as lo
    from dolfinx_lopinf.fem._dolfinx import MPI, dolfinx

    msh = dolfinx.mesh.create_unit_interval(MPI.COMM_WORLD, 8)
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
    u = dolfinx.fem.Function(V)
    rec = lo.SnapshotRecorder(u)
    rec.record(0.0, u, inputs=[1.0])
    rec.record(0.1, u, inputs=[1.0])
    with pytest.raises(ValueError, match="uniform spacing"):
        rec.record(0.25, u, inputs=[1.0])
    with pytest.raises(ValueError, match="increase"):
        rec.record(0.1, u, inputs=[1.0])
    with pytest.raises(ValueError, match="inputs had 1 entries"):
        rec.record(0.2, u, inputs=[1.0, 2.0])
    u.x.array[2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        rec.record(0.2, u, inputs=[1.0])
    assert len(rec) == 2


def test_stability_cantilever_is_the_demo_cantilever():
    """scenes/cantilever.py is a copy of the demo's self-contained user program (the installed
    package cannot import demos/); the two must stay the same model."""
    import importlib.util

    import dolfinx_lopinf as lo
    from dolfinx_lopinf.scenes import cantilever

    spec = importlib.util.spec_from_file_location("existing_code", ROOT / "demos" / "existing_code.py")
    demo = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(demo)
    for name in ("LENGTH", "WIDTH", "HEIGHT", "E_MOD", "NU", "RHO", "ALPHA", "BETA", "DT"):
        assert getattr(demo, name) == getattr(cantilever, name), name
    runs = [sim(cantilever.train_load, 0.05, (12, 2, 2), lambda q: lo.SnapshotRecorder(q))[1].snapshots()
            for sim in (demo.simulate_cantilever, cantilever.simulate)]
    assert runs[0].Q.shape == runs[1].Q.shape and np.abs(runs[0].Q).max() > 0
    assert np.array_equal(runs[0].Q, runs[1].Q) and np.array_equal(runs[0].U, runs[1].U)


def test_beam_unseen_ic_demo_quick(quick_demo):
    """Several trajectories through lo.fit: the demo runs, every ROM is finite, and no ROM beats
    the projection floor of its basis on the test trajectories."""
    tmp_path, m = quick_demo("beam_unseen_ic")
    assert m["train_a"] == [0.2, 0.3, 0.4, 0.5] and m["test_a"] == [0.1, 0.6]
    assert {x["method"] for x in m["roms"]} == {"lopinf", "lopinf_fd", "lopinf_mass_I", "intrusive"}
    assert {x["basis"] for x in m["roms"]} == {"euclidean-block", "mass-orthonormal"}
    for x in m["roms"]:
        assert x["stable"] and x["test_error"] >= 0.5 * x["projection_error_test"]
    for png in ("error_vs_r.png", "error_vs_r_mass_orthonormal.png"):
        assert (tmp_path / png).stat().st_size > 10_000


def test_report_reads_the_shared_vocabulary(quick_demo, tmp_path):
    """report.py reads every demo's metrics.json with one vocabulary: test_error of the
    scene's error kind, times as numbers (state errors: beam; output errors: the cantilever)."""
    import shutil

    from dolfinx_lopinf.studies import report

    for name in ("beam", "existing_code"):
        out, m = quick_demo(name)
        assert m["error"] in ("state", "output") and "stable_definition" in m
        (tmp_path / name).mkdir()
        shutil.copy(out / "metrics.json", tmp_path / name / "metrics.json")
    table = report.main([str(tmp_path)])
    assert any(line.startswith("| existing_code_cantilever | lopinf |") for line in table)
    assert any(line.startswith("| beam | lopinf (mass-orthonormal) |") for line in table)
    # the ROM time of both loops: the default (compiled with numba) and the numpy reference
    cells = [c.strip() for c in next(line for line in table
                                     if line.startswith("| beam | lopinf (mass-orthonormal) |")).split("|")]
    assert float(cells[6]) > 0 and cells[7].endswith("x"), cells
    assert (tmp_path / "report_beam.png").stat().st_size > 10_000


def test_a_run_that_grew_far_past_the_truth_is_not_stable():
    """A ROM whose states stay finite but whose error is 1e12 (it grew by that much) is not
    reported as stable; an inaccurate but bounded one (error 1.5) keeps its verdict."""
    from dolfinx_lopinf.studies import harness

    assert not harness.rom_row("lopinf", 10, train_error=1e-3, test_error=6.7e12, stable=True)["stable"]
    assert not harness.rom_row("opinf", 4, train_error=80.0, test_error=None, stable=True)["stable"]
    assert harness.rom_row("lopinf", 2, train_error=0.1, test_error=1.5, stable=True)["stable"]
    assert not harness.rom_row("lopinf", 2, train_error=0.1, test_error=0.2, stable=False)["stable"]
    assert harness.rom_row("lopinf", 2, train_error=float("nan"), test_error=0.2, stable=True)["stable"]
