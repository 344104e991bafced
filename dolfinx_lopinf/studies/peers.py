"""Peer baselines: the established first-order operator inference of the ``opinf`` package,
fitted the way its tutorials fit it, so the demos can show it beside L-OpInf.

    pip install 'dolfinx_lopinf[peers]'        # opinf >= 0.6, < 0.7

:func:`opinf_first_order` takes the same snapshot arrays our fits take and builds what an
``opinf`` user would build from them (``opinf`` 0.6 tutorials "basics", "inputs" and
"lifting"):

* the state: a second-order system is written first order, x = [q; q_t] (2n rows). Recorded
  velocities are used when the snapshots have them; otherwise q_t is what such a user would
  take: ``opinf.ddt.UniformFiniteDifferencer(times, "ord6")`` applied to the recorded states;
* preprocessing: each variable (q and q_t) scaled to max |.| = 1 by
  ``opinf.pre.ShiftScaleTransformer(centering=False, scaling="maxabs")`` inside an
  ``opinf.pre.TransformerMulti`` (the lifting tutorial's multi-variable pattern; no centering,
  because the models below have no constant term and the equilibrium is 0);
* the basis (``basis=``): ``"stacked"`` - one ``opinf.basis.PODBasis`` with 2r vectors of the
  scaled [q; q_t]; ``"blocks"`` - an ``opinf.basis.BasisMulti`` with an r-vector
  ``PODBasis`` per variable; or a given (n, r) array / :class:`dolfinx_lopinf.core.Basis` used
  for both q and q_t (``opinf.basis.LinearBasis``, with the Basis' weight, e.g. the mass
  matrix). Either way the first-order model has 2r states - as many reduced unknowns as a
  second-order ROM of dimension r has (q and q_t);
* the time derivatives of the reduced states: ``UniformFiniteDifferencer(times, "ord6")``;
* the model: ``opinf.models.ContinuousModel("A")`` (no inputs) or ``"AB"`` (inputs),
  dx/dt = A x (+ B u), solved by ``opinf.lstsq.L2Solver`` whose regulariser is chosen by
  ``ROM.fit_regselect_continuous`` over the candidates ``np.logspace(-12, 2, 15)`` (grid
  search, then opinf's own 1-D optimisation): the smallest training error among the models
  that stay within opinf's stability margin on the training window.

Time integration (``integrator=``). The tutorials integrate with ``solve_ivp(method="BDF")``
at its default tolerances (rtol 1e-3), which adds an error of its own: for the beam demo's
mass-orthonormal r = 20 peer, test error 1.9e-3 instead of 8.5e-7 and FOM energy error 3.6e-3
instead of 1e-8 to 2 s, and a slow run. The default here, ``"exact"``, integrates
the *inferred* linear ODE exactly: x_{k+1} = expm(A dt) x_k, with inputs linear between the
sample times (first-order hold, an augmented matrix exponential). So a peer's error is that of its
model, not of an integrator tolerance - and the regulariser search (which integrates once
per candidate, through the model's ``predict``) takes milliseconds per candidate. Pass
``integrator="BDF"`` for the tutorials' integration in the search and in :meth:`predict`.

Only ``opinf``'s own classes fit the model; this module adds the data plumbing, the exact
integrator and the checks. ``opinf`` is imported on first use; without it the functions here
raise ``ImportError`` with the install command.
"""

from __future__ import annotations

import copy
import sys
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..core._blas import one_blas_thread
from ..core._checks import as_real_array, check_finite, check_uniform_times
from ..errors import InputError

INSTALL_HINT = "pip install 'dolfinx_lopinf[peers]'"
#: the regulariser candidates of opinf's tutorials and regression tests (lifting tutorial)
DEFAULT_CANDIDATES = tuple(np.logspace(-12, 2, 15))
BASIS_KINDS = ("stacked", "blocks")
INTEGRATORS = ("exact", "BDF")
SVD_SOLVERS = ("dense", "randomized")


