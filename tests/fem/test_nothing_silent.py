"""Issue 27, nothing silent, nothing lost (DOLFINx layer, one rank): the silent wrong results
are refused with a named error, write_vtx never deletes what it did not write and its folder
swap survives a kill at any instant, a full disk raises instead of aborting, and the unclear
messages name the offending item."""

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

import ufl  # noqa: E402

import dolfinx_lopinf as lo  # noqa: E402
from dolfinx_lopinf.errors import InputError  # noqa: E402
from dolfinx_lopinf.fem._dolfinx import MPI, PETSc, dolfinx  # noqa: E402
from dolfinx_lopinf.fem.loop import OutputProbe  # noqa: E402
from dolfinx_lopinf.fem.state import point_output_matrix  # noqa: E402
from dolfinx_lopinf.fem.newmark import NewmarkIntegrator  # noqa: E402
from dolfinx_lopinf.fem.probes import probe_points  # noqa: E402

DT = 1e-3
ROOT = Path(__file__).resolve().parents[2]


def _string(n=16):
    msh = dolfinx.mesh.create_interval(MPI.COMM_WORLD, n, [0.0, 1.0])
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
    q, qt = dolfinx.fem.Function(V), dolfinx.fem.Function(V)
    ends = dolfinx.fem.locate_dofs_geometrical(V, lambda x: np.isclose(x[0], 0) | np.isclose(x[0], 1))
    bc = dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), ends, V)
    system = lo.LagrangianSystem((0.5 * qt**2 - 0.5 * q.dx(0) ** 2) * ufl.dx, q, qt, bcs=[bc])
    x = V.tabulate_dof_coordinates()[:, 0]
    return system, V, x * (1 - x), np.zeros_like(x)


@pytest.fixture(scope="module")
def square():
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 3, 3)
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
    return V, V.dofmap.index_map.size_global


def _bp_values(path):
    adios2 = pytest.importorskip("adios2")
    with adios2.Stream(str(path), "r") as f:
        return [f.read("u").ravel().copy() for _ in f.steps()]


# -- silent wrong results ---------------------------------------------------------------------

def test_write_vtx_refuses_a_hermite_space(beam, tmp_path):
    """The beam's Hermite dofs are (w, dw/dx) pairs: VTX wrote them as point values (w = 1,
    theta = 0 came out as 1, 0, 1, 0, ...)."""
    n = len(beam.state_map.order) // 2
    S = np.concatenate([np.ones(n), np.zeros(n)])[:, None]
    with pytest.raises(InputError, match="Hermite space, which VTX cannot show"):
        lo.write_vtx(tmp_path / "beam.bp", beam.system.V, S, [0.0], state_map=beam.state_map)
    assert os.listdir(tmp_path) == []
    f = lo.fem.states_to_function(beam.system.V, S[:, 0], beam.state_map)  # a Function is fine
    assert np.isclose(f.x.array[beam.value_dofs], 1.0).all() and not f.x.array[beam.slope_dofs].any()


def test_run_refuses_an_integrator_never_initialised():
    """run(MidpointIntegrator(system, dt), 5) stepped from q = p = 0 and recorded zeros."""
    system, V, q0, v0 = _string()
    with lo.fem.MidpointIntegrator(system, DT) as it:
        with pytest.raises(InputError, match="never initialised"):
            lo.run(it, 5)
        with pytest.raises(InputError, match="never initialised"):
            it.step()
        it.initialize(q0, v0)
        lo.run(it, 5)
        assert np.abs(it.q.x.array).max() > 0.1
    with NewmarkIntegrator(system, DT) as nm:
        with pytest.raises(InputError, match="never initialised"):
            lo.run(nm, 5)
        nm.initialize()
        lo.run(nm, 2)


