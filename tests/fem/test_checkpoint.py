"""No lost work: a FOM run killed mid-way resumes from its last checkpoint and produces the
same snapshots as an unbroken run."""

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

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


def test_checkpoint_of_an_older_format_is_refused_with_its_name(tmp_path):
    import dolfinx_lopinf as lo
    from dolfinx_lopinf.errors import FileFormatError
    from dolfinx_lopinf.scenes import beam as scene

    b = scene.build(200)
    q0, v0 = b.initial_state()
    prefix = tmp_path / "c"
    np.savez(f"{prefix}.rank0.npz", settings=np.zeros(9), k=1)  # the format before issue 13
    with pytest.raises(FileFormatError, match=r"c\.rank0\.npz.*checkpoint_restart=True"):
        lo.run(b.system, q0, v0, scene.DT, 0.001, state_map=b.state_map, progress=False,
               checkpoint=prefix)


def test_stale_checkpoint_of_another_run_is_refused(tmp_path, interrupted_run):
    """A parameter sweep reusing a prefix: the run with EI doubled must not resume the killed
    run with the paper's EI (issue 13, item 1); nor a run from another initial state."""
    import dolfinx_lopinf as lo
    from dolfinx_lopinf.errors import CheckpointMismatchError
    from dolfinx_lopinf.scenes import beam as scene

    kw = dict(dt=scene.DT, t_end=0.004, record_every=10, checkpoint_every=100)
    b = scene.build(60)
    q0, v0 = b.initial_state()
    prefix = tmp_path / "sweep"
    interrupted_run(b.system, q0, v0, prefix, 250,
                     state_map=b.state_map, **kw)
    assert Path(f"{prefix}.rank0.npz").exists()
    stiff = scene.build(60, ei=2 * scene.EI)
    with pytest.raises(CheckpointMismatchError, match="step residual") as err:
        lo.run(stiff.system, q0, v0, state_map=stiff.state_map, progress=False,
               checkpoint=prefix, **kw)
    assert "initial state" not in str(err.value) and "checkpoint_restart" in str(err.value)
    q0_other, _ = b.initial_state(a=0.5)
    with pytest.raises(CheckpointMismatchError, match=r"initial state q0") as err:
        lo.run(b.system, q0_other, v0, state_map=b.state_map, progress=False,
               checkpoint=prefix, **kw)
    assert "residual" not in str(err.value)
    with pytest.raises(CheckpointMismatchError, match="record_every: 10 in the checkpoint, 20"):
        lo.run(b.system, q0, v0, state_map=b.state_map, progress=False, checkpoint=prefix,
               **dict(kw, record_every=20))
    # the same run resumes (from step 200) and equals an unbroken run; restart starts over
    snaps, info = lo.run(b.system, q0, v0, state_map=b.state_map, progress=False,
                         checkpoint=prefix, **kw)
    ref, _ = lo.run(b.system, q0, v0, state_map=b.state_map, progress=False, **kw)
    assert info["resumed_from_step"] == 200
    assert np.array_equal(snaps.Q, ref.Q) and np.array_equal(snaps.V, ref.V)
    assert np.array_equal(snaps.energy, ref.energy)
    interrupted_run(stiff.system, q0, v0, prefix, 150,
                     state_map=stiff.state_map, **kw)
    _, info = lo.run(b.system, q0, v0, state_map=b.state_map, progress=False,
                     checkpoint=prefix, checkpoint_restart=True, **kw)
    assert info["resumed_from_step"] == 0
    assert not list(tmp_path.glob("sweep*"))


def test_stability_suite(tmp_path):
    """The documented stability command: L-OpInf stays symmetric and bounded on noisy and
    badly scaled data, and the two hopeless cases fail with clear messages."""
    from dolfinx_lopinf.studies import stability

    rows = {r["case"]: r for r in stability.main(["--out", str(tmp_path / "s.json")])}
    for case, row in rows.items():
        if case.startswith("beam") and case.endswith("lopinf"):
            assert row["symmetric"] and row["min_real_eig_K"] > 0 and row["result"] == "bounded"
    assert rows["beam theta block x 1e8, lopinf"]["test_error"] < 1e-2
    assert "StepFailed" in rows["sine-Gordon FOM, dt = 5 (too large)"]["result"]
    deficient = rows["rank-deficient training data"]
    assert "rank 2 < 3" in deficient["result"] and "strict=True: RankDeficientDataError" in deficient["result"]
    assert deficient["symmetric"] and deficient["min_real_eig_K"] >= 1e-8
    assert deficient["fit_relative_residual"] < 1e-3
