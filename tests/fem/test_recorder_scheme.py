"""The integrator a user declares for their recording: SnapshotRecorder(u, scheme=...) ->
Snapshots.scheme, validated, kept by window() and by save/load (old files without it load as
None)."""

import numpy as np
import pytest

import dolfinx_lopinf as lo
from dolfinx_lopinf.errors import FileFormatError, InputError
from dolfinx_lopinf.core.snapshots import RECORDED_SCHEMES

T = np.arange(12) * 0.1
Q = np.vstack([np.cos(T), np.sin(T)])


@pytest.mark.parametrize("scheme", [None, *RECORDED_SCHEMES])
def test_valid_schemes_round_trip(tmp_path, scheme):
    s = lo.Snapshots(T, Q, U=np.sin(2 * T)[None], scheme=scheme)
    assert s.scheme == scheme
    w = s.window(0.2, 0.8)
    assert w.scheme == scheme and w.Q.shape == (2, 7)
    back = lo.Snapshots.load(s.save(tmp_path / "s.npz"))
    assert back.scheme == scheme and type(back.scheme) in (str, type(None))
    np.testing.assert_array_equal(back.Q, Q)
    np.testing.assert_array_equal(back.U, s.U)
    assert lo.Snapshots.load(w.save(tmp_path / "w.npz")).scheme == scheme


def test_numpy_str_is_stored_as_plain_str():
    s = lo.Snapshots(T, Q, scheme=np.str_("newmark"))
    assert s.scheme == "newmark" and type(s.scheme) is str


@pytest.mark.parametrize("bad, hint", [
    ("auto", "pass None"), ("Newmark", "did you mean 'newmark'"), ("generalised-alpha", None),
    ("", None), (1, None), (["newmark"], None), (b"newmark", None)])
def test_bad_scheme_names_value_and_choices(bad, hint):
    with pytest.raises(InputError) as info:
        lo.Snapshots(T, Q, scheme=bad)
    msg = str(info.value)
    assert repr(bad) in msg
    for choice in RECORDED_SCHEMES:
        assert repr(choice) in msg
    if hint:
        assert hint in msg


def test_old_files_without_scheme_load_as_none(tmp_path):
    # a file as Snapshots.save wrote it before the field existed
    path = tmp_path / "old.npz"
    np.savez_compressed(path, times=T, Q=Q, block__a=np.array([0]), block__b=np.array([1]))
    s = lo.Snapshots.load(path)
    assert s.scheme is None and sorted(s.blocks) == ["a", "b"]


@pytest.mark.parametrize("stored, match", [
    (np.array("generalised-alpha"), "stored snapshots are invalid"),
    (np.array(["newmark", "midpoint"]), "one text value"),
    (np.array(3.0), "one text value")])
def test_bad_stored_scheme_is_a_file_format_error(tmp_path, stored, match):
    path = tmp_path / "bad.npz"
    np.savez_compressed(path, times=T, Q=Q, scheme=stored)
    with pytest.raises(FileFormatError, match=match):
        lo.Snapshots.load(path)


# ---- the recorder (a tiny dolfinx mesh) ----

dolfinx = pytest.importorskip("dolfinx_lopinf.fem._dolfinx").dolfinx


def _space():
    from mpi4py import MPI
    msh = dolfinx.mesh.create_unit_interval(MPI.COMM_WORLD, 4)
    return dolfinx.fem.functionspace(msh, ("Lagrange", 1))


@pytest.mark.parametrize("scheme", [None, "newmark", "midpoint", "continuous"])
def test_recorder_passes_scheme_through(tmp_path, scheme):
    V = _space()
    u = dolfinx.fem.Function(V)
    rec = lo.SnapshotRecorder(u, scheme=scheme)
    for k in range(4):
        u.interpolate(lambda x, k=k: np.sin(x[0] + 0.1 * k))
        rec.record(0.1 * k, u, inputs=[float(k)])
    snaps = rec.snapshots()
    assert snaps.scheme == scheme
    assert lo.Snapshots.load(snaps.save(tmp_path / "rec")).scheme == scheme


def test_recorder_default_is_unknown():
    u = dolfinx.fem.Function(_space())
    rec = lo.SnapshotRecorder(u)
    rec.record(0.0, u)
    rec.record(0.1, u)
    assert rec.snapshots().scheme is None


@pytest.mark.parametrize("bad", ["generalized_alpha", "auto", 2])
def test_recorder_refuses_unknown_scheme_before_recording(bad):
    u = dolfinx.fem.Function(_space())
    with pytest.raises(InputError, match=r"SnapshotRecorder\(scheme=\.\.\.\).*'newmark'"):
        lo.SnapshotRecorder(u, scheme=bad)
