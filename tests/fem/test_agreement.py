"""Issue 27, every rank agrees: a bad or different argument on one rank raises the same error
on every rank (never a hang), an exception on one rank alone ends the job (never a hang), and
the pieces behind it (fem.agreement, the excepthook safety net) do what they say.

The 2-rank cases run tests/fem/mpi_disagree.py under mpiexec with a timeout."""

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

from dolfinx_lopinf.errors import InputError  # noqa: E402

SCRIPT = Path(__file__).with_name("mpi_disagree.py")
TIMEOUT = 120  # s: for every case of mpi_disagree.py on 2 ranks together, with a wide margin

# case -> (error class, a piece of the message) expected on BOTH ranks
CASES = {
    "run_dt": ("RanksDisagreeError", r"run: the ranks passed different arguments - dt \(rank 0: 0.001; rank 1: 0.002\)"),
    "run_t_end": ("RanksDisagreeError", r"t_end \(rank 0: 0.02; rank 1: 0.04\)"),
    "run_record_every": ("RanksDisagreeError", r"record_every \(rank 0: 1; rank 1: 2\)"),
    "run_t_end_not_whole_on_one_rank": ("InputError", r"not a whole number of steps.*\[found on rank 1 of 2"),
    "run_state_map": ("RanksDisagreeError", r"state_map \(rank 0: \(array of shape \(17,\) \(digest \w+\), array of shape \(17,\) \(sum 17,"),
    "loop_steps": ("RanksDisagreeError", r"n_steps \(rank 0: 7; rank 1: 10\)"),
    "loop_sinks": ("RanksDisagreeError", r"sinks \(rank 0: \[\]; rank 1: \['OutputProbe'\]\)"),
    "loop_bad_sink_one_rank": ("InputError", r"sinks\[0\] = 5 is neither a Sink"),
    "loop_closed": ("InputError", r"MidpointIntegrator was closed"),
    "step_input_one_rank": ("InputError", r"takes no input values.*\[found on rank 1 of 2"),
    "initialize_nan_one_rank": ("InputError", r"q0 contains NaN or inf \[found on rank 1 of 2"),
    "integrator_dt": ("RanksDisagreeError", r"MidpointIntegrator: .* dt \(rank 0: 0.001; rank 1: 0.002\)"),
    "newmark_inputs_differ": ("RanksDisagreeError", r"NewmarkIntegrator.step: .* input values"),
    "newmark_step_length": ("InputError", r"expected 1 input value\(s\).*got 2 \[found on rank 1"),
    "probe_nan_V_one_rank": ("InputError", r"V contains 1 NaN/inf entries.*\[found on rank 1 of 2"),
    "probe_Q_differs": ("RanksDisagreeError", r"probe: .* - Q \(rank 0: array of shape \(2, 3\) \(sum 6, max \|.\| 1\); rank 1: array of shape \(2, 3\) \(sum 12, max \|.\| 2\)\)"),
    "points_differ": ("RanksDisagreeError", r"point_output_matrix: .* points"),
    "points_nan_one_rank": ("InputError", r"points contain NaN or inf.*\[found on rank 1 of 2"),
    "reduced_matrix_basis_differs": ("RanksDisagreeError", r"reduced_matrix: .* basis"),
    "pod_append_nan_one_rank": ("InputError", r"snapshot 3 contains NaN or inf \[found on rank 1"),
    "pod_r_differs": ("RanksDisagreeError", r"StreamingPOD.compute: .* r \(rank 0: 1; rank 1: 2\)"),
    "galerkin_basis_nan_one_rank": ("InputError", r"basis contains 1 NaN/inf entries.*\[found on rank 1"),
    "galerkin_q_differs": ("RanksDisagreeError", r"GalerkinForce: .* q \(rank 0"),
    "recorder_scheme_one_rank": ("InputError", r"SnapshotRecorder arguments differ between ranks \(scheme, order\)"),
    "recorder_time_differs": ("InputError", r"record\(\) called with different times or inputs on different ranks \(\[\(0.001, None\), \(0.002, None\)\]\)"),
    "vtx_engine_differs": ("RanksDisagreeError", r"write_vtx: .* engine \(rank 0: 'BP4'; rank 1: 'BP5'\)"),
    "vtx_unrelated_folder": ("InputError", r"photos.bp' exists and is not a VTX .bp folder.*IMG_001.jpg"),
}


