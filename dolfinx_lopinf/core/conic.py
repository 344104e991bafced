"""The reference conic solver: Clarabel through cvxpy, with its own primal and dual objectives.

cvxpy reports the primal value alone; the fits' certificates also want Clarabel's dual
objective (their relative gap), its iteration count and residuals. :func:`solve_raw` runs
Clarabel on a cvxpy problem and unpacks the solution into the problem's variables, returning
Clarabel's raw result; :func:`clarabel` adds the checks and the gap.
"""

from __future__ import annotations

from ..errors import SolverFailedError


def solve_raw(cp, prob, options=None):
    """Solve ``prob`` (a ``cvxpy.Problem``) with Clarabel (its default tolerances unless
    ``options``), unpack the answer into its variables and return Clarabel's result object."""
    from cvxpy.reductions.solvers.solver_inverse_data import SolverInverseData

    data, chain, inverse = prob.get_problem_data(cp.CLARABEL)
    raw = chain.solver.solve_via_data(data, False, False, dict(options or {}))
    inverse[-1] = SolverInverseData(inverse[-1], solver_options={})
    prob.unpack_results(raw, chain, inverse)
    return raw


def clarabel(cp, prob, options=None) -> dict:
    """Solve ``prob`` with Clarabel (:func:`solve_raw`) and read its own primal and dual
    objectives: status, iterations, relative gap |p - d| / max(|p|, |d|). A solver error or a
    status other than (inaccurately) optimal raises
    :class:`~dolfinx_lopinf.errors.SolverFailedError`."""
    try:
        raw = solve_raw(cp, prob, options)
    except cp.error.SolverError as exc:
        raise SolverFailedError(f"Clarabel failed: {exc}") from exc
    if prob.status not in ("optimal", "optimal_inaccurate"):
        raise SolverFailedError(f"Clarabel failed: status {prob.status}")
    p, d = float(raw.obj_val), float(raw.obj_val_dual)
    return {"status": str(raw.status), "iterations": int(raw.iterations),
            "relative_gap": abs(p - d) / max(abs(p), abs(d), 1e-300)}