def have_opinf() -> bool:
    """True when ``opinf`` (0.6.x) can be imported."""
    try:
        _opinf()
    except ImportError:
        return False
    return True


def _import_h5py_own_hdf5():
    """Import h5py so that it binds its own bundled HDF5, whatever was imported before.

    With numba installed, ``dolfinx.fem.petsc`` loads libpetsc - and with it the DOLFINx
    wheel's HDF5 - into the process's global symbol scope; an h5py imported afterwards then
    resolves HDF5's global type identifiers to that other copy and fails with "Not a
    datatype". Loading h5py's extension modules with ``RTLD_DEEPBIND`` puts their own
    dependencies (h5py.libs/libhdf5) ahead of the global scope, so the import order of the
    user's script does not matter. Nothing is done when h5py is already imported or the
    platform has no ``RTLD_DEEPBIND`` (macOS, Windows: no such global loading there).
    """
    import os

    if "h5py" in sys.modules or not hasattr(os, "RTLD_DEEPBIND"):
        return
    flags = sys.getdlopenflags()
    sys.setdlopenflags(flags | os.RTLD_DEEPBIND)
    try:
        import h5py  # noqa: F401
    except ImportError:  # no h5py: opinf's own import reports it
        pass
    finally:
        sys.setdlopenflags(flags)


def _opinf():
    try:
        _import_h5py_own_hdf5()
        import opinf
    except ImportError as exc:
        raise ImportError(f"the opinf peer baseline needs the optional package opinf: "
                          f"{INSTALL_HINT}") from exc
    except ValueError as exc:  # h5py bound to another HDF5 ("Not a datatype")
        raise ImportError("opinf could not import h5py in this process: its HDF5 clashes with "
                          "another HDF5 loaded before it (e.g. by PETSc); import h5py (or "
                          "dolfinx_lopinf.studies.peers) before dolfinx.fem.petsc") from exc
    major_minor = tuple(int(x) for x in opinf.__version__.split(".")[:2])
    if major_minor != (0, 6):
        raise ImportError(f"the opinf peer baseline is written for opinf 0.6.x, found "
                          f"{opinf.__version__}: {INSTALL_HINT}")
    return opinf


@dataclass
class PeerPrediction:
    """A peer trajectory.

    Attributes:
        times: (K,) times.
        Xh: (2r, K) reduced first-order states (opinf's coordinates).
        Q, V: (n, K) reconstructed states and velocities (None when ``full=False``).
        Y: (p, K) outputs E q when the peer has an output matrix, else None.
        seconds: wall time of the reduced integration.
        finite: False when the trajectory blew up (the columns from there on are NaN).
    """

    times: np.ndarray
    Xh: np.ndarray
    Q: np.ndarray | None
    V: np.ndarray | None
    Y: np.ndarray | None
    seconds: float
    finite: bool


