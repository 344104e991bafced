"""Issue 13, DOLFINx layer: no silent wrong answers, no lost data. Every input of ``run``,
``LagrangianSystem``, the integrators and the recorder is checked before any work; bcs on
another space, stale or corrupt checkpoints and half-done records are refused or repaired."""

import os
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

import ufl

import dolfinx_lopinf as lo
from dolfinx_lopinf.fem._dolfinx import MPI, PETSc, dolfinx
from dolfinx_lopinf.errors import (CheckpointMismatchError, FileFormatError,
                                   InputCorrectedWarning, InputError)
from dolfinx_lopinf.scenes import beam as scene

DT = 1e-3


def _p1(n=32, comm=MPI.COMM_WORLD, degree=1):
    msh = dolfinx.mesh.create_interval(comm, n, [0.0, 1.0])
    return dolfinx.fem.functionspace(msh, ("Lagrange", degree))


def _ends(V):
    return dolfinx.fem.locate_dofs_geometrical(
        V, lambda x: np.isclose(x[0], 0.0) | np.isclose(x[0], 1.0))


def _string(V, bcs=None, *, kinetic=True):
    """A P1 string L = 1/2 q_t^2 - 1/2 q_x^2 with fixed ends (bcs on V unless given)."""
    q, qt = dolfinx.fem.Function(V), dolfinx.fem.Function(V)
    L = (0.5 * qt**2 - 0.5 * q.dx(0) ** 2) * ufl.dx if kinetic else \
        (q * qt - 0.5 * q.dx(0) ** 2) * ufl.dx
    if bcs is None:
        bcs = [dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), _ends(V), V)]
    return lo.LagrangianSystem(L, q, qt, bcs=bcs)


def _initial(V, lift=0.0):
    x = V.tabulate_dof_coordinates()[:, 0]
    return x * (1 - x) + lift, np.zeros_like(x)


@pytest.fixture
def no_steps(monkeypatch):
    """Any step taken is a failure: the error must come before the run."""
    def step(self):
        raise AssertionError("a step was taken before the input error")
    monkeypatch.setattr(lo.fem.MidpointIntegrator, "step", step)


# -- item 2 / 13: a bc on another space ------------------------------------------------------

def test_bc_on_a_separately_created_identical_space_constrains_the_same_dofs():
    V = _p1()
    V2 = dolfinx.fem.functionspace(V.mesh, ("Lagrange", 1))  # the same, created again
    bc2 = dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), _ends(V2), V2)
    q0, v0 = _initial(V)
    ref, _ = lo.run(_string(V), q0, v0, DT, 0.2, record_every=10, progress=False)
    snaps, info = lo.run(_string(V, [bc2]), q0, v0, DT, 0.2, record_every=10, progress=False)
    assert np.abs(snaps.Q[[0, -1]]).max() == 0.0  # the ends stay fixed
    assert np.array_equal(snaps.Q, ref.Q)
    assert info["energy_drift"] < 1e-12


def test_bc_on_another_mesh_or_element_is_refused(beam):
    V = _p1()
    other = _p1()  # another mesh with the same number of dofs
    bc = dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), _ends(other), other)
    with pytest.raises(InputError, match=r"bcs\[0\] is defined on another mesh"):
        _string(V, [bc])
    P2 = dolfinx.fem.functionspace(V.mesh, ("Lagrange", 2))
    bc = dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), _ends(P2), P2)
    with pytest.raises(InputError, match=r"bcs\[0\] is defined on another function space"):
        _string(V, [bc])
    with pytest.raises(InputError, match=r"bcs\[1\] must be a dolfinx.fem.DirichletBC"):
        _string(V, [dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), _ends(V), V), _ends(V)])
    # the beam (cubic Hermite): a bc built on a P2 space of its mesh means other dofs
    Vb = beam.system.V
    P2b = dolfinx.fem.functionspace(Vb.mesh, ("Lagrange", 2))
    bc = dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), _ends(P2b), P2b)
    w, w_t = dolfinx.fem.Function(Vb), dolfinx.fem.Function(Vb)
    with pytest.raises(InputError, match=r"bcs\[0\].*Hermite"):
        lo.LagrangianSystem(ufl.replace(beam.system.lagrangian,
                                        {beam.system.q: w, beam.system.q_t: w_t}), w, w_t, bcs=[bc])


