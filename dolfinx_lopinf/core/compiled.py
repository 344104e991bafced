"""Compiled time loops of the reduced models (numba, optional; ``pip install '.[fast]'``).

The numpy loops in :mod:`dolfinx_lopinf.core.rom` stay the fallback and the reference: the
kernels here do the same arithmetic step by step (same propagators, same Newton iteration,
same stopping test), so trajectories agree to rounding (tests: 1e-12 relative).

* Linear ROMs (midpoint and Newmark): one step is the affine map x1 = G x0 + f_k with the
  propagator G and the forcing f_k = H u_k formed by numpy exactly as the numpy path forms
  them; the kernel runs the 2r x 2r matvec recurrence (row dot products summed in SIMD
  lanes, as a BLAS gemv does) and keeps every ``every``-th state.
* The wave ROM q_tt = K q - V^T (w * sin(V q)) (sine-Gordon, full or ECSW-sampled rows): the
  midpoint step's reduced Newton with a small in-place LU; ``lazy`` keeps the LU of an older
  Jacobian (simplified Newton) and refreshes it only when the contraction rate
  |dq_k| / |dq_{k-1}| exceeds ``theta``. Other nonlinearities use the numpy path.

Which loop runs is chosen per call: ``simulate(..., backend="auto" | "numpy" | "numba")``;
``auto`` is numba when it imports and ``DOLFINX_LOPINF_JIT`` is not ``0``. The kernels are
compiled eagerly for fixed signatures with ``cache=True`` the first time they are needed
(or by :func:`warm_up`, which returns the seconds that took), before any simulation timer
starts, and run without the GIL (``nogil``: threads run them side by side); later
processes load them from numba's cache. When neither the package directory
nor numba's user-wide cache directory is writable (a read-only install without a home
directory), the cache goes to a directory under the system temp dir; if that fails too,
the kernels are compiled without a cache and a warning says so.
"""

from __future__ import annotations

import os
import tempfile
import threading
import time
import warnings

import numpy as np

from ..errors import InputError, LOpInfWarning

#: Accepted values of ``simulate(..., backend=...)``.
BACKENDS = ("auto", "numpy", "numba")
#: Environment variable that disables the JIT when set to 0 / false / no / off.
JIT_ENV = "DOLFINX_LOPINF_JIT"

#: A full-Newton correction below this times max(|q|, |d|) ends a polynomial-ROM step: the
#: iterate has converged to the rounding of the state (PolynomialROM.simulate; both loops).
NEWTON_STALL = 16 * np.finfo(np.float64).eps


def jit_disabled() -> bool:
    """True when ``DOLFINX_LOPINF_JIT`` switches the compiled loops off."""
    return os.environ.get(JIT_ENV, "").strip().lower() in ("0", "false", "no", "off")


def _numba_missing() -> str | None:
    """Why numba cannot be used (a sentence), or None when it can."""
    if jit_disabled():
        return f"the JIT is disabled ({JIT_ENV}={os.environ.get(JIT_ENV)!r})"
    try:
        import numba  # noqa: F401
    except ImportError as exc:  # pragma: no cover - depends on the install
        return f"numba is not installed ({exc}); pip install 'dolfinx_lopinf[fast]'"
    return None


def available() -> bool:
    """Whether the compiled loops can run here (numba imports and the JIT is enabled)."""
    return _numba_missing() is None


def resolve_backend(backend) -> str:
    """``"numpy"`` or ``"numba"`` for a ``backend`` argument (see :data:`BACKENDS`)."""
    if not isinstance(backend, str) or backend not in BACKENDS:
        raise InputError(f"backend must be one of {', '.join(map(repr, BACKENDS))}, got {backend!r}")
    if backend == "numpy":
        return "numpy"
    why = _numba_missing()
    if backend == "numba" and why is not None:
        raise InputError(f"backend='numba' was requested but {why}; pass backend='auto' to fall "
                         "back to numpy")
    return "numpy" if why else "numba"


# --------------------------------------------------------------------------------------------
# Kernels: plain Python source, compiled by kernels(). The names are rebound to the compiled
# dispatchers in this module's globals, so kernels calling helpers see compiled helpers.
# --------------------------------------------------------------------------------------------

