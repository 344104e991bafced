"""The learned-mass and polynomial tables of the inference benchmark
(``python -m dolfinx_lopinf.studies.benchmark --mass --poly``): our certified interior points
against Clarabel on the same problem, on held-out-style data.

Learned-mass data kinds (:func:`mass_data`), each a forced, damped system whose mass is not I
in the coordinates the fit sees, with sensor noise:

* ``modal``: a random SPD mass (two decades), stiffness and Rayleigh damping in random
  coordinates - the learned mass test's system, r coordinates;
* ``chainpod``: a 60-mass chain (non-uniform masses, both ends free: a rigid mode, half the
  dampers missing) in the Euclidean POD basis of its Newmark trajectory - the state
  covariance W of POD coordinates, eigenvalues over many decades (ill-conditioned W), as a
  black-box user's basis gives;
* ``active``: a modal system with rigid and undamped modes in random non-orthogonal
  coordinates: the K and C floors active at the optimum;
* ``nearexact``: near-exact data, as a recorded dolfinx loop gives them - a 150-node bar
  (consistent mass, Rayleigh damping) under a smooth body load, integrated with the
  average-acceleration Newmark scheme, Euclidean POD to r without noise: the POD spectrum
  falls to 1e-6 .. 1e-8 by r = 8 .. 16 and the fit's residual is the truncation alone
  (:func:`near_exact` also predicts an unseen load against the free fit and the intrusive
  ROM);
* ``nearbeam``: the same with a clamped Euler-Bernoulli beam (Hermite elements): its modal
  amplitudes fall as omega^-2 ~ k^-4, the POD spectrum to 1e-8 / 7e-10 by r = 8 / 12 - the
  regime of the recorded 3D cantilevers;
* ``file:PATH``: recorded snapshots (``lo.Snapshots.save``, e.g. ``demos/own_loop.py``'s
  train_newmark.npz), Euclidean POD to r, the Newmark relation.

The Clarabel row solves the same problem (the same regulariser tau, taken from our answer)
through cvxpy with its default tolerances; ``phi`` compares the objectives, ``gap`` is each
solver's own certificate (ours: the dual bound; Clarabel: its primal-dual gap).

Polynomial data (:func:`poly_data`): the sum-of-squares potential of the polynomial tests
(coordinates 1 .. 1e-4 in scale), sampled as probe data with 1e-4 noise.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

MASS_KINDS = ("modal", "chainpod", "active", "nearexact", "nearbeam")


def _spd(rng, r, spread):
    Q = np.linalg.qr(rng.standard_normal((r, r)))[0]
    return Q @ np.diag(np.geomspace(1.0, spread, r)) @ Q.T


def _newmark(M, K, C, B, u, n, dt, rng):
    from ..core.rom import LagrangianROM

    rom = LagrangianROM(K=K, M=M, C=C, B=B, scheme="newmark", lagrangian=False)
    return rom.simulate(rng.standard_normal(len(K)) * 0.1, np.zeros(len(K)), dt, n, inputs=u)


def _relation(Q, dt, u, noise, rng):
    from ..core.ddt import newmark_data

    t = dt * np.arange(Q.shape[1])
    U = np.array([u(s) for s in t]).T
    Q = Q + noise * np.abs(Q).max() * rng.standard_normal(Q.shape)
    return newmark_data(Q, t, U)


def mass_data(kind: str, r: int, n: int = 1500, seed: int = 0):
    """(Qbar, D1, D2, Ubar) of a learned-mass data set (module docstring)."""
    rng = np.random.default_rng(seed + 100 * r)
    dt = 0.01
    f = rng.uniform(0.5, 3.0, 3)

    def u(t):
        return np.array([np.sin(f[0] * t) + 0.5 * np.sin(f[1] * t), np.cos(f[2] * t)])

    if kind == "modal":
        M, K = _spd(rng, r, 1e-2), _spd(rng, r, 100.0)
        C, B = 0.02 * M + 1e-3 * K, rng.standard_normal((r, 2))
        tr = _newmark(M, K, C, B, u, n, dt, rng)
        return _relation(tr.Qh, dt, u, 1e-4, rng)
    if kind == "active":
        T = rng.standard_normal((r, r)) + 2.0 * np.eye(r)  # non-orthogonal coordinates
        w2 = np.concatenate([np.zeros(1 + r // 4), np.geomspace(1.0, 400.0, r - 1 - r // 4)])
        zeta = np.where(rng.permutation(r) < max(2, r // 3), 0.0, 0.02)
        Mm = np.geomspace(1.0, 0.05, r)
        K, C = np.diag(Mm * w2), np.diag(2 * zeta * np.sqrt(w2) * Mm)
        Ti = np.linalg.inv(T)
        M, K, C = Ti.T @ np.diag(Mm) @ Ti, Ti.T @ K @ Ti, Ti.T @ C @ Ti
        B = rng.standard_normal((r, 2))
        tr = _newmark(0.5 * (M + M.T), 0.5 * (K + K.T), 0.5 * (C + C.T), B, u, n, dt, rng)
        return _relation(tr.Qh, dt, u, 1e-4, rng)
    if kind == "chainpod":
        N = 60
        k = rng.uniform(50.0, 200.0, N - 1)
        m = rng.uniform(0.5, 2.0, N)
        c = np.where(rng.uniform(size=N - 1) < 0.5, 0.0, rng.uniform(0.01, 0.05, N - 1))
        K, C = np.zeros((N, N)), np.zeros((N, N))
        for i in range(N - 1):
            for A, v in ((K, k[i]), (C, c[i])):
                A[i, i] += v
                A[i + 1, i + 1] += v
                A[i, i + 1] -= v
                A[i + 1, i] -= v
        B = np.zeros((N, 2))
        B[0, 0], B[N // 2, 1] = 1.0, 1.0
        tr = _newmark(np.diag(m), K, C, B, u, n, dt, rng)
        from ..core.basis import pod

        basis = pod(tr.Qh, r)
        return _relation(basis.project(tr.Qh), dt, u, 1e-6, rng)
    if kind in ("nearexact", "nearbeam"):
        return near_exact(r, "beam" if kind == "nearbeam" else "bar")["relation"]
    if kind.startswith("file:"):
        from ..core.basis import pod
        from ..core.ddt import newmark_data
        from ..core.snapshots import Snapshots

        S = Snapshots.load(kind[5:])
        return newmark_data(pod(S.Q, r).project(S.Q), S.times, S.U)
    raise ValueError(f"kind must be one of {MASS_KINDS} or file:PATH, not {kind!r}")


def _bar(N=150):
    """The near-exact kind's full model: a clamped-free bar of N linear elements (consistent
    mass, unit stiffness and density, Rayleigh damping) loaded by the body force x^2."""
    h = 1.0 / N
    K, M = np.zeros((N + 1, N + 1)), np.zeros((N + 1, N + 1))
    for e in range(N):
        K[e:e + 2, e:e + 2] += np.array([[1.0, -1.0], [-1.0, 1.0]]) / h
        M[e:e + 2, e:e + 2] += h / 6.0 * np.array([[2.0, 1.0], [1.0, 2.0]])
    K, M = K[1:, 1:], M[1:, 1:]  # clamped at x = 0
    x = h * np.arange(1, N + 1)
    return M, K, 0.05 * M + 2e-4 * K, (M @ x**2)[:, None]


def _beam(N=40):
    """nearbeam's full model: a clamped Euler-Bernoulli beam of N Hermite elements (deflection
    and slope per node, consistent mass, unit EI and density, Rayleigh damping) under the
    body load x on the deflections."""
    h = 1.0 / N
    ke = np.array([[12, 6 * h, -12, 6 * h], [6 * h, 4 * h * h, -6 * h, 2 * h * h],
                   [-12, -6 * h, 12, -6 * h], [6 * h, 2 * h * h, -6 * h, 4 * h * h]]) / h**3
    me = h / 420 * np.array([[156, 22 * h, 54, -13 * h], [22 * h, 4 * h * h, 13 * h, -3 * h * h],
                             [54, 13 * h, 156, -22 * h], [-13 * h, -3 * h * h, -22 * h, 4 * h * h]])
    n = 2 * (N + 1)
    K, M = np.zeros((n, n)), np.zeros((n, n))
    for e in range(N):
        K[2 * e:2 * e + 4, 2 * e:2 * e + 4] += ke
        M[2 * e:2 * e + 4, 2 * e:2 * e + 4] += me
    K, M = K[2:, 2:], M[2:, 2:]  # clamped at x = 0
    f = np.zeros(len(K))
    f[0::2] = h * h * np.arange(1, N + 1)
    return M, K, 0.05 * M + 2e-4 * K, f[:, None]


def _bar_train(t):
    return np.array([np.sin(0.7 * t) * min(t / 2.0, 1.0) + 0.5 * np.sin(1.1 * t)])


def _bar_test(t):
    return np.array([np.tanh(t) * np.cos(0.9 * t) + 0.3 * np.sin(0.5 * t)])


def near_exact(r: int, model: str = "bar", n: int = 400, dt: float = 0.02) -> dict:
    """The ``nearexact`` kind at r (``model="beam"``: ``nearbeam``): ``relation`` (Qk, Qc, Qm, Uf) of the Newmark scheme on the
    POD coordinates of the training run, ``predict(ops)`` (the relative error of a fitted
    model on the unseen load, in the POD coordinates), ``free`` and ``intrusive`` (the same
    error of the free fit - M = I, K, C, B unconstrained - and of the Galerkin ROM V^T {M, K,
    C, B} V), ``sv_ratio`` (the last POD singular value over the first)."""
    from ..core.basis import pod
    from ..core.identify import Residual
    from ..core.metrics import relative_error
    from ..core.rom import LagrangianROM
    from ..core.schemes import Newmark

    scheme = Newmark(0.25, 0.5)
    M, K, C, B = _beam() if model == "beam" else _bar()
    N = len(K)
    fom = LagrangianROM(K=K, M=M, C=C, B=B, scheme=scheme, lagrangian=False)
    train = fom.simulate(np.zeros(N), np.zeros(N), dt, n, inputs=_bar_train)
    test = fom.simulate(np.zeros(N), np.zeros(N), dt, n, inputs=_bar_test)
    basis = pod(train.Qh, r)
    Qh, truth = basis.project(train.Qh), basis.project(test.Qh)
    t = dt * np.arange(n + 1)
    U = np.array([_bar_train(s) for s in t]).T

    def predict(M_, K_, C_, B_):
        rom = LagrangianROM(K=K_, M=M_, C=C_, B=B_, scheme=scheme, lagrangian=False)
        return relative_error(truth, rom.simulate(np.zeros(r), np.zeros(r), dt, n, inputs=_bar_test).Qh)

    free = Residual([(Qh, t, U, None, None, None)]).free_operators(scheme)
    V = basis.V
    sv = np.linalg.svd(Qh, compute_uv=False)
    return {"relation": scheme.relation(Qh, t, U), "predict": predict,
            "free": predict(np.eye(r), free.K, free.C, free.B),
            "intrusive": predict(V.T @ M @ V, V.T @ K @ V, V.T @ C @ V, V.T @ B),
            "sv_ratio": float(sv[-1] / sv[0])}


def _phi(problem, theta, tau):
    r = problem.r
    x = problem.index.vech(theta.reshape(r, problem.n_blocks, r).transpose(1, 0, 2)) - problem.x_floor
    return problem.misfit(x) - tau * np.linalg.slogdet(theta[:, :r] - problem.floors[0])[1]


def mass_row(kind: str, r: int, repeats: int = 3, clarabel: bool = True) -> dict:
    """One learned-mass row: ours (median of ``repeats`` solves, compiled when numba is there)
    against Clarabel on the same problem."""
    from ..core import mass
    from ..core.lsq.fractional import MassInteriorPoint

    data = mass_data(kind, r)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prep = mass.prepare(*data, damping=True, eps=1e-8, ridge=1e-9, strict=False, rho=mass.RHO)
    p = prep.problem
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        xs, Y, tau, cert = MassInteriorPoint().solve(p)
        times.append(time.perf_counter() - t0)
    row = {"set": kind, "r": r, "ours_ms": 1e3 * float(np.median(times)), "iterations": cert.iterations,
           "gap": cert.duality_gap, "certified": bool(cert.converged), "backend": cert.details["backend"],
           "phi": _phi(p, p.theta(xs), tau), "clarabel_ms": float("nan"), "clarabel_gap": float("nan"),
           "clarabel_phi": float("nan"), "clarabel_status": None}
    if clarabel:
        try:
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                theta, info = mass.solve_cvxpy(p, tau=tau)
            row.update(clarabel_ms=1e3 * (time.perf_counter() - t0), clarabel_gap=info["duality_gap"],
                       clarabel_phi=_phi(p, theta, tau), clarabel_status=info["clarabel_status"])
        except Exception as exc:  # noqa: BLE001 - a failed reference is a row entry, not a crash
            row["clarabel_status"] = f"failed: {exc}"[:80]
    scale = max(abs(row["phi"]), 1e-300)
    row["phi_difference"] = (row["clarabel_phi"] - row["phi"]) / scale
    return row


def poly_data(r: int, seed: int = 2):
    """Probe-style data of the polynomial tests' sum-of-squares potential (1e-4 noise)."""
    from ..core import polynomial as pl

    rng = np.random.default_rng(seed)
    n = r + r * (r + 1) // 2
    H = rng.standard_normal((n, n))
    G = H @ H.T / n + 0.1 * np.eye(n)
    M2, M3, M4 = pl.gram_maps(r)
    theta0 = np.concatenate([M2 @ G.ravel(), M3 @ G.ravel(), M4 @ G.ravel()])
    scales = np.logspace(0, -4, r)
    div = np.concatenate([pl._monomial_scale(np.sqrt(scales), pl.monomials(r, d)) for d in (2, 3, 4)])
    pot = pl.PolynomialPotential.from_coefficients(theta0 / div, r)
    N = int(3 * pl.n_unknowns(r, 1)["total"] / r) + 10
    rng = np.random.default_rng(4)
    Q = scales[:, None] * rng.standard_normal((r, N))
    V = scales[:, None] * rng.standard_normal((r, N))
    U = rng.uniform(-1, 1, (1, N))
    C = np.diag(0.1 / scales) @ (np.eye(r) + 0.1) @ np.diag(0.1 / scales) * 1e-3
    C = 0.5 * (C + C.T) + 1e-3 * np.eye(r)
    B = rng.standard_normal((r, 1))
    A = -(pot.gradient(Q) + C @ V) + B @ U
    return pl.point_data(Q, V, A * (1 + 1e-4 * rng.standard_normal(A.shape)), U)


