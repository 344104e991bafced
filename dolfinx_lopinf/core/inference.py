"""Lagrangian operator inference (L-OpInf) and the standard OpInf baseline
(docs/method.md#certificate).

Mechanical ROM with reduced mass fixed to I:

    qh_tt + Ch qh_t + Kh qh = Bh u,        y = Eh qh.

L-OpInf solves the constrained least-squares problem

    min  || ddQh + Kh Qh + Ch dQh - Bh U ||_F
    s.t. Kh = Kh^T, Ch = Ch^T, Kh >= eps I, Ch >= eps I   (matrix inequalities),

so the learned ROM is the Euler-Lagrange equation of ``L_h = 1/2 |qh_t|^2 - 1/2 qh^T Kh qh``
(with Rayleigh-like dissipation Ch and input Bh u) by construction.

Compression (:mod:`dolfinx_lopinf.core.gram`): with Theta = [Kh, Ch, -Bh] (r, p) and
D = [Qh; dQh; U] (p, K), ||ddQh + Theta D||_F^2 = ||Theta L + Z||_F^2 + const with G = D D^T =
L L^T, so after one pass over the data (cost O(K p^2)) the problem no longer depends on K.
Solvers (:mod:`dolfinx_lopinf.core.lsq`: a :class:`~dolfinx_lopinf.core.lsq.Problem` and strategy
objects). Without damping and inputs, the symmetric-only problem has the closed-form
Lyapunov solution G K + K G = -(X + X^T), X = ddQh Qh^T; if that minimiser already satisfies
K >= eps I it *is* the L-OpInf solution (KKT holds with zero multiplier). Otherwise ADMM in
the eigenbasis of G (K alone) or, for damped fits, a primal-dual interior point method with
a certified duality gap (:class:`~dolfinx_lopinf.core.lsq.Auto`). ``solver="cvxpy"`` (Clarabel on
the compressed problem) is the reference.

Nonlinear-wave ROM (gray box):  qh_tt = Kh qh - Fh,  Fh = V^T f_nl(V qh), Kh = Kh^T:

    min ||ddQh + Fh - Kh Qh||_F   ->   G K + K G = T Qh^T + Qh T^T,  T = ddQh + Fh.

Standard (second-order) OpInf drops every constraint: Theta = -ddQh D^+ by least squares.
"""

from __future__ import annotations

import time
import warnings

import numpy as np
import scipy.linalg

from . import lsq
from ._blas import serial_blas
from ._checks import check_matrix, pow2_scale
from .conic import clarabel
from ..errors import InputError, SolverFailedError, SolverWarning, warn
from .gram import GAP_TOL, RIDGE, GramData, MechanicalOperators, compress, gram_data, psd_floor


def _split_theta(theta, r, m, has_damping):
    K = theta[:, :r]
    C = theta[:, r : 2 * r] if has_damping else None
    B = -theta[:, theta.shape[1] - m :] if m else None
    return K, C, B


def _certificate(gram, K, C, B, solver, status, seconds, eps):
    theta = np.hstack([K] + ([C] if C is not None else []) + ([-B] if B is not None else []))
    obj = max(gram.objective(theta), 0.0)
    misfit = max(gram.data_objective(theta), 0.0)
    cert = {
        "solver": solver,
        "status": status,
        "objective": obj,
        "data_misfit": misfit,
        "relative_residual": float(np.sqrt(misfit / gram.target_norm2)),
        "data_rank": gram.rank,
        "data_rows": int(gram.L.shape[0]),
        "symmetry_error": float(np.abs(K - K.T).max() / max(np.abs(K).max(), 1e-300)),
        "min_eig_K": float(np.linalg.eigvalsh(0.5 * (K + K.T)).min()),
        "seconds": seconds,
        "eps": eps,
        "data_condition": gram.condition,
    }
    if C is not None:
        cert["min_eig_C"] = float(np.linalg.eigvalsh(0.5 * (C + C.T)).min())
    return cert


#: The names ``solver=`` of :func:`infer_mechanical` accepts.
SOLVERS = ("auto", "lyapunov", "admm", "cvxpy")