@pytest.mark.parametrize("kwargs, match", [
    ({"spread": float("nan")}, "spread must be a finite number >= 0"),
    ({"spread": float("inf")}, "spread must be a finite number >= 0"),
    ({"spread": -0.1}, "spread must be a finite number >= 0"),
    ({"scale_max": float("nan")}, "scale_max must be a finite number >= 1"),
    ({"n": 0}, "n .points to sample. must be"),
    ({"n": 2.5}, "n .points to sample. must be"),
    ({"rng": 7}, "rng must be a numpy Generator"),
    ({"inputs_range": (1.0, float("nan"))}, "inputs_range must be finite"),
    ({"inputs_range": (2.0, 1.0)}, "lo <= hi"),
])
def test_probe_points_refuse_what_would_make_nan_points(kwargs, match):
    Qh = np.random.default_rng(0).standard_normal((2, 10))
    args = {"n": 3, "rng": np.random.default_rng(1), **kwargs}
    n = args.pop("n")
    with pytest.raises(InputError, match=match):
        probe_points(Qh, Qh, n, **args)
    Q, Vel, _ = probe_points(Qh, Qh, 3, rng=np.random.default_rng(1))
    assert np.all(np.isfinite(Q)) and np.all(np.isfinite(Vel))


# -- lost data: write_vtx ---------------------------------------------------------------------

def test_write_vtx_never_deletes_a_folder_it_did_not_write(square, tmp_path):
    V, n = square
    photos = tmp_path / "photos.bp"
    photos.mkdir()
    (photos / "IMG_001.jpg").write_bytes(b"precious")
    (photos / "data.0").write_bytes(b"looks like ADIOS2 but has no index")
    with pytest.raises(InputError, match=r"not a VTX .bp folder: it holds 1 entries that are not "
                                         r"ADIOS2 files \(IMG_001.jpg\).*overwrite=True"):
        lo.write_vtx(photos, V, np.ones((n, 1)), [0.0])
    assert sorted(os.listdir(photos)) == ["IMG_001.jpg", "data.0"]
    (photos / "IMG_001.jpg").unlink()
    with pytest.raises(InputError, match="no ADIOS2 index"):
        lo.write_vtx(photos, V, np.ones((n, 1)), [0.0])
    assert os.listdir(photos) == ["data.0"]
    lo.write_vtx(photos, V, np.ones((n, 1)), [0.0], overwrite=True)  # asked for: replaced
    assert "md.idx" in os.listdir(photos) and sorted(os.listdir(tmp_path)) == ["photos.bp"]
    (tmp_path / "file.bp").write_text("a file")
    with pytest.raises(InputError, match="not a .bp folder"):
        lo.write_vtx(tmp_path / "file.bp", V, np.ones((n, 1)), [0.0], overwrite=True)
    (tmp_path / "empty.bp").mkdir()
    lo.write_vtx(tmp_path / "empty.bp", V, np.ones((n, 1)), [0.0])  # nothing to lose


def test_write_vtx_replaces_a_vtx_folder_of_dolfinx(square, tmp_path):
    """The FOM's own output (dolfinx's VTXWriter) is a VTX .bp: replaced without overwrite=."""
    V, n = square
    f = dolfinx.fem.Function(V, name="u")
    with dolfinx.io.VTXWriter(MPI.COMM_WORLD, tmp_path / "fom.bp", [f], engine="BP5") as w:
        w.write(0.0)
    lo.write_vtx(tmp_path / "fom.bp", V, np.full((n, 2), 3.0), [0.0, 1.0])
    assert [v.max() for v in _bp_values(tmp_path / "fom.bp")] == [3.0, 3.0]