def _affine_run(G, x, FT, n, k0, every, X, j):
    """n steps of x <- G x (+ FT[i]); stores x in X[:, j] after global step k0 + i + 1 when
    that is a multiple of every; returns the next free column j."""
    d = x.shape[0]
    d4 = d - d % 4
    forced = FT.shape[0] > 0
    y = np.empty(d)
    since = k0 % every  # steps since the last stored state
    for i in range(n):
        # row dot products, four rows at a time sharing the loads of x, each summed in SIMD
        # lanes (reassoc, as a BLAS gemv does): fewer loads than one row at a time
        for a in range(0, d4, 4):
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            s3 = 0.0
            for b in range(d):
                xb = x[b]
                s0 += G[a, b] * xb
                s1 += G[a + 1, b] * xb
                s2 += G[a + 2, b] * xb
                s3 += G[a + 3, b] * xb
            y[a] = s0
            y[a + 1] = s1
            y[a + 2] = s2
            y[a + 3] = s3
        for a in range(d4, d):
            acc = 0.0
            for b in range(d):
                acc += G[a, b] * x[b]
            y[a] = acc
        if forced:
            for a in range(d):
                x[a] = y[a] + FT[i, a]
        else:
            for a in range(d):
                x[a] = y[a]
        since += 1
        if since == every:
            since = 0
            for a in range(d):
                X[a, j] = x[a]
            j += 1
    return j


def _lu_factor(A, piv):
    """In-place LU with partial pivoting (row-major, Doolittle); False if exactly singular."""
    r = A.shape[0]
    for k in range(r):
        p = k
        big = abs(A[k, k])
        for i in range(k + 1, r):
            if abs(A[i, k]) > big:
                big = abs(A[i, k])
                p = i
        piv[k] = p
        if big == 0.0:
            return False
        if p != k:
            for c in range(r):
                t = A[k, c]
                A[k, c] = A[p, c]
                A[p, c] = t
        inv = 1.0 / A[k, k]
        for i in range(k + 1, r):
            l = A[i, k] * inv
            A[i, k] = l
            for c in range(k + 1, r):
                A[i, c] -= l * A[k, c]
    return True


def _lu_solve(LU, piv, b):
    """Solve with the factors of _lu_factor, b overwritten by the solution."""
    r = LU.shape[0]
    for k in range(r):
        p = piv[k]
        if p != k:
            t = b[k]
            b[k] = b[p]
            b[p] = t
    for i in range(r):
        s = b[i]
        for c in range(i):
            s -= LU[i, c] * b[c]
        b[i] = s
    for i in range(r - 1, -1, -1):
        s = b[i]
        for c in range(i + 1, r):
            s -= LU[i, c] * b[c]
        b[i] = s / LU[i, i]


def _sine_force(V, VT, w, m, z, gw, F):
    """z = V m, gw = w * sin z and F = V^T gw (VT = V^T in C order)."""
    s, r = V.shape
    for i in range(s):
        z[i] = 0.0
    for a in range(r):  # z += V[:, a] m[a]: vectorised over the s rows
        ma = m[a]
        for i in range(s):
            z[i] += VT[a, i] * ma
    for i in range(s):
        gw[i] = w[i] * np.sin(z[i])
    for a in range(r):  # F[a] = V[:, a] . gw: a dot product over the s rows
        acc = 0.0
        for i in range(s):
            acc += VT[a, i] * gw[i]
        F[a] = acc


def _matvec_T(AT, x, y):
    """y = A x from AT = A^T (C order)."""
    n = x.shape[0]
    for a in range(AT.shape[1]):
        y[a] = 0.0
    for b in range(n):
        xb = x[b]
        for a in range(AT.shape[1]):
            y[a] += AT[b, a] * xb