def _check_solver(solver):
    if isinstance(solver, str):
        if solver not in SOLVERS:
            raise InputError(f"unknown solver {solver!r}; choose one of "
                             f"{', '.join(repr(s) for s in SOLVERS)}, or pass a strategy object "
                             "with a solve(problem) method (e.g. dolfinx_lopinf.core.lsq.PSDBlocks())")
    elif not callable(getattr(solver, "solve", None)):
        raise InputError(f"solver must be one of {', '.join(repr(s) for s in SOLVERS)} or an "
                         f"object with a solve(problem) method, not a {type(solver).__name__}")


@serial_blas
def infer_mechanical(Qh, dQh, ddQh, U=None, *, eps: float = 1e-8, damping: bool = True,
                     solver: str | lsq.Strategy = "auto", ridge: float | None = None,
                     strict: bool = False, mass: str = "identity",
                     raise_ridge: bool = True, _ridge_factor: float = 1.0) -> MechanicalOperators:
    """L-OpInf for Mh qh_tt + Ch qh_t + Kh qh = Bh u with Kh, Ch symmetric, >= eps I and
    Mh = I (``mass="identity"``) or learned too (``mass="learned"``, :mod:`dolfinx_lopinf.core.mass`).

    Args:
        Qh, dQh, ddQh: (r, K) reduced states and their first/second time derivatives on
            the same grid (see :func:`dolfinx_lopinf.core.ddt.derivatives`). ``dQh`` may be None
            when ``damping=False``.
        U: (m, K) inputs, or None for an unforced system.
        eps: lower bound on the eigenvalues of Kh (and Ch).
        damping: fit Ch too; ``False`` gives the conservative form (Kh, and Bh with inputs).
        solver: ``"auto"`` (:class:`~dolfinx_lopinf.core.lsq.Auto`); ``"lyapunov"`` (the
            symmetric minimiser, unconstrained: the conservative unforced fit only);
            ``"admm"`` (the ADMM strategies without the interior point, a comparison
            path); ``"cvxpy"`` (Clarabel on the compressed problem, the reference); or a
            strategy object whose ``solve(problem)`` returns ``(Theta, Certificate)`` for
            a :class:`~dolfinx_lopinf.core.lsq.Problem` (e.g. ``lsq.PSDBlocks(gap_tol=1e-10)``).
        ridge: relative Tikhonov parameter that decides the directions the data do not
            determine (see :func:`gram_data`); 0 turns it off. None (default): ``RIDGE``,
            raised for a learned mass that it leaves uncertified (``raise_ridge``); a number:
            that ridge and no other.
        strict: raise :class:`~dolfinx_lopinf.errors.RankDeficientDataError` when the data
            do not determine every operator entry, instead of warning and regularising, and
            :class:`~dolfinx_lopinf.errors.SolverFailedError` when the fit is not certified
            (duality gap above its tolerance) instead of returning it with a warning.
        mass: ``"identity"`` (Mh = I: right in a mass-orthonormal basis) or ``"learned"``
            (Mh symmetric positive definite, fitted with the others by a convex problem
            whose answer does not depend on the coordinates of the reduced space - use it
            in a Euclidean, black-box basis).
        raise_ridge: ``mass="learned"`` with ``ridge=None`` only: a fit the interior point
            leaves uncertified is refitted with the ridge raised by :data:`RIDGE_STEPS` and
            the first certified one is returned, with a
            :class:`~dolfinx_lopinf.errors.SolverWarning` and ``certificate["ridge"]`` naming
            the ridge (its certificate is for that problem); when none certifies, the first
            fit as it was. ``False``: the first fit only. (``_ridge_factor``, lo.fit's final
            fit: start at ridge times this factor of RIDGE_STEPS - where the candidate it
            scored was certified.)

    Returns:
        :class:`MechanicalOperators` with a certificate; warns if the solver did not reach
        optimality.

    Example:
        >>> t = np.linspace(0, 10, 2001); w = np.array([[1.0], [2.0]])
        >>> Q = np.vstack([np.cos(t), 0.5 * np.sin(2 * t)])
        >>> from dolfinx_lopinf.core.ddt import derivatives
        >>> ops = infer_mechanical(*derivatives(Q, t), damping=False)
        >>> bool(np.allclose(ops.K, np.diag([1.0, 4.0]), atol=1e-5))
        True
    """
    _check_solver(solver)
    if not (np.isfinite(eps) and eps >= 0):
        raise InputError(f"eps must be a finite number >= 0, got {eps}")
    if mass not in ("identity", "learned"):
        raise InputError(f"mass must be 'identity' or 'learned', got {mass!r}")
    chosen_ridge, ridge = ridge is not None, _check_ridge(ridge)
    (Qh, dQh, ddQh, U), c_state, c_input = _unit_scaled(Qh, dQh, ddQh, U)
    if mass == "learned":
        def fit(ridge_used):
            from .mass import infer_with_mass

            return infer_with_mass(Qh, dQh if damping else None, ddQh, U, damping=damping,
                                   eps=eps, ridge=ridge_used, strict=strict, solver=solver)

        retry = raise_ridge and not chosen_ridge and solver == "auto"
        return _unscaled(_certified_by_ridge(fit, ridge, _ridge_factor) if retry else fit(ridge),
                         c_state, c_input)
    gram = gram_data(Qh, dQh, ddQh, U, damping=damping, ridge=ridge, strict=strict)
    conservative = not gram.has_damping and gram.m == 0
    named = solver if isinstance(solver, str) else None
    if named == "lyapunov" and not conservative:
        raise InputError("solver='lyapunov' handles the conservative, unforced fit only "
                         "(damping=False, U=None); use 'auto', 'admm' or 'cvxpy'")
    if named == "cvxpy":
        ops = _solve_cvxpy(gram, eps)
    elif conservative and (named in ("auto", "lyapunov") or _is_auto(solver)):
        ops = _solve_lyapunov(gram, eps)
        if named != "lyapunov" and ops.certificate["min_eig_K"] < eps:
            ops = _solve_constrained(gram, eps, solver if _is_auto(solver) else lsq.Auto())
    else:
        ops = _solve_constrained(gram, eps, lsq.Auto(named) if named else solver)
    if strict and not ops.certificate.get("certified", False) and named != "lyapunov":
        c = ops.certificate
        raise SolverFailedError(f"the fit is not certified ({c['solver']}: duality gap "
                                f"{c.get('duality_gap', float('nan')):.2e}, status {c['status']}); "
                                "strict=True asks for an error instead of an uncertified model")
    return _unscaled(ops, c_state, c_input)