@dataclass
class OpInfPeer:
    """A fitted opinf first-order ROM (see the module docstring) and how it was made.

    Attributes:
        rom: the ``opinf.ROM`` (transformer, basis, ddt estimator, ContinuousModel).
        r: configuration dimension; the first-order model has ``2 r`` states.
        operators: ``"A"`` or ``"AB"``.
        regularizer: the L2 regulariser opinf's search chose.
        basis_kind: ``"stacked"``, ``"blocks"`` or ``"given"``.
        velocity_source: ``"recorded"`` or ``"opinf ord6 finite differences of q"``.
        integrator: ``"exact"`` or ``"BDF"``.
        fit_seconds: wall time of the regulariser search and fit (the shared POD excluded).
        output_matrix: optional (p, n) matrix, y = E q.
    """

    rom: object
    r: int
    n: int
    operators: str
    regularizer: float
    basis_kind: str
    velocity_source: str
    integrator: str
    fit_seconds: float
    output_matrix: np.ndarray | None = None
    _decoder: np.ndarray | None = field(default=None, repr=False)
    _encoder: np.ndarray | None = field(default=None, repr=False)

    @property
    def A(self) -> np.ndarray:
        """(2r, 2r) inferred state operator."""
        return self.rom.model.operators[0].entries

    @property
    def B(self) -> np.ndarray | None:
        """(2r, m) inferred input operator, or None."""
        return self.rom.model.operators[1].entries if self.operators == "AB" else None

    @property
    def decoder(self) -> tuple[np.ndarray, np.ndarray]:
        """(Dq, Dv), each (n, 2r): q = Dq xh and q_t = Dv xh (opinf's decode of the unit
        vectors: its scaling has no shift and its bases are linear)."""
        if self._decoder is None:
            self._decoder = np.asarray(self.rom.decode(np.eye(2 * self.r)))
        return self._decoder[: self.n], self._decoder[self.n:]

    @property
    def encoder(self) -> tuple[np.ndarray, np.ndarray]:
        """(Eq, Ev), each (2r, n): xh = Eq q + Ev q_t (opinf's encode of the unit vectors,
        formed 512 columns at a time)."""
        if self._encoder is None:
            cols = []
            for start in range(0, 2 * self.n, 512):
                unit = np.zeros((2 * self.n, min(512, 2 * self.n - start)))
                unit[start + np.arange(unit.shape[1]), np.arange(unit.shape[1])] = 1.0
                cols.append(np.asarray(self.rom.encode(unit)))
            self._encoder = np.hstack(cols)
        return self._encoder[:, : self.n], self._encoder[:, self.n:]

    def encode(self, q0, v0) -> np.ndarray:
        """Reduced first-order state of a full (q0, v0)."""
        q0 = _vector(q0, "q0", self.n)
        v0 = _vector(v0, "v0", self.n)
        return np.asarray(self.rom.encode(np.concatenate([q0, v0])))

    def projection_error(self, Q, V=None, times=None) -> float:
        """||Q - Dq encode([Q; Q_t])||_F / ||Q||_F: how well this peer's basis holds the states
        (the floor of its q error). Q_t = ``V``, or opinf's finite differences over ``times``."""
        Q = as_real_array(Q, "Q")
        if Q.ndim != 2 or Q.shape[0] != self.n:
            raise InputError(f"Q must be ({self.n}, K), got shape {Q.shape}")
        if V is None:
            if times is None:
                raise InputError("pass the velocities V or the sample times (for differences)")
            estimator = self.rom.ddt_estimator  # the same differences as the fit's
            V = estimator.__class__(_times(times, "times"), estimator.scheme.__name__).estimate(Q)[1]
        V = as_real_array(V, "V")
        if V.shape != Q.shape:
            raise InputError(f"V has shape {V.shape}; it must be {Q.shape} like Q")
        Eq, Ev = self.encoder
        Xh = Eq @ Q + Ev @ V
        Dq, _ = self.decoder
        denom = np.linalg.norm(Q)
        if denom == 0:
            raise InputError("Q is identically zero; its relative projection error is undefined")
        return float(np.linalg.norm(Q - Dq @ Xh) / denom)

    def energy(self, Xh: np.ndarray, mass: np.ndarray, stiffness: np.ndarray) -> np.ndarray:
        """1/2 v^T M v + 1/2 q^T K q of the reconstructed states, per column of ``Xh`` -
        the FOM energy the demos score every ROM with."""
        Dq, Dv = self.decoder
        Mh, Kh = Dv.T @ mass @ Dv, Dq.T @ stiffness @ Dq
        Xh = np.asarray(Xh)
        return 0.5 * np.sum(Xh * ((Mh + Kh) @ Xh), axis=0)

    def predict(self, q0, v0, times, inputs=None, *, full: bool = True,
                velocities: bool = True) -> PeerPrediction:
        """Integrate the peer from (q0, v0) over ``times`` (uniform for the exact integrator).

        Args:
            q0, v0: (n,) initial state and velocity.
            times: (K,) increasing output times; the first is the initial time.
            inputs: for an ``"AB"`` peer, a callable t -> (m,) (or scalar), or an (m, K) / (K,)
                array of the inputs at ``times``; must be None for an ``"A"`` peer.
            full: also reconstruct Q and V (n, K); False keeps only Xh (and Y).
            velocities: with ``full``, reconstruct V too (False: V is None).
        """
        times = _times(times, "times")
        if self.integrator == "exact":
            check_uniform_times(times)
        x0 = self.encode(q0, v0)
        u = self._input_arg(inputs, times)
        t0 = time.perf_counter()
        with warnings.catch_warnings(), one_blas_thread():
            warnings.simplefilter("ignore")
            if self.integrator == "exact":
                Xh = self.rom.model.predict(x0, times, u)
            else:
                Xh = self.rom.model.predict(x0, times, u, method="BDF")
        seconds = time.perf_counter() - t0
        Xh = np.asarray(Xh, dtype=float)
        finite = Xh.shape[1] == len(times) and bool(np.all(np.isfinite(Xh)))
        if Xh.shape[1] < len(times):  # the integration stopped: a blow-up
            Xh = np.hstack([Xh, np.full((Xh.shape[0], len(times) - Xh.shape[1]), np.nan)])
        Dq, Dv = self.decoder
        Q = Dq @ Xh if full else None
        V = Dv @ Xh if full and velocities else None
        Y = (self.output_matrix @ Dq) @ Xh if self.output_matrix is not None else None
        return PeerPrediction(times, Xh, Q, V, Y, seconds, finite)

    def _input_arg(self, inputs, times):
        if self.operators == "A":
            if inputs is not None:
                raise InputError("this peer was fitted without inputs (model 'A'); pass inputs=None")
            return None
        m = self.B.shape[1]
        if inputs is None:
            raise InputError(f"this peer was fitted with {m} input(s) (model 'AB'); pass inputs as "
                             "a callable t -> (m,) or an (m, K) array at the output times")
        if callable(inputs):
            u = _callable_input(inputs, m)
            if self.integrator == "BDF":
                return u
            return np.column_stack([u(t) for t in times])  # the exact integrator's samples
        return _row_matrix(inputs, "inputs", lambda shape: shape == (m, len(times)),
                           f"({m}, {len(times)}): one column per output time")


