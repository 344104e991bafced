"""Synthetic data sets of known mechanical systems, for the tests and the inference benchmark.

Every generator simulates a system whose operators are known (numpy only) and returns data in
the form the fits take, with sensor noise where stated:

* :func:`forced_data`, :func:`active_data`, :func:`chain_data` (:func:`mechanical_data` picks
  one by name): (Qh, dQh, ddQh, U) for :func:`~dolfinx_lopinf.core.infer_mechanical`, forced
  and damped, with the PSD constraints of the fit active in the ``active`` and ``chain`` kinds;
* :func:`wave_data`: (Qh, ddQh, Fh) for :func:`~dolfinx_lopinf.core.infer_wave`;
* :func:`mass_data`: the Newmark relation (Qbar, D1, D2, Ubar) of systems whose mass is not I
  in the coordinates the fit sees (the learned-mass fit);
* :func:`stiff_potential`, :func:`potential_samples`: a sum-of-squares quartic potential whose
  coordinates differ in scale by 1e4 and probe-style samples of its forced, damped dynamics
  (the polynomial fit).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .basis import pod
from .ddt import derivatives, newmark_data
from .polynomial.fit import _monomial_scale, point_data
from .polynomial.potential import PolynomialPotential, gram_maps, monomials
from .rom import LagrangianROM


def orthogonal(rng, r):
    """A random (r, r) rotation (Haar-distributed: QR of a Gaussian matrix, signs fixed)."""
    Q, R = np.linalg.qr(rng.standard_normal((r, r)))
    return Q * np.sign(np.diag(R))


def forced_data(r, n, seed=0):
    """(Qh, dQh, ddQh, U) of a forced, damped system (K, C SPD, one input of three sines), the
    states with 1e-3 noise and differentiated: the unconstrained fit is indefinite."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((r, r))
    K = A @ A.T / r + 0.5 * np.eye(r)
    Cm = rng.standard_normal((r, r))
    C = 0.05 * Cm @ Cm.T / r + 0.01 * np.eye(r)
    B = rng.standard_normal((r, 1))
    freqs = rng.uniform(0.5, 3.0, size=3)

    def u(t):
        return np.array([np.sin(freqs * t).sum()])

    dt = 2e-3
    tr = LagrangianROM(K=K, C=C, B=B).simulate(rng.standard_normal(r), rng.standard_normal(r),
                                               dt, n + 7, inputs=u)
    Q = tr.Qh + 1e-3 * np.abs(tr.Qh).max() * rng.standard_normal(tr.Qh.shape)
    Qh, dQh, ddQh = derivatives(Q, tr.times)
    U = np.column_stack([u(t) for t in tr.times])[:, 4:-4]
    return Qh, dQh, ddQh, U


#: kinds of :func:`active_data`: data whose certified fit has BOTH Kh and Ch on their
#: constraint (eigenvalues at eps), each of a different spectrum
ACTIVE_KINDS = ("rigid", "mixed", "short")


#: held-out-style kinds of :func:`chain_data` (in the --table run, not in the default one)
HELD_OUT_KINDS = ("chain",)