#: a learned-mass fit left uncertified at the default ridge is tried again with the ridge raised
#: by these factors (the directions the data barely determine are then fixed by the ridge
#: instead of by rounding, and the interior point can close its gap); the first certified
#: one is kept, with a warning naming the ridge. No 10x: the ridge's curvature in the Newton
#: systems is (factor * RIDGE)^2 sigma_1^2 - 1e-16 sigma_1^2 at 10x, the rounding of those
#: systems, where rounding decided whether it certified or stalled (at a full fit's cost);
#: 100x puts it at 1e-14, two decades above
RIDGE_STEPS = (100.0, 1000.0)


def _certified_by_ridge(fit, ridge, first=1.0):
    """``fit(ridge * first)``, and if not certified ``fit(ridge * f)`` for f in RIDGE_STEPS
    above ``first``: the first certified fit (warning, ``certificate["ridge"]``), else the
    first as it was (its warnings, or its SolverFailedError under strict=True)."""
    with warnings.catch_warnings(record=True) as first_warnings:
        warnings.simplefilter("always")
        try:
            ops, failure = fit(ridge * first), None
        except SolverFailedError as exc:  # strict=True and not certified
            ops, failure = None, exc
    if ops is not None and first != 1.0:
        ops.certificate["ridge"] = float(f"{ridge * first:.6g}")
    if ops is not None and ops.certificate.get("certified"):
        _replay(first_warnings)
        if first != 1.0:
            _warn_ridge(ridge, ridge * first, "the ridge lo.fit's chosen candidate needed")
        return ops
    gap = ops.certificate.get("duality_gap") if ops is not None else None
    for factor in (f for f in RIDGE_STEPS if f > first):
        with warnings.catch_warnings(record=True) as trial_warnings:
            warnings.simplefilter("always")
            try:
                trial = fit(ridge * factor)
            except SolverFailedError:
                continue
        if trial.certificate.get("certified"):
            _replay([w for w in trial_warnings if not issubclass(w.category, SolverWarning)])
            trial.certificate["ridge"] = float(f"{ridge * factor:.6g}")
            _warn_ridge(ridge, ridge * factor, f"not certified at {ridge * first:g}: duality gap "
                        f"{gap if gap is not None else float('nan'):.2e}")
            return trial
    if failure is not None:
        raise failure
    _replay(first_warnings)
    return ops


