"""write_vtx / states_to_function: recorded states go back into the user's space and a .bp file
(values checked by reading the file with the adios2 python module where it is installed),
the same on 1 and 2 ranks, and bad input refused before anything is written."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

import dolfinx
from mpi4py import MPI

import dolfinx_lopinf as lo
from dolfinx_lopinf.errors import InputError
from dolfinx_lopinf.fem.state import StateMap
from dolfinx_lopinf.fem.vtx import state_rows, states_to_function, write_vtx

TIMES = 0.1 * np.arange(4)


def _field(x, t):
    return np.vstack([x[0] + t, x[1] * x[2] * (1 + t), np.sin(3 * x[0] + t)])


@pytest.fixture(scope="module", params=[1, 2], ids=["P1", "P2"])
def recorded(request):
    """A vector Lagrange field on a unit cube recorded at four times: (V, recorder, Q, the
    Function's local arrays (owned + ghosts) at each time)."""
    msh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 2, 2, 2)
    V = dolfinx.fem.functionspace(msh, ("Lagrange", request.param, (3,)))
    u = dolfinx.fem.Function(V)
    rec = lo.SnapshotRecorder(u)
    arrays = []
    for t in TIMES:
        u.interpolate(lambda x, t=t: _field(x, t))
        rec.record(t, u)
        arrays.append(u.x.array.copy())
    return V, rec, rec.snapshots().Q, arrays


def _expected_at_points(V, rec, Q):
    """(coordinate key -> (n_points, 3, K) values) from the recorded states: state row i is
    dof order[i] (block order[i] // 3, component order[i] % 3) at that block's coordinate."""
    X = V.tabulate_dof_coordinates()  # serial: local block index = global block index
    inverse = np.empty(len(rec.state_map.order), dtype=int)
    inverse[rec.state_map.order] = np.arange(len(inverse))
    rows = inverse.reshape(-1, 3)  # rows[b, c]: the state row of block b, component c
    return {tuple(np.round(x, 10)): Q[rows[b]] for b, x in enumerate(X)}


def _read_bp(path):
    adios2 = pytest.importorskip("adios2", reason="the adios2 python module reads .bp files")
    steps, points, values = [], [], []
    with adios2.Stream(str(path), "r") as f:
        for st in f.steps():
            nblocks = len(f.all_blocks_info("u")[st.current_step()])
            steps.append(float(f.read("step")))
            points.append(np.vstack([f.read("geometry", block_id=b) for b in range(nblocks)]))
            values.append(np.vstack([f.read("u", block_id=b) for b in range(nblocks)]))
    return np.array(steps), points, values


def _index_steps(path):
    """Steps in a BP4 index: a 64-byte header and one 64-byte record per step."""
    return (Path(path) / "md.idx").stat().st_size // 64 - 1


def test_file_values_equal_recorded(recorded, tmp_path):
    """recorder -> states -> write_vtx -> read the .bp: the values at every mesh point equal
    the recorded ones (matched by coordinates)."""
    V, rec, Q, _ = recorded
    path = write_vtx(tmp_path / "rom.bp", V, Q, TIMES, state_map=rec.state_map)
    assert _index_steps(path) == len(TIMES)
    expected = _expected_at_points(V, rec, Q)
    steps, points, values = _read_bp(path)
    np.testing.assert_array_equal(steps, TIMES)
    worst = 0.0
    for k in range(len(TIMES)):
        assert len(points[k]) >= len(expected)
        for x, val in zip(points[k], values[k]):
            worst = max(worst, np.abs(val - expected[tuple(np.round(x, 10))][:, k]).max())
    assert worst <= 1e-12 * np.abs(Q).max(), worst


def test_function_equals_recorded_arrays(recorded, tmp_path):
    """states_to_function is the exact inverse of the recorder (owned and ghost entries), and
    the .bp folder holds one step per column (no reader needed)."""
    V, rec, Q, arrays = recorded
    for k, arr in enumerate(arrays):
        f = states_to_function(V, Q[:, k], rec.state_map)
        np.testing.assert_array_equal(f.x.array, arr)
    path = write_vtx(tmp_path / "rom.bp", V, Q, TIMES)   # default state map = the recorder's
    assert path == (tmp_path / "rom.bp").absolute() and (path / "md.idx").exists()
    assert _index_steps(path) == len(TIMES)
    assert sorted(os.listdir(tmp_path)) == ["rom.bp"]      # no temporary folder left behind


