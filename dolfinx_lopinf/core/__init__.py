"""The numpy core: bases, data relations, certified fits, reduced models, metrics.

Needs numpy and scipy only; optional extras (cvxpy, numba) are imported where used."""
