"""No lost work: a FOM run killed mid-way resumes from its last checkpoint and produces the
same snapshots as an unbroken run."""

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf._dolfinx")

SCRIPT = Path(__file__).with_name("ckpt_beam.py")


def test_killed_run_resumes_to_the_same_snapshots(tmp_path):
    prefix = tmp_path / "beam_ckpt"
    ckpt = Path(f"{prefix}.rank0.npz")
    proc = subprocess.Popen([sys.executable, str(SCRIPT), str(tmp_path / "killed.npz"), str(prefix)])
    deadline = time.time() + 120
    while not ckpt.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert ckpt.exists(), "no checkpoint was written"
    time.sleep(0.3)  # let it run on a little past the checkpoint, then kill it hard
    proc.kill()
    proc.wait()
    assert not (tmp_path / "killed.npz").exists()  # it really died before finishing
    subprocess.run([sys.executable, str(SCRIPT), str(tmp_path / "resumed.npz"), str(prefix)],
                   check=True, timeout=300)
    subprocess.run([sys.executable, str(SCRIPT), str(tmp_path / "unbroken.npz"), "none"],
                   check=True, timeout=300)
    a, b = np.load(tmp_path / "resumed.npz"), np.load(tmp_path / "unbroken.npz")
    assert int(a["resumed"]) >= 500 and int(b["resumed"]) == 0
    for key in ("Q", "V", "Y", "E"):
        assert np.array_equal(a[key], b[key]), key
    assert not ckpt.exists()  # cleaned up after completion


def test_checkpoint_from_other_settings_is_refused(tmp_path):
    import dolfinx_lopinf as lo
    from dolfinx_lopinf.scenes import beam as scene

    b = scene.build(200)
    q0, v0 = b.initial_state()
    prefix = tmp_path / "c"
    Path(f"{prefix}.rank0.npz").write_bytes(b"")  # placeholder to be replaced by a real one
    np.savez(f"{prefix}.rank0.npz", settings=np.zeros(9), k=1)
    with pytest.raises(ValueError, match="other settings"):
        lo.run(b.system, q0, v0, scene.DT, 0.001, state_map=b.state_map, progress=False,
               checkpoint=prefix)


def test_stability_suite(tmp_path):
    """The documented stability command: L-OpInf stays symmetric and bounded on noisy and
    badly scaled data, and the two hopeless cases fail with clear messages."""
    from dolfinx_lopinf import stability

    rows = {r["case"]: r for r in stability.main(["--out", str(tmp_path / "s.json")])}
    for case, row in rows.items():
        if case.startswith("beam") and case.endswith("lopinf"):
            assert row["symmetric"] and row["min_real_eig_K"] > 0 and row["result"] == "bounded"
    assert rows["beam theta block x 1e8, lopinf"]["test_error"] < 1e-2
    assert "StepFailed" in rows["sine-Gordon FOM, dt = 5 (too large)"]["result"]
    assert "numerical rank 2" in rows["rank-deficient training data"]["result"]