def _mpirun(mpiexec, which, logs: Path, timeout=TIMEOUT, **env):
    """(return code or None on timeout, output, seconds) of mpi_disagree.py ``which`` on 2 ranks;
    the output is the job's stdout and stderr, then each rank's own log (whole lines)."""
    environment = {**os.environ, **env}
    logs.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    try:
        proc = subprocess.run([mpiexec, "-n", "2", sys.executable, str(SCRIPT), which, str(logs)],
                              capture_output=True, text=True, timeout=timeout, env=environment)
        rc, out = proc.returncode, proc.stdout + proc.stderr
    except subprocess.TimeoutExpired as exc:
        rc, out = None, "".join(x.decode() if isinstance(x, bytes) else x
                                for x in (exc.stdout or "", exc.stderr or ""))
    seconds = time.perf_counter() - t0
    out += "".join("\n" + log.read_text() for log in sorted(logs.glob("rank*.txt")))
    return rc, out, seconds


@pytest.fixture(scope="module")
def disagreeing(mpiexec, tmp_path_factory):
    """Every case of mpi_disagree.py on 2 ranks, once: (results {case: {rank: line}}, output,
    return code, seconds)."""
    logs = tmp_path_factory.mktemp("disagree")
    rc, out, seconds = _mpirun(mpiexec, "agree", logs)
    results: dict = {}
    lines = "".join(log.read_text() for log in sorted(logs.glob("rank*.txt")))
    for m in re.finditer(r"^RESULT (\S+) rank=(\d) (.*)$", lines, re.M):
        results.setdefault(m[1], {})[int(m[2])] = m[3]
    print(f"\n2-rank disagreement cases: {seconds:.1f} s (return code {rc})")
    return results, out, rc, seconds


@pytest.mark.mpi
@pytest.mark.parametrize("name", list(CASES))
def test_two_ranks_raise_the_same_error(disagreeing, name):
    results, out, rc, _ = disagreeing
    started = re.findall(r"^START (\S+)", out, re.M)
    assert name in results and set(results[name]) == {0, 1}, (
        f"no result from both ranks for {name} (return code {rc}; last case started: "
        f"{started[-1] if started else None}): a hang or a crash\n{out[-3000:]}")
    cls, pattern = CASES[name]
    assert results[name][0] == results[name][1], results[name]  # the same text on both ranks
    assert results[name][0].startswith(cls + ":"), results[name][0]
    assert re.search(pattern, results[name][0]), results[name][0]


@pytest.mark.mpi
def test_all_cases_ran_and_nothing_was_lost(disagreeing):
    results, out, rc, _ = disagreeing
    assert rc == 0, out[-3000:]
    assert set(results) == set(CASES)
    assert "ALL DONE rank=0" in out and "ALL DONE rank=1" in out
    assert "PHOTOS ['IMG_001.jpg']" in out  # the unrelated folder was left alone


@pytest.mark.mpi
def test_uncaught_exception_on_one_rank_aborts_instead_of_hanging(mpiexec, tmp_path):
    """lo.fit refuses rank 1's data (uncaught) while rank 0 waits in a barrier: the safety net
    aborts the job with rank 1's traceback (on main: a hang until killed)."""
    rc, out, seconds = _mpirun(mpiexec, "fit", tmp_path, timeout=90)
    assert rc is not None, f"hung for {seconds:.0f} s\n{out[-2000:]}"
    assert rc != 0
    assert "rank 1 of 2 stopped on the uncaught InputError above (Q contains 1 non-finite value" in out
    assert "PASSED THE BARRIER" not in out