def _row_matrix(a, name, fits, must):
    """``a`` as a finite 2-D array (a 1-D ``a`` is one row) whose shape ``fits``; otherwise an
    InputError naming the shape given and what it ``must`` be."""
    A = as_real_array(a, name)
    A = A[None, :] if A.ndim == 1 else A
    if A.ndim != 2 or not fits(A.shape):
        raise InputError(f"{name} has shape {np.shape(a)}; it must be {must}")
    check_finite(A, name)
    return A


def opinf_first_order(Q, times, r, *, velocities=None, inputs=None, basis="stacked",
                      svdsolver: str = "dense", scale: bool = True, ddt_scheme: str = "ord6",
                      candidates=DEFAULT_CANDIDATES, output_matrix=None,
                      integrator: str = "exact", test_time_length: float = 0.0,
                      verbose: bool = False):
    """Fit opinf's first-order linear ROM the way opinf's tutorials do (module docstring).

    Args:
        Q: (n, K) training states at ``times``.
        times: (K,) uniform, increasing sample times (K >= 7 for the 6th-order differences).
        r: configuration dimension (the model has 2r states), or a list of them: one POD is
            then computed and truncated for each, and a list of peers is returned.
        velocities: (n, K) recorded velocities, or None (then q_t = opinf's "ord6" finite
            differences of Q).
        inputs: None (model "A"), or the training inputs for model "AB": an (m, K) / (K,)
            array aligned with ``times`` or a callable t -> (m,) (or scalar for m = 1).
        basis: ``"stacked"``, ``"blocks"``, or an (n, r) array / :class:`dolfinx_lopinf.core.Basis`
            used for q and for q_t (with the Basis' weight; ``r`` must then equal its r).
        svdsolver: ``PODBasis`` SVD: ``"dense"`` (opinf's default, the tutorials') or
            ``"randomized"`` (opinf's option for large snapshot matrices; seeded here, so
            repeatable). Only for ``"stacked"`` and ``"blocks"``.
        scale: scale each variable to max |.| = 1 first (tutorial practice; default True).
        ddt_scheme: opinf ``UniformFiniteDifferencer`` scheme for the reduced derivatives.
        candidates: regulariser candidates for ``fit_regselect_continuous``.
        output_matrix: optional (p, n) matrix; predictions then carry y = E q.
        integrator: ``"exact"`` (default) or ``"BDF"`` (the tutorials' solve_ivp).
        test_time_length: opinf's option: time after the training window over which the
            regulariser search also requires stability (0: the tutorials' setting).
        verbose: print opinf's regulariser search.

    Returns:
        An :class:`OpInfPeer` (or a list of them when ``r`` is a list).

    Raises:
        ImportError: opinf is not installed (the message gives the pip command).
        InputError: an argument has the wrong shape, type or value (named in the message).
    """
    opinf = _opinf()
    Q, times = _training_states(opinf, Q, times, ddt_scheme, svdsolver, integrator)
    n, K = Q.shape
    r_list = _r_list(r)
    Vel, velocity_source = _velocities(opinf, Q, times, velocities, ddt_scheme)
    input_func = _input_function(inputs, times)
    operators = "A" if input_func is None else "AB"
    E = None
    if output_matrix is not None:
        E = _row_matrix(output_matrix, "output_matrix", lambda shape: shape[1] == n,
                        f"(p, {n}) (y = E q)")
    X = np.vstack([Q, Vel])
    transformer = _maxabs_transformer(opinf, X, Q, Vel) if scale else None
    Xs = transformer.transform(X) if transformer is not None else X
    shared, basis_kind = _shared_basis(opinf, basis, Xs, n, K, r_list, svdsolver)

    peers = []
    for ri in r_list:
        rom = opinf.ROM(
            transformer=transformer, basis=_truncated(opinf, shared, basis_kind, ri),
            ddt_estimator=opinf.ddt.UniformFiniteDifferencer(times, ddt_scheme),
            model=_model_class(opinf, integrator)(operators, solver=opinf.lstsq.L2Solver()))
        options = {"method": "BDF"} if integrator == "BDF" else {}
        t0 = time.perf_counter()
        with warnings.catch_warnings(), one_blas_thread():
            warnings.simplefilter("ignore")  # opinf warns per unstable candidate / edge winner
            rom.fit_regselect_continuous(
                candidates=list(candidates), train_time_domains=times, states=X,
                input_functions=input_func, fit_transformer=False, fit_basis=False,
                test_time_length=test_time_length, verbose=verbose, **options)
        peers.append(OpInfPeer(rom=rom, r=ri, n=n, operators=operators,
                               regularizer=float(rom.model.solver.regularizer),
                               basis_kind=basis_kind, velocity_source=velocity_source,
                               integrator=integrator, fit_seconds=time.perf_counter() - t0,
                               output_matrix=E))
    return peers[0] if np.isscalar(r) or isinstance(r, (int, np.integer)) else peers


