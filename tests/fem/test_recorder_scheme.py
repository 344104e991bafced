"""The integrator a user declares for their recording: SnapshotRecorder(u, scheme=...) ->
Snapshots.scheme (a schemes object, from a name, an object or its spec text), validated,
kept by window() and by save/load (old files without it load as None; old name-only files
load as the named scheme). The recorder's rows, velocity/acceleration Functions and input
times."""

import numpy as np
import pytest

import dolfinx_lopinf as lo
from dolfinx_lopinf.core import schemes
from dolfinx_lopinf.errors import FileFormatError, InputError

T = np.arange(12) * 0.1
Q = np.vstack([np.cos(T), np.sin(T)])
SCHEMES = [None, "newmark", "midpoint", "continuous", "central_difference",
           schemes.GeneralizedAlpha(rho_inf=0.8), schemes.HHT(0.1), schemes.Newmark(1 / 6, 0.5),
           "generalized_alpha(alpha_m=0.2, alpha_f=0.4)"]


@pytest.mark.parametrize("scheme", SCHEMES)
def test_valid_schemes_round_trip(tmp_path, scheme):
    s = lo.Snapshots(T, Q, U=np.sin(2 * T)[None], scheme=scheme)
    want = None if scheme is None else schemes.from_spec(scheme)
    assert s.scheme == want
    w = s.window(0.2, 0.8)
    assert w.scheme == want and w.Q.shape == (2, 7)
    back = lo.Snapshots.load(s.save(tmp_path / "s.npz"))
    assert back.scheme == want and (want is None or back.scheme.spec == want.spec)
    np.testing.assert_array_equal(back.Q, Q)
    np.testing.assert_array_equal(back.U, s.U)
    assert lo.Snapshots.load(w.save(tmp_path / "w.npz")).scheme == want


def test_names_compare_equal_to_their_scheme():
    s = lo.Snapshots(T, Q, scheme=np.str_("newmark"))
    assert s.scheme == "newmark" and s.scheme == schemes.Newmark(0.25, 0.5)
    assert s.scheme != "midpoint" and s.scheme != "no such scheme"


@pytest.mark.parametrize("bad, hint", [
    ("auto", "pass None"), ("generalised-alpha", "GeneralizedAlpha"), ("", "unknown scheme"),
    (1, "schemes object"), (["newmark"], "schemes object"), (b"newmark", "schemes object"),
    ("newmark(beta=0.25, gamma=0.4)", "gamma = 0.4 < 1/2"),
    ("generalized_alpha(rho_inf=1.5)", "rho_inf must lie in"), ("hht(alpha=-0.1)", "pass alpha=0.1")])
def test_bad_scheme_names_value_and_choices(bad, hint):
    with pytest.raises(InputError) as info:
        lo.Snapshots(T, Q, scheme=bad)
    assert hint in str(info.value)


def test_old_files_without_scheme_load_as_none(tmp_path):
    # a file as Snapshots.save wrote it before the field existed
    path = tmp_path / "old.npz"
    np.savez_compressed(path, times=T, Q=Q, block__a=np.array([0]), block__b=np.array([1]))
    s = lo.Snapshots.load(path)
    assert s.scheme is None and sorted(s.blocks) == ["a", "b"]
    np.savez_compressed(path, times=T, Q=Q, scheme=np.array("newmark"))  # a name-only file
    assert lo.Snapshots.load(path).scheme == schemes.Newmark()


@pytest.mark.parametrize("stored, match", [
    (np.array("generalised-alpha"), "stored snapshots are invalid"),
    (np.array(["newmark", "midpoint"]), "one text value"),
    (np.array(3.0), "one text value")])
def test_bad_stored_scheme_is_a_file_format_error(tmp_path, stored, match):
    path = tmp_path / "bad.npz"
    np.savez_compressed(path, times=T, Q=Q, scheme=stored)
    with pytest.raises(FileFormatError, match=match):
        lo.Snapshots.load(path)


def test_input_times_and_accelerations_round_trip(tmp_path):
    ti = np.concatenate([[0.0], T[1:] - 0.04])  # a generalised-alpha loop: t_{n+1-alpha_f}
    s = lo.Snapshots(T, Q, V=-Q, A=-Q, U=np.sin(ti)[None], input_times=ti)
    back = lo.Snapshots.load(s.save(tmp_path / "s"))
    np.testing.assert_array_equal(back.input_times, ti)
    np.testing.assert_array_equal(back.A, -Q)
    w = s.window(0.3, 0.7)  # keeps the inputs around the window (one sample either side)
    assert w.input_times[0] <= 0.3 and w.input_times[-1] >= 0.7
    with pytest.raises(InputError, match="input_times must be strictly increasing"):
        lo.Snapshots(T, Q, U=np.sin(ti)[None], input_times=ti[::-1])
    with pytest.raises(InputError, match=r"U has shape \(1, 11\); it must be \(m, 12\)"):
        lo.Snapshots(T, Q, U=np.sin(ti[1:])[None], input_times=ti)
    with pytest.raises(InputError, match="A has shape"):
        lo.Snapshots(T, Q, A=Q[:, 1:])


