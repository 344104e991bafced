"""The inference benchmark's command runs end to end on a small selection and writes rows
whose fits are certified and agree with Clarabel (no timing is asserted)."""

import json

from dolfinx_lopinf.studies import benchmark


def test_benchmark_table_rows(tmp_path, capsys):
    out = tmp_path / "bench.json"
    rows = benchmark.main(["--table", "--sets", "forced,rigid,wave", "--r", "4", "--repeats", "1",
                           "--out", str(out)])
    assert [(row["set"], row["K"]) for row in rows] == [
        (s, k) for s in ("forced", "rigid", "wave") for k in (3000, 10000)]
    for row in rows:
        assert row["symmetric"] and row["relative_gap"] <= 1e-6
        if row["set"] != "wave":
            assert row["certified_gap"] <= 1e-8 and row["min_eig_K"] >= 1e-8 * (1 - 1e-9)
            assert row["ours_solve_seconds_numpy"] > 0  # the numpy iteration ran alongside
    assert json.loads(out.read_text())["rows"] == json.loads(json.dumps(rows))
    assert "cert. gap" in capsys.readouterr().out


def test_rom_benchmark_warm_up_command_runs():
    """bench_rom times the cold compile and the cache load by running WARM_UP in fresh
    processes; the layer refactor had left it importing a module that no longer exists."""
    import contextlib
    import io

    from dolfinx_lopinf.core import compiled
    from dolfinx_lopinf.studies import bench_rom

    with contextlib.redirect_stdout(io.StringIO()) as printed:
        exec(bench_rom.WARM_UP, {})
    seconds = float(printed.getvalue().strip().splitlines()[-1]) if compiled.available() else None
    assert seconds is None or seconds >= 0.0


def test_benchmark_mass_and_poly_tables(tmp_path, capsys):
    """--mass --poly: our interior points against Clarabel on the same problems; ours certified
    and at least as good as Clarabel's answer (phi), the polynomial fits with the same residual."""
    out = tmp_path / "bench.json"
    benchmark.main(["--no-mh", "--mass", "--mass-sets", "modal,chainpod", "--mass-r", "3",
                    "--poly", "--poly-r", "3", "--repeats", "1", "--out", str(out)])
    saved = json.loads(out.read_text())
    assert [(row["set"], row["r"]) for row in saved["mass_rows"]] == [("modal", 3), ("chainpod", 3)]
    for row in saved["mass_rows"]:
        assert row["certified"] and row["gap"] <= 1e-8
        assert row["phi_difference"] >= -1e-8  # Clarabel's answer is not better than ours
        assert row["default_certified"] and row["default_ms"] > 0  # the user's call, the same data
    (poly,) = saved["poly_rows"]
    assert abs(poly["ipm"]["relative_residual"] - poly["cvxpy"]["relative_residual"]) \
        <= 1e-2 * poly["cvxpy"]["relative_residual"]
    printed = capsys.readouterr().out
    assert "learned mass" in printed and "polynomial sos fit" in printed


def test_benchmark_fit_table_on_recorded_snapshots(tmp_path, capsys):
    """--fit: lo.fit with its defaults on saved snapshots, one row per r - the choice, the
    certificate, the warnings counted; a reduced dimension the data cannot carry is a row
    with its refusal, not a crash."""
    import numpy as np

    import dolfinx_lopinf as lo

    t = np.arange(400) * 0.01
    Q = np.vstack([np.cos(t), np.sin(1.7 * t), np.cos(2.3 * t + 0.4)])
    Q = np.vstack([Q, 0.5 * Q[:1] + 0.2 * Q[1:2]])  # 4 states of rank 3
    path = tmp_path / "loop.npz"
    lo.Snapshots(t, Q).save(path)
    out = tmp_path / "bench.json"
    benchmark.main(["--no-mh", "--fit", str(path), "--fit-r", "2,6", "--repeats", "1", "--out", str(out)])
    rows = json.loads(out.read_text())["fit_rows"]
    assert [row["r"] for row in rows] == [2, 6]
    ok, refused = rows
    assert ok["seconds"] > 0 and ok["mass"] in ("identity", "learned") and isinstance(ok["certified"], bool)
    assert ok["n_states"] == 4 and ok["n_samples"] == 400 and "refused" not in ok
    assert "refused" in refused and "numerical rank" in refused["refused"]
    assert "lo.fit defaults end to end" in capsys.readouterr().out


def test_benchmark_table_on_recorded_snapshots(tmp_path, capsys):
    """--table --sets file:PATH: the Mh = I fit on recorded snapshots (Euclidean POD, the
    Newmark relation, every sample) against Clarabel, one row per r; an r the snapshots cannot
    carry is a row with its refusal."""
    import numpy as np

    import dolfinx_lopinf as lo

    t = np.arange(300) * 0.01
    Q = np.vstack([np.cos((k + 1) * t + 0.3 * k) * np.exp(-0.05 * k * t) for k in range(6)])
    U = np.sin(0.9 * t)[None, :]
    path = tmp_path / "loop.npz"
    lo.Snapshots(t, Q, U=U).save(path)
    out = tmp_path / "bench.json"
    rows = benchmark.main(["--table", "--sets", f"file:{path}", "--r", "4,8", "--repeats", "1",
                           "--out", str(out)])
    ok, refused = rows
    assert ok["set"] == f"file:{path}" and ok["r"] == 4 and ok["K"] == 300 - 2
    assert ok["certified_gap"] <= 1e-8 and ok["min_eig_K"] >= 1e-8 * (1 - 1e-9) and ok["symmetric"]
    assert refused["r"] == 8 and "numerical rank" in refused["refused"]
    assert "refused" in capsys.readouterr().out