def poly_row(r: int, data=None, label: str = "stiff") -> dict:
    from ..core import polynomial as pl

    data = poly_data(r) if data is None else data
    row = {"set": label, "r": r}
    for solver in ("ipm", "cvxpy"):
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ops = pl.fit_polynomial(data, constraint="sos", solver=solver)
        c = ops.certificate
        row[solver] = {"seconds": time.perf_counter() - t0, "gap": c["duality_gap"], "certified": c["certified"],
                       "iterations": c.get("iterations"), "relative_residual": c["relative_residual"],
                       "min_eig_gram": c["min_eig_gram"]}
    return row


def print_mass_header():
    print(f"\nlearned mass: ours (certified interior point) vs Clarabel on the same problem\n"
          f"{'set':>9} {'r':>3} {'ours ms':>9} {'its':>4} {'gap':>9} {'Clarabel ms':>12} {'gap':>9} "
          f"{'speed-up':>9} {'phi diff':>9} cert")


def print_mass_row(row):
    speed = row["clarabel_ms"] / row["ours_ms"] if row["ours_ms"] > 0 else float("nan")
    print(f"{row['set'][:9]:>9} {row['r']:>3} {row['ours_ms']:9.2f} {row['iterations']:>4} {row['gap']:9.1e} "
          f"{row['clarabel_ms']:12.1f} {row['clarabel_gap']:9.1e} {speed:9.1f} "
          f"{row['phi_difference']:9.1e} {row['certified']}", flush=True)


def print_poly_header():
    print(f"\npolynomial sos fit: ours (solver='ipm') vs Clarabel (the default)\n"
          f"{'set':>6} {'r':>3} {'ipm s':>8} {'gap':>9} {'rel.res':>9} {'Clarabel s':>11} {'gap':>9} "
          f"{'rel.res':>9}")


def print_poly_row(row):
    a, b = row["ipm"], row["cvxpy"]
    print(f"{row['set']:>6} {row['r']:>3} {a['seconds']:8.2f} {a['gap']:9.1e} {a['relative_residual']:9.2e} "
          f"{b['seconds']:11.2f} {b['gap']:9.1e} {b['relative_residual']:9.2e}", flush=True)