def _check_ridge(ridge) -> float:
    """The ridge to use: ``RIDGE`` for None, else a number in [0, 1) (as :func:`gram_data`)."""
    if ridge is None:
        return RIDGE
    if isinstance(ridge, bool) or not isinstance(ridge, (int, float, np.floating, np.integer)) \
            or not (np.isfinite(ridge) and 0 <= ridge < 1):
        raise InputError(f"ridge must be a number in [0, 1) (or None for the default), got {ridge!r}")
    return float(ridge)


def _warn_ridge(ridge, used, why):
    warn(f"learned-mass fit: certified with the ridge {used:g} * sigma_1 instead of "
         f"{ridge:g} ({why}) - the directions the data barely determine are fixed by "
         "the ridge (towards zero). Pass ridge= to choose it yourself", SolverWarning)


def _replay(records):
    for w in records:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


def _is_auto(solver) -> bool:
    """An :class:`~dolfinx_lopinf.core.lsq.Auto` object with the interior point (as "auto",
    perhaps without its fallbacks)."""
    return isinstance(solver, lsq.Auto) and solver.method == "auto"


def _unit_scaled(Qh, dQh, ddQh, U):
    """Take the state and input units out of the data, exactly (powers of two), so that data
    in any units - 1e160 or 1e-170 included - neither overflow nor underflow. K and C are
    invariant under a common scaling of Qh, dQh and ddQh; B scales by c_state / c_input."""
    arrays = [None if a is None else check_matrix(a, name)
              for a, name in ((Qh, "Qh"), (dQh, "dQh"), (ddQh, "ddQh"))]
    U = None if U is None else check_matrix(np.atleast_2d(U), "U")
    c_state = pow2_scale(*arrays)
    c_input = pow2_scale(U)
    arrays = [None if a is None else np.asarray(a) / c_state for a in arrays]
    return (*arrays, None if U is None else U / c_input), c_state, c_input


def _unscaled(ops: MechanicalOperators, c_state: float, c_input: float) -> MechanicalOperators:
    if c_state == 1.0 and c_input == 1.0:
        return ops
    cert = dict(ops.certificate)
    with np.errstate(over="ignore"):  # the squared misfit in user units may pass 1e308
        for key in ("objective", "data_misfit"):
            if key in cert:
                cert[key] = float(np.float64(cert[key]) * c_state * c_state)
    B = None if ops.B is None else ops.B * (c_state / c_input)
    return MechanicalOperators(ops.K, ops.C, B, cert, M=ops.M)


def _solve_lyapunov(gram: GramData, eps: float) -> MechanicalOperators:
    """Symmetric least-squares minimiser: G K + K G = -(X + X^T), via the SVD of L."""
    t0 = time.perf_counter()
    K = lsq.solve_symmetric(gram.L, gram.Z)
    seconds = time.perf_counter() - t0
    cert = _certificate(gram, K, None, None, "lyapunov", "optimal", seconds, eps)
    cert.update(lsq.kkt(gram.L, gram.Z, K, [], eps))  # unconstrained: stationarity only
    G = gram.L @ gram.L.T
    X = gram.Z @ gram.L.T
    grad = K @ G + G @ K + X + X.T
    cert["stationarity"] = float(np.linalg.norm(grad) / max(np.linalg.norm(2 * X), 1e-300))
    feasible = cert["min_eig_K"] >= eps
    if not feasible:
        cert["status"] = "infeasible: the symmetric minimiser has min eigenvalue < eps"
    # the unconstrained symmetric minimiser, exact: optimal (gap 0) when it is feasible
    cert.update(duality_gap=0.0 if feasible else float("inf"), certified=bool(feasible), iterations=0)
    return MechanicalOperators(K, None, None, cert)