# -- item 5: an initial state that violates the bcs ------------------------------------------

def test_initial_state_violating_the_bcs_is_corrected_with_a_warning():
    V = _p1()
    q0, v0 = _initial(V, lift=0.1)
    v0 = v0 + 0.5
    with pytest.warns(InputCorrectedWarning) as record:
        snaps, _ = lo.run(_string(V), q0, v0, DT, 0.05, record_every=5, progress=False)
    messages = sorted(str(w.message) for w in record)
    assert len(messages) == 2
    assert messages[0].startswith("q0 violates the Dirichlet conditions by up to 0.1 ")
    assert messages[1].startswith("v0 violates the Dirichlet conditions by up to 0.5 ")
    assert np.abs(snaps.Q[[0, -1]]).max() == 0.0
    assert np.abs(snaps.V[[0, -1]]).max() == 0.0
    q0, v0 = _initial(V)
    with warnings.catch_warnings():
        warnings.simplefilter("error", InputCorrectedWarning)  # a consistent state: no warning
        lo.run(_string(V), q0, v0, DT, 0.01, progress=False)


# -- items 3 and 13: every argument of run checked before the first step ---------------------

@pytest.mark.parametrize("kw, match", [
    ({"dt": 0.0}, "dt must be a positive finite number, got 0.0"),
    ({"dt": float("nan")}, "dt must be a positive finite number, got nan"),
    ({"t_end": float("inf")}, "t_end must be finite"),
    ({"state_until": 0.3}, r"state_until = 0.3 must lie in \[record_every \* dt, t_end\]"),
    ({"state_until": -0.01}, "state_until = -0.01 must lie in"),
    ({"state_until": 0.0}, "state_until = 0.0 must lie in"),
    ({"record_every": 500}, "record_every = 500 is more than the 100 steps"),
    ({"record_every": 0}, "record_every must be >= 1"),
    ({"energy_until": 1.0}, "energy_until = 1.0 must lie in"),
    ({"energy_every": -1}, "energy_every must be >= 0"),
    ({"checkpoint_every": 0, "checkpoint": "CKPT"}, "checkpoint_every must be >= 1, got 0"),
    ({"checkpoint": "MISSING/run"}, "directory .*MISSING does not exist"),
    ({"output_matrix": np.ones((1, 3))}, r"output_matrix must be a real \(p, n_local\)"),
    ({"state_map": lo.fem.StateMap(np.arange(3), np.ones(3))}, "the space has 33 dofs"),
])
def test_run_refuses_bad_arguments_before_the_first_step(no_steps, tmp_path, kw, match):
    V = _p1()
    q0, v0 = _initial(V)
    args = dict(dt=DT, t_end=0.1, progress=False)
    args.update(kw)
    for key in ("checkpoint",):
        if key in args:
            args[key] = str(tmp_path / args[key])
    with pytest.raises(InputError, match=match):
        lo.run(_string(V), q0, v0, **args)


def test_lagrangian_without_kinetic_energy_is_refused_at_construction():
    V = _p1()
    with pytest.raises(InputError, match="no kinetic energy"):
        _string(V, kinetic=False)
    # kinetic energy for one component only: the mass matrix is singular
    W = dolfinx.fem.functionspace(V.mesh, ("Lagrange", 1, (2,)))
    q, qt = dolfinx.fem.Function(W), dolfinx.fem.Function(W)
    system = lo.LagrangianSystem((0.5 * qt[0] ** 2 - 0.5 * ufl.inner(ufl.grad(q), ufl.grad(q)))
                                 * ufl.dx, q, qt)
    with pytest.raises(InputError, match="mass matrix .* diagonal at 33 free dofs"):
        lo.fem.MidpointIntegrator(system, DT, prefix="nokin_")


