"""The README's API example runs as written and does what it claims."""

import re
from pathlib import Path

import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")


def test_readme_example_runs(capsys):
    text = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    namespace = {}
    exec(compile(code, "README.md", "exec"), namespace)
    assert namespace["error"] < 1e-2
    assert namespace["ops"].certificate["min_eig_K"] >= 1e-8
    assert "state error" in capsys.readouterr().out


def test_readme_own_code_path_runs(tmp_path, monkeypatch):
    """The README's "own dolfinx time loop" block, as written: its first line builds the
    recorder inside a real Newmark loop (the packaged cantilever), the lines after the loop run
    verbatim."""
    import numpy as np

    import dolfinx_lopinf as lo
    from dolfinx_lopinf.scenes import cantilever

    text = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    block = re.findall(r"```python\n(.*?)```", text, re.S)[1]
    lines = block.strip("\n").split("\n")
    assert lines[0].startswith("rec = lo.SnapshotRecorder(u,") and lines[1].startswith("for n in")
    after = "\n".join(lines[lines.index(next(x for x in lines if x.startswith("model = "))):])
    namespace = {"lo": lo, "np": np, "dt": cantilever.DT,
                 "new_load": lambda t: np.array([np.tanh(t / 0.1)])}

    def factory(q):  # the README's first line, with the user's u and V
        exec(lines[0], namespace | {"u": q, "V": q.function_space}, namespace)
        namespace["V"] = q.function_space
        return namespace["rec"]

    cantilever.simulate(cantilever.train_load, 1.0, (12, 2, 2), factory)
    monkeypatch.chdir(tmp_path)
    exec(compile(after, "README.md (own code)", "exec"), namespace)
    model = namespace["model"]
    assert model.scheme == "newmark", model.report
    assert np.all(np.isfinite(namespace["tip"])) and np.abs(namespace["tip"]).max() > 0
    assert (tmp_path / "rom.npz").exists() and (tmp_path / "rom.bp").is_dir()