# ---- the recorder (a tiny dolfinx mesh) ----

dolfinx = pytest.importorskip("dolfinx_lopinf.fem._dolfinx").dolfinx


def _space(dim=1):
    from mpi4py import MPI
    if dim == 1:
        msh = dolfinx.mesh.create_unit_interval(MPI.COMM_WORLD, 4)
        return dolfinx.fem.functionspace(msh, ("Lagrange", 1))
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 3, 2)
    return dolfinx.fem.functionspace(msh, ("Lagrange", 2, (2,)))


@pytest.mark.parametrize("scheme", [None, "newmark", "midpoint", "continuous",
                                    schemes.GeneralizedAlpha(0.2, 0.4)])
def test_recorder_passes_scheme_through(tmp_path, scheme):
    V = _space()
    u = dolfinx.fem.Function(V)
    rec = lo.SnapshotRecorder(u, scheme=scheme)
    for k in range(4):
        u.interpolate(lambda x, k=k: np.sin(x[0] + 0.1 * k))
        rec.record(0.1 * k, u, inputs=[float(k)])
    snaps = rec.snapshots()
    want = None if scheme is None else schemes.from_spec(scheme)
    assert snaps.scheme == want
    assert lo.Snapshots.load(snaps.save(tmp_path / "rec")).scheme == want


def test_recorder_default_is_unknown():
    u = dolfinx.fem.Function(_space())
    rec = lo.SnapshotRecorder(u)
    rec.record(0.0, u)
    rec.record(0.1, u)
    assert rec.snapshots().scheme is None


@pytest.mark.parametrize("bad", ["generalized_alpha", "auto", 2, "Newmark(gamma=0.3)"])
def test_recorder_refuses_unknown_scheme_before_recording(bad):
    u = dolfinx.fem.Function(_space())
    with pytest.raises(InputError, match=r"SnapshotRecorder\(scheme=\.\.\.\)"):
        lo.SnapshotRecorder(u, scheme=bad)


def test_rows_are_the_users_dofs_unless_asked_otherwise():
    """Q[i] is u.x.array[i] (serial): a user's own matrices apply to the snapshots as they are
    (before, the rows were sorted by coordinates and Q[i] was not dof i)."""
    V = _space(2)
    u = dolfinx.fem.Function(V)
    rec, by_xyz = lo.SnapshotRecorder(u), lo.SnapshotRecorder(u, order="coordinates")
    for k in range(3):
        u.x.array[:] = np.random.default_rng(k).standard_normal(u.x.array.size)
        rec.record(0.1 * k, u)
        by_xyz.record(0.1 * k, u)
        last = u.x.array.copy()
    Q = rec.snapshots().Q
    np.testing.assert_array_equal(Q[:, -1], last)
    Qc = by_xyz.snapshots().Q
    np.testing.assert_array_equal(Qc[:, -1], last[by_xyz.state_map.order])
    with pytest.raises(InputError, match="order must be one of"):
        lo.SnapshotRecorder(u, order="xyz")


def test_velocity_and_acceleration_functions_and_input_times():
    V = _space()
    u, v, a = (dolfinx.fem.Function(V) for _ in range(3))
    rec = lo.SnapshotRecorder(u, velocity=v, acceleration=a)
    dt, alpha_f = 0.1, 0.4
    for k in range(5):
        for f, c in ((u, 1.0), (v, 2.0), (a, 3.0)):
            f.x.array[:] = c * k
        rec.record(k * dt, u, inputs=[np.sin(k)], input_time=max(k * dt - alpha_f * dt, 0.0))
    s = rec.snapshots()
    np.testing.assert_allclose(s.V, 2 * s.Q)
    np.testing.assert_allclose(s.A, 3 * s.Q)
    np.testing.assert_allclose(s.input_times, [0.0, 0.06, 0.16, 0.26, 0.36])
    with pytest.raises(InputError, match="give it once"):
        rec.record(5 * dt, u, velocity=v)
    with pytest.raises(InputError, match="input times must increase"):
        rec.record(5 * dt, u, inputs=[0.0], input_time=0.1)
    w = dolfinx.fem.Function(_space(2))
    with pytest.raises(InputError, match="acceleration is a Function on another space"):
        lo.SnapshotRecorder(u, acceleration=w)
    with pytest.raises(InputError, match="velocity must be your loop's dolfinx Function"):
        lo.SnapshotRecorder(u, velocity=np.zeros(5))
    assert len(rec) == 5  # the refused calls stored nothing