@pytest.mark.mpi
def test_exception_on_one_rank_inside_the_loop_aborts_instead_of_hanging(mpiexec, tmp_path):
    """A sink raises on rank 1 only (and the user catches it): the other rank is in the next
    step's solve; run's region notices that rank 0 never failed and aborts the job."""
    rc, out, seconds = _mpirun(mpiexec, "sink_one", tmp_path, timeout=90, LOPINF_MPI_TIMEOUT="3")
    assert rc is not None, f"hung for {seconds:.0f} s\n{out[-2000:]}"
    assert rc != 0
    assert "sink failed at step 3 on rank 1" in out
    assert "rank 1 of 2 raised the RuntimeError above (sink failed at step 3 on rank 1) in run" in out
    assert "DONE rank=" not in out


@pytest.mark.mpi
def test_snapshots_reached_late_by_one_rank_is_named(mpiexec, tmp_path):
    """rank 1 reaches rec.snapshots() 4 s after rank 0 (the pattern of a call made on rank 0
    only): rank 0 says why it waits after LOPINF_MPI_TIMEOUT (1 s) and both finish."""
    rc, out, seconds = _mpirun(mpiexec, "late", tmp_path, timeout=90, LOPINF_MPI_TIMEOUT="1")
    assert rc == 0, out[-2000:]
    assert "rank 0 of 2 has waited 1 s in SnapshotRecorder.snapshots() for the other ranks" in out
    assert "call it on every rank" in out
    assert "LATE DONE rank=0 (" in out and "LATE DONE rank=1 None" in out


@pytest.mark.mpi
def test_exception_on_every_rank_is_raised_on_every_rank(mpiexec, tmp_path):
    """The same sink failing on both ranks: each raises it, the program goes on (no abort)."""
    rc, out, seconds = _mpirun(mpiexec, "sink_all", tmp_path, timeout=90, LOPINF_MPI_TIMEOUT="3")
    assert rc == 0, out[-2000:]
    for r in (0, 1):
        assert f"RESULT sink rank={r} RuntimeError: sink failed at step 3 on rank {r}" in out
        assert f"DONE rank={r}" in out


# -- the pieces, on one rank ------------------------------------------------------------------

class FakeComm:
    """A 2-rank communicator whose other rank's allgather contribution is given."""

    size, rank = 2, 0

    def __init__(self, other):
        self.other = other

    def allgather(self, mine):
        return [mine, self.other]


def _other(problem=None, **settings):
    from dolfinx_lopinf.fem.agreement import digest

    return (problem, {k: digest(v) for k, v in settings.items()})


def test_agree_names_each_differing_setting_and_every_rank():
    from dolfinx_lopinf.errors import RanksDisagreeError
    from dolfinx_lopinf.fem.agreement import agree

    comm = FakeComm(_other(dt=0.002, n=3, name="u"))
    with pytest.raises(RanksDisagreeError, match=r"run: .* dt \(rank 0: 0.001; rank 1: 0.002\), "
                                                  r"n \(rank 0: 4; rank 1: 3\)\. Every rank") as info:
        agree(comm, "run", None, dt=0.001, n=4, name="u")
    assert getattr(info.value, "__lopinf_collective__", False)
    agree(FakeComm(_other(dt=np.float64(0.001), a=np.arange(3.0))), "run", None, dt=0.001,
          a=np.arange(3.0))  # equal values of other types agree


def test_agree_raises_another_ranks_problem_with_its_class():
    from dolfinx_lopinf.errors import FileFormatError
    from dolfinx_lopinf.fem.agreement import agree

    comm = FakeComm(_other(("dolfinx_lopinf.errors", "FileFormatError", "chunk 3 is corrupt")))
    with pytest.raises(FileFormatError, match=r"chunk 3 is corrupt \[found on rank 1 of 2; raised "
                                              r"on every rank\]"):
        agree(comm, "run", None, dt=1.0)
    comm = FakeComm(_other(("builtins", "ZeroDivisionError", "division by zero")))
    with pytest.raises(InputError, match="ZeroDivisionError: division by zero"):
        agree(comm, "run", None)
    with pytest.raises(InputError, match="mine"):  # the lowest failing rank's problem first
        agree(FakeComm(_other(("builtins", "ValueError", "theirs"))), "run", "mine")


