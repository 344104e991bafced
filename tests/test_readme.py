"""The README's API example runs as written and does what it claims."""

import re
from pathlib import Path

import pytest

pytest.importorskip("dolfinx_lopinf._dolfinx")


def test_readme_example_runs(capsys):
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    namespace = {}
    exec(compile(code, "README.md", "exec"), namespace)
    assert namespace["error"] < 1e-2
    assert namespace["ops"].certificate["min_eig_K"] >= 1e-8
    assert "state error" in capsys.readouterr().out
