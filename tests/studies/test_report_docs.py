"""report --docs: the documentation's generated pages come from the metrics, say which mode
produced them, prefer a default run to a quick one, and carry the figures along."""

import json

import pytest

pytest.importorskip("matplotlib")

from dolfinx_lopinf.studies import report  # noqa: E402

PNG = b"\x89PNG\r\n\x1a\n" + b"\0" * 64  # copied, never decoded


def _beam_metrics(quick: bool, scale: float) -> dict:
    rows = []
    for basis in ("euclidean-block", "mass-orthonormal"):
        for r in (4, 8):
            for method in ("lopinf", "lopinf_del", "opinf", "intrusive"):
                rows.append({"method": method, "basis": basis, "r": r, "train_error": scale * 1e-5,
                             "test_error": scale * r * 1e-4, "projection_error_test": scale * 1e-6,
                             "max_energy_error": 1e-8, "infer_seconds": 1e-3, "rom_seconds": 2e-3,
                             "rom_backend": "numpy", "stable": True})
    return {"scene": "beam", "n_dofs": 400, "dt": 1e-5, "t_train": 0.03, "t_end": 0.18,
            "fom_seconds": 3.0, "fom_seconds_to_t_end": 1.5, "fom_steps": 300_000,
            "fom_energy_drift": 1e-12, "quick": quick, "error": "state",
            "error_definition": "relative state error", "roms": rows}


def _write(folder, metrics, figures=("error_vs_r_euclidean-block.png",)):
    folder.mkdir(parents=True)
    (folder / "metrics.json").write_text(json.dumps(metrics))
    for name in figures:
        (folder / name).write_bytes(PNG)


def test_pages_from_metrics_default_wins_over_quick(tmp_path):
    _write(tmp_path / "quick" / "beam", _beam_metrics(True, 7.0), ())
    _write(tmp_path / "full" / "beam", _beam_metrics(False, 1.0))
    out = tmp_path / "docs" / "generated"
    # the quick run comes last on the command line and still loses to the default one
    written = report.main(["--docs", str(out), str(tmp_path / "full"), str(tmp_path / "quick")])
    assert written is None
    page = (out / "beam.md").read_text()
    assert "`python demos/beam.py` (**default** mode)" in page
    assert "| 8 | 8.00e-04 | 8.00e-04 | 8.00e-04 | 8.00e-04 | 1.00e-06 |" in page  # the pivot
    assert "5.60e-03" not in page  # the quick run's r = 8 error is not shown
    assert (out / "beam" / "error_vs_r_euclidean-block.png").read_bytes() == PNG
    assert "```{figure} /generated/beam/error_vs_r_euclidean-block.png" in page
    bench = (out / "benchmarks.md").read_text()
    assert "| beam | default | 400 | 1.5 | state |" in bench
    assert "| beam (default) | lopinf (mass-orthonormal) | 4 | 4.00e-04 |" in bench
    assert (out / "beam" / "speed_vs_error_report.png").stat().st_size > 10_000


def test_a_quick_run_says_so_and_a_missing_folder_is_an_error(tmp_path):
    _write(tmp_path / "beam", _beam_metrics(True, 1.0), ())
    out = tmp_path / "generated"
    report.write_docs([tmp_path / "beam"], out)
    assert "`python demos/beam.py --quick` (**quick** mode)" in (out / "beam.md").read_text()
    assert "| beam | quick |" in (out / "benchmarks.md").read_text()
    with pytest.raises(SystemExit, match="run the demos first"):
        report.write_docs([tmp_path / "nothing"], tmp_path / "other")