def test_digest_tells_values_apart_but_not_rounding():
    """Rounding differences between ranks (1e-15) must not decide a verdict; real ones must."""
    from dolfinx_lopinf.fem.agreement import digest, same

    def eq(a, b):
        return same(digest(a)[0], digest(b)[0])

    a = np.random.default_rng(0).standard_normal((300, 7))
    rounded = a * (1 + 1e-15 * np.random.default_rng(1).standard_normal(a.shape))
    assert eq(a, a.copy()) and eq(a, rounded) and eq(0.001, 0.001 * (1 + 1e-15))
    for other in (a * (1 + 1e-6), a[::-1].copy(), -a, np.where(np.arange(7) == 3, -a, a),
                  a.T.copy(), a[:, :6].copy(), a + 1e-6 * np.eye(300, 7)):
        assert not eq(a, other)
    swapped = a.copy()
    swapped[[10, 11]] = swapped[[11, 10]]  # two rows exchanged
    assert not eq(a, swapped)
    assert not eq(0.001, 0.002) and eq(np.nan, float("nan"))
    small = np.array([1.0, 1e-17, 3.0])  # small arrays: entry by entry, to 1e-10 of the largest
    assert eq(small, np.array([1.0, -2e-17, 3.0 * (1 + 1e-15)]))
    assert not eq(small, np.array([1.0, 1e-6, 3.0])) and not eq(small, small[:2].copy())
    assert eq({"ksp_type": "cg", "rtol": 1e-8}, {"rtol": 1e-8, "ksp_type": "cg"})
    assert not eq({"ksp_type": "cg"}, {"ksp_type": "gmres"})
    assert eq(np.int64(3), 3) and not eq(3, 3.0) and not eq(np.arange(5), np.arange(5)[::-1].copy())
    assert eq((np.arange(4), a), (np.arange(4), rounded)) and not eq([1, 2], (1, 2))


def test_together_on_one_rank_is_transparent():
    from dolfinx_lopinf.fem._dolfinx import MPI
    from dolfinx_lopinf.fem.agreement import together

    with pytest.raises(KeyError):
        with together(MPI.COMM_SELF, "x"):
            raise KeyError("k")
    with together(MPI.COMM_SELF, "x"):
        pass


def test_safety_net_is_installed_only_on_several_ranks_and_never_over_a_users_hook(monkeypatch):
    from dolfinx_lopinf import _mpi_abort

    monkeypatch.setattr(sys, "excepthook", sys.__excepthook__)
    assert _mpi_abort.install() is False  # one rank (this pytest process): nothing to guard
    assert sys.excepthook is sys.__excepthook__

    class World:  # a fake 2-rank MPI
        class COMM_WORLD:
            aborted = []

            @staticmethod
            def Get_size():
                return 2

            @staticmethod
            def Get_rank():
                return 1

            @classmethod
            def Abort(cls, code):
                cls.aborted.append(code)

        Is_initialized = staticmethod(lambda: True)
        Is_finalized = staticmethod(lambda: False)

    monkeypatch.setitem(sys.modules, "mpi4py.MPI", World)
    users = lambda *a: None  # noqa: E731
    monkeypatch.setattr(sys, "excepthook", users)
    assert _mpi_abort.install() is False and sys.excepthook is users  # the user's hook stays
    monkeypatch.setattr(sys, "excepthook", sys.__excepthook__)
    monkeypatch.setenv("LOPINF_MPI_ABORT", "0")
    assert _mpi_abort.install() is False
    monkeypatch.delenv("LOPINF_MPI_ABORT")
    assert _mpi_abort.install() is True and sys.excepthook is _mpi_abort._hook
    try:
        raise InputError("only on this rank")
    except InputError as exc:
        _mpi_abort._hook(type(exc), exc, exc.__traceback__)
    assert World.COMM_WORLD.aborted == [1]
    collective = InputError("on every rank")
    collective.__lopinf_collective__ = True
    _mpi_abort._hook(InputError, collective, None)  # every rank raises it: no abort
    assert World.COMM_WORLD.aborted == [1]