def _wave_sine_run(KT, V, VT, w, q, p, dt, n_steps, every, tol, max_newton, lazy, theta,
                   Q, P, stats):
    """Midpoint VI of q_tt = K q - V^T (w sin(V q)) with the numpy path's Newton (see
    WaveROM.simulate). stats: [0] 0 or the failing step (k + 1), -(k + 1) for an exactly
    singular Jacobian; [1] Jacobians factorised; [2] Newton iterations. Returns |R| of the
    last iterate (meaningful on failure)."""
    r = q.shape[0]
    s = V.shape[0]
    z = np.empty(s)
    gw = np.empty(s)
    F = np.empty(r)
    Km = np.empty(r)
    m = np.empty(r)
    q1 = np.empty(r)
    R = np.empty(r)
    J = np.empty((r, r))
    piv = np.empty(r, dtype=np.int64)
    have_lu = False
    n_jac = 0
    n_it = 0
    j = 1
    rnorm = 0.0
    for k in range(n_steps):
        for a in range(r):
            q1[a] = q[a] + dt * p[a]
        refresh = not lazy or not have_lu
        prev = np.inf
        converged = False
        for _ in range(max_newton):
            n_it += 1
            for a in range(r):
                m[a] = 0.5 * (q[a] + q1[a])
            _sine_force(V, VT, w, m, z, gw, F)
            _matvec_T(KT, m, Km)
            rnorm = 0.0
            for a in range(r):
                R[a] = p[a] - (q1[a] - q[a]) / dt + 0.5 * dt * (Km[a] - F[a])
                rnorm += R[a] * R[a]
            rnorm = np.sqrt(rnorm)
            if refresh:
                # J = -I/dt + dt/4 (K - V^T diag(w cos z) V)
                for i in range(s):
                    gw[i] = w[i] * np.cos(z[i])
                for a in range(r):  # the symmetric V^T diag(w cos z) V, by dot products
                    for b in range(a, r):
                        acc = 0.0
                        for i in range(s):
                            acc += VT[a, i] * gw[i] * VT[b, i]
                        J[a, b] = acc
                        J[b, a] = acc
                for a in range(r):
                    for b in range(r):
                        J[a, b] = 0.25 * dt * (KT[b, a] - J[a, b])
                    J[a, a] -= 1.0 / dt
                if not _lu_factor(J, piv):
                    stats[0] = -(k + 1)
                    stats[1] = n_jac
                    stats[2] = n_it
                    return rnorm
                n_jac += 1
                have_lu = True
                refresh = not lazy
            for a in range(r):
                R[a] = -R[a]
            _lu_solve(J, piv, R)  # R is now dq
            nd = 0.0
            nq = 0.0
            for a in range(r):
                q1[a] += R[a]
                nd += R[a] * R[a]
                nq += q1[a] * q1[a]
            nd = np.sqrt(nd)
            if nd <= tol * max(np.sqrt(nq), 1.0):
                converged = True
                break
            if lazy and nd > theta * prev:
                refresh = True  # convergence slowed: a fresh Jacobian at the next iterate
            prev = nd
        if not converged:
            stats[0] = k + 1
            stats[1] = n_jac
            stats[2] = n_it
            return rnorm
        for a in range(r):
            m[a] = 0.5 * (q[a] + q1[a])
        _sine_force(V, VT, w, m, z, gw, F)
        _matvec_T(KT, m, Km)
        for a in range(r):
            p[a] = (q1[a] - q[a]) / dt + 0.5 * dt * (Km[a] - F[a])
            q[a] = q1[a]
        if (k + 1) % every == 0:
            for a in range(r):
                Q[a, j] = q[a]
                P[a, j] = p[a]
            j += 1
    stats[0] = 0
    stats[1] = n_jac
    stats[2] = n_it
    return rnorm


_SIGNATURES = {
    "_affine_run": "int64(float64[:, ::1], float64[::1], float64[:, ::1], int64, int64, int64, "
                   "float64[:, ::1], int64)",
    "_lu_factor": "boolean(float64[:, ::1], int64[::1])",
    "_lu_solve": "void(float64[:, ::1], int64[::1], float64[::1])",
    "_sine_force": "void(float64[:, ::1], float64[:, ::1], float64[::1], float64[::1], "
                   "float64[::1], float64[::1], float64[::1])",
    "_matvec_T": "void(float64[:, ::1], float64[::1], float64[::1])",
    "_wave_sine_run": "float64(float64[:, ::1], float64[:, ::1], float64[:, ::1], float64[::1], "
                      "float64[::1], float64[::1], float64, int64, int64, float64, int64, boolean, "
                      "float64, float64[:, ::1], float64[:, ::1], int64[::1])",
}
# LLVM fast-math flags: 'contract' fuses a*b + c into one FMA (one rounding instead of two);
# 'reassoc' lets dot products be summed in SIMD lanes (a different but equally exact summation
# order, as any BLAS uses: vectorised dot products, so the wave ROM's V^T diag(c) V over n
# rows runs as a BLAS would). The LU keeps its plain order. No flag that
# assumes finite values, so a trajectory that blows up still shows inf/nan.
_FASTMATH = {name: {"contract", "reassoc"} for name in ("_affine_run", "_sine_force", "_wave_sine_run")}
# helpers first: a kernel is compiled against the compiled helpers it calls
_ORDER = ("_lu_factor", "_lu_solve", "_sine_force", "_matvec_T", "_affine_run", "_wave_sine_run")


