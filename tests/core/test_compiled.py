"""Compiled (numba) ROM loops against the numpy reference loops: trajectories to 1e-12."""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from dolfinx_lopinf.core import compiled
from dolfinx_lopinf.errors import InputError
from dolfinx_lopinf.core.rom import LagrangianROM, WaveROM

RTOL = 1e-12
needs_numba = pytest.mark.skipif(not compiled.available(), reason="numba not installed or JIT disabled")


def _rel(a, b):
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(a)), 1e-300))


def _linear_rom(scheme, r=5, m=2, mass=False, damped=True, outputs=True, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((r, r))
    K = A @ A.T + r * np.eye(r)
    M = None
    if mass:
        Bm = rng.standard_normal((r, r))
        M = np.eye(r) + 0.1 * Bm @ Bm.T
    C = 0.05 * np.eye(r) + 0.01 * (lambda X: X @ X.T)(rng.standard_normal((r, r))) if damped else None
    B = rng.standard_normal((r, m)) if m else None
    E = rng.standard_normal((3, r)) if outputs else None
    return LagrangianROM(K=K, M=M, C=C, B=B, E=E, scheme=scheme)


def _compare(a, b):
    assert a.backend == "numpy" and b.backend == "numba"
    np.testing.assert_array_equal(a.times, b.times)
    assert _rel(a.Qh, b.Qh) <= RTOL and _rel(a.Vh, b.Vh) <= RTOL
    if a.Y is not None:
        assert _rel(a.Y, b.Y) <= RTOL


@needs_numba
@pytest.mark.parametrize("scheme", ["midpoint", "newmark"])
@pytest.mark.parametrize("forcing", [None, "array", "callable"])
@pytest.mark.parametrize("every", [1, 7])
def test_linear_matches_numpy(scheme, forcing, every):
    """Every linear kind: midpoint / Newmark, unforced / array / callable inputs over several
    input chunks (n > 1024), outputs E, every-k sampling, a mass matrix and damping."""
    rom = _linear_rom(scheme, m=0 if forcing is None else 2, mass=scheme == "midpoint")
    n, dt = 2500, 0.01
    n_u = n if scheme == "midpoint" else n + 1
    t = dt * (np.arange(n_u) + (0.5 if scheme == "midpoint" else 0.0))
    U = np.vstack([np.sin(3 * t), np.cos(t) ** 2])
    inputs = {None: None, "array": U, "callable": lambda s: [np.sin(3 * s), np.cos(s) ** 2]}[forcing]
    q0, v0 = np.linspace(1, -1, rom.r), np.linspace(0, 0.5, rom.r)
    a = rom.simulate(q0, v0, dt, n, inputs=inputs, every=every, backend="numpy")
    b = rom.simulate(q0, v0, dt, n, inputs=inputs, every=every, backend="numba")
    _compare(a, b)
    assert a.Qh.shape == (rom.r, n // every + 1)


@needs_numba
def test_linear_auto_and_edge_cases():
    rom = _linear_rom("midpoint", m=0, damped=False, outputs=False)
    assert rom.simulate(np.ones(5), np.zeros(5), 0.1, 10).backend == "numba"  # auto
    for n, every in ((0, 1), (5, 10), (10, 10)):
        a = rom.simulate(np.ones(5), np.zeros(5), 0.1, n, every=every, backend="numpy")
        b = rom.simulate(np.ones(5), np.zeros(5), 0.1, n, every=every, backend="numba")
        _compare(a, b)


def _wave(r=6, n=120, ecsw=False, seed=1):
    rng = np.random.default_rng(seed)
    V = np.linalg.qr(rng.standard_normal((n, r)))[0] * np.sqrt(n / 8)
    L = rng.standard_normal((r, r))
    K = -(L @ L.T + np.diag(np.arange(1, r + 1.0) ** 2))
    w = None
    if ecsw:
        rows = np.sort(rng.choice(n, 23, replace=False))
        V, w = V[rows], rng.uniform(0.5, 2.0, len(rows))
    return K, V, w


@needs_numba
@pytest.mark.parametrize("ecsw", [False, True])
@pytest.mark.parametrize("jacobian", ["fresh", "lazy"])
@pytest.mark.parametrize("every", [1, 3])
def test_wave_matches_numpy(ecsw, jacobian, every):
    K, V, w = _wave(ecsw=ecsw)
    rom = WaveROM(K=K, V=V, g=np.sin, dg=np.cos, U=lambda z: 1 - np.cos(z), weights=w)
    v0 = np.linspace(1.5, -1.0, rom.r)
    a = rom.simulate(np.zeros(rom.r), v0, 0.01, 1500, every=every, jacobian=jacobian, backend="numpy")
    b = rom.simulate(np.zeros(rom.r), v0, 0.01, 1500, every=every, jacobian=jacobian, backend="numba")
    _compare(a, b)
    assert a.info == b.info  # the same Newton iterations and Jacobian refreshes
    if jacobian == "lazy":
        assert b.info["jacobians"] < b.info["newton_iterations"] / 10
        fresh = rom.simulate(np.zeros(rom.r), v0, 0.01, 1500, every=every, backend="numba")
        # simplified Newton: same stopping test |dq| <= 1e-12 max(|q|, 1); the converged
        # states agree to the Newton tolerance
        assert _rel(fresh.Qh, b.Qh) <= 1e-10


@needs_numba
def test_wave_nonlinearity_detection():
    K, V, w = _wave(ecsw=True)
    # sin and cos as other function objects (like nonlinear.identify's) still compile
    rom = WaveROM(K=K, V=V, g=lambda z: 0.0 - (0.0 - np.sin(z)), dg=lambda z: 1.0 * np.cos(z), U=np.cos,
                  weights=w)
    assert rom.simulate(np.zeros(rom.r), np.ones(rom.r), 0.01, 5).backend == "numba"
    cubic = WaveROM(K=K, V=V, g=lambda z: z**3, dg=lambda z: 3 * z**2, U=lambda z: z**4 / 4,
                    weights=w)
    assert cubic.simulate(np.zeros(rom.r), np.ones(rom.r), 0.01, 5).backend == "numpy"  # auto
    with pytest.raises(InputError, match="sine-Gordon"):
        cubic.simulate(np.zeros(rom.r), np.ones(rom.r), 0.01, 5, backend="numba")


@needs_numba
def test_wave_newton_failure_is_the_same():
    K, V, w = _wave()
    rom = WaveROM(K=K, V=V, g=np.sin, dg=np.cos, U=np.cos)
    msgs = []
    for backend in ("numpy", "numba"):
        with pytest.raises(RuntimeError, match="did not converge at step 1 ") as exc:
            rom.simulate(np.zeros(rom.r), np.ones(rom.r), 0.01, 5, max_newton=1, backend=backend)
        msgs.append(str(exc.value).split("|R|")[0])
    assert msgs[0] == msgs[1]


def test_bad_arguments():
    rom = _linear_rom("midpoint", m=0)
    for bad in ("jit", "NUMBA", None, 1):
        with pytest.raises(InputError, match="backend must be one of"):
            rom.simulate(np.ones(5), np.zeros(5), 0.1, 3, backend=bad)
    K, V, w = _wave()
    wave = WaveROM(K=K, V=V, g=np.sin, dg=np.cos, U=np.cos)
    with pytest.raises(InputError, match="jacobian must be"):
        wave.simulate(np.zeros(6), np.ones(6), 0.01, 3, jacobian="frozen")
    with pytest.raises(InputError, match="backend must be one of"):
        wave.simulate(np.zeros(6), np.ones(6), 0.01, 3, backend="c")


def test_jit_disabled_falls_back(monkeypatch):
    """DOLFINX_LOPINF_JIT=0: auto runs numpy, an explicit numba request is a clear error."""
    monkeypatch.setenv(compiled.JIT_ENV, "0")
    assert not compiled.available() and compiled.warm_up() is None
    rom = _linear_rom("newmark", m=1)
    tr = rom.simulate(np.ones(5), np.zeros(5), 0.1, 20, inputs=np.ones((1, 21)))
    assert tr.backend == "numpy"
    with pytest.raises(InputError, match="JIT is disabled"):
        rom.simulate(np.ones(5), np.zeros(5), 0.1, 20, inputs=np.ones((1, 21)), backend="numba")
    K, V, w = _wave()
    wave = WaveROM(K=K, V=V, g=np.sin, dg=np.cos, U=np.cos)
    assert wave.simulate(np.zeros(6), np.ones(6), 0.01, 20, jacobian="lazy").backend == "numpy"


def test_jit_disabled_never_imports_numba():
    code = textwrap.dedent("""
        import sys, numpy as np
        from dolfinx_lopinf.core.rom import LagrangianROM, WaveROM
        tr = LagrangianROM(K=np.eye(2)).simulate(np.ones(2), np.zeros(2), 0.1, 50)
        wv = WaveROM(K=-np.eye(2), V=np.eye(2), g=np.sin, dg=np.cos, U=np.cos).simulate(
            np.zeros(2), np.ones(2), 0.1, 50)
        assert tr.backend == wv.backend == "numpy"
        print("numba" in sys.modules)
    """)
    env = dict(os.environ, DOLFINX_LOPINF_JIT="0")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "False"


@needs_numba
def test_cache_fallback_when_nothing_is_writable(tmp_path):
    """A read-only install without a writable home: numba's own locators all fail, the cache
    moves under the system temp dir (root ignores permissions, so unwritable = a file where
    the directory should be)."""
    src = tmp_path / "pkg"
    src.mkdir()
    (src / "mod.py").write_text("def f(x):\n    return 2.0 * x\n")
    (src / "__pycache__").write_text("not a directory")
    blocked = tmp_path / "blocked"
    blocked.write_text("a file, so no cache directory can be made below it")
    code = textwrap.dedent(f"""
        import sys, numba
        sys.path.insert(0, {str(src)!r})
        import mod
        from dolfinx_lopinf.core import compiled
        f = compiled.jit(mod.f, "float64(float64)")
        assert f(2.0) == 4.0
        print(numba.config.CACHE_DIR)
    """)
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(HOME=str(blocked / "home"), XDG_CACHE_HOME=str(blocked / "cache"),
               PYTHONDONTWRITEBYTECODE="1")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == compiled._fallback_cache_dir()


@needs_numba
def test_warm_up_reports_seconds():
    s = compiled.warm_up()
    assert s is not None and s >= 0.0
    assert compiled.compile_seconds() is not None