# --- internals -----------------------------------------------------------------------------
def _training_states(opinf, Q, times, ddt_scheme, svdsolver, integrator):
    """Checked (Q, times) and the options that depend on them (named InputError otherwise)."""
    Q = as_real_array(Q, "Q")
    if Q.ndim != 2 or min(Q.shape) < 1:
        raise InputError(f"Q must be an (n, K) array of training states, got shape {Q.shape}")
    check_finite(Q, "Q")
    K = Q.shape[1]
    times = _times(times, "times")
    if len(times) != K:
        raise InputError(f"times has {len(times)} entries but Q has {K} columns (one per sample)")
    check_uniform_times(times)
    if ddt_scheme not in opinf.ddt.UniformFiniteDifferencer._schemes:
        raise InputError(f"ddt_scheme {ddt_scheme!r} is not an opinf UniformFiniteDifferencer "
                         f"scheme ({', '.join(opinf.ddt.UniformFiniteDifferencer._schemes)})")
    if K < 7:
        raise InputError(f"Q has {K} samples; opinf's finite differences need at least 7")
    if svdsolver not in SVD_SOLVERS:
        raise InputError(f"svdsolver must be one of {SVD_SOLVERS}, got {svdsolver!r}")
    if integrator not in INTEGRATORS:
        raise InputError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
    return Q, times