def _fallback_cache_dir() -> str:
    uid = os.getuid() if hasattr(os, "getuid") else "user"
    return os.path.join(tempfile.gettempdir(), f"dolfinx_lopinf-numba-cache-{uid}")


def jit(func, signature=None, **options):
    """``numba.njit(signature, cache=True, **options)(func)`` that survives an unwritable cache.

    numba caches next to the source (``__pycache__``), else in its user-wide cache dir
    (``NUMBA_CACHE_DIR`` or ~/.cache/numba); when none is writable it raises at decoration.
    Then the cache moves to a directory under the system temp dir (numba.config.CACHE_DIR),
    and if even that fails the function is compiled uncached with a warning.
    """
    import numba

    args = (signature,) if signature is not None else ()
    try:
        return numba.njit(*args, cache=True, **options)(func)
    except RuntimeError as exc:
        if "cannot cache" not in str(exc):
            raise
    if not numba.config.CACHE_DIR:
        numba.config.CACHE_DIR = _fallback_cache_dir()
        try:
            return numba.njit(*args, cache=True, **options)(func)
        except RuntimeError as exc:
            if "cannot cache" not in str(exc):
                raise
    warnings.warn(f"dolfinx_lopinf.core.compiled: no writable numba cache directory for "
                  f"{func.__name__} (set NUMBA_CACHE_DIR); compiling without a cache, so every "
                  f"new process compiles again", LOpInfWarning, stacklevel=2)
    return numba.njit(*args, cache=False, **options)(func)


#: serialises every KernelSet build in the process (sets call one another's kernels; a
#: background build and a foreground one must not both compile the same module's globals)
BUILD_LOCK = threading.RLock()


class KernelSet:
    """Named numba kernels of one module, compiled (or loaded from numba's cache) together on
    first use. Each compiled kernel replaces the module global of its name, so kernels that
    call one another call the compiled versions; ``order`` lists helpers before their callers.

    Args:
        namespace: the module's ``globals()``.  signatures: name -> numba signature.
        fastmath: name -> fastmath flags (default {"contract"}: FMA contraction only).
        order: compilation order (default: the signatures' order).
        before: called once before compiling (e.g. another set's kernels, or externals).
        unavailable: the message of the error raised when the JIT cannot be used.
    """

    def __init__(self, namespace, signatures, *, fastmath=None, order=None, before=None,
                 unavailable="the compiled loops are unavailable"):
        self._ns, self._signatures = namespace, signatures
        self._fastmath = fastmath or {}
        self._order = tuple(order or signatures)
        self._before, self._unavailable = before, unavailable
        self._kernels: dict | None = None
        self.compile_seconds: float | None = None  # of the first kernels() in this process

    def kernels(self) -> dict:
        """The compiled kernels (compiled or loaded from the cache on the first call). Builds
        are serialised process-wide (:data:`BUILD_LOCK`): a set built in a background thread
        while another thread asks for it (or for a set it calls) is built once."""
        if self._kernels is not None:
            return self._kernels
        with BUILD_LOCK:
            if self._kernels is not None:  # built while this thread waited
                return self._kernels
            why = _numba_missing()
            if why is not None:
                raise InputError(f"{self._unavailable}: {why}")
            if self._before is not None:
                self._before()
            t0 = time.perf_counter()
            out = {}
            for name in self._order:
                fn = getattr(self._ns[name], "py_func", self._ns[name])  # a retry after a failure
                out[name] = jit(fn, self._signatures[name],
                                fastmath=self._fastmath.get(name, {"contract"}), error_model="numpy",
                                nogil=True)
                self._ns[name] = out[name]
            self._kernels = out
            self.compile_seconds = time.perf_counter() - t0
        return self._kernels

    def warm_up(self) -> float | None:
        """Compile (or load) the kernels now: the seconds that took in this process (0.0 when
        already done), or None when the JIT is unavailable or disabled. Call it before timing."""
        if not available():
            return None
        if self._kernels is not None:
            return 0.0
        self.kernels()
        return self.compile_seconds


_ROM_KERNELS = KernelSet(globals(), _SIGNATURES, fastmath=_FASTMATH, order=_ORDER)