def test_initial_state_on_another_space_is_refused():
    V = _p1()
    system = _string(V)
    other = dolfinx.fem.Function(_p1())
    with pytest.raises(InputError, match="q0 is a Function on another function space or mesh"):
        lo.run(system, other, other, DT, 0.01, progress=False)


# -- item 8: the recorder --------------------------------------------------------------------

def test_recorder_refuses_a_function_of_another_mesh():
    V = _p1()
    u = dolfinx.fem.Function(V)
    rec = lo.SnapshotRecorder(u)
    stranger = dolfinx.fem.Function(_p1())  # same number of dofs, another mesh
    with pytest.raises(InputError, match="u is a Function on another mesh"):
        rec.record(0.0, stranger)
    assert len(rec) == 0


def test_recorder_record_is_all_or_nothing():
    V = _p1()
    u = dolfinx.fem.Function(V)
    u.x.array[:] = 1.0
    E = lo.point_output_matrix(V, np.array([[0.5, 0, 0]]))
    rec = lo.SnapshotRecorder(u, output_matrix=E)
    rec.record(0.0, u, velocity=u, inputs=[1.0])
    for bad in (dict(velocity=np.ones(5), inputs=[1.0]),        # wrong velocity size
                dict(velocity=u, inputs=[np.nan]),               # NaN input
                dict(velocity=u, inputs=[1.0, 2.0]),             # input count changed
                dict(velocity=np.full(u.x.array.shape, np.inf), inputs=[1.0])):
        with pytest.raises(InputError):
            rec.record(0.1, u, **bad)
        assert len(rec) == 1 and len(rec._states) == len(rec._velocities) == len(rec._outputs) == 1
    rec.record(0.1, u, velocity=u, inputs=[2.0])
    snaps = rec.snapshots()
    assert snaps.Q.shape[1] == snaps.V.shape[1] == snaps.U.shape[1] == snaps.Y.shape[1] == 2


def test_a_nan_state_is_named_by_time_and_dof():
    """A diverged loop's state: the recorder's refusal names the time, how many values, the
    rank and the first dof (global) - not only "at this time"."""
    V = _p1()
    u = dolfinx.fem.Function(V)
    rec = lo.SnapshotRecorder(u)
    rec.record(0.0, u)
    u.x.array[3] = np.nan
    owned = V.dofmap.index_map.size_local
    first = V.dofmap.index_map.local_range[0] + 3
    with pytest.raises(InputError, match=rf"u recorded at t = 0.25 contains 1 NaN or inf value\(s\) "
                                         rf"on rank 0, first at dof {first} \(global") as info:
        rec.record(0.25, u)
    assert owned > 3 and "diverged" in str(info.value) and len(rec) == 1


# -- items 10 and 11: checkpoints ------------------------------------------------------------

def _written_bytes():
    with open("/proc/self/io") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("wchar"))


@pytest.mark.skipif(not os.path.exists("/proc/self/io"), reason="needs Linux /proc/self/io")
def test_checkpoints_write_only_what_changed(tmp_path):
    b = scene.build(60)
    q0, v0 = b.initial_state()
    before = _written_bytes()
    snaps, info = lo.run(b.system, q0, v0, scene.DT, 0.01, state_map=b.state_map, progress=False,
                         checkpoint=tmp_path / "c", checkpoint_every=50)
    written = _written_bytes() - before
    recorded = snaps.Q.nbytes + snaps.V.nbytes  # 1.9 MB; 19 full rewrites would be 37 MB
    assert written < 1.5 * recorded, (written, recorded)
    assert info["checkpoint_bytes"] < 1.5 * recorded
    assert not list(tmp_path.iterdir())


