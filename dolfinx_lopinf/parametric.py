"""``lo.parametric``: one reduced model for a family of designs::

    import dolfinx_lopinf as lo
    psys = lo.parametric.ParametricSystem(L, q, q_t, {"mu": mu_c}, input_forms=[b], bcs=bcs)
    print(psys.describe())                         # the affine terms read from the UFL
    data = [(mu, lo.parametric.simulate(psys, mu, dt, n, inputs=u)[0]) for mu in train ...]
    model = lo.parametric.fit(data, r=12, structure=psys.structure,
                              weight=psys.mass_matrix())   # certified for every mu of the cone
    traj = model.predict(mu=2.7, n_steps=400, inputs=u_test)

* :func:`fit` - :func:`fit_affine` (parametric L-OpInf, the affine structure given) or, with
  ``structure=None`` (a non-affine parameter), :func:`fit_interpolated` (per-parameter fits
  interpolated on the SPD manifold);
* :class:`AffineStructure`, :class:`ParametricModel`, :class:`InterpolatedModel` (numpy);
* the DOLFINx layer, loaded on first use: :class:`ParametricSystem` (the UFL split,
  :mod:`dolfinx_lopinf.fem.affine`), :func:`simulate` (the FOM at any mu,
  :mod:`dolfinx_lopinf.fem.param_fom`), :func:`split_form`.
"""

from __future__ import annotations

from .core.interpolated import InterpolatedModel, fit_interpolated
from .core.parametric import (AffineStructure, ParametricModel, fit_affine, intrusive,
                              sample_design)

_LAZY = {"ParametricSystem": "fem.affine", "split_form": "fem.affine", "simulate": "fem.param_fom"}


def fit(data, r: int | None = None, *, structure: AffineStructure | None = None, **kwargs):
    """:func:`fit_affine` when ``structure`` is given, else :func:`fit_interpolated`
    (``kwargs``: theirs)."""
    if structure is None:
        return fit_interpolated(data, r, **kwargs)
    return fit_affine(data, structure, r, **kwargs)


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"dolfinx_lopinf.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["AffineStructure", "InterpolatedModel", "ParametricModel", "fit", "fit_affine",
           "fit_interpolated", "intrusive", "sample_design", *_LAZY]