def kernels() -> dict:
    """The compiled ROM-loop kernels (compiled or loaded from the cache on the first call)."""
    return _ROM_KERNELS.kernels()


def warm_up() -> float | None:
    """Compile (or load from numba's cache) every ROM-loop kernel now; returns the seconds that
    took in this process (0.0 when already done), or None when the JIT is unavailable/disabled.
    Call it before timing a first simulation."""
    return _ROM_KERNELS.warm_up()


def compile_seconds() -> float | None:
    """Seconds the first :func:`kernels` call took in this process (None before it)."""
    return _ROM_KERNELS.compile_seconds


# --------------------------------------------------------------------------------------------
# Drivers called by rom.py
# --------------------------------------------------------------------------------------------

def affine_run(G, x, FT, n, k0, every, X, j) -> int:
    """Run :func:`_affine_run` (x and X updated in place); G (d, d) C order, FT (n, d) or
    None (unforced)."""
    k = kernels()
    FT = np.empty((0, x.shape[0])) if FT is None else np.ascontiguousarray(FT, dtype=float)
    return int(k["_affine_run"](G, x, FT, int(n), int(k0), int(every), X, int(j)))


def is_sine(g, dg) -> bool:
    """Whether g, dg are sin, cos (the sine-Gordon nonlinearity) - identical objects, or equal
    to rounding on probe points in [-40, 40] (e.g. the functions nonlinear.identify compiles
    from 1 - cos q)."""
    if g is np.sin and dg is np.cos:
        return True
    z = np.linspace(-40.0, 40.0, 801) + 0.123
    try:
        with np.errstate(all="ignore"):
            gz = np.asarray(g(z), dtype=float)
            dz = np.asarray(dg(z), dtype=float)
    except Exception:  # noqa: BLE001 - any failure means: not the known case
        return False
    if gz.shape != z.shape or dz.shape != z.shape:
        return False
    tol = 8 * np.finfo(float).eps
    return bool(np.all(np.abs(gz - np.sin(z)) <= tol) and np.all(np.abs(dz - np.cos(z)) <= tol))


# --------------------------------------------------------------------------------------------
# The polynomial Lagrangian ROM (dolfinx_lopinf.core.polynomial.PolynomialROM): its own kernel
# registry, compiled after (and against) the helpers above.
# --------------------------------------------------------------------------------------------

def _poly_force(K, F2, F3, x, g, J, T2, T3):
    """g = K x + F2(x, x) + F3(x, x, x), J = K + 2 F2(., x) + 3 F3(., x, x) for F2, F3
    symmetric in their trailing indices; T2, T3 (r, r) work arrays."""
    r = x.shape[0]
    for i in range(r):
        for j in range(r):
            s2 = 0.0
            s3 = 0.0
            for k in range(r):
                s2 += F2[i, j, k] * x[k]
                t = 0.0
                for m in range(r):
                    t += F3[i, j, k, m] * x[m]
                s3 += t * x[k]
            T2[i, j] = s2
            T3[i, j] = s3
    for i in range(r):
        acc = 0.0
        for j in range(r):
            acc += (K[i, j] + T2[i, j] + T3[i, j]) * x[j]
            J[i, j] = K[i, j] + 2.0 * T2[i, j] + 3.0 * T3[i, j]
        g[i] = acc