def test_corrupt_checkpoint_names_the_file_and_the_remedy(tmp_path, interrupted_run):
    V = _p1()
    system = _string(V)
    q0, v0 = _initial(V)
    kw = dict(dt=DT, t_end=0.1, record_every=2, checkpoint_every=20)
    prefix = tmp_path / "c"
    interrupted_run(system, q0, v0, prefix, 70, **kw)
    head = Path(f"{prefix}.rank0.npz")  # a head (step 40; the old format's only file)
    data = head.read_bytes()
    head.write_bytes(data[: len(data) // 2])
    with pytest.raises(FileFormatError, match=r"c\.rank0\.npz is truncated or corrupt.*"
                                              r"checkpoint_restart=True"):
        lo.run(system, q0, v0, progress=False, checkpoint=prefix, **kw)
    head.write_bytes(data)
    chunk = Path(f"{prefix}.rank0.part00001.npz")
    chunk.write_bytes(chunk.read_bytes()[:100])
    with pytest.raises(FileFormatError, match=r"c\.rank0\.part00001\.npz"):
        lo.run(system, q0, v0, progress=False, checkpoint=prefix, **kw)
    snaps, info = lo.run(system, q0, v0, progress=False, checkpoint=prefix,
                         checkpoint_restart=True, **kw)
    ref, _ = lo.run(system, q0, v0, progress=False, **kw)
    assert info["resumed_from_step"] == 0 and np.array_equal(snaps.Q, ref.Q)
    assert not list(tmp_path.iterdir())


def test_checkpoint_of_a_changed_forcing_is_refused(tmp_path, interrupted_run):
    V = _p1()
    q, qt = dolfinx.fem.Function(V), dolfinx.fem.Function(V)
    t = dolfinx.fem.Constant(V.mesh, PETSc.ScalarType(0.0))
    amp = dolfinx.fem.Constant(V.mesh, PETSc.ScalarType(1.0))
    v = ufl.TestFunction(V)
    bc = dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), _ends(V), V)
    system = lo.LagrangianSystem((0.5 * qt**2 - 0.5 * q.dx(0) ** 2) * ufl.dx, q, qt, bcs=[bc],
                                 forcing=amp * ufl.sin(5 * t) * v * ufl.dx, time=t)
    q0, v0 = _initial(V)
    kw = dict(dt=DT, t_end=0.1, checkpoint_every=20)
    interrupted_run(system, q0, v0, tmp_path / "f", 50, **kw)
    amp.value = 1.5
    with pytest.raises(CheckpointMismatchError, match="forcing at a probe state"):
        lo.run(system, q0, v0, progress=False, checkpoint=tmp_path / "f", **kw)
    amp.value = 1.0
    _, info = lo.run(system, q0, v0, progress=False, checkpoint=tmp_path / "f", **kw)
    assert info["resumed_from_step"] == 40


# -- MPI: same verdict on every rank ---------------------------------------------------------

