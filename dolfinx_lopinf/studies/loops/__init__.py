"""User time loops written the way the FEniCSx community writes them, an independent reference
of their schemes, and the study that scores today's ``lo.fit`` on their recordings.

    python -m dolfinx_lopinf.studies.loops [--size quick|default] [--verify]  # -> results/loops

The loops (each a user's program; none imports dolfinx_lopinf):

=================================  ==========================================================
``comet_gen_alpha``                COMET / numerical-tour 3D cantilever, generalised-alpha
                                   (alpha_m 0.2, alpha_f 0.4), Rayleigh damping, LU once +
                                   RHS per step, ``update_fields``; ramp-and-release traction
``hht_plane_strain``               2D plane-strain cantilever, HHT-alpha (alpha 0.1),
                                   LinearProblem + ``fem.Expression`` updates, end traction
``membrane_central_difference``    2D membrane wave, explicit central differences, lumped
                                   (vertex-quadrature) mass, matrix-free RHS, no damping
``newmark_nonlinear_problem``      average-acceleration Newmark as a residual solved by
                                   ``NonlinearProblem`` (SNES) each step; the positive control
``newmark_every_k``                Newmark (gamma 0.6) on assembled PETSc matrices, KSP,
                                   recorded every 5th step only
=================================  ==========================================================

Each loop module has ``simulate(load, t_end, *, size, on_step)`` (``on_step(t, u, v, a,
applied_load, applied_time)`` at t = 0 and after each (k-th) step; returns V, dt, the scheme
and seconds), ``train_load``, ``test_load``, ``SIZES`` ("quick", "default"), ``OUTPUT`` (the
point output the study records), ``scheme()`` and ``fe_forms(V)`` (its own mass, damping,
stiffness and input forms and Dirichlet conditions). :mod:`.operators` turns those forms into
dense matrices in the recorder's snapshot row order; :mod:`.reference` (numpy only) projects
them and integrates the generalised-alpha family; :mod:`.study` records, fits and tabulates.
"""