def _r_list(r) -> list:
    """The reduced dimensions asked for, as a checked list of positive ints."""
    r_list = [r] if np.isscalar(r) or isinstance(r, (int, np.integer)) else list(r)
    if not r_list:
        raise InputError("r is an empty list; give at least one reduced dimension")
    for ri in r_list:
        if isinstance(ri, (bool, np.bool_)) or not isinstance(ri, (int, np.integer)) or ri < 1:
            raise InputError(f"r must be a positive integer (or a list of them), got {ri!r}")
    return [int(ri) for ri in r_list]


def _velocities(opinf, Q, times, velocities, ddt_scheme):
    """(q_t, where it came from): the recorded velocities, checked, or opinf's differences."""
    if velocities is None:
        fd = opinf.ddt.UniformFiniteDifferencer(times, ddt_scheme)
        Vel, source = np.asarray(fd.estimate(Q)[1]), f"opinf {ddt_scheme} finite differences of q"
    else:
        Vel = as_real_array(velocities, "velocities")
        if Vel.shape != Q.shape:
            raise InputError(f"velocities has shape {Vel.shape}; it must be {Q.shape} like Q")
        check_finite(Vel, "velocities")
        source = "recorded"
    if not np.any(Q) and not np.any(Vel):
        raise InputError("Q and its velocities are identically zero: nothing to learn")
    return Vel, source


def _input_function(inputs, times):
    """opinf's input function: None (model "A"), the callable, or a cubic spline of the
    sampled inputs."""
    if inputs is None:
        return None
    if callable(inputs):
        return _callable_input(inputs, np.size(inputs(times[0])))
    U = _row_matrix(inputs, "inputs", lambda shape: shape[1] == len(times),
                    f"(m, {len(times)}) or ({len(times)},): one column per sample time "
                    "(or a callable of t)")
    import scipy.interpolate

    return _callable_input(scipy.interpolate.CubicSpline(times, U, axis=1), U.shape[0])


def _maxabs_transformer(opinf, X, Q, Vel):
    """opinf's per-variable max|.| = 1 scaling of [q; q_t], fitted on X (tutorial practice)."""
    if not np.any(Q) or not np.any(Vel):
        raise InputError("scale=True needs q and q_t that are not identically zero; pass "
                         "scale=False")
    transformer = opinf.pre.TransformerMulti(
        [opinf.pre.ShiftScaleTransformer(centering=False, scaling="maxabs") for _ in range(2)])
    transformer.fit(X)
    return transformer


def _times(times, name):
    t = as_real_array(times, name)
    if t.ndim != 1 or len(t) < 2:
        raise InputError(f"{name} must be a 1-D array with at least 2 entries, got shape {t.shape}")
    check_finite(t, name)
    if np.any(np.diff(t) <= 0):
        raise InputError(f"{name} must be strictly increasing")
    return t


