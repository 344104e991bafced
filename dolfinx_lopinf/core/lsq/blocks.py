"""Several symmetric blocks >= eps I, all strategies composed (:class:`PSDBlocks`), and the
default dispatch of :func:`dolfinx_lopinf.core.infer_mechanical` (:class:`Auto`)."""

from __future__ import annotations

import copy
import time

import numpy as np

from ...errors import IllConditionedDataWarning, warn
from .barrier import Barrier
from .face import FaceADMM, FaceNewton
from .ipm import InteriorPoint, interior_point, ip_answer
from .lyapunov import EigenbasisADMM, Lyapunov
from .problem import Problem, Strategy, symmetric_answer, symmetric_start
from ...errors import InputError

#: ``fallback=False`` (lo.fit's candidates, which only predict held-back data): an interior
#: point stopped uncertified with a gap at most this skips its crossover to the face (which
#: certifies it or not at ~1e-8; measured on the held-out membrane loop at r = 20: 280 ms of
#: a 340 ms candidate fit, for a gap of 2.6e-7 either way)
CANDIDATE_GAP = 1e-6
#: ``fallback=True`` (the default): an interior point (and its crossover) stopped uncertified
#: with a gap at most this is the answer - ADMM and the barrier are not tried. Measured on the
#: 139 Mh = I problems of the benchmark and of lo.fit on the loop recordings, and 256 held-out
#: fits (``studies.held_out``, seeds 0-7): the fallbacks ran on two problems (the membrane
#: loop at r = 20, interior point gaps 2.6e-7 and 1.0e-6) and certified neither - ADMM ended
#: at 1.1e7, the barrier at 4.6e-6 and 8.3e-6 - after 4.3-5.7 s. Where the fallbacks do run
#: and end uncertified too, the smaller of the gaps is kept (never a worse proof for more work)
FALLBACK_ABOVE_GAP = 1e-5


#: :class:`Auto` tries the interior point on the active blocks alone from this r on
ELIMINATE_FROM_R = 16


class PSDBlocks(Strategy):
    """min f(Theta) = ||Theta L + Z||_F^2 over Theta = [S_1 .. S_b], S_k = S_k^T >= eps I.

    In the vech unknowns x, f = x^T H x + 2 h^T x + ||Z||^2 (:func:`symmetric_normal_equations`).

    1. The symmetric minimiser H x = -h; if every block is >= eps I it is the answer.
    2. ``method="auto"``: the primal-dual interior point (:func:`interior_point`, 7-10
       iterations of one Cholesky each; first on the blocks whose symmetric minimiser is
       not >= eps I only when ``eliminate``), with a crossover to Newton on the face it
       shows. If it is not certified (or ``method="admm"``), unless it stopped at a gap of at
       most FALLBACK_ABOVE_GAP (its point is then the answer, uncertified):
    3. :class:`FaceADMM`: ADMM to the optimal face, polish and Newton on it.

    Certificate: the point is feasible and the projected multipliers
    Lambda_k = [grad_{S_k} f]_+ >= 0 give the dual bound (:meth:`Problem.dual_gap`), accepted
    when (f - g) / f <= ``gap_tol``: a proof of optimality to that relative accuracy.
    """

    def __init__(self, gap_tol: float = 1e-8, kkt_tol: float = 1e-9, admm_tol: float = 1e-4,
                 max_iter: int = 5000, memory: int = 8, rho0: float = 0.3, method: str = "auto",
                 ipm_max_iter: int = 40, eliminate: bool = True, backend: str = "auto",
                 resolve: bool = False, fallback: bool = True):
        if method not in ("auto", "admm"):
            raise InputError(f"method must be 'auto' (interior point, ADMM as fallback) or 'admm', "
                             f"not {method!r}")
        self.method, self.ipm_max_iter, self.eliminate = method, ipm_max_iter, eliminate
        self.backend = backend  # the interior point's iteration: "numpy", "numba" or "auto"
        # interior point failed (or H singular) on a problem Problem.resolved changes: solve
        # the resolved one instead (certificate: ridge_raised_to, gap_floor)
        self.resolve = resolve
        # the interior point uncertified: ADMM to the face (True), or its own point as it is
        self.fallback = fallback
        self.face_admm = FaceADMM(gap_tol, kkt_tol, admm_tol, max_iter, memory, rho0)

    def solve_blocks(self, problem: Problem):
        t0 = time.perf_counter()
        x, feasible = symmetric_start(problem)
        if feasible.all():
            return symmetric_answer(problem, x, t0)
        newton = FaceNewton(problem, self.face_admm.gap_tol)
        details, best = {}, None
        if self.method == "auto" and problem.spd.ok:  # the certificate needs H > 0
            x_ip, ip, details = interior_point(problem, x, feasible, newton,
                                               gap_tol=self.face_admm.gap_tol,
                                               max_iter=self.ipm_max_iter, eliminate=self.eliminate,
                                               backend=self.backend,
                                               crossover_above=0.0 if self.fallback else CANDIDATE_GAP)
            if ip.converged:
                return problem.index.theta(x_ip), ip_answer(ip, details, newton, t0)
            best = (x_ip, ip)
        if self.resolve:  # H singular, or the interior point failed: is double precision why?
            resolved, ridge = _resolved(problem)
            if resolved is not problem:
                again = copy.copy(self)
                again.resolve = False
                theta, cert = again.solve_blocks(resolved)
                cert.details.update(ridge_raised_to=ridge, gap_floor=resolved.floor)
                return theta, cert
        if best is None or (self.fallback and best[1].duality_gap > FALLBACK_ABOVE_GAP):
            theta, cert = self.face_admm.run(problem, x, newton, details, t0)
            if best is None or cert.converged or not best[1].duality_gap < cert.duality_gap:
                return theta, cert
        # the interior point's point, uncertified (no fallback, or none that did better)
        return problem.index.theta(best[0]), ip_answer(best[1], details, newton, t0)


