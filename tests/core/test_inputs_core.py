"""Issue 13, numpy core: every input checked at the door, every file written atomically.

Each test names the defect it covers (the item number of issue 13); each failed on the code
before the fix. numpy (+ scipy) only, no DOLFINx.
"""

import os
import tracemalloc
import warnings

import numpy as np
import pytest

import dolfinx_lopinf as lo
from dolfinx_lopinf.errors import FileFormatError, InputError


def _snaps(n=4, k=30, seed=0):
    rng = np.random.default_rng(seed)
    return lo.Snapshots(times=np.linspace(0, 1, k), Q=rng.standard_normal((n, k)),
                        blocks={"a": np.arange(n // 2), "b": np.arange(n // 2, n)})


def _fail_half_way(monkeypatch):
    """Make np.savez / np.savez_compressed write some bytes, then fail like a full disk."""

    def broken(file, *args, **kwargs):
        if hasattr(file, "write"):
            file.write(b"PK\x03\x04 half a zip")
        else:
            name = os.fspath(file)
            name = name if name.endswith(".npz") else name + ".npz"
            with open(name, "wb") as f:
                f.write(b"PK\x03\x04 half a zip")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez", broken)
    monkeypatch.setattr(np, "savez_compressed", broken)


# -- 4. atomic saves ----------------------------------------------------------------------

def test_item4_snapshots_save_interrupted_keeps_the_previous_file(tmp_path, monkeypatch):
    old = _snaps(seed=1)
    path = old.save(tmp_path / "s.npz")
    with monkeypatch.context() as m:
        _fail_half_way(m)
        with pytest.raises(OSError, match="No space"):
            _snaps(seed=2).save(tmp_path / "s.npz")
    assert sorted(os.listdir(tmp_path)) == ["s.npz"]  # no temporary file left behind
    assert np.array_equal(lo.Snapshots.load(path).Q, old.Q)


def test_item4_save_rom_interrupted_keeps_the_previous_file(tmp_path, monkeypatch):
    old = lo.core.LagrangianROM(K=np.diag([1.0, 2.0]))
    path = lo.core.rom.save_rom(tmp_path / "rom.npz", old)
    with monkeypatch.context() as m:
        _fail_half_way(m)
        with pytest.raises(OSError, match="No space"):
            lo.core.rom.save_rom(tmp_path / "rom.npz", lo.core.LagrangianROM(K=np.diag([3.0, 4.0])))
    assert sorted(os.listdir(tmp_path)) == ["rom.npz"]
    assert np.array_equal(lo.core.rom.load_rom(path)[0].K, old.K)


def test_item4_snapshots_save_returns_the_path_it_wrote(tmp_path):
    s = _snaps()
    path = s.save(tmp_path / "x")
    assert path == tmp_path / "x.npz" and path.exists()
    assert sorted(os.listdir(tmp_path)) == ["x.npz"]
    assert np.array_equal(lo.Snapshots.load(path).Q, s.Q)
    assert lo.core.rom.save_rom(tmp_path / "r", lo.core.LagrangianROM(K=[[1.0]])) == tmp_path / "r.npz"


def test_item4_atomic_writer(tmp_path, monkeypatch):
    from dolfinx_lopinf.core import io_atomic

    path = io_atomic.atomic_savez(tmp_path / "a", x=np.arange(3))
    assert path == tmp_path / "a.npz"
    with np.load(path) as data:
        assert np.array_equal(data["x"], np.arange(3))
    mode = os.stat(path).st_mode & 0o777
    umask = os.umask(0)
    os.umask(umask)
    assert mode == 0o666 & ~umask  # same permissions as a plain np.savez
    text = io_atomic.atomic_write_text(tmp_path / "m.json", '{"a": 1}')
    assert text.read_text() == '{"a": 1}'

    def boom(f):
        f.write(b"partial")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        io_atomic.atomic_write(tmp_path / "m.json", boom)
    assert text.read_text() == '{"a": 1}' and sorted(os.listdir(tmp_path)) == ["a.npz", "m.json"]


# -- 6. blocks -------------------------------------------------------------------------

def test_item6_pod_refuses_overlapping_and_incomplete_blocks():
    Q = np.random.default_rng(0).standard_normal((10, 30))
    with pytest.raises(InputError, match=r"overlap.*'a'.*'b'.*4, 5"):
        lo.pod(Q, 4, blocks={"a": np.arange(6), "b": np.arange(4, 10)})
    with pytest.raises(InputError, match=r"no block.*3, 4"):
        lo.pod(Q, 4, blocks={"a": np.arange(3), "b": np.arange(5, 10)})
    with pytest.raises(InputError, match="repeats row"):
        lo.pod(Q, 2, blocks={"a": [0, 1, 1, 2, 3, 4], "b": np.arange(5, 10)})
    with pytest.raises(InputError, match="outside"):
        lo.pod(Q, 2, blocks={"a": np.arange(5), "b": np.arange(5, 11)})
    V = lo.pod(Q, 4, blocks={"a": np.arange(0, 10, 2), "b": np.arange(1, 10, 2)}).V
    assert np.allclose(V.T @ V, np.eye(4), atol=1e-13)  # a valid partition still works


def test_item6_snapshots_refuse_overlapping_and_incomplete_blocks():
    t, Q = np.linspace(0, 1, 30), np.zeros((10, 30))
    with pytest.raises(InputError, match="overlap"):
        lo.Snapshots(t, Q, blocks={"a": np.arange(6), "b": np.arange(4, 10)})
    with pytest.raises(InputError, match=r"no block.*3, 4"):
        lo.Snapshots(t, Q, blocks={"a": np.arange(3), "b": np.arange(5, 10)})
    with pytest.raises(InputError, match="integer"):
        lo.Snapshots(t, Q, blocks={"a": np.arange(5) + 0.5, "b": np.arange(5, 10)})
    assert lo.Snapshots(t, Q).blocks == {}


# -- 7. ROM operators, initial states, inputs -------------------------------------------

@pytest.mark.parametrize("name", ["M", "C", "B", "E"])
def test_item7_rom_refuses_non_finite_operators(name):
    value = {"M": np.eye(2), "C": np.eye(2), "B": np.ones((2, 1)), "E": np.ones((1, 2))}[name]
    value = value.copy()
    value[0, 0] = np.nan
    with pytest.raises(InputError, match=rf"{name} contains 1 non-finite"):
        lo.core.LagrangianROM(K=np.eye(2), **{name: value})


def test_item7_simulate_refuses_non_finite_initial_state_and_bad_counts():
    rom = lo.core.LagrangianROM(K=np.eye(2))
    with pytest.raises(InputError, match="q0 contains"):
        rom.simulate([np.nan, 0], [0, 0], 0.1, 5)
    with pytest.raises(InputError, match="v0 contains"):
        rom.simulate([0, 0], [0, np.inf], 0.1, 5)
    with pytest.raises(InputError, match="n_steps"):
        rom.simulate([0, 0], [0, 0], 0.1, 5.5)
    with pytest.raises(InputError, match="dt"):
        rom.simulate([0, 0], [0, 0], "0.1", 5)
    forced = lo.core.LagrangianROM(K=np.eye(2), B=np.ones((2, 1)))
    with pytest.raises(InputError, match=r"inputs.*non-finite.*t = 0.25"):
        forced.simulate([0, 0], [0, 0], 0.1, 5, inputs=lambda t: [np.nan if t > 0.2 else 1.0])
    with pytest.raises(InputError, match="complex"):
        forced.simulate([0, 0], [0, 0], 0.1, 5, inputs=lambda t: [1j])


def test_item7_load_rom_refuses_non_finite_operators(tmp_path):
    path = tmp_path / "nan.npz"
    np.savez(path, K=np.eye(2), M=np.full((2, 2), np.nan), scheme=np.array("midpoint"),
             meta=np.array("{}"))
    with pytest.raises(FileFormatError, match=r"nan\.npz.*M contains 4 non-finite"):
        lo.core.rom.load_rom(path)


def test_item7_non_lagrangian_stiffness_is_named():
    skew = np.array([[1.0, 5.0], [-5.0, 1.0]])
    with pytest.warns(lo.errors.NonLagrangianWarning, match=r"K is not symmetric.*\|K - K\^T\|"):
        lo.core.LagrangianROM(K=skew)
    with pytest.warns(lo.errors.NonLagrangianWarning, match=r"K is indefinite.*-1"):
        lo.core.LagrangianROM(K=np.diag([1.0, -1.0]))
    with pytest.warns(lo.errors.NonLagrangianWarning, match=r"M is indefinite"):
        lo.core.LagrangianROM(K=np.eye(2), M=np.diag([1.0, -1.0]))
    with pytest.warns(lo.errors.NonLagrangianWarning, match=r"C is not symmetric"):
        lo.core.LagrangianROM(K=np.eye(2), C=skew)
    with pytest.raises(InputError, match="K is not symmetric"):
        lo.core.LagrangianROM(K=skew, lagrangian=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lo.core.LagrangianROM(K=skew, lagrangian=False)  # standard OpInf: said so, no warning
        lo.core.LagrangianROM(K=np.diag([1.0, 0.0]))  # semidefinite (a free mode) is fine
        spd = np.array([[2.0, 0.3], [0.3, 1.0]])
        lo.core.LagrangianROM(K=spd, M=spd, C=0.1 * spd)
    with pytest.raises(InputError, match="singular"):
        lo.core.LagrangianROM(K=np.eye(2), M=np.zeros((2, 2)))


def test_item7_non_lagrangian_flag_round_trips(tmp_path):
    rom = lo.core.LagrangianROM(K=np.array([[1.0, 0.2], [0.0, 1.0]]), lagrangian=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loaded = lo.core.rom.load_rom(lo.core.rom.save_rom(tmp_path / "opinf.npz", rom))[0]
    assert loaded.lagrangian is False and np.array_equal(loaded.K, rom.K)


# -- 9. complex input, relative_error at extreme scales ---------------------------------

def test_item9_complex_arrays_are_refused_everywhere():
    rng = np.random.default_rng(0)
    Q = rng.standard_normal((6, 20)) * (1 + 1j)
    t = np.linspace(0, 1, 20)
    calls = {
        "pod": lambda: lo.pod(Q, 2),
        "derivatives": lambda: lo.core.derivatives(Q, t),
        "variational_data": lambda: lo.core.ddt.variational_data(Q, t),
        "Snapshots": lambda: lo.Snapshots(t, Q),
        "times": lambda: lo.Snapshots(t * (1 + 0j), Q.real),
        "LagrangianROM": lambda: lo.core.LagrangianROM(K=np.eye(2) * (1 + 1j)),
        "relative_error": lambda: lo.relative_error(Q, Q.real),
        "project": lambda: lo.pod(Q.real, 2).project(Q),
        "reconstruct": lambda: lo.pod(Q.real, 2).reconstruct(Q[:2]),
        "object": lambda: lo.pod(Q.astype(object), 2),
    }
    for name, call in calls.items():
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no ComplexWarning either
            with pytest.raises(InputError, match="complex"):
                call()
            print(name, "refused")


@pytest.mark.parametrize("scale", [1e160, 1e-170, 1e300, 1e-300])
def test_item9_relative_error_is_scale_invariant(scale):
    rng = np.random.default_rng(1)
    ref = rng.standard_normal((5, 7))
    approx = ref + 1e-2 * rng.standard_normal((5, 7))
    assert lo.relative_error(scale * ref, scale * approx) == pytest.approx(
        lo.relative_error(ref, approx), rel=1e-12)


def test_item9_other_dtypes_have_clear_errors():
    with pytest.raises(InputError, match=r"Q.*ragged"):
        lo.pod([[1.0, 2.0], [3.0]], 1)
    with pytest.raises(InputError, match=r"Q.*text"):
        lo.pod(np.array([["1", "2"], ["3", "4"]]), 1)
    with pytest.raises(InputError, match=r"Q.*None"):
        lo.pod(np.array([[1.0, None], [2.0, 3.0]], dtype=object), 1)
    assert lo.pod(np.eye(3, dtype=int), 1).r == 1  # integers and booleans convert exactly
    assert lo.pod(np.eye(3, dtype=bool), 1).r == 1


# -- 10. forcing streamed, trajectory unchanged ------------------------------------------

def _old_simulate(rom, q0, v0, dt, n_steps, U, every):
    """The forced branch of LagrangianROM.simulate with the forcing of all steps formed up
    front (U: at the midpoints for the midpoint rule, at t_0 .. t_n for Newmark)."""
    r = rom.r
    n_out = n_steps // every + 1
    G, H = rom.step(dt)
    if rom.scheme == "midpoint":
        x = np.concatenate([q0, rom.mass @ v0])
        forcing = H @ U
    else:  # Newmark: the load of step k -> k + 1 is u(t_{k+1}); state [q; v; a]
        x = np.concatenate([q0, v0, np.linalg.solve(rom.mass, rom.B @ U[:, 0] - rom.C @ v0 - rom.K @ q0)])
        forcing = H @ U[:, 1:]
    X = np.empty((len(x), n_out))
    X[:, 0] = x
    j = 1
    for k in range(n_steps):
        x = G @ x
        x += forcing[:, k]
        if (k + 1) % every == 0:
            X[:, j] = x
            j += 1
    Vh = np.linalg.solve(rom.mass, X[r:]) if rom.scheme == "midpoint" else X[r:2 * r]
    return X[:r], Vh


@pytest.mark.parametrize("scheme", ["midpoint", "newmark"])
@pytest.mark.parametrize("m", [1, 3])
def test_item10_streamed_forcing_is_bit_identical(scheme, m):
    rng = np.random.default_rng(5)
    r, dt, n = 6, 1e-2, 10_007
    A = rng.standard_normal((r, r))
    K = A @ A.T + np.eye(r)
    rom = lo.core.LagrangianROM(K=K, C=0.01 * np.eye(r), B=rng.standard_normal((r, m)), scheme=scheme)
    freqs = rng.uniform(0.5, 3, m)
    u = lambda t: np.sin(freqs * t)  # noqa: E731
    times = dt * (np.arange(n) + 0.5) if scheme == "midpoint" else dt * np.arange(n + 1)
    U = np.column_stack([u(t) for t in times])
    q0, v0 = rng.standard_normal(r), rng.standard_normal(r)
    for every in (1, 7):
        Qo, Vo = _old_simulate(rom, q0, v0, dt, n, U, every)
        for inputs in (u, U):
            tr = rom.simulate(q0, v0, dt, n, inputs=inputs, every=every, backend="numpy")
            assert np.array_equal(tr.Qh, Qo) and np.array_equal(tr.Vh, Vo)
            # the compiled loop sums the rows in another order: equal to rounding
            tr = rom.simulate(q0, v0, dt, n, inputs=inputs, every=every)
            assert np.abs(tr.Qh - Qo).max() <= 1e-11 * np.abs(Qo).max()


@pytest.mark.parametrize("scheme", ["midpoint", "newmark"])
def test_item10_forcing_memory_does_not_grow_with_the_steps(scheme):
    r, n = 20, 20_000
    rom = lo.core.LagrangianROM(K=np.diag(np.arange(1.0, r + 1)), B=np.ones((r, 2)), scheme=scheme)
    u = lambda t: np.array([np.sin(t), np.cos(t)])  # noqa: E731
    tracemalloc.start()
    try:
        rom.simulate(np.zeros(r), np.zeros(r), 1e-3, n, inputs=u, every=n)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2e6, f"peak {peak / 1e6:.1f} MB for {n} steps"  # was 6.7 / 13 MB (the 2r x n forcing)


# -- 14. unreadable files ---------------------------------------------------------------

def test_item14_load_rom_and_snapshots_load_name_the_file_and_the_problem(tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("hello\n")
    npy = tmp_path / "a.npy"
    np.save(npy, np.eye(2))
    no_k = tmp_path / "noK.npz"
    np.savez(no_k, M=np.eye(2), scheme=np.array("midpoint"), meta=np.array("{}"))
    bad_meta = tmp_path / "meta.npz"
    np.savez(bad_meta, K=np.eye(2), scheme=np.array("midpoint"), meta=np.array("{oops"))
    truncated = tmp_path / "cut.npz"
    lo.core.rom.save_rom(truncated, lo.core.LagrangianROM(K=np.eye(2)))
    truncated.write_bytes(truncated.read_bytes()[:100])
    cases = [(text, "not an .npz"), (npy, "a single .npy array"), (no_k, "lacks 'K'"),
             (bad_meta, "meta"), (truncated, "truncated or corrupt")]
    for path, what in cases:
        with pytest.raises(FileFormatError, match=rf"{path.name}.*{what}"):
            lo.core.rom.load_rom(path)
    with pytest.raises(FileNotFoundError):
        lo.core.rom.load_rom(tmp_path / "missing.npz")
    for path, what in [(text, "not an .npz"), (npy, "a single .npy array"),
                       (no_k, r"lacks 'times', 'Q'"), (truncated, "truncated or corrupt")]:
        with pytest.raises(FileFormatError, match=rf"{path.name}.*{what}"):
            lo.Snapshots.load(path)
    extra = tmp_path / "extra.npz"
    np.savez(extra, times=np.linspace(0, 1, 3), Q=np.ones((1, 3)), K=np.eye(1))
    with pytest.raises(FileFormatError, match=r"extra\.npz.*unknown entries \['K'\]"):
        lo.Snapshots.load(extra)


# -- 15. valid data refused for the wrong reason ---------------------------------------

def test_item15_float32_and_offset_times_are_accepted():
    rng = np.random.default_rng(0)
    t32 = np.arange(200, dtype=np.float32) * np.float32(1e-3)
    s = lo.Snapshots(t32, rng.standard_normal((2, 200)))
    assert s.dt == pytest.approx(1e-3, rel=1e-6)
    t_off = 1e6 + 1e-5 * np.arange(100)
    s = lo.Snapshots(t_off, rng.standard_normal((2, 100)))
    assert s.dt == pytest.approx(1e-5, rel=1e-9)
    Qh, dQh, ddQh = lo.core.derivatives(np.sin(t_off - 1e6)[None], t_off)
    assert np.allclose(dQh[0], np.cos(t_off[4:-4] - 1e6), atol=1e-6)
    Qbar, D1, D2, _ = lo.core.ddt.newmark_data(np.sin(1e3 * (t_off - 1e6))[None], t_off)
    assert np.allclose(D1[0], 1e3 * np.cos(1e3 * (t_off[1:-1] - 1e6)), rtol=1e-3, atol=1e-3)
    # ... but a real gap, a duplicate, or times too coarse to tell are still refused
    with pytest.raises(InputError, match="uniformly spaced"):
        lo.Snapshots(np.delete(t_off, 50), rng.standard_normal((2, 99)))
    with pytest.raises(InputError, match="increasing"):
        lo.Snapshots(t_off[::-1], rng.standard_normal((2, 100)))
    with pytest.raises(InputError, match="float64"):
        lo.Snapshots((1e6 + 1e-3 * np.arange(100)).astype(np.float32), rng.standard_normal((2, 100)))


@pytest.mark.parametrize("scale", [1e155, 1e-170])
def test_item15_pod_and_metrics_at_extreme_scales(scale):
    rng = np.random.default_rng(2)
    Q = rng.standard_normal((8, 40))
    ref = lo.pod(Q, 3)
    big = lo.pod(scale * Q, 3)
    assert np.allclose(np.abs(big.V), np.abs(ref.V), atol=1e-12)
    assert big.projection_error(scale * Q) == pytest.approx(ref.projection_error(Q), rel=1e-10)
    assert np.allclose(big.project(scale * Q) / scale, ref.project(Q) * np.sign(big.V[0] * ref.V[0])[:, None])
    e = lo.core.energy_error(scale * np.array([1.0, 1.5]))
    assert e[1] == pytest.approx(0.5)


# -- other entry points of the numpy core -------------------------------------------------

def test_core_entry_points_validate_what_they_are_given():
    rng = np.random.default_rng(3)
    Q, t = rng.standard_normal((6, 40)), np.linspace(0, 1, 40)
    with pytest.raises(InputError, match="energy.*at least 1"):
        lo.core.energy_error([])
    with pytest.raises(InputError, match="energy contains a non-finite initial"):
        lo.core.energy_error([np.nan, 1.0])
    blown_up = lo.core.energy_error([1.0, np.inf])  # a result, not an input error
    assert not lo.core.metrics.is_stable(np.zeros((1, 2)), blown_up)
    assert lo.relative_error(np.ones(3), np.array([1.0, np.inf, 1.0])) == np.inf
    basis = lo.pod(Q, 2)
    with pytest.raises(InputError, match="Q contains"):
        basis.project(np.where(Q > 1, np.nan, Q))
    assert np.isnan(basis.reconstruct(np.full((2, 3), np.nan))).all()  # a blown-up ROM: a result
    with pytest.raises(InputError, match="r must be a positive integer"):
        lo.pod(Q, 2.5)
    with pytest.raises(InputError, match="weight contains"):
        lo.pod(Q, 2, weight=np.full((6, 6), np.nan))
    with pytest.raises(InputError, match="U has shape"):
        lo.Snapshots(t, Q, U=np.ones((2, 3, 40)))
    with pytest.raises(InputError, match="energy has shape"):
        lo.Snapshots(t, Q, energy=np.ones((2, 40)))
    with pytest.raises(InputError, match="output_times"):
        lo.Snapshots(t, Q, Y=np.ones((1, 3)), output_times=[0, 0.5, 0.2])
    with pytest.raises(InputError, match="output_times.*without Y"):
        lo.Snapshots(t, Q, output_times=[0, 0.5, 1.0])
    with pytest.raises(InputError, match="t_start"):
        lo.Snapshots(t, Q).window(np.nan, 1)
    with pytest.raises(InputError, match="r_values"):
        lo.core.choose_r(Q, t, [], 0.1)
    with pytest.raises(InputError, match="V0"):
        lo.core.choose_r(Q, t, [1], 0.1, V0=np.ones(5))
    with pytest.raises(InputError, match="times has 39 entries"):
        lo.core.ddt.variational_data(Q, t[:-1])
    with pytest.raises(InputError, match="inputs contains"):
        lo.core.ddt.newmark_data(Q, t, np.full((1, 40), np.nan))
    with pytest.raises(InputError, match="q0 and v0"):
        lo.core.rom.WaveROM(K=np.eye(2), V=np.eye(2), g=np.sin, dg=np.cos, U=np.cos).simulate(
            np.zeros(3), np.zeros(3), 0.1, 2)
    with pytest.raises(InputError, match="K contains"):
        lo.core.rom.WaveROM(K=np.full((2, 2), np.nan), V=np.eye(2), g=np.sin, dg=np.cos, U=np.cos)
    from dolfinx_lopinf.core import hyper

    with pytest.raises(InputError, match="Qh contains"):
        hyper.ecsw(np.eye(3), np.full((3, 4), np.nan), np.sin)