def _vector(v, name, n):
    v = as_real_array(v, name)
    if v.shape != (n,):
        raise InputError(f"{name} has shape {v.shape}; it must be ({n},), a full state")
    check_finite(v, name)
    return v


def _callable_input(fn, m):
    """t -> (m,) array (opinf wants arrays, users write scalar loads)."""
    def u(t):
        value = np.atleast_1d(np.asarray(fn(t), dtype=float)).reshape(-1)
        if value.shape != (m,):
            raise InputError(f"the input function returned {value.shape[0]} values at t = {t}; "
                             f"expected {m}")
        return value
    return u


def _shared_basis(opinf, basis, Xs, n, K, r_list, svdsolver):
    """Fit the POD once (for the largest r) or wrap a given basis; returns (basis, kind)."""
    r_max = max(r_list)
    # opinf's randomized SVD (sklearn) draws a random test matrix: seeded for repeatability
    svd = {"svdsolver": svdsolver, **({"random_state": 0} if svdsolver == "randomized" else {})}
    if isinstance(basis, str):
        if basis not in BASIS_KINDS:
            raise InputError(f"basis must be one of {BASIS_KINDS} or an (n, r) array / Basis, got "
                             f"{basis!r}")
        if basis == "stacked":
            if 2 * r_max > min(2 * n, K):
                raise InputError(f"r = {r_max} asks for {2 * r_max} POD vectors of [q; q_t], but the "
                                 f"data have at most {min(2 * n, K)}")
            pod = opinf.basis.PODBasis(num_vectors=2 * r_max, max_vectors=2 * r_max, **svd)
            pod.fit(Xs)
            return pod, "stacked"
        if r_max > min(n, K):
            raise InputError(f"r = {r_max} asks for {r_max} POD vectors per variable, but the data "
                             f"have at most {min(n, K)}")
        multi = opinf.basis.BasisMulti(
            [opinf.basis.PODBasis(num_vectors=r_max, max_vectors=r_max, name=name, **svd)
             for name in ("q", "q_t")])
        multi.fit(Xs)
        return multi, "blocks"
    weight = getattr(basis, "weight", None)
    V = as_real_array(getattr(basis, "V", basis), "basis")
    if V.ndim != 2 or V.shape[0] != n:
        raise InputError(f"a given basis must be an (n, r) array with n = {n} (Q's rows), got shape "
                         f"{V.shape}")
    check_finite(V, "basis")
    if r_list != [V.shape[1]]:
        raise InputError(f"r = {r_list} but the given basis has {V.shape[1]} columns; pass "
                         f"r = {V.shape[1]} (truncate the basis first)")
    cls = opinf.basis.LinearBasis if weight is None else _weighted_basis_class(opinf)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # non-orthogonality is the caller's choice
        given = opinf.basis.BasisMulti(
            [cls(V, weights=weight, name=name) for name in ("q", "q_t")])
    return given, "given"


_WEIGHTED_BASIS = None


def _weighted_basis_class(opinf):
    """opinf's LinearBasis with a dense weight W whose compression V^T W q is formed as
    (W V)^T q: the same map, without a W-product per call."""
    global _WEIGHTED_BASIS
    if _WEIGHTED_BASIS is None:
        class WeightedLinearBasis(opinf.basis.LinearBasis):
            def compress(self, state):
                if getattr(self, "_wv", None) is None:
                    self._wv = np.asarray(self.weights.T @ self.entries)  # (W^T V)^T q = V^T W q
                return self._wv.T @ state

        _WEIGHTED_BASIS = WeightedLinearBasis
    return _WEIGHTED_BASIS


def _truncated(opinf, shared, kind, r):
    if kind == "given":
        return shared
    out = copy.deepcopy(shared)
    if kind == "stacked":
        out.set_dimension(num_vectors=2 * r)
    else:
        for b in out.bases:
            b.set_dimension(num_vectors=r)
    return out


