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


def _own_loop_demo():
    """demos/own_loop.py as a module (its `simulate` is a user's tutorial-style loop)."""
    import importlib.util

    path = Path(__file__).resolve().parents[2] / "demos" / "own_loop.py"
    spec = importlib.util.spec_from_file_location("own_loop_demo", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_readme_own_code_path_runs(tmp_path, monkeypatch):
    """The README's "own dolfinx time loop" block, as written: the lines before its loop build
    the recorder inside a real generalised-alpha loop (demos/own_loop.py's tutorial-style
    cantilever, rho_inf = 0.8, which records the load it applied at t_{n+1-alpha_f}), the
    lines after the loop run verbatim. The model must use the named scheme and predict the
    tip under the unseen load of the demo close to the loop itself."""
    import numpy as np

    import dolfinx_lopinf as lo

    demo = _own_loop_demo()
    text = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    block = re.findall(r"```python\n(.*?)```", text, re.S)[1]
    lines = block.strip("\n").split("\n")
    loop = next(i for i, x in enumerate(lines) if x.startswith("for n in"))
    before = "\n".join(lines[:loop])
    assert "lo.SnapshotRecorder(u," in before and "GeneralizedAlpha" in before
    after = "\n".join(lines[lines.index(next(x for x in lines if x.startswith("model = "))):])
    assert "rec.record(t, u, inputs=[applied], input_time=t - scheme.alpha_f * dt)" in block
    dt = 0.01
    namespace = {"lo": lo, "np": np, "dt": dt, "new_load": demo.test_load}

    def factory(u):  # the README's lines before the loop, with the user's u and V
        exec(before, namespace | {"u": u, "V": u.function_space}, namespace)
        namespace["V"] = u.function_space
        return namespace["rec"]

    demo.simulate(demo.train_load, 2.0, dt, "gen-alpha", (8, 1, 1), factory)
    monkeypatch.chdir(tmp_path)
    exec(compile(after, "README.md (own code)", "exec"), namespace)
    model, tip = namespace["model"], namespace["tip"]
    assert model.scheme == lo.schemes.GeneralizedAlpha(rho_inf=0.8), model.report
    # the loop itself under the unseen load: the README's prediction follows it
    tip_point = [[1.0, 0.05, 0.05]]
    _, rec, _ = demo.simulate(demo.test_load, 1.0, dt, "gen-alpha", (8, 1, 1), lambda u: lo.SnapshotRecorder(
        u, output_matrix=lo.point_output_matrix(u.function_space, tip_point, component=2)))
    fom = rec.snapshots().Y
    assert tip.shape == fom.shape and np.abs(fom).max() > 1e-3
    assert lo.relative_error(fom, tip) < 5e-2, lo.relative_error(fom, tip)
    assert (tmp_path / "rom.npz").exists() and (tmp_path / "rom.bp").is_dir()
