"""Shared fixtures. After each test, collect garbage and synchronise ranks so PETSc objects
are destroyed collectively (as DOLFINx's own test-suite does).

Rounding condition. With ``LOPINF_TEST_PERTURB=<delta>`` (e.g. 1e-15; ``make test-rounding``)
every floating-point array handed to the numerical core's entry points (the fits and the POD)
is multiplied by 1 + delta * N(0, 1), seeded by the array's bytes (so equal inputs stay equal).
That is what another BLAS, thread count or MPI layout does to the data; a test whose verdict
changes under it asserts something rounding decides.
"""

import functools
import gc
import hashlib
import importlib.util
import os
import sys

import numpy as np
import pytest

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
HAVE_DOLFINX = importlib.util.find_spec("dolfinx") is not None
PERTURB = float(os.environ.get("LOPINF_TEST_PERTURB", "0") or 0)
#: the numerical core's entry points whose array arguments are perturbed
PERTURBED_ENTRY_POINTS = ("infer_mechanical", "infer_opinf", "infer_wave", "infer_output", "pod",
                          "gram_data", "point_data", "midpoint_data", "identify")


def _perturbed(a):
    if isinstance(a, (list, tuple)):  # identify's pieces: [(Qh, times, U, ...), ...]
        return type(a)(_perturbed(x) for x in a)
    if not (isinstance(a, np.ndarray) and a.dtype.kind == "f" and a.size):
        return a
    seed = int.from_bytes(hashlib.blake2b(a.tobytes(), digest_size=8).digest(), "little")
    return a * (1.0 + PERTURB * np.random.default_rng(seed).standard_normal(a.shape))


def _perturbing(fn):
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        return fn(*(_perturbed(a) for a in args), **{k: _perturbed(v) for k, v in kwargs.items()})
    wrapper.__lopinf_perturbed__ = True
    return wrapper


@pytest.fixture(autouse=True, scope="session")
def _rounding_condition():
    """Install the perturbation in every loaded dolfinx_lopinf module (see the docstring)."""
    if not PERTURB:
        yield
        return
    import dolfinx_lopinf  # noqa: F401  (loads the numpy core)

    patched = []
    for name, module in list(sys.modules.items()):
        if not name.startswith("dolfinx_lopinf") or module is None:
            continue
        for attr in PERTURBED_ENTRY_POINTS:
            fn = getattr(module, attr, None)
            if callable(fn) and not getattr(fn, "__lopinf_perturbed__", False):
                patched.append((module, attr, fn))
                setattr(module, attr, _perturbing(fn))
    print(f"\nrounding condition: data at the core's entry points perturbed by {PERTURB:g} "
          f"relative ({len(patched)} entry points)")
    yield
    for module, attr, fn in patched:
        setattr(module, attr, fn)


@pytest.fixture(autouse=True)
def _collect():
    yield
    gc.collect()
    if HAVE_DOLFINX:
        from dolfinx_lopinf.fem._dolfinx import MPI

        MPI.COMM_WORLD.Barrier()


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="session")
def mpiexec():
    """The venv's mpiexec (the mpich wheel installs it beside python), else the one on PATH;
    the test is skipped without one."""
    import shutil

    exe = os.path.join(os.path.dirname(sys.executable), "mpiexec")
    found = exe if os.path.exists(exe) else shutil.which("mpiexec")
    if found is None:
        pytest.skip("no mpiexec")
    return found


@pytest.fixture
def serial_and_parallel(mpiexec, tmp_path):
    """run(script) -> the npz files ``script OUT.npz`` wrote on 1 and on 2 ranks."""
    import subprocess

    def run(script):
        serial, parallel = tmp_path / "serial.npz", tmp_path / "parallel.npz"
        subprocess.run([sys.executable, str(script), str(serial)], check=True, timeout=300)
        proc = subprocess.run([mpiexec, "-n", "2", sys.executable, str(script), str(parallel)],
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr[-3000:]
        return np.load(serial), np.load(parallel)
    return run


def load_demo(name):
    """The module demos/<name>.py (demos are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(f"demo_{name}", os.path.join(ROOT, "demos", f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def quick_demo(tmp_path_factory):
    """``quick_demo(name) -> (out_dir, metrics)``: ``demos/<name>.py --quick`` run in-process
    once per session (its ``main`` returns the metrics; they are read back from the written
    metrics.json, as a user would), shared by the demo's own tests and the serial half of the
    MPI check."""
    import json

    pytest.importorskip("dolfinx_lopinf.fem._dolfinx")
    cache = {}

    def run(name):
        if name not in cache:
            out = tmp_path_factory.mktemp(f"{name}_quick")
            load_demo(name).main(["--quick", "--out", str(out)])
            with open(out / "metrics.json") as f:
                cache[name] = (out, json.load(f))
        return cache[name]

    return run


@pytest.fixture(scope="session")
def beam():
    """The paper's beam (200 Hermite nodes, state in R^400)."""
    pytest.importorskip("dolfinx_lopinf.fem._dolfinx")
    from dolfinx_lopinf.scenes import beam as scene

    return scene.build(200)


class Killed(Exception):
    """Raised by ``interrupted_run``'s integrator step: the run dies as a killed process would."""


@pytest.fixture
def interrupted_run(monkeypatch):
    """``interrupted_run(system, q0, v0, prefix, kill_after, **run_kwargs)``: run the FOM with
    checkpoints and stop it (an exception from the step) after ``kill_after`` steps, leaving
    its checkpoint files behind."""
    import dolfinx_lopinf as lo

    def run(system, q0, v0, prefix, kill_after, **kw):
        original = lo.fem.MidpointIntegrator.step
        calls = {"n": 0}

        def step(self):
            calls["n"] += 1
            if calls["n"] > kill_after:
                raise Killed
            original(self)

        with monkeypatch.context() as m:
            m.setattr(lo.fem.MidpointIntegrator, "step", step)
            with pytest.raises(Killed):
                lo.run(system, q0, v0, progress=False, checkpoint=prefix, **kw)

    return run