def _solve_constrained(gram: GramData, eps: float, strategy) -> MechanicalOperators:
    """PSD-constrained fit by ``strategy`` (:mod:`dolfinx_lopinf.core.lsq`) on the compressed
    problem; K and C floored at eps against rounding, the certificate a dict: the solver's
    :class:`~dolfinx_lopinf.core.lsq.Certificate` fields, the fit's and the KKT residuals."""
    t0 = time.perf_counter()
    problem = lsq.Problem(gram.L, gram.Z, 2 if gram.has_damping else 1, eps, gram.m)
    theta, solved = strategy.solve(problem)
    K, C, B = _split_theta(theta, gram.r, gram.m, gram.has_damping)
    if C is None:
        K = psd_floor(K, eps)
    else:
        K, C = psd_floor(np.stack([K, C]), eps)
    cert = _certificate(gram, K, C, B, solved.solver, solved.status, time.perf_counter() - t0, eps)
    cert.update({k: v for k, v in solved.as_dict().items() if k != "seconds"})
    cert.update(problem.kkt(np.hstack([K] + ([C] if C is not None else [])
                                      + ([-B] if B is not None else []))))
    gap = solved.duality_gap
    cert["certified"] = bool(solved.converged and gap is not None
                             and gap <= getattr(strategy, "gap_tol", GAP_TOL))
    if not solved.converged:
        warn(f"{solved.solver} stopped after {solved.iterations} iterations without "
             "meeting its tolerance; see the certificate's KKT residuals", SolverWarning)
    return MechanicalOperators(K, C, B, cert)


def _solve_cvxpy(gram: GramData, eps: float) -> MechanicalOperators:
    try:
        import cvxpy as cp
    except ImportError as exc:  # pragma: no cover
        raise ImportError("solver='cvxpy' needs cvxpy: pip install cvxpy clarabel") from exc
    r, m = gram.r, gram.m
    # Scale unknowns so the conic solver sees O(1) numbers: Theta = s * Theta_s.
    s = np.linalg.norm(gram.Z) / max(np.linalg.norm(gram.L), 1e-300)
    K = cp.Variable((r, r), symmetric=True)
    blocks = [K]
    cons = [K >> (eps / s) * np.eye(r)]
    C = None
    if gram.has_damping:
        C = cp.Variable((r, r), symmetric=True)
        blocks.append(C)
        cons.append(C >> (eps / s) * np.eye(r))
    negB = cp.Variable((r, m)) if m else None
    if m:
        blocks.append(negB)
    theta = cp.hstack(blocks) if len(blocks) > 1 else K
    zn = np.linalg.norm(gram.Z)
    prob = cp.Problem(cp.Minimize(cp.sum_squares(theta @ (gram.L * s / zn) + gram.Z / zn)), cons)
    t0 = time.perf_counter()
    try:
        raw = clarabel(cp, prob)
    except SolverFailedError as exc:
        raise SolverFailedError(f"cvxpy/Clarabel failed on the L-OpInf problem: {exc}") from exc
    seconds = time.perf_counter() - t0
    Kv = s * K.value
    Kv = 0.5 * (Kv + Kv.T)
    Cv = None if C is None else s * 0.5 * (C.value + C.value.T)
    Bv = None if negB is None else -s * negB.value
    cert = _certificate(gram, Kv, Cv, Bv, "cvxpy-clarabel", prob.status, seconds, eps)
    cert.update(duality_gap=raw["relative_gap"], iterations=raw["iterations"],
                certified=bool(prob.status == "optimal" and raw["relative_gap"] <= GAP_TOL))
    if prob.status != "optimal":
        warn(f"Clarabel returned {prob.status}; check the certificate", SolverWarning)
    return MechanicalOperators(Kv, Cv, Bv, cert)


