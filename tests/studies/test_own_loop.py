"""demos/own_loop.py in quick mode: a tutorial-style dolfinx cantilever (Q2 hexahedra,
LinearProblem + MUMPS, UFL-expression updates, a body force) with two integrators, recorded
by SnapshotRecorder and fitted by lo.fit(scheme=auto/newmark/continuous).

Measured on the quick mesh (459 dofs, numbers at commit time; the margins below are >= 3x):

* Newmark loop, Euclidean POD, the black-box default (mass="auto"): the learned reduced mass
  predicts the held-back end 10-170x better than Mh = I, auto takes it with the Newmark
  relation, and the unseen-load tip error is 2.9e-3 / 7.9e-4 / 5.9e-5 at r = 2 / 4 / 8
  (Mh = I forced: 9e-3 to 1.3e-2, and the scheme choice is a near-tie there).
* Newmark loop, mass-orthonormal POD (reduced mass exactly I): auto keeps Mh = I and picks
  "newmark" at every r (held-back 9.5e-6 vs 5.8e-4 at r = 4); unseen 2.0e-3 / 4.5e-5 / 9.8e-7.
* Generalised-alpha loop: it obeys neither relation; its best held-back error is ~300x the
  Newmark loop's (auto picks newmark; "continuous" predicts the unseen load better there,
  2.4e-3 vs 4.2e-3 with the learned mass: recorded, not asserted).
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / "demos" / "own_loop.py"


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("own_loop")
    proc = subprocess.run([sys.executable, str(DEMO), "--quick", "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, json.loads((out / "metrics.json").read_text())


def _rows(metrics, integrator, basis, mass="auto"):
    """(requested scheme, r) -> row of the fits in ``basis`` with reduced mass ``mass``."""
    return {(x["requested"], x["r"]): x for x in metrics["loops"][integrator]["roms"]
            if x["basis"] == basis and x["mass"] == mass}


@pytest.mark.slow
def test_outputs_written(quick):
    out, m = quick
    assert m["scene"] == "own_loop_cantilever" and set(m["loops"]) == {"newmark", "gen-alpha"}
    for integrator, loop in m["loops"].items():
        assert loop["n_dofs"] == 459 and loop["fom_seconds"] > 0
        # the body force moves the tip visibly, and the unseen load differs from training
        assert 1e-3 < loop["max_abs_tip_test"] < 0.05 and 1e-3 < loop["max_abs_tip_train"] < 0.05
        assert {(x["basis"], x["mass"], x["requested"], x["r"]) for x in loop["roms"]} == {
            (b, mm, s, r) for b, mm in (("euclidean", "auto"), ("euclidean", "identity"),
                                        ("euclidean", "learned"), ("mass-orthonormal", "auto"))
            for s in ("auto", "newmark", "continuous") for r in (2, 4, 8)}
        for name in ("tip", "tip_error"):
            png = out / f"{name}_{integrator}.png"
            assert png.stat().st_size > 10_000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        for split in ("train", "test"):
            assert (out / f"{split}_{integrator}.npz").exists()


@pytest.mark.slow
def test_every_rom_is_stable_and_close(quick):
    _, m = quick
    for loop in m["loops"].values():
        for x in loop["roms"]:
            assert x["stable"], x
            assert x["test_error"] < 4e-2, x  # measured <= 1.3e-2 on every row


@pytest.mark.slow
def test_newmark_loop_auto_finds_newmark_in_mass_orthonormal_basis(quick):
    _, m = quick
    rows = _rows(m, "newmark", "mass-orthonormal")
    for r in (2, 4, 8):
        auto, nm, fd = rows[("auto", r)], rows[("newmark", r)], rows[("continuous", r)]
        assert auto["scheme"] == "newmark", auto["scheme_errors"]
        assert auto["mass_chosen"] == "identity"  # exact in this basis: no SDP needed
        assert auto["test_error"] <= 1.5 * min(nm["test_error"], fd["test_error"])
        if r >= 4:  # the loop obeys the three-point relation: measured 62x and 1100x
            errors = auto["scheme_errors"]
            assert errors["continuous"] > 10 * errors["newmark"], errors
    assert rows[("auto", 2)]["test_error"] < 8e-3    # measured 2.0e-3
    assert rows[("auto", 4)]["test_error"] < 5e-4    # measured 4.5e-5 (target 5e-3)
    assert rows[("auto", 8)]["test_error"] < 5e-5    # measured 9.8e-7


@pytest.mark.slow
def test_newmark_loop_black_box_default_meets_the_target(quick):
    """Euclidean POD, lo.fit's defaults (scheme="auto", mass="auto"): the learned reduced mass
    and the Newmark relation are chosen, and the unseen-load error is far below Mh = I's."""
    _, m = quick
    rows = _rows(m, "newmark", "euclidean")
    identity = _rows(m, "newmark", "euclidean", "identity")
    for r in (2, 4, 8):
        auto = rows[("auto", r)]
        assert (auto["mass_chosen"], auto["scheme"]) == ("learned", "newmark"), auto
        best_identity = min(identity[(s, r)]["test_error"] for s in ("newmark", "continuous"))
        assert auto["test_error"] < 0.5 * best_identity, (auto, best_identity)  # 3x-170x
    assert rows[("auto", 4)]["test_error"] < 5e-3    # the target; measured 7.9e-4
    assert rows[("auto", 8)]["test_error"] < 1e-3    # measured 5.9e-5


@pytest.mark.slow
def test_generalised_alpha_obeys_neither_relation(quick):
    _, m = quick
    nm_loop = _rows(m, "newmark", "mass-orthonormal")[("auto", 4)]["scheme_errors"]
    ga_loop = _rows(m, "gen-alpha", "mass-orthonormal")[("auto", 4)]["scheme_errors"]
    # measured: 5.6e-3 (best relation on the gen-alpha data) vs 9.5e-6
    assert min(ga_loop.values()) > 30 * nm_loop["newmark"], (ga_loop, nm_loop)


@pytest.mark.mpi
def test_two_ranks_give_the_serial_figures(quick, tmp_path, mpiexec):
    """The recorder gathers to rank 0: the Newmark loop under mpiexec -n 2 reports the
    serial errors and choices."""
    proc = subprocess.run([mpiexec, "-n", "2", sys.executable, str(DEMO), "--quick",
                           "--integrator", "newmark", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    par = json.loads((tmp_path / "metrics.json").read_text())
    assert par["ranks"] == 2
    serial = quick[1]["loops"]["newmark"]["roms"]
    for a, b in zip(serial, par["loops"]["newmark"]["roms"]):
        assert (a["basis"], a["mass"], a["requested"], a["r"], a["scheme"]) == \
            (b["basis"], b["mass"], b["requested"], b["r"], b["scheme"])
        assert a.get("mass_chosen") == b.get("mass_chosen")
        if "learned" in (a["mass"], a.get("mass_chosen")):  # the SDP's answer moves with rounding
            continue  # -level data changes (full mesh, r = 8: 9.3e-5 on 1 rank, 5.1e-6 on 2)
        assert b["test_error"] == pytest.approx(a["test_error"], rel=1e-3, abs=1e-8)
    assert np.isclose(par["loops"]["newmark"]["max_abs_tip_test"],
                      quick[1]["loops"]["newmark"]["max_abs_tip_test"], rtol=1e-8)