def _poly_run(K, F2, F3, A0, Cm, BUT, q, p, dt, n_steps, avf, tol, atol, max_iter, limit, Q, P,
              stats):
    """PolynomialROM.simulate's loop (same residual, Newton update and stopping test; see
    there). stats: [0] steps done, [1] Newton iterations, [2] 1 when stable, 0 when Newton
    failed or the state left ``limit``, -1 for an exactly singular Newton matrix."""
    r = q.shape[0]
    forced = BUT.shape[0] > 0
    g = np.empty(r)
    g2 = np.empty(r)
    J = np.empty((r, r))
    J2 = np.empty((r, r))
    T2 = np.empty((r, r))
    T3 = np.empty((r, r))
    A = np.empty((r, r))
    x = np.empty(r)
    d = np.empty(r)
    Ad = np.empty(r)
    R = np.empty(r)
    rhs = np.empty(r)
    piv = np.empty(r, dtype=np.int64)
    ga = 0.5 - 0.5 / np.sqrt(3.0)
    gb = 0.5 + 0.5 / np.sqrt(3.0)
    for a in range(r):
        d[a] = dt * p[a]
    iters = 0
    for k in range(n_steps):
        for a in range(r):
            rhs[a] = p[a] + (0.5 * dt * BUT[k, a] if forced else 0.0)
        ok = False
        for _ in range(max_iter):
            if avf:
                for a in range(r):
                    x[a] = q[a] + ga * d[a]
                _poly_force(K, F2, F3, x, g, J, T2, T3)
                for a in range(r):
                    x[a] = q[a] + gb * d[a]
                _poly_force(K, F2, F3, x, g2, J2, T2, T3)
                for a in range(r):
                    g[a] = 0.5 * (g[a] + g2[a])
                    for b in range(r):
                        J[a, b] = 0.5 * (ga * J[a, b] + gb * J2[a, b])
            else:
                for a in range(r):
                    x[a] = q[a] + 0.5 * d[a]
                _poly_force(K, F2, F3, x, g, J, T2, T3)
                for a in range(r):
                    for b in range(r):
                        J[a, b] = 0.5 * J[a, b]
            finite = True
            mad = 0.0
            mg = 0.0
            mr = 0.0
            for a in range(r):
                acc = 0.0
                for b in range(r):
                    acc += A0[a, b] * d[b]
                Ad[a] = acc
                R[a] = acc + 0.5 * dt * g[a] - rhs[a]
                if not np.isfinite(R[a]):
                    finite = False
                mad = max(mad, abs(acc))
                mg = max(mg, abs(g[a]))
                mr = max(mr, abs(rhs[a]))
            if not finite:
                break
            size = mad + 0.5 * dt * mg + mr
            rmax = 0.0
            for a in range(r):
                rmax = max(rmax, abs(R[a]))
            if rmax <= tol * max(size, 1e-300) + atol:
                ok = True
                break
            iters += 1
            for a in range(r):
                for b in range(r):
                    A[a, b] = A0[a, b] + 0.5 * dt * J[a, b]
            if not _lu_factor(A, piv):
                stats[0] = k
                stats[1] = iters
                stats[2] = -1
                return
            _lu_solve(A, piv, R)
            mdelta = 0.0
            mstate = 0.0
            for a in range(r):
                d[a] -= R[a]
                mdelta = max(mdelta, abs(R[a]))
                mstate = max(mstate, abs(q[a]), abs(d[a]))
            if mdelta <= NEWTON_STALL * mstate:
                ok = True  # the correction is below the state's rounding (see simulate)
                break
        bad = not ok
        for a in range(r):
            x[a] = q[a] + d[a]
            if not np.isfinite(x[a]) or abs(x[a]) > limit:
                bad = True
        if bad:
            stats[0] = k
            stats[1] = iters
            stats[2] = 0
            return
        for a in range(r):
            acc = 0.0
            for b in range(r):
                acc += Cm[a, b] * d[b]
            p[a] = d[a] / dt - 0.5 * acc - 0.5 * dt * g[a] + (0.5 * dt * BUT[k, a] if forced else 0.0)
            q[a] = x[a]
            Q[a, k + 1] = q[a]
            P[a, k + 1] = p[a]
    stats[0] = n_steps
    stats[1] = iters
    stats[2] = 1


_POLY_SIGNATURES = {
    "_poly_force": "void(float64[:, ::1], float64[:, :, ::1], float64[:, :, :, ::1], float64[::1], "
                   "float64[::1], float64[:, ::1], float64[:, ::1], float64[:, ::1])",
    "_poly_run": "void(float64[:, ::1], float64[:, :, ::1], float64[:, :, :, ::1], float64[:, ::1], "
                 "float64[:, ::1], float64[:, ::1], float64[::1], float64[::1], float64, int64, "
                 "boolean, float64, float64, int64, float64, float64[:, ::1], float64[:, ::1], "
                 "int64[::1])",
}
_POLY_KERNELS = KernelSet(globals(), _POLY_SIGNATURES, before=lambda: kernels(),
                          unavailable="the compiled polynomial ROM loop is unavailable")


def polynomial_kernels() -> dict:
    """The compiled polynomial-ROM kernels (after :func:`kernels`, whose LU they call);
    compiled or loaded from numba's cache on the first call."""
    return _POLY_KERNELS.kernels()


def warm_up_polynomial() -> float | None:
    """:func:`warm_up` for the polynomial ROM's kernels: seconds spent compiling or loading
    them in this process (0.0 when already done), None when the JIT is unavailable."""
    return _POLY_KERNELS.warm_up()