_KILL = textwrap.dedent("""
    import os, sys
    import numpy as np
    from dolfinx_lopinf.fem._dolfinx import MPI, dolfinx
    import dolfinx_lopinf as lo
    from dolfinx_lopinf.core import io_atomic
    from dolfinx_lopinf.fem import vtx
    where, target = sys.argv[1], sys.argv[2]
    V = dolfinx.fem.functionspace(dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 3, 3), ("Lagrange", 1))
    n = V.dofmap.index_map.size_global
    if where == "between_renames":       # a file system that cannot exchange: the two-step swap
        io_atomic._exchange = lambda a, b: False
        real = os.replace
        def replace(a, b):
            real(a, b)
            os._exit(9)                    # killed right after parking the old version
        io_atomic.os.replace = replace
    elif where == "after_swap":          # killed while deleting the old version
        vtx.shutil.rmtree = lambda *a, **k: os._exit(9)
    lo.write_vtx(target, V, np.full((n, 1), 2.0), [0.0])
""")


@pytest.mark.parametrize("where", ["between_renames", "after_swap"])
def test_write_vtx_swap_survives_a_kill(square, tmp_path, where):
    """A kill at either instant of the replacement: the target is never lost, and the next
    write finishes the job (restores the parked old version / removes the dead temporary)."""
    V, n = square
    target = tmp_path / "out.bp"
    lo.write_vtx(target, V, np.full((n, 1), 1.0), [0.0])
    proc = subprocess.run([sys.executable, "-c", _KILL, where, str(target)], capture_output=True,
                          text=True, timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 9, proc.stderr[-2000:]
    left = sorted(os.listdir(tmp_path))
    if where == "between_renames":
        # the target is gone for now, the old version parked under a known name
        assert ".out.bp.previous" in left and "out.bp" not in left and len(left) == 2
        with pytest.raises(InputError, match="NaN"):  # even a refused write puts it back first
            lo.write_vtx(target, V, np.full((n, 1), np.nan), [0.0])
        assert "out.bp" in os.listdir(tmp_path) and ".out.bp.previous" not in os.listdir(tmp_path)
        assert _bp_values(target)[0].max() == 1.0
    else:
        assert "out.bp" in left and len(left) >= 2   # the new version, and the dead temporary
        assert _bp_values(target)[0].max() == 2.0
    lo.write_vtx(target, V, np.full((n, 1), 3.0), [0.0])
    assert sorted(os.listdir(tmp_path)) == ["out.bp"]  # nothing left behind
    assert _bp_values(target)[0].max() == 3.0


def test_write_vtx_checks_the_free_space_before_and_during_the_write(square, tmp_path, monkeypatch):
    from dolfinx_lopinf.errors import OutOfSpaceError
    from dolfinx_lopinf.fem import vtx

    V, n = square
    target = tmp_path / "out.bp"
    lo.write_vtx(target, V, np.full((n, 1), 1.0), [0.0])
    real = shutil.disk_usage
    calls = {"n": 0}

    def disk_usage(path, free_after=None):
        calls["n"] += 1
        usage = real(path)
        free = 10_000 if free_after is None or calls["n"] > free_after else usage.free
        return usage._replace(free=free)

    monkeypatch.setattr(vtx.shutil, "disk_usage", disk_usage)
    with pytest.raises(OutOfSpaceError, match=r"writing out.bp \(5 steps of about .* MB free"):
        lo.write_vtx(target, V, np.full((n, 5), 2.0), np.arange(5.0))
    calls["n"] = 0  # enough space at first, then the disk fills during the write
    monkeypatch.setattr(vtx.shutil, "disk_usage", lambda p: disk_usage(p, free_after=3))
    with pytest.raises(OutOfSpaceError, match=r"step 3 of 5 of out.bp"):
        lo.write_vtx(target, V, np.full((n, 5), 2.0), np.arange(5.0))
    assert sorted(os.listdir(tmp_path)) == ["out.bp"]      # no temporary left
    assert [v.max() for v in _bp_values(target)] == [1.0]  # the previous version untouched


_FULL = textwrap.dedent("""
    import sys
    import numpy as np
    from dolfinx_lopinf.fem._dolfinx import MPI, dolfinx
    import dolfinx_lopinf as lo
    V = dolfinx.fem.functionspace(dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 64, 64), ("Lagrange", 1))
    n = V.dofmap.index_map.size_global
    try:
        lo.write_vtx(sys.argv[1] + "/out.bp", V, np.ones((n, 40)), np.arange(40.0))
    except lo.errors.OutOfSpaceError as exc:
        print("REFUSED", exc)
""")


def test_write_vtx_on_a_really_full_disk_raises_instead_of_aborting(tmp_path):
    """A 1 MB tmpfs (in a private mount namespace): ADIOS2 used to abort the process (SIGABRT,
    'No space left on device'); now OutOfSpaceError before anything is written."""
    if shutil.which("unshare") is None:
        pytest.skip("no unshare")
    mnt = tmp_path / "small"
    mnt.mkdir()
    shell = (f"mount -t tmpfs -o size=1m tmpfs {mnt} && {sys.executable} -c \"$0\" {mnt} && "
             f"ls -A {mnt}")
    for prefix in (["unshare", "-m"], ["unshare", "-rm"]):
        proc = subprocess.run([*prefix, "sh", "-c", shell, _FULL], capture_output=True, text=True,
                              timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT)})
        if "mount" not in proc.stderr and "unshare" not in proc.stderr:
            break
    else:
        pytest.skip(f"cannot mount a small tmpfs here: {proc.stderr.strip()[-200:]}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "REFUSED [Errno 28] writing out.bp (40 steps" in proc.stdout
    assert proc.stdout.strip().splitlines()[-1].startswith("REFUSED")  # ls -A: an empty disk


# -- unclear messages -------------------------------------------------------------------------

def test_sinks_that_are_not_sinks_are_named():
    system, V, q0, v0 = _string()
    with lo.fem.MidpointIntegrator(system, DT) as it:
        it.initialize(q0, v0)
        with pytest.raises(InputError, match=r"sinks\[1\] = 5 is neither a Sink .* nor a callable"):
            lo.run(it, 3, sinks=[lambda s: None, 5])
        E = point_output_matrix(V, [[0.5]])
        with pytest.raises(InputError, match="wrap a single sink in a list: sinks=\\[sink\\]"):
            lo.run(it, 3, sinks=OutputProbe(E))
        with pytest.raises(InputError, match="inputs must be a callable"):
            lo.run(it, 3, inputs=[1.0])
        with pytest.raises(InputError, match="MidpointIntegrator takes no input values"):
            lo.run(it, 3, inputs=lambda t: [1.0])


def test_a_closed_integrator_says_so():
    system, V, q0, v0 = _string()
    it = lo.fem.MidpointIntegrator(system, DT)
    it.initialize(q0, v0)
    it.close()
    for call in (lambda: lo.run(it, 3), it.step, it.velocity, it.energy, lambda: it.initialize(q0, v0),
                 lambda: lo.run(system, q0, v0, DT, 0.01, integrator=it, progress=False)):
        with pytest.raises(InputError, match="closed"):
            call()
    nm = NewmarkIntegrator(system, DT)
    nm.initialize()
    nm.close()
    for call in (lambda: lo.run(nm, 3), nm.step, nm.velocity, nm.energy, nm.initialize):
        with pytest.raises(InputError, match="closed"):
            call()


def test_newmark_inputs_are_named():
    system, V, q0, v0 = _string()
    with NewmarkIntegrator(system, DT, input_forms=[ufl.TestFunction(V) * ufl.dx]) as nm:
        nm.initialize([0.0])
        with pytest.raises(InputError, match="has 1 input channel"):
            lo.run(nm, 3)
        with pytest.raises(InputError, match="has 1 input channel"):
            nm.step()
        with pytest.raises(InputError, match="input values must be 1 numbers"):
            nm.step("abc")
        lo.run(nm, 3, inputs=lambda t: [1.0])
    with NewmarkIntegrator(system, DT) as nm:
        nm.initialize()
        with pytest.raises(InputError, match="no input forms"):
            lo.run(nm, 3, inputs=lambda t: [1.0])


def test_point_output_matrix_takes_points_of_the_mesh_dimension(square):
    V, _ = square
    E2 = point_output_matrix(V, [[0.7, 0.4]])  # was a raw pybind TypeError
    E3 = point_output_matrix(V, [[0.7, 0.4, 0.0]])
    np.testing.assert_array_equal(E2, E3)
    f = dolfinx.fem.Function(V)
    f.interpolate(lambda x: 1 + 2 * x[0] + 3 * x[1])
    assert np.isclose(E2 @ f.x.array, [1 + 1.4 + 1.2]).all()
    for points, match in (([[0.7]], r"shape \(p, 2\) or \(p, 3\)"), ([[1, 2, 3, 4]], "shape"),
                          ([[0.5, np.nan]], "NaN or inf"), ("abc", "array of coordinates"),
                          ([[2.0, 2.0]], "outside the mesh")):
        with pytest.raises(InputError, match=match):
            point_output_matrix(V, points)
    with pytest.raises(InputError, match="component must be an integer"):
        point_output_matrix(V, [[0.5, 0.5]], component=0.5)


def test_point_output_matrix_on_a_mixed_space():
    """A mixed (Taylor-Hood-like) space: Function.eval does not evaluate mixed elements (it
    raised a raw RuntimeError); each flat component is read from its collapsed sub-space, equal
    to evaluating that sub-function."""
    import basix.ufl

    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 5, 4)
    P2 = basix.ufl.element("Lagrange", msh.basix_cell(), 2, shape=(2,))
    P1 = basix.ufl.element("Lagrange", msh.basix_cell(), 1)
    V = dolfinx.fem.functionspace(msh, basix.ufl.mixed_element([P2, P1]))
    u = dolfinx.fem.Function(V)
    u.sub(0).interpolate(lambda x: np.vstack([x[0] ** 2 + x[1], np.sin(3 * x[0]) * x[1]]))
    u.sub(1).interpolate(lambda x: 1 + x[0] * x[1])
    points = np.array([[0.31, 0.47, 0.0], [0.9, 0.13, 0.0]])
    tree = dolfinx.geometry.bb_tree(msh, 2)
    cells = dolfinx.geometry.compute_colliding_cells(
        msh, dolfinx.geometry.compute_collisions_points(tree, points), points)
    subs = [u.sub(0).collapse(), u.sub(1).collapse()]
    for comp, (sub, k) in enumerate([(0, 0), (0, 1), (1, 0)]):
        E = point_output_matrix(V, points, component=comp)
        expected = [subs[sub].eval(pt, np.array([cells.links(i)[0]], dtype=np.int32))[k]
                    for i, pt in enumerate(points)]
        np.testing.assert_allclose(E @ u.x.array, expected, rtol=1e-13, atol=1e-14)
    with pytest.raises(InputError, match="3 components"):
        point_output_matrix(V, points)


def test_snapshot_recorder_checks_its_blocks_before_the_run(square):
    """blocks= is checked when the recorder is made (it was first refused by rec.snapshots(),
    after the whole run): rows outside the space, a row in no block, rows given as a 2-D array."""
    V, n = square
    u = dolfinx.fem.Function(V)
    half = np.arange(n // 2)
    for blocks, match in (({"a": [0, n + 5]}, "outside"), ({"a": half}, "no block"),
                          ({"a": half[None, :], "b": np.arange(n // 2, n)}, "1-D")):
        with pytest.raises(InputError, match=match):
            lo.SnapshotRecorder(u, blocks=blocks)
    rec = lo.SnapshotRecorder(u, blocks={"a": half, "b": np.arange(n // 2, n)})
    for k in range(3):
        rec.record(0.1 * k, u)
    assert sorted(rec.snapshots().blocks) == ["a", "b"]
