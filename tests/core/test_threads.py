"""lo.fit's candidates on threads: the same fit as on one thread, bit for bit, and the thread
count (environment, cores, MPI ranks). After test_mass in the suite's order, so the compiled
learned-mass kernels are built by then (no extra build here on a fresh machine)."""

import warnings
from pathlib import Path

import numpy as np
import pytest

import dolfinx_lopinf as lo


def test_candidates_on_threads_give_the_serial_fit_bit_for_bit(monkeypatch):
    """From r = PARALLEL_FROM_R on, lo.fit fits its candidates on threads (the compiled
    kernels release the GIL): every candidate's held-back error, the choice and the final
    operators are those of the one-thread run, to the last bit; the work did run on the pool."""
    import importlib
    import threading

    from dolfinx_lopinf.core import compiled
    from dolfinx_lopinf.core.lsq import _fractional_compiled

    F = importlib.import_module("dolfinx_lopinf.core.fit")
    if compiled.available():  # both runs on the compiled (GIL-free) iteration, not one on the
        _fractional_compiled.warm_up()  # numpy path while a cold cache builds in the background
    d = np.load(Path(__file__).with_name("data") / "own_loop_newmark_pod64.npz")
    train = lo.Snapshots(d["train_times"], d["train_Q"], U=d["train_U"])
    seen = set()
    original = F._fit_relation

    def spy(*args, **kwargs):
        seen.add(threading.current_thread().name.split("_")[0])
        return original(*args, **kwargs)

    monkeypatch.setattr(F, "_fit_relation", spy)
    models = {}
    for threads in ("1", "2"):
        monkeypatch.setenv(F.FIT_THREADS_ENV, threads)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            models[threads] = lo.fit(train, F.PARALLEL_FROM_R)
    assert "lopinf-candidate" in seen and "MainThread" in seen
    one, two = models["1"], models["2"]
    assert one.report["candidate_errors"] == two.report["candidate_errors"]
    assert one.report["why"] == two.report["why"]
    for name in ("M", "K", "C", "B"):
        a, b = getattr(one.rom, name), getattr(two.rom, name)
        assert (a is None and b is None) or np.array_equal(a, b), name


@pytest.mark.parametrize("value", ["0", "two", "-1"])
def test_a_bad_thread_count_is_named(monkeypatch, value):
    import importlib

    F = importlib.import_module("dolfinx_lopinf.core.fit")
    monkeypatch.setenv(F.FIT_THREADS_ENV, value)
    with pytest.raises(lo.errors.InputError, match=F.FIT_THREADS_ENV):
        F.fit_threads()
    monkeypatch.setenv(F.FIT_THREADS_ENV, "3")
    assert F.fit_threads() == 3


def test_fit_threads_are_shared_among_mpi_ranks(monkeypatch):
    """Under MPI (mpi4py initialised) each rank takes its share of the cores, at least one."""
    import importlib
    import os
    import sys
    import types

    F = importlib.import_module("dolfinx_lopinf.core.fit")
    monkeypatch.delenv(F.FIT_THREADS_ENV, raising=False)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(8)), raising=False)
    fake = types.SimpleNamespace(Is_initialized=lambda: True, Is_finalized=lambda: False,
                                 COMM_WORLD=types.SimpleNamespace(size=3))
    monkeypatch.setitem(sys.modules, "mpi4py.MPI", fake)
    assert F.fit_threads() == 2
    fake.COMM_WORLD.size = 16
    assert F.fit_threads() == 1
    monkeypatch.delitem(sys.modules, "mpi4py.MPI")
    assert F.fit_threads() == 8


class _Comm:
    """A communicator stand-in: ``size`` ranks, all on this node."""

    def __init__(self, size):
        self.size = size

    def Split_type(self, kind):
        return self

    def Free(self):
        pass


def test_ranks_share_the_cores_blas_threads(monkeypatch):
    """Under MPI each rank's BLAS gets its share of the cores, max(1, cores // ranks on the
    node) - unless the user set the threads; one rank, nothing; the cap is undone on request."""
    import os

    from threadpoolctl import threadpool_info

    from dolfinx_lopinf.core import _blas

    def blas_threads():
        return {i["filepath"]: i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}

    before = blas_threads()
    cores = len(os.sched_getaffinity(0))
    for name in _blas.THREAD_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(_blas, "_comm_type_shared", lambda comm: 0)
    monkeypatch.setattr(_blas, "_SHARED", {})
    assert _blas.share_cores_among_ranks(_Comm(1)) is None and _blas._SHARED == {}
    try:
        assert _blas.share_cores_among_ranks(_Comm(2 * cores)) == 1
        assert max(blas_threads().values()) == 1
        assert _blas.share_cores_among_ranks(_Comm(2)) == 1  # once per process
    finally:
        _blas._SHARED["limit"].restore_original_limits()
    assert blas_threads() == before
    monkeypatch.setattr(_blas, "_SHARED", {})
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    assert _blas.share_cores_among_ranks(_Comm(2 * cores)) is None
    assert blas_threads() == before