def _resolved(problem: Problem):
    """:meth:`Problem.resolved`, and an IllConditionedDataWarning if the ridge was raised."""
    resolved, ridge = problem.resolved()
    if ridge is not None:
        cond = problem.spd.condition
        warn(
            "the normal equations of the constrained fit "
            + ("are singular to double precision" if not np.isfinite(cond)
               else f"have condition {cond:.1e}")
            + " (rank-deficient data: they square its condition, and the ridge is below what "
            f"they resolve); solved with the ridge raised to {ridge:g} * sigma_1 (condition "
            f"{resolved.spd.condition:.1e}): it decides the directions with singular value "
            f"below ~{ridge:g} sigma_1 and moves those 100x above by ~1e-4",
            IllConditionedDataWarning)
    return resolved, ridge


class Auto(Strategy):
    """The default of :func:`dolfinx_lopinf.core.infer_mechanical`.

    Two blocks (K, C): :class:`PSDBlocks`, and the log barrier (:class:`Barrier`) if that is
    not certified - unless the interior point stopped at a gap of at most FALLBACK_ABOVE_GAP,
    where the fallbacks did no better in seconds (measured there); of two uncertified answers
    the smaller gap is kept. Where H is singular to double precision or the interior point
    fails, :meth:`Problem.resolved` decides first whether double precision is why (condition of H
    beyond COND_MAX: the ridge is raised; beyond ~2e9: the gap floor rises); if so the fit is
    solved again on that problem (``PSDBlocks(resolve=True)``; certificate:
    ``ridge_raised_to``, ``gap_floor``). One block (K): the Lyapunov minimiser if it is
    >= eps I, else the interior point (:class:`InteriorPoint`, crossover included), and :class:`EigenbasisADMM` if that
    is not certified (held-out one-block fits, ``studies.held_out --conservative``: the
    interior point needs far fewer iterations than EigenbasisADMM there).
    ``method="admm"`` skips the interior point and the Lyapunov shortcut: the ADMM
    strategies alone (the comparison path). ``fallback=False`` stops after the interior point
    (and its crossover): an uncertified answer is its point, with its gap - what lo.fit's
    candidates use, whose fits only predict held-back data (the fallbacks took seconds there
    for a gap no smaller: the membrane loop at r = 20).

    The interior point first tries the blocks whose symmetric minimiser is indefinite alone
    (``PSDBlocks(eliminate=True)``) only from r = ``ELIMINATE_FROM_R`` on: the attempt
    saves 7/8 of the Schur Cholesky per iteration, which pays only where that Cholesky is
    the cost (large r); at small r, or where the attempt fails and the full run follows, it
    costs more than it saves (``python -m dolfinx_lopinf.studies.benchmark --table`` times
    both).
    """

    def __init__(self, method: str = "auto", backend: str = "auto", fallback: bool = True):
        if method not in ("auto", "admm"):
            raise InputError(f"method must be 'auto' or 'admm', not {method!r}")
        self.method, self.backend, self.fallback = method, backend, fallback

    def solve_blocks(self, problem: Problem):
        if problem.n_blocks > 1:
            resolve = self.method == "auto"
            theta, cert = PSDBlocks(method=self.method, backend=self.backend, resolve=resolve,
                                    eliminate=problem.r >= ELIMINATE_FROM_R,
                                    fallback=self.fallback).solve_blocks(problem)
            near = cert.solver == "ipm" and cert.duality_gap <= FALLBACK_ABOVE_GAP
            if not cert.converged and not near and (self.fallback or cert.solver != "ipm"):
                # on the problem PSDBlocks last solved (resolved is cached)
                solved, ridge = problem.resolved() if resolve else (problem, None)
                theta_b, cert_b = Barrier().solve_blocks(solved)
                if solved is not problem:
                    cert_b.details.update(ridge_raised_to=ridge, gap_floor=solved.floor)
                if cert_b.converged or not cert.duality_gap <= cert_b.duality_gap:
                    theta, cert = theta_b, cert_b
            return theta, cert
        if self.method == "auto":
            theta, cert = Lyapunov().solve_blocks(problem)
            if np.linalg.eigvalsh(theta).min() >= problem.eps:
                return theta, cert
            if problem.spd.ok:  # the interior point's certificate needs H > 0
                theta, cert = InteriorPoint(backend=self.backend).solve_blocks(problem)
                # only its own answer: on rank-edge data its Cholesky-based symmetric
                # minimiser can come out >= eps I where Lyapunov's did not (the weak directions
                # are rounding there; make test-rounding) - one verdict, so EigenbasisADMM
                if (cert.converged or not self.fallback) and cert.solver == "ipm":
                    return theta, cert
        return EigenbasisADMM().solve_blocks(problem)