def test_partial_rows_and_replace(recorded, tmp_path):
    """rows=: the listed state rows carry the given values, all others `fill`; an existing
    .bp folder is replaced."""
    V, rec, Q, arrays = recorded
    rows = state_rows(V, lambda x: np.isclose(x[2], 1.0))
    blocks = dolfinx.fem.locate_dofs_geometrical(V, lambda x: np.isclose(x[2], 1.0))
    assert len(rows) == 3 * len(blocks)
    f = states_to_function(V, Q[rows, 2], rec.state_map, rows=rows)
    dofs = (blocks[:, None] * 3 + np.arange(3)).ravel()
    mask = np.zeros(len(f.x.array), bool)
    mask[dofs] = True
    np.testing.assert_array_equal(f.x.array[mask], arrays[2][mask])
    assert np.all(f.x.array[~mask] == 0.0)
    path = tmp_path / "top.bp"
    write_vtx(path, V, Q[:, :2], TIMES[:2])
    write_vtx(path, V, Q[rows], TIMES, rows=rows, fill=np.nan)
    assert _index_steps(path) == len(TIMES) and sorted(os.listdir(tmp_path)) == ["top.bp"]


@pytest.mark.parametrize("case, match", [
    ("size", "rows but the space has"),
    ("nan", "NaN/inf"),
    ("times", "times must increase"),
    ("times_len", "one time per state column"),
    ("parent", "does not exist"),
    ("suffix", "must end in .bp"),
    ("rows", "rows lists"),
    ("engine", "engine must be one of"),
])
def test_bad_input_refused_before_writing(recorded, tmp_path, case, match):
    V, _, Q, _ = recorded
    args = {"path": tmp_path / "out.bp", "states": Q, "times": TIMES, "rows": None,
            "engine": "BP4"}
    if case == "size":
        args["states"] = Q[:-3]
    elif case == "nan":
        args["states"] = Q.copy()
        args["states"][5, 2] = np.nan
    elif case == "times":
        args["times"] = TIMES[[0, 2, 1, 3]]
    elif case == "times_len":
        args["times"] = TIMES[:3]
    elif case == "parent":
        args["path"] = tmp_path / "missing" / "out.bp"
    elif case == "suffix":
        args["path"] = tmp_path / "out.vtx"
    elif case == "rows":
        args["rows"] = np.arange(4)
    elif case == "engine":
        args["engine"] = "HDF5"
    with pytest.raises(InputError, match=match):
        write_vtx(args["path"], V, args["states"], args["times"], rows=args["rows"],
                  engine=args["engine"])
    assert os.listdir(tmp_path) == []                      # nothing written, no temporary


def test_bad_state_for_function(recorded):
    V, _, Q, _ = recorded
    with pytest.raises(InputError, match="rows but the space has"):
        states_to_function(V, Q[:-1, 0])
    with pytest.raises(InputError, match="1-d vector"):
        states_to_function(V, Q)
    other = dolfinx.fem.functionspace(V.mesh, ("Lagrange", 1))
    with pytest.raises(InputError, match="state map has"):
        states_to_function(V, Q[:, 0], StateMap.from_coordinates(other))
    dg = dolfinx.fem.functionspace(V.mesh, ("DG", 1))  # the default map is the dof order
    f = states_to_function(dg, np.arange(dg.dofmap.index_map.size_global, dtype=float))
    np.testing.assert_array_equal(f.x.array, np.arange(dg.dofmap.index_map.size_global))


@pytest.mark.mpi
def test_two_ranks_write_the_serial_values(tmp_path, mpiexec):
    """tests/fem/mpi_vtx.py on 1 and 2 ranks (states given on rank 0 only): the states put back
    into the Function and the values in the written file equal the serial ones."""
    script = Path(__file__).with_name("mpi_vtx.py")
    serial, parallel = tmp_path / "serial.npz", tmp_path / "parallel.npz"
    subprocess.run([sys.executable, str(script), str(serial)], check=True, timeout=300)
    proc = subprocess.run([mpiexec, "-n", "2", sys.executable, str(script), str(parallel)],
                          check=False, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    a, b = np.load(serial), np.load(parallel)
    scale = np.abs(a["Q"]).max()
    for d in (a, b):  # the Function holds exactly the states given, on any number of ranks
        np.testing.assert_array_equal(d["back"], d["Q"])
        assert int(d["index_steps"]) == 4
        assert int(d["refused"]) == 1 and not bool(d["bad_written"])   # refused on every rank
    assert np.abs(a["Q"] - b["Q"]).max() <= 1e-12 * scale       # interpolation rounding only
    if "read_u" in a.files and "read_u" in b.files:
        np.testing.assert_array_equal(a["read_x"], b["read_x"])
        np.testing.assert_array_equal(a["read_t"], b["read_t"])
        assert np.abs(a["read_u"] - b["read_u"]).max() <= 1e-12 * scale