def active_data(kind: str, r: int, n: int, seed: int = 0):
    """Forced data (Qh, dQh, ddQh, U) whose certified fit has both Kh and Ch active.

    A modal system K = V diag(w^2) V^T, C = V diag(2 zeta w) V^T (V a random rotation, so
    neither is diagonal in the coordinates), one input of three sines, simulated exactly;
    then "sensor" noise (positions, velocities and accelerations each with independent
    Gaussian noise relative to their largest entry - unbiased in K, unlike differencing a
    noisy Qh, whose second difference correlates negatively with Qh and biases K upwards).
    Undamped modes (zeta = 0) make Ch's fit indefinite, modes of (near-)zero or slightly
    negative stiffness Kh's:

    * ``rigid``: 1 + r // 4 rigid-body modes (w = 0), stiffness condition 1e3 on the rest,
      a third of the modes (at least two) undamped, noise 1e-3;
    * ``mixed``: a softening mode (w^2 = -1e-3) and a rigid one, stiffness condition 1e4
      on the rest, every other mode overdamped (zeta 2-5), the others undamped, dt = 1e-3;
    * ``short``: a short record (n dt = 0.6-2 s at dt = 2e-4: less than a period of the slow
      modes), modes w^2 = 0, 1e-6, 1e-4 and 0.5-2e3, half undamped, noise 3e-3, faster input.
    """
    rng = np.random.default_rng(seed + 1000 * r)
    V = orthogonal(rng, r)
    dt, noise, fscale = 2e-3, 1e-3, 1.0
    if kind == "rigid":
        nr = 1 + r // 4
        w2 = np.concatenate([np.zeros(nr), np.geomspace(1.0, 1e3, r - nr)])
        zeta = np.where(rng.permutation(r) < max(2, r // 3), 0.0, 0.02)
    elif kind == "mixed":
        w2 = np.concatenate([[-1e-3, 0.0], np.geomspace(1.0, 1e4, r - 2)])
        zeta = np.where(np.arange(r) % 2 == 0, rng.uniform(2, 5, r), 0.0)
        dt = 1e-3
    elif kind == "short":
        w2 = np.concatenate([[0.0, 1e-6, 1e-4], np.geomspace(0.5, 2e3, r - 3)])
        zeta = np.where(rng.permutation(r) < r // 2, 0.0, 0.05)
        noise, dt, fscale = 3e-3, 2e-4, 10.0
    else:
        raise InputError(f"kind must be one of {ACTIVE_KINDS}, not {kind!r}")
    w = np.sqrt(np.abs(w2))
    K = V @ np.diag(w2) @ V.T
    C = V @ np.diag(2 * zeta * w) @ V.T
    B = rng.standard_normal((r, 1))
    freqs = rng.uniform(0.5, 3.0, size=3) * fscale

    def u(t):
        return np.array([np.sin(freqs * t).sum()])

    tr = LagrangianROM(K=0.5 * (K + K.T), C=0.5 * (C + C.T), B=B, lagrangian=False).simulate(
        rng.standard_normal(r), rng.standard_normal(r), dt, n + 7, inputs=u)
    exact = derivatives(tr.Qh, tr.times)
    Qh, dQh, ddQh = (A + noise * np.abs(A).max() * rng.standard_normal(A.shape) for A in exact)
    U = np.column_stack([u(t) for t in tr.times])[:, 4:-4]
    return Qh, dQh, ddQh, U


def _chain(n, k, c):
    """(K, C, B) of a chain of n masses joined by springs k[i] and dampers c[i] between masses i
    and i + 1 (both ends free), two inputs: at the first and at the middle mass."""
    K, C = np.zeros((n, n)), np.zeros((n, n))
    for i in range(n - 1):
        for A, v in ((K, k[i]), (C, c[i])):
            A[i, i] += v
            A[i + 1, i + 1] += v
            A[i, i + 1] -= v
            A[i + 1, i] -= v
    B = np.zeros((n, 2))
    B[0, 0], B[n // 2, 1] = 1.0, 1.0
    return K, C, B


def chain_data(r: int, n: int, seed: int = 0):
    """A forced, damped spring chain of r masses, both ends free (a rigid mode), half the
    dampers missing, two inputs (at the first and the middle mass), n samples, sensor noise
    1e-3: the held-out style (both Kh and Ch active at the optimum)."""
    rng = np.random.default_rng(seed + 7 * r)
    k = rng.uniform(0.5, 2.0, r)
    c = np.where(rng.uniform(size=r) < 0.5, 0.0, rng.uniform(0.01, 0.1, r))
    K, C, B = _chain(r, k, c)
    f1, f2 = rng.uniform(0.3, 2.0, 2)

    def u(t):
        return np.array([np.sin(f1 * t) + 0.3 * np.sin(3.1 * f1 * t), np.cos(f2 * t)])

    tr = LagrangianROM(K=K, C=C, B=B, lagrangian=False).simulate(
        rng.standard_normal(r), rng.standard_normal(r), 0.01, n + 7, inputs=u)
    exact = derivatives(tr.Qh, tr.times)
    Qh, dQh, ddQh = (A + 1e-3 * np.abs(A).max() * rng.standard_normal(A.shape) for A in exact)
    U = np.column_stack([u(t) for t in tr.times])[:, 4:-4]
    return Qh, dQh, ddQh, U


def mechanical_data(kind: str, r: int, n: int, seed: int = 0):
    """(Qh, dQh, ddQh, U) of a forced data set: :func:`forced_data` for ``"forced"``,
    :func:`chain_data` for ``"chain"``, else :func:`active_data` of that kind."""
    if kind == "chain":
        return chain_data(r, n, seed)
    return forced_data(r, n, seed) if kind == "forced" else active_data(kind, r, n, seed)


def wave_data(r, n, seed=0):
    """(Qh, ddQh, Fh) of the gray-box wave relation ddQh = K Qh - Fh (K symmetric negative
    definite, Fh = sin(Qh)) with 1e-6 noise."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((r, r))
    K = -(A @ A.T) / r
    t = np.linspace(0, 20, n)
    Qh = np.vstack([np.sin((i + 1) * 0.7 * t + rng.uniform(0, 6)) for i in range(r)])
    Fh = np.sin(Qh)
    ddQh = K @ Qh - Fh + 1e-6 * rng.standard_normal(Qh.shape)
    return Qh, ddQh, Fh


#: kinds of :func:`mass_data`
MASS_KINDS = ("modal", "chainpod", "active", "nearexact", "nearbeam")


def _spd(rng, r, spread):
    Q = np.linalg.qr(rng.standard_normal((r, r)))[0]
    return Q @ np.diag(np.geomspace(1.0, spread, r)) @ Q.T


def _newmark(M, K, C, B, u, n, dt, rng):
    rom = LagrangianROM(K=K, M=M, C=C, B=B, scheme="newmark", lagrangian=False)
    return rom.simulate(rng.standard_normal(len(K)) * 0.1, np.zeros(len(K)), dt, n, inputs=u)


def _relation(Q, dt, u, noise, rng):
    t = dt * np.arange(Q.shape[1])
    U = np.array([u(s) for s in t]).T
    Q = Q + noise * np.abs(Q).max() * rng.standard_normal(Q.shape)
    return newmark_data(Q, t, U)


def mass_data(kind: str, r: int, n: int = 1500, seed: int = 0):
    """(Qbar, D1, D2, Ubar) of the Newmark relation of a forced, damped system whose mass is not
    I in the coordinates the fit sees, with sensor noise:

    * ``modal``: a random SPD mass (two decades), stiffness and Rayleigh damping in random
      coordinates, r coordinates;
    * ``chainpod``: a 60-mass chain (non-uniform masses, both ends free: a rigid mode, half the
      dampers missing) in the Euclidean POD basis of its Newmark trajectory - the state
      covariance of POD coordinates, eigenvalues over many decades, as a black-box user's
      basis gives;
    * ``active``: a modal system with rigid and undamped modes in random non-orthogonal
      coordinates: the K and C floors active at the optimum;
    * ``nearexact`` / ``nearbeam``: :func:`near_exact`'s bar / beam, no noise.
    """
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
        K, C, B = _chain(N, k, c)
        tr = _newmark(np.diag(m), K, C, B, u, n, dt, rng)
        basis = pod(tr.Qh, r)
        return _relation(basis.project(tr.Qh), dt, u, 1e-6, rng)
    if kind in ("nearexact", "nearbeam"):
        return near_exact(r, "beam" if kind == "nearbeam" else "bar")["relation"]
    raise InputError(f"kind must be one of {MASS_KINDS}, not {kind!r}")


def stiff_potential(r: int = 4, seed: int = 2):
    """A gradient system U(q) = U0(S^-1/2 q), U0 = m^T G m (G SPD, m = [q; vech(q q^T)]),
    S = diag(scales), scales 1 .. 1e-4: sampled at |q_l| ~ scale_l every row has accelerations of
    order 1 while the coordinates differ by 1e4 - like the trailing (small, stiff) POD
    coordinates of elastic data. Returns (PolynomialPotential, scales)."""
    rng = np.random.default_rng(seed)
    n = r + r * (r + 1) // 2
    H = rng.standard_normal((n, n))
    G = H @ H.T / n + 0.1 * np.eye(n)
    M2, M3, M4 = gram_maps(r)
    theta0 = np.concatenate([M2 @ G.ravel(), M3 @ G.ravel(), M4 @ G.ravel()])
    scales = np.logspace(0, -4, r)
    div = np.concatenate([_monomial_scale(np.sqrt(scales), monomials(r, d)) for d in (2, 3, 4)])
    return PolynomialPotential.from_coefficients(theta0 / div, r), scales


def potential_samples(pot, scales, n: int, rng, noise: float = 0.0):
    """Probe-style samples of qh_tt + C qh_t + grad U(qh) = B u at n random states and
    velocities of the coordinates' scales, one input: (point_data with the accelerations times
    (1 + noise N(0, 1)), the exact accelerations, C, B)."""
    r = pot.r
    Q = scales[:, None] * rng.standard_normal((r, n))
    V = scales[:, None] * rng.standard_normal((r, n))
    U = rng.uniform(-1, 1, (1, n))
    C = np.diag(0.1 / scales) @ (np.eye(r) + 0.1) @ np.diag(0.1 / scales) * 1e-3
    C = 0.5 * (C + C.T) + 1e-3 * np.eye(r)
    B = rng.standard_normal((r, 1))
    A = -(pot.gradient(Q) + C @ V) + B @ U
    A_noisy = A * (1 + noise * rng.standard_normal(A.shape))
    return point_data(Q, V, A_noisy, U), A, C, B


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
    body load x on the deflections. Its modal amplitudes fall as omega^-2 ~ k^-4: the POD
    spectrum falls to 1e-8 / 7e-10 by r = 8 / 12, the regime of recorded 3D cantilevers."""
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
    from .basis import pod
    from .identify import Residual
    from .metrics import relative_error
    from .rom import LagrangianROM
    from .schemes import Newmark

    scheme = Newmark(0.25, 0.5)
    if model not in ("bar", "beam"):
        raise InputError(f"model must be 'bar' or 'beam', not {model!r}")
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