@serial_blas
def infer_opinf(Qh, dQh, ddQh, U=None, *, damping: bool = True, ridge: float = RIDGE,
                strict: bool = False) -> MechanicalOperators:
    """Standard second-order OpInf: unconstrained least squares for [Kh, Ch, Bh].

    The baseline L-OpInf is compared against: it fits the training data, but Kh is
    neither symmetric nor definite, so the ROM carries no Lagrangian structure. The same
    ridge-regularised problem as L-OpInf (:func:`gram_data`), without constraints:
    Theta = -Z L^{-1}.
    """
    (Qh, dQh, ddQh, U), c_state, c_input = _unit_scaled(Qh, dQh, ddQh, U)
    gram = gram_data(Qh, dQh, ddQh, U, damping=damping, ridge=ridge, strict=strict)
    t0 = time.perf_counter()
    theta = -scipy.linalg.solve_triangular(gram.L, gram.Z.T, trans="T", lower=True).T
    seconds = time.perf_counter() - t0
    K, C, B = _split_theta(theta, gram.r, gram.m, damping)
    cert = _certificate(gram, K, C, B, "lstsq", "optimal", seconds, None)
    cert.update(duality_gap=0.0, certified=True, iterations=0)  # the exact least squares
    ops = MechanicalOperators(K, C, B, cert)
    return _unscaled(ops, c_state, c_input)


@serial_blas
def infer_wave(Qh, ddQh, Fh, *, negative_semidefinite: bool = False, ridge: float = RIDGE,
               strict: bool = False) -> MechanicalOperators:
    """Symmetric Kh of the gray-box wave ROM qh_tt = Kh qh - Fh (docs/method.md#wave-and-sine-gordon).

    Args:
        Qh, ddQh, Fh: (r, K) reduced states, their second derivatives and the reduced
            nonlinear term V^T f_nl(V qh) on the same grid.
        negative_semidefinite: also require Kh <= 0. The paper asks only for symmetry; but
            -Kh is a reduced discrete Laplacian, and a symmetric Kh with a positive
            eigenvalue makes the linear part of the ROM grow exponentially.
        ridge, strict: as in :func:`infer_mechanical`.

    Returns:
        :class:`MechanicalOperators` with ``K`` = Kh (symmetric, unique when Qh has full
        rank) and a certificate (stationarity of the Lyapunov equation).
    """
    Qh = check_matrix(Qh, "Qh")
    r, K = Qh.shape
    Fh = check_matrix(Fh, "Fh", rows=r, cols=K)
    # qh_tt = Kh qh - Fh  <=>  ddQh + Fh + (-Kh) Qh = 0: the mechanical form with K -> -Kh
    target = check_matrix(ddQh, "ddQh", rows=r, cols=K) + Fh
    if negative_semidefinite:  # -Kh >= 0: the conservative mechanical fit with eps = 0
        ops = infer_mechanical(Qh, None, target, damping=False, eps=0.0, ridge=ridge,
                               strict=strict)
        cert = dict(ops.certificate, max_eig_K=float(np.linalg.eigvalsh(-ops.K).max()))
        return MechanicalOperators(-ops.K, None, None, cert)
    (Qh, _, target, _), c_state, _ = _unit_scaled(Qh, None, target, None)
    gram = gram_data(Qh, None, target, damping=False, ridge=ridge, strict=strict)
    ops = _unscaled(_solve_lyapunov(gram, -np.inf), c_state, 1.0)
    Kh = -ops.K
    cert = dict(ops.certificate, min_eig_K=float(np.linalg.eigvalsh(Kh).min()), status="optimal",
                duality_gap=0.0, certified=True)  # unconstrained: the exact minimiser
    return MechanicalOperators(Kh, None, None, cert)


@serial_blas
def infer_output(Qh, Y, *, ridge: float = RIDGE, strict: bool = False) -> np.ndarray:
    """Output operator Eh = argmin ||Y - Eh Qh||_F^2 (+ the ridge of :func:`gram_data`),
    (p, r) from Qh (r, K) and Y (p, K)."""
    Qh = check_matrix(Qh, "Qh")
    Y = check_matrix(np.atleast_2d(Y), "Y", cols=Qh.shape[1])
    c_state, c_out = pow2_scale(Qh), pow2_scale(Y)
    if not np.any(Y):
        return np.zeros((Y.shape[0], Qh.shape[0]))
    L, Z, *_ = compress([Qh / c_state], -Y / c_out, [f"Qh[{i}]" for i in range(Qh.shape[0])],
                         ridge, strict, "Qh")
    E = -scipy.linalg.solve_triangular(L, Z.T, trans="T", lower=True).T
    return E * (c_out / c_state)
