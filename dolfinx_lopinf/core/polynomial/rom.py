"""The polynomial Lagrangian ROM qh_tt + C qh_t + f(qh) = B u, stepped (numpy; numba optional).

:class:`PolynomialROM` integrates qh with the midpoint VI (``scheme="midpoint"``, the FOM's
scheme: symplectic, bounded energy error) or with the average-vector-field discrete gradient
(``scheme="avf"``: grad U replaced by the exact integral of grad U over the segment [q0, q1],
two-point Gauss-Legendre is exact for a quartic U; the energy 1/2 |p|^2 + U(q) of the
conservative system is then conserved to the Newton tolerance). Each step is a reduced Newton
solve; f is a :class:`~dolfinx_lopinf.core.polynomial.potential.PolynomialPotential` (f = grad U),
a :class:`~dolfinx_lopinf.core.polynomial.potential.PolynomialForce`, or any object with
``force_and_jacobian`` (numpy loop only).
"""

from __future__ import annotations

import time

import numpy as np
import scipy.linalg

from ...errors import InputError, NonLagrangianWarning, StepFailedError, warn
from .._checks import as_real_array, check_positive
from ..compiled import NEWTON_STALL
from .potential import polynomial_tensors


SCHEMES = ("midpoint", "avf")


_GAUSS = (0.5 - 0.5 / np.sqrt(3.0), 0.5 + 0.5 / np.sqrt(3.0))


_LAZY_THETA = 0.1  # simplified Newton: refresh the Jacobian when |delta_k| > this |delta_(k-1)|


