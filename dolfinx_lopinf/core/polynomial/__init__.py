"""Polynomial Lagrangian operator inference: a reduced potential learned as one convex fit.

For St. Venant-Kirchhoff elasticity the reduced potential is exactly a quartic polynomial of
the reduced coordinates; this package learns it (and damping C, input B) from reduced
snapshots as the gradient of one potential, so the ROM qh_tt + C qh_t + grad U(qh) = B u is
Lagrangian by construction. numpy (+ cvxpy/clarabel for constrained fits) only; no DOLFINx.

* :mod:`.potential` - U(q) (:class:`PolynomialPotential`), the unconstrained baseline force
  (:class:`PolynomialForce`), monomials and the Gram map of the sum-of-squares form;
* :mod:`.fit` - the data relation (:func:`midpoint_data`, :func:`point_data`) and the convex
  fit (:func:`fit_polynomial`, :func:`fit_force`); :mod:`.sos` - its sum-of-squares form by
  our certified interior point;
* :mod:`.rom` - :class:`PolynomialROM`, the midpoint VI or AVF discrete gradient in time.
"""

from .fit import (CONSTRAINTS, MidpointData, PolynomialOperators, concat_data, fit_force,
                  fit_polynomial, midpoint_data, point_data)
from .potential import (PolynomialForce, PolynomialPotential, gram_maps, monomial_gradients,
                        monomial_values, monomials, n_unknowns, polynomial_tensors)
from .rom import SCHEMES, PolynomialROM

__all__ = ["CONSTRAINTS", "MidpointData", "PolynomialForce", "PolynomialOperators",
           "PolynomialPotential", "PolynomialROM", "SCHEMES", "concat_data", "fit_force",
           "fit_polynomial", "gram_maps", "midpoint_data", "monomial_gradients", "monomial_values",
           "monomials", "n_unknowns", "point_data", "polynomial_tensors"]
