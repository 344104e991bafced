"""The numpy core works without any optional dependency (issue 15, layers and extras).

A subprocess blocks DOLFINx and every extra (``sys.modules[name] = None`` makes ``import name``
fail and ``importlib.util.find_spec(name)`` return None, as on a machine without them), then
runs the black-box path end to end: Snapshots -> lo.fit (scheme and mass "auto": the learned
mass is our own interior point, a candidate without cvxpy) -> predict -> save/load. A DOLFINx-only name must fail with the install hint.
"""

import ast
import json
import pathlib
import subprocess
import sys

BLOCKED = ["dolfinx", "dolfinx_solver", "ufl", "basix", "ffcx", "petsc4py", "mpi4py", "cvxpy",
           "clarabel", "pyvista", "vtk", "matplotlib", "gmsh", "numba", "llvmlite", "tqdm",
           "imageio", "opinf", "h5py", "adios2"]

SCRIPT = r"""
import json, sys, tempfile, warnings
for name in json.loads(sys.argv[1]):
    sys.modules[name] = None
import numpy as np
import dolfinx_lopinf as lo

# a 3-dof Newmark system, forced: the core's whole black-box path
rng = np.random.default_rng(0)
K = np.diag([1.0, 4.0, 9.0]); C = 0.01 * K; B = np.array([[1.0], [0.5], [0.2]])
rom = lo.core.LagrangianROM(K=K, C=C, B=B, scheme="newmark")
dt, n = 0.05, 800
u = lambda t: np.array([np.sin(1.3 * t) + 0.3 * np.sin(3.1 * t)])
tr = rom.simulate(np.zeros(3), np.zeros(3), dt, n, inputs=u)
U = np.array([u(t)[0] for t in tr.times])[None, :]
lift = np.linalg.qr(rng.standard_normal((12, 3)))[0]  # orthonormal: the reduced mass stays I
snaps = lo.Snapshots(tr.times, lift @ tr.Qh, U=U)
with warnings.catch_warnings():
    warnings.simplefilter("ignore", lo.errors.LOpInfWarning)
    model = lo.fit(snaps, 3)
pred = model.predict(n, inputs=U)
err = lo.relative_error(snaps.Q, model.reconstruct(pred.Qh))
with tempfile.TemporaryDirectory() as d:
    back = lo.ReducedModel.load(model.save(d + "/rom.npz"))
try:
    lo.run
    dolfinx_error = "none"
except ImportError as exc:
    dolfinx_error = str(exc)
viz = sorted(lo.viz.__all__)  # lo.viz is reachable and imports pyvista/matplotlib only to draw
loaded = sorted(m for m in json.loads(sys.argv[1]) if sys.modules.get(m) is not None)
print(json.dumps({"scheme": model.scheme.spec, "mass": model.report["mass"], "error": err,
                  "candidates": sorted(model.report.get("candidate_errors", {})),
                  "backend": pred.backend, "same": bool(np.array_equal(back.rom.K, model.rom.K)),
                  "dolfinx_error": dolfinx_error, "loaded": loaded, "viz": viz}))
"""


def test_numpy_core_runs_without_dolfinx_or_any_extra():
    proc = subprocess.run([sys.executable, "-c", SCRIPT, json.dumps(BLOCKED)], capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["loaded"] == [], out                      # nothing blocked slipped in
    assert out["scheme"] == "newmark(beta=0.25, gamma=0.5)", out
    assert any("learned" in c for c in out["candidates"]), out  # no cvxpy needed for it
    assert out["backend"] == "numpy", out                # the fallback loop, no numba
    assert out["error"] < 1e-6, out                      # exact data, exact relation
    assert out["same"], out
    assert "DOLFINx" in out["dolfinx_error"], out        # the FOM layer names what to install
    assert "deformed_side_by_side" in out["viz"], out     # lo.viz without its extras loaded


# -- the import graph: layers, no circles, core tests on the core alone -----------------------

ROOT = pathlib.Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "dolfinx_lopinf"


def _module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: pathlib.Path, modules: set) -> set:
    """The package's modules ``path`` imports anywhere (function-local imports included)."""
    name = _module_name(path)
    base = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            stem = base[:len(base) - node.level + 1] if node.level else []
            mod = ".".join(stem + ([node.module] if node.module else []))
            targets = [f"{mod}.{a.name}" for a in node.names] + [mod]
        else:
            continue
        for t in targets:
            while t and t not in modules:
                t = t.rpartition(".")[0]
            if t and t != name and not name.startswith(t + "."):  # a module's own package: its face
                out.add(t)
    return out


def _graph():
    files = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    return {m: _imports(p, set(files)) for m, p in files.items()}


def test_no_two_modules_import_each_other():
    """No circle of two modules, function-local imports included (a package's __init__ that
    hands its submodules' names on is its face, not a party)."""
    graph = _graph()
    pairs = sorted({tuple(sorted((a, b))) for a, deps in graph.items() for b in deps
                    if a in graph.get(b, ()) and not (a.startswith(b + ".") or b.startswith(a + "."))})
    assert pairs == [], pairs


def test_core_imports_neither_the_dolfinx_layer_nor_anything_above_it():
    graph = _graph()
    above = ("dolfinx_lopinf.fem", "dolfinx_lopinf.scenes", "dolfinx_lopinf.studies",
             "dolfinx_lopinf.viz")
    bad = {m: sorted(d for d in deps if d.startswith(above)) for m, deps in graph.items()
           if m.startswith("dolfinx_lopinf.core")}
    assert not {m: d for m, d in bad.items() if d}, bad


def test_core_tests_use_the_core_alone():
    """The numpy core's tests do not import the studies, scenes or the DOLFINx layer (their
    data generators live in dolfinx_lopinf.core.synthetic)."""
    bad = {}
    for path in sorted((ROOT / "tests" / "core").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            for n in names:
                if n.startswith(("dolfinx_lopinf.studies", "dolfinx_lopinf.scenes", "dolfinx_lopinf.fem")):
                    bad.setdefault(path.name, []).append(n)
    assert bad == {}, bad