MPI_SCRIPT = '''
import sys
import numpy as np
import ufl
import dolfinx_lopinf as lo
from dolfinx_lopinf.fem._dolfinx import MPI, PETSc, dolfinx
from dolfinx_lopinf.errors import CheckpointMismatchError, InputError
from dolfinx_lopinf.scenes import beam as scene

comm = MPI.COMM_WORLD
out = []
def ends(V):
    return dolfinx.fem.locate_dofs_geometrical(V, lambda x: np.isclose(x[0], 0) | np.isclose(x[0], 1))
def string(V, bcV):
    q, qt = dolfinx.fem.Function(V), dolfinx.fem.Function(V)
    bc = dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), ends(bcV), bcV)
    return lo.LagrangianSystem((0.5 * qt**2 - 0.5 * q.dx(0)**2) * ufl.dx, q, qt, bcs=[bc])
msh = dolfinx.mesh.create_interval(comm, 40, [0.0, 1.0])
V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
x = V.tabulate_dof_coordinates()[:, 0]
q0, v0 = x * (1 - x), 0 * x
ref, _ = lo.run(string(V, V), q0, v0, 1e-3, 0.05, progress=False)
V2 = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
snaps, _ = lo.run(string(V, V2), q0, v0, 1e-3, 0.05, progress=False)
out.append("mapped" if comm.rank or np.array_equal(snaps.Q, ref.Q) else "mapped-differs")
other = dolfinx.fem.functionspace(dolfinx.mesh.create_interval(comm, 40, [0.0, 1.0]), ("Lagrange", 1))
try:
    string(V, other)
except InputError:
    out.append("refused")
b = scene.build(40, comm)
q0, v0 = b.initial_state()
kw = dict(dt=scene.DT, t_end=0.003, record_every=10, checkpoint_every=100, state_map=b.state_map,
          progress=False, checkpoint=sys.argv[1])
class Killed(Exception):
    pass
step, n = lo.fem.MidpointIntegrator.step, [0]
def killer(self):
    n[0] += 1
    if n[0] > 150:
        raise Killed
    step(self)
lo.fem.MidpointIntegrator.step = killer
try:
    lo.run(b.system, q0, v0, **kw)
except Killed:
    pass
lo.fem.MidpointIntegrator.step = step
try:
    lo.run(scene.build(40, comm, ei=1.01 * scene.EI).system, q0, v0, **kw)
except CheckpointMismatchError as exc:
    out.append("stale-refused" if "step residual" in str(exc) else "stale-wrong-message")
snaps, info = lo.run(b.system, q0, v0, **kw)
kw.pop("checkpoint")
ref, _ = lo.run(b.system, q0, v0, **kw)
out.append(f"resumed{info['resumed_from_step']}")
if comm.rank == 0:
    out.append("equal" if np.array_equal(snaps.Q, ref.Q) and np.array_equal(snaps.V, ref.V) else "differs")
with open(f"{sys.argv[1]}.result{comm.rank}", "w") as f:
    f.write(f"rank{comm.rank}:" + ",".join(out))
'''


@pytest.mark.mpi
def test_bc_check_and_checkpoint_fingerprint_agree_on_two_ranks(tmp_path):
    import shutil

    exe = Path(sys.executable).with_name("mpiexec")
    mpiexec = str(exe) if exe.exists() else shutil.which("mpiexec")
    if mpiexec is None:
        pytest.skip("no mpiexec")
    script = tmp_path / "mpi_inputs.py"
    script.write_text(textwrap.dedent(MPI_SCRIPT))
    proc = subprocess.run([mpiexec, "-n", "2", sys.executable, str(script), str(tmp_path / "ck")],
                          capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = [(tmp_path / f"ck.result{r}").read_text() for r in range(2)]
    assert lines == ["rank0:mapped,refused,stale-refused,resumed100,equal",
                     "rank1:mapped,refused,stale-refused,resumed100"], proc.stdout
    assert not list(tmp_path.glob("ck.rank*"))


# -- the rest of the DOLFINx layer -----------------------------------------------------------

def test_streaming_pod_refuses_a_function_of_another_mesh(tmp_path):
    from dolfinx_lopinf.fem.streaming import StreamingPOD

    V = _p1()
    with StreamingPOD(V, capacity=3, directory=tmp_path) as spod:
        with pytest.raises(InputError, match="another mesh or function space"):
            spod.append(dolfinx.fem.Function(_p1()))
        assert spod.count == 0
    with pytest.raises(InputError, match="capacity must be an integer >= 2"):
        StreamingPOD(V, capacity=2.5)


def test_galerkin_rom_refuses_a_basis_of_the_wrong_size(beam):
    with pytest.raises(InputError, match=r"basis must be a finite \(n, r\) array with n = 400"):
        lo.fem.galerkin_rom(beam.system, np.eye(399)[:, :4], beam.state_map)