def _model_class(opinf, integrator):
    if integrator == "BDF":
        return opinf.models.ContinuousModel
    return _exact_model_class(opinf)


_EXACT_MODEL = None


def _exact_model_class(opinf):
    """opinf's ContinuousModel whose ``predict`` integrates the linear ODE exactly."""
    global _EXACT_MODEL
    if _EXACT_MODEL is not None:
        return _EXACT_MODEL
    import scipy.linalg

    class ExactLinearContinuousModel(opinf.models.ContinuousModel):
        """``ContinuousModel`` ("A" / "AB") with an exact ``predict``: x_{k+1} = expm(A dt) x_k
        (+ the exact response to inputs linear between the samples). Like ``solve_ivp``, it
        stops at the first non-finite state (opinf's regulariser search reads a short
        trajectory as unstable)."""

        def predict(self, state0, t, input_func=None, **options):
            self._check_is_trained()
            t = np.asarray(t, dtype=float)
            dt = float(t[1] - t[0])
            A = self.operators[0].entries
            r = A.shape[0]
            x = np.asarray(state0, dtype=float).copy()
            out = np.empty((r, len(t)))
            out[:, 0] = x
            if len(self.operators) == 1:
                Phi = scipy.linalg.expm(A * dt)
                # x_{j+i} = Phi^i x_j for i = 1..L: one (L r, r) matrix product per L steps
                L = min(64, len(t) - 1)
                powers = [Phi]
                for _ in range(L - 1):
                    powers.append(Phi @ powers[-1])
                P = np.vstack(powers)
                with np.errstate(all="ignore"):
                    j = 0
                    while j < len(t) - 1:
                        steps = min(L, len(t) - 1 - j)
                        block = (P[: steps * r] @ out[:, j]).reshape(steps, r).T
                        out[:, j + 1: j + 1 + steps] = block
                        bad = ~np.all(np.isfinite(block), axis=0)
                        if bad.any():
                            return out[:, : j + 1 + int(np.argmax(bad))]
                        j += steps
                return out
            # inputs linear between samples: expm([[A dt, B dt, 0], [0, 0, I], [0, 0, 0]])
            # maps [x_k; u_k; u_{k+1} - u_k] to [x_{k+1}; u_{k+1}; u_{k+1} - u_k]
            Bm = self.operators[1].entries
            m = Bm.shape[1]
            if not callable(input_func):
                U = np.atleast_2d(np.asarray(input_func, dtype=float))
            elif (getattr(self, "_inputs_cache", None) is not None
                  and self._inputs_cache[0] is input_func and np.array_equal(self._inputs_cache[1], t)):
                U = self._inputs_cache[2]  # the regulariser search: same inputs, every candidate
            else:
                U = np.column_stack([np.atleast_1d(input_func(tt)) for tt in t])
                self._inputs_cache = (input_func, t.copy(), U)  # holds input_func: no id reuse
            big = np.zeros((r + 2 * m, r + 2 * m))
            big[:r, :r], big[:r, r:r + m] = A * dt, Bm * dt
            big[r:r + m, r + m:] = np.eye(m)
            F = scipy.linalg.expm(big)
            Phi, G0, G1 = F[:r, :r], F[:r, r:r + m], F[:r, r + m:]
            with np.errstate(all="ignore"):
                forced = G0 @ U[:, :-1] + G1 @ np.diff(U, axis=1)  # (r, K - 1)
                for k in range(1, len(t)):
                    x = Phi @ x + forced[:, k - 1]
                    out[:, k] = x
                    if k % 128 == 0 or k == len(t) - 1:
                        bad = ~np.all(np.isfinite(out[:, max(1, k - 127): k + 1]), axis=0)
                        if bad.any():
                            return out[:, : max(1, k - 127) + int(np.argmax(bad))]
            return out

    _EXACT_MODEL = ExactLinearContinuousModel
    return _EXACT_MODEL