class PolynomialROM:
    """qh_tt + C qh_t + f(qh) = B u, integrated by the midpoint VI or the AVF discrete gradient.

    Args:
        model: a :class:`PolynomialPotential` (f = grad U) or :class:`PolynomialForce`, or any
            object with ``r`` and ``force_and_jacobian(q) -> (f, J)`` (e.g. the FOM-assembled
            Galerkin force of :mod:`dolfinx_lopinf.fem.galerkin_nonlinear`; numpy loop only).
        C: (r, r) damping or None.  B: (r, m) input matrix or None.
    """

    def __init__(self, model, C=None, B=None):
        if not hasattr(model, "force_and_jacobian"):
            raise InputError("model must be a PolynomialPotential, a PolynomialForce or have "
                             f"force_and_jacobian(q); got {type(model).__name__}")
        self.model = model
        self.r = model.r
        self.C = None if C is None else as_real_array(C, "C")
        self.B = None if B is None else as_real_array(B, "B")
        for name, A, shape in (("C", self.C, (self.r, self.r)),):
            if A is not None and A.shape != shape:
                raise InputError(f"{name} must be {shape}, got {A.shape}")
        if self.B is not None and (self.B.ndim != 2 or self.B.shape[0] != self.r):
            raise InputError(f"B must be (r = {self.r}, m), got {self.B.shape}")
        for name, A in (("C", self.C), ("B", self.B)):
            if A is not None and not np.all(np.isfinite(A)):
                raise InputError(f"{name} contains NaN or inf; an operator must be finite (did "
                                 "its fit fail?)")
        if self.C is not None:
            from ..rom import _structure_problems

            problems = _structure_problems("C", self.C)
            if problems:
                warn("; ".join(problems) + ": this damping is not dissipative - the "
                     "model's energy can grow", NonLagrangianWarning)
        self._tensors = None

    def energy(self, Q, P):
        if not hasattr(self.model, "value"):
            return None
        return 0.5 * np.sum(P * P, axis=0) + self.model.value(Q)

    def simulate(self, q0, v0, dt: float, n_steps: int, *, inputs=None, every: int = 1,
                 backend: str = "auto", on_failure: str = "raise", scheme="midpoint",
                 tol: float = 1e-13, max_iter: int = 50, blowup: float = 1e8,
                 atol: float = 0.0, jacobian: str = "fresh", inputs_mid=None):
        """Integrate n_steps from (q0, v0) - the contract of every ROM's ``simulate``
        (:class:`~dolfinx_lopinf.core.rom.Trajectory`).

        Each step solves, for d = q1 - q0 (reduced Newton until the residual is below ``tol``
        times the size of its terms)::

            d/dt + C d/2 + dt/2 g(q0, q1) = p0 + dt/2 B u_{k+1/2},
            p1 = d/dt - C d/2 - dt/2 g(q0, q1) + dt/2 B u_{k+1/2},

        with g = f((q0+q1)/2) (midpoint) or the two-point Gauss average of f on [q0, q1] (AVF).
        A Newton correction below NEWTON_STALL (16 eps) times the state also ends the
        iteration (full Newton, both loops): the residual test alone, at tol = 1e-13, let the
        force's rounding decide whether a step converged. ``atol`` (default 0) is added to the
        stopping test, ``|R| <= tol size + atol``: the rounding floor of a force that is not
        evaluated to machine precision relative to its own size (a DOLFINx-assembled force
        near rest sums cell terms that cancel).

        Args:
            inputs: for a forced model, u(t) -> (m,) (evaluated at the step midpoints), an
                (m, n_steps) array at the midpoints or an (m, n_steps + 1) array at
                t_0 .. t_n (averaged to the midpoints); None: the free response.
                (``inputs_mid``: the former name of the midpoint array.)
            every: keep every ``every``-th step.
            on_failure: a step whose Newton iteration fails, or a state beyond ``blowup``
                times the initial scale: ``"raise"`` (default) a
                :class:`~dolfinx_lopinf.errors.StepFailedError` naming the step; ``"stop"``:
                the trajectory up to it, NaN after (``trajectory.stable`` False).
            jacobian: ``"fresh"`` (Newton) or ``"lazy"`` (simplified Newton, numpy loop only:
                the last factorised Newton matrix is kept, across steps too, and formed afresh
                when convergence slows, ``|delta_k| > 0.1 |delta_(k-1)|``; it pays when the
                Jacobian costs far more than the force, e.g. the FOM-assembled Galerkin force).
            backend: ``"numpy"`` (the reference loop, any model), ``"numba"`` (the compiled
                loop for a :class:`PolynomialPotential` or :class:`PolynomialForce`, equal to
                rounding) or ``"auto"``. Compilation happens before the timer.

        Returns:
            :class:`~dolfinx_lopinf.core.rom.Trajectory` (Vh: the momenta p = qh_t, the
            reduced mass being I); ``info``: ``newton_iterations``, ``jacobians``,
            ``energy`` (``1/2 |p|^2 + U(q)`` per stored column, when the model has a potential).
        """
        from ..rom import Trajectory, _check_on_failure, _initial_state

        _check_on_failure(on_failure)
        if scheme not in SCHEMES:
            raise InputError(f"scheme must be one of {SCHEMES}, got {scheme!r}")
        dt = check_positive(dt, "dt")
        if isinstance(n_steps, bool) or int(n_steps) != n_steps or n_steps < 0:
            raise InputError(f"n_steps must be a non-negative integer, got {n_steps!r}")
        if isinstance(every, bool) or int(every) != every or every < 1:
            raise InputError(f"every must be a positive integer, got {every!r}")
        try:
            atol = float(atol)
        except (TypeError, ValueError):
            atol = float("nan")
        if not (np.isfinite(atol) and atol >= 0):
            raise InputError(f"atol must be a finite number >= 0, got {atol!r}")
        if inputs_mid is not None:
            if inputs is not None:
                raise InputError("give inputs or inputs_mid (its former name), not both")
            inputs = inputs_mid
        r = self.r
        q, p = (np.array(a) for a in _initial_state(q0, v0, r))
        n_steps = int(n_steps)
        BU = self._midpoint_forcing(inputs, dt, n_steps)
        if jacobian not in ("fresh", "lazy"):
            raise InputError(f"jacobian must be 'fresh' or 'lazy', got {jacobian!r}")
        lazy = jacobian == "lazy"
        backend = self._backend(backend, lazy)
        Qs = np.full((r, n_steps + 1), np.nan)
        Ps = np.full((r, n_steps + 1), np.nan)
        Qs[:, 0], Ps[:, 0] = q, p
        Cm = np.zeros((r, r)) if self.C is None else self.C
        A0 = np.eye(r) / dt + 0.5 * Cm
        limit = blowup * max(np.abs(q).max(), np.abs(p).max() * dt, 1e-300) + blowup
        run = self._run_numba if backend == "numba" else self._run_numpy
        t0 = time.perf_counter()
        iters, n_jac, stable = run(q, p, dt, n_steps, BU, A0, Cm, scheme,
                                   float(tol), atol, int(max_iter), float(limit), Qs, Ps, lazy)
        seconds = time.perf_counter() - t0
        info = {"newton_iterations": iters, "jacobians": n_jac}
        if not stable:
            k = int(np.argmax(~np.all(np.isfinite(Qs), axis=0)))
            message = (f"the reduced step {k} (t = {k * dt:.6g}) failed: Newton did not "
                       f"converge in {max_iter} iterations or the state grew beyond {blowup:g} "
                       "times its initial scale; try a smaller dt")
            if on_failure == "raise":
                raise StepFailedError(message, step=k)
            info["failure"] = message
        Qs, Ps = Qs[:, ::every], Ps[:, ::every]
        info["energy"] = self.energy(Qs, Ps)
        return Trajectory(dt * every * np.arange(Qs.shape[1]), Qs, Ps, None, seconds, backend,
                          info)

    def _midpoint_forcing(self, inputs, dt, n_steps):
        """B u at the step midpoints (r, n_steps), or None (unforced / the free response)."""
        if self.B is None:
            if inputs is not None:
                raise InputError("this ROM has no input operator B (it is unforced); do not "
                                 "pass inputs")
            return None
        if inputs is None:
            return None
        m = self.B.shape[1]
        if callable(inputs):
            U = np.column_stack([np.atleast_1d(np.asarray(inputs(dt * (k + 0.5)), dtype=float))
                                 for k in range(n_steps)]) if n_steps else np.zeros((m, 0))
        else:
            U = as_real_array(inputs, "inputs")
            U = U.reshape(1, -1) if U.ndim == 1 else U
            if U.shape == (m, n_steps + 1):
                U = 0.5 * (U[:, 1:] + U[:, :-1])
        if U.shape != (m, n_steps):
            raise InputError(f"inputs must be (m = {m}, n_steps = {n_steps}) at the step midpoints "
                             f"or (m, n_steps + 1) at t_0 .. t_n, or a callable, got {U.shape}")
        if not np.all(np.isfinite(U)):
            raise InputError("inputs contain NaN or inf; the forcing must be finite")
        return self.B @ U

    def _backend(self, requested, lazy) -> str:
        """The loop that runs: numba when asked for (or "auto" and available) and the model is
        polynomial and the Jacobian fresh; numpy otherwise (a named error when "numba" was
        asked for explicitly and cannot run). Compiles the kernels outside any timer."""
        from .. import compiled

        backend = compiled.resolve_backend(requested)
        if backend == "numba" and lazy:
            if requested == "numba":
                raise InputError("jacobian='lazy' runs in the numpy loop only (the compiled loop's "
                                 "polynomial Jacobian is cheap); pass backend='auto' or 'numpy'")
            return "numpy"
        if backend == "numba":
            if self._tensors is None:
                self._tensors = polynomial_tensors(self.model)
            if self._tensors is None:
                if requested == "numba":
                    raise InputError("backend='numba' compiles the polynomial ROM for a "
                                     "PolynomialPotential or PolynomialForce; this model is a "
                                     f"{type(self.model).__name__} - pass backend='auto' or 'numpy'")
                return "numpy"
            compiled.polynomial_kernels()  # compile / load from the cache outside the timer
        return backend

    def _run_numba(self, q, p, dt, n_steps, BU, A0, Cm, scheme, tol, atol, max_iter, limit, Qs,
                   Ps, lazy):
        """The compiled loop (same residual, update and stopping tests as :meth:`_run_numpy`)."""
        from .. import compiled

        K, F2, F3 = self._tensors
        BUT = np.ascontiguousarray(BU.T) if BU is not None else np.empty((0, self.r))
        stats = np.zeros(3, dtype=np.int64)
        c = np.ascontiguousarray
        compiled.polynomial_kernels()["_poly_run"](
            c(K), c(F2), c(F3), c(A0), c(Cm, dtype=float), BUT, q, p, dt, n_steps,
            scheme == "avf", tol, atol, max_iter, limit, Qs, Ps, stats)
        if stats[2] < 0:
            raise np.linalg.LinAlgError(f"Singular matrix (the reduced Newton matrix at step "
                                        f"{int(stats[0]) + 1})")
        return int(stats[1]), int(stats[1]), bool(stats[2] == 1)

    def _scheme_force(self, q, d, scheme, fresh):
        """g(q0, q1 = q0 + d) of the scheme and (when ``fresh``) its Jacobian in d."""
        fj = self.model.force_and_jacobian
        if scheme == "midpoint":
            if fresh:
                g, J = fj(q + 0.5 * d)
                return g, 0.5 * J
            return self._force_only(q + 0.5 * d), None
        if fresh:
            g1, J1 = fj(q + _GAUSS[0] * d)
            g2, J2 = fj(q + _GAUSS[1] * d)
            return 0.5 * (g1 + g2), 0.5 * (_GAUSS[0] * J1 + _GAUSS[1] * J2)
        return 0.5 * (self._force_only(q + _GAUSS[0] * d) + self._force_only(q + _GAUSS[1] * d)), None

    def _force_only(self, x):
        f_only = getattr(self.model, "force", None) or getattr(self.model, "gradient", None)
        return f_only(x) if f_only is not None else self.model.force_and_jacobian(x)[0]

    def _run_numpy(self, q, p, dt, n_steps, BU, A0, Cm, scheme, tol, atol, max_iter, limit, Qs,
                   Ps, lazy):
        """The reference loop; returns (Newton iterations, Jacobians formed, stable)."""
        iters, n_jac = 0, 0
        lu, need_j = None, True
        d = dt * p
        for k in range(n_steps):
            half_input = 0.5 * dt * BU[:, k] if BU is not None else 0.0
            rhs = p + half_input
            ok, prev = False, np.inf
            for _ in range(max_iter):
                fresh = not lazy or need_j or lu is None
                g, J = self._scheme_force(q, d, scheme, fresh)
                Ad = A0 @ d
                R = Ad + 0.5 * dt * g - rhs
                size = np.abs(Ad).max() + 0.5 * dt * np.abs(g).max() + np.abs(rhs).max()
                if not np.all(np.isfinite(R)):
                    break
                if np.abs(R).max() <= tol * max(size, 1e-300) + atol:
                    ok = True
                    break
                iters += 1
                if not lazy:
                    n_jac += 1
                    delta = np.linalg.solve(A0 + 0.5 * dt * J, R)
                    d = d - delta
                    if np.abs(delta).max() <= NEWTON_STALL * max(np.abs(q).max(), np.abs(d).max()):
                        ok = True  # the correction is below the state's rounding: converged
                        break
                    continue
                if fresh:
                    n_jac += 1
                    lu = scipy.linalg.lu_factor(A0 + 0.5 * dt * J)
                    need_j = False
                delta = scipy.linalg.lu_solve(lu, R)
                d = d - delta
                step = np.abs(delta).max()
                if step > _LAZY_THETA * prev:
                    need_j = True  # convergence slowed: a fresh Jacobian at the next iterate
                prev = step
            q1 = q + d
            if not ok or not np.all(np.isfinite(q1)) or np.abs(q1).max() > limit:
                return iters, n_jac, False
            p = d / dt - 0.5 * Cm @ d - 0.5 * dt * g + half_input
            q = q1
            Qs[:, k + 1], Ps[:, k + 1] = q, p
        return iters, n_jac, True
