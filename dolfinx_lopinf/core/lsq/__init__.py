"""Structured least-squares solvers behind :mod:`dolfinx_lopinf.core.inference` (numpy; numba
optional).

All solve, for an unknown Theta (r, p) whose column blocks are "symmetric PSD" (K, C) or
free (B), the compressed problem

    min_Theta  ||Theta L + Z||_F^2,     G = L L^T (p, p),  X = Z L^T (r, p)

(see :class:`~dolfinx_lopinf.core.gram.GramData`), so their cost never depends on the number
of snapshots K. A :class:`Problem` holds (L, Z, the block layout, eps); a strategy's
``solve(problem)`` returns ``(Theta, Certificate)``, the free columns minimised out exactly
first (:func:`eliminate_free`):

* :class:`Lyapunov` - one symmetric block, no constraint: G K + K G = -(X + X^T), exact
  through the SVD of L (:func:`solve_symmetric`).
* :class:`EigenbasisADMM` - one symmetric block >= eps I: ADMM whose K-step is exact in the
  eigenbasis of G (robust to the 1e12 condition numbers of block-POD beam data).
* :class:`InteriorPoint` - several symmetric blocks >= eps I: a primal-dual interior point
  method (HKM, Mehrotra) with a certified duality gap (closed-form dual bound), crossover to
  :class:`FaceNewton` on the face it shows.
* :class:`FaceADMM` - the same problem by ADMM until the optimal face shows, an exact solve
  on that face (:func:`polish`) and Newton on the fixed-rank face.
* :class:`PSDBlocks` - the symmetric minimiser if feasible, else the interior point, else
  ADMM + face.
* :class:`Barrier` - a log-barrier interior point method with a duality-gap certificate
  (slow; the last resort).
* :class:`Auto` - the default of :func:`~dolfinx_lopinf.core.infer_mechanical`.

Layout: ``linalg`` (the shared numerics: objective, PSD projection, SPD solve, vech index
tables, normal equations), ``problem`` (Problem, Certificate, KKT residuals, elimination of
the free columns), ``lyapunov``, ``ipm``, ``face``, ``barrier``, ``blocks``, and
``_compiled``: the interior point's iteration compiled with numba when it is installed
(``backend="auto"`` of :class:`InteriorPoint`, :class:`PSDBlocks`, :class:`Auto`; the numpy
iteration is the reference and the fallback, also with ``DOLFINX_LOPINF_JIT=0``).
"""

from .barrier import Barrier
from .blocks import Auto, PSDBlocks
from .face import FaceADMM, FaceNewton, polish
from .ipm import InteriorPoint, PrimalDualIPM, interior_point
from .linalg import SPDSolver, psd_project, residual_norm2, symmetric_normal_equations
from .lyapunov import EigenbasisADMM, Lyapunov, solve_symmetric
from .problem import Certificate, Problem, Strategy, eliminate_free, kkt

__all__ = ["Auto", "Barrier", "Certificate", "EigenbasisADMM", "FaceADMM", "FaceNewton",
           "InteriorPoint", "Lyapunov", "PSDBlocks", "PrimalDualIPM", "Problem", "SPDSolver",
           "Strategy", "eliminate_free", "interior_point", "kkt", "polish", "psd_project",
           "residual_norm2", "solve_symmetric", "symmetric_normal_equations"]
